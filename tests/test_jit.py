"""Quick compilation (`jaxtable/_jit.py`): which programs get XLA's classic emitters, the
environment variable that turns it off, the fallback when a backend does not know the
option, and that the results do not depend on it."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtable as jt
from jaxtable import _batch, _jit


@pytest.fixture
def spy_filter_jit(monkeypatch):
    """Record the keyword arguments `_jit.jit` hands to `eqx.filter_jit`."""
    calls = []
    real = eqx.filter_jit

    def spy(fun, **kwargs):
        calls.append(kwargs)
        return real(fun, **kwargs)

    monkeypatch.setattr(_jit.eqx, "filter_jit", spy)
    return calls


def _twice(x):
    return jnp.sin(x) * 2.0


def test_jit_compiles_with_the_quick_options_by_default(monkeypatch, spy_filter_jit):
    monkeypatch.delenv(_jit.ENV, raising=False)
    f = _jit.jit(_twice)
    x = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(f(x), 2 * np.sin(np.linspace(0.0, 1.0, 5)), rtol=1e-15)
    assert spy_filter_jit == [{"compiler_options": _jit.QUICK}]
    assert _jit.QUICK == {"xla_cpu_use_fusion_emitters": False}


def test_environment_variable_turns_it_off_and_bad_values_are_refused(monkeypatch, spy_filter_jit):
    monkeypatch.setenv(_jit.ENV, "0")
    assert _jit.compiler_options() == {}
    f = _jit.jit(_twice)
    f(jnp.ones(3))
    assert spy_filter_jit == [{}]
    monkeypatch.setenv(_jit.ENV, "1")  # changed between calls: the next call follows it
    f(jnp.ones(3))
    assert spy_filter_jit[-1] == {"compiler_options": _jit.QUICK}
    for bad in ("yes", "2", "off"):
        monkeypatch.setenv(_jit.ENV, bad)
        with pytest.raises(ValueError, match=_jit.ENV):
            _jit.compiler_options()


def test_inside_a_users_trace_it_is_a_plain_jit(monkeypatch, spy_filter_jit):
    """JAX refuses compiler options on a nested jit: traced arguments, or constant ones
    inside a trace, get the plain program."""
    monkeypatch.delenv(_jit.ENV, raising=False)
    f = _jit.jit(_twice)
    x = jnp.linspace(0.0, 1.0, 4)
    expected = 2 * np.sin(np.linspace(0.0, 1.0, 4))
    np.testing.assert_allclose(jax.jit(f)(x), expected, rtol=1e-15)
    np.testing.assert_allclose(jax.jit(lambda s: s * f(x))(2.0), 2 * expected, rtol=1e-15)
    np.testing.assert_allclose(
        jax.grad(lambda s: f(s * x).sum())(1.0),
        2 * (np.cos(np.asarray(x)) * np.asarray(x)).sum(),
        rtol=1e-14,
    )
    assert spy_filter_jit == [{}]  # one plain program, shared by the three
    np.testing.assert_allclose(f(x), expected, rtol=1e-15)
    assert spy_filter_jit[-1] == {"compiler_options": _jit.QUICK}


def test_an_option_the_backend_does_not_know_falls_back_to_the_defaults(monkeypatch):
    monkeypatch.delenv(_jit.ENV, raising=False)
    monkeypatch.setattr(_jit, "QUICK", {"xla_no_such_option_in_any_backend": True})
    _jit._supported.cache_clear()
    try:
        assert _jit.compiler_options() == {}
        np.testing.assert_allclose(_jit.jit(_twice)(jnp.zeros(2)), 0.0)
    finally:
        _jit._supported.cache_clear()
    # the real option is known to this jaxlib (else quick compilation is silently off)
    monkeypatch.undo()
    assert _jit.compiler_options() == _jit.QUICK


def test_small_batches_compile_quick_and_large_ones_keep_the_defaults(table, monkeypatch):
    used = []
    for name in ("_vmapped", "_vmapped_quick", "_blocked"):
        real = getattr(_batch, name)

        def spy(fn, shared, batched, real=real, name=name):
            used.append((name, jax.tree.leaves(batched)[0].shape[0]))
            return real(fn, shared, batched)

        monkeypatch.setattr(_batch, name, spy)
    poses = np.zeros((_jit.LARGE_BATCH + 10, 6))
    poses[:, 2] = np.linspace(-20, 20, len(poses))
    small = jt.actuator_command(table, poses[:100])
    large = jt.actuator_command(table, poses)
    assert used[0] == ("_vmapped_quick", 256)  # 100 rows padded to SMALL_BATCH (chunk_rows)
    # on the CPU a large batch runs in per-core pieces of blocks (`_batch._blocked`)
    assert {name for name, _ in used[1:]} == {"_blocked"}
    assert sum(rows for _, rows in used[1:]) >= len(poses)
    # the two programs agree (to rounding: different code generation)
    np.testing.assert_allclose(small, large[:100], rtol=0, atol=1e-12)


def test_a_fit_gives_the_same_result_either_way(table, monkeypatch):
    """The calibration fit program compiled both ways: the same optimum and covariance to
    rounding. The step count may differ by one: the two code generations round
    differently, and a change near the stopping rule's tolerance can fall either side
    (seen: 5 steps quick, 4 default, optima 2.4e-12 apart)."""
    true = jt.perturb_table(table, seed=3)
    data = jt.simulate(table, true, jt.plan_random(40, seed=4), jt.tracker6(), seed=5)
    st = jt.setup(table, data, ("zero_lengths", "platform_joints"))
    monkeypatch.setenv(_jit.ENV, "1")
    quick = jt.fit(st)
    monkeypatch.setenv(_jit.ENV, "0")
    default = jt.fit(st)
    assert abs(quick.steps - default.steps) <= 1
    np.testing.assert_allclose(quick.value, default.value, rtol=0, atol=1e-9)
    np.testing.assert_allclose(quick.covariance, default.covariance, rtol=1e-8, atol=1e-18)


def test_device_array_places_numpy_without_an_eager_program():
    """`device_array` gives what `jnp.asarray(x, dtype).reshape(shape)` gives (values,
    dtype, an uncommitted device array) without lowering a program; a device array of the
    asked shape and dtype is returned as it is; a traced value goes through jnp."""
    from conftest import compiled_programs

    from benchmarks.compile_profile import is_eager_operation

    rng = np.random.default_rng(0)
    x = rng.normal(size=(13, 7))  # a shape no other test uses, so nothing is cached for it
    n = np.arange(91, dtype=np.int64)
    with compiled_programs("jaxpr_to_mlir_module") as lowered:
        a = _jit.device_array(x)
        b = _jit.device_array(x, (7, 13))
        c = _jit.device_array(n, (13, 7), dtype=np.int32)
    assert lowered == [], lowered
    for got, want in ((a, x), (b, x.reshape(7, 13)), (c, n.reshape(13, 7).astype(np.int32))):
        assert isinstance(got, jax.Array) and not got.committed
        assert got.dtype == want.dtype and got.shape == want.shape
        np.testing.assert_array_equal(np.asarray(got), want)
    assert _jit.device_array(a) is a and _jit.device_array(a, (13, 7)) is a
    # the same call eagerly through jnp lowers a program for the shape (what it replaces)
    with compiled_programs("jaxpr_to_mlir_module") as lowered:
        jnp.asarray(x)
    assert any(is_eager_operation(name) for name in lowered), lowered
    traced = jax.jit(lambda v: _jit.device_array(v, (7, 13), dtype=np.float32))(x)
    assert traced.dtype == np.float32
    np.testing.assert_allclose(np.asarray(traced), x.reshape(7, 13), rtol=1e-7)
