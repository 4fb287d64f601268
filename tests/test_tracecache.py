"""Traced programs stored beside the compilation cache (`jaxtable/_tracecache.py`): a stored
program gives the same results without tracing, the key separates what tracing depends on,
and code from outside jaxtable, unexportable programs and broken entries are traced as
before."""

import dataclasses
import functools
import inspect
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxtable as jt
from jaxtable import _jit, _tracecache

TRACE = "/jax/core/compile/jaxpr_trace_duration"


@pytest.fixture
def store(tmp_path, monkeypatch):
    """An empty store in tmp_path, and no program of this process remembered."""
    monkeypatch.setattr(_tracecache, "directory", lambda: tmp_path)
    monkeypatch.setattr(_tracecache, "_MEMORY", {})
    monkeypatch.setattr(_tracecache, "_REFUSED", set())
    monkeypatch.setattr(_tracecache, "_REPEATS", {})
    return tmp_path


@pytest.fixture
def traces():
    """The names of the functions JAX traces while the test runs."""
    names = []

    def listen(event, duration, fun_name="?", **_):
        if event == TRACE:
            names.append(fun_name)

    jax.monitoring.register_event_duration_secs_listener(listen)
    yield names
    jax.monitoring.unregister_event_duration_listener(listen)


def _entries(folder):
    return sorted(p.name for p in folder.glob(f"*{_tracecache.SUFFIX}"))


def _poses(n, z=0.0):
    q = np.zeros((n, 6))
    q[:, 0] = np.linspace(-50.0, 50.0, n)
    q[:, 2] = z
    q[:, 5] = np.linspace(-0.05, 0.05, n)
    return q


def test_a_stored_program_gives_the_same_results_without_tracing(table, store, traces, monkeypatch):
    q = _poses(7)
    first = jt.actuator_command(table, q)
    assert len(_entries(store)) == 1  # the command's batch kernel, exported once ...
    assert "flat" in traces  # ... by tracing it
    _tracecache._MEMORY.clear()  # as in a new process: only the stored entry is left
    traces.clear()
    np.testing.assert_array_equal(jt.actuator_command(table, q), first)
    assert "flat" not in traces and "_vmap" not in traces  # loaded, not traced ...
    assert "_vmap__command_row" in traces  # ... and compiled under the kernel's name
    traces.clear()  # other values of the same shapes: the same program, nothing traced
    higher = jt.actuator_command(table, _poses(7, z=10.0))
    assert traces == [] and len(_entries(store)) == 1
    assert np.all(higher > first)  # every leg longer 10 mm up
    monkeypatch.setenv(_tracecache.ENV, "0")  # the plain program gives the same numbers
    np.testing.assert_allclose(jt.actuator_command(table, q), first, rtol=0, atol=1e-12)


def test_the_key_separates_what_tracing_depends_on(table, store, monkeypatch):
    q = _poses(5)
    jt.actuator_command(table, q)
    assert len(_entries(store)) == 1
    jt.actuator_command(table, q, compensated=False)  # another function in the kernel
    assert len(_entries(store)) == 2
    jt.actuator_command(table, np.concatenate([q] * 60))  # 300 rows: another batch size
    assert len(_entries(store)) == 3
    monkeypatch.setenv(_jit.ENV, "0")  # other compiler options
    jt.actuator_command(table, q)
    assert len(_entries(store)) == 4
    monkeypatch.setenv(_jit.ENV, "1")
    before = _entries(store)
    renamed = dataclasses.replace(table, name="renamed")
    jt.actuator_command(renamed, q)  # a static field of the table
    assert len(_entries(store)) == 5
    # a new jaxtable source (any file) is a new key for every program
    monkeypatch.setattr(_tracecache, "fingerprint", lambda: "another version")
    jt.actuator_command(table, q)
    assert len(_entries(store)) == 6 and set(before) < set(_entries(store))


def _outside(x):
    return jnp.sin(x) * 2.0


def test_a_repeated_call_finds_its_program_without_pickling_its_arguments(
    table, store, monkeypatch
):
    """A call with the same objects where an earlier call had objects that are not arrays,
    and arrays of the same shapes, runs that call's program without pickling its arguments
    for the key (a fit calls its block program several times a step). Another static
    field, other numbers that are not arrays (part of the program), another dtype or
    another jaxtable version make the key again."""
    pickled = []
    real = _tracecache._static_bytes
    monkeypatch.setattr(_tracecache, "_static_bytes", lambda obj: pickled.append(1) or real(obj))
    lengths = _jit.jit(jt._kinematics.leg_lengths)
    pose = jnp.array([10.0, 0.0, 5.0, 0.01, 0.0, 0.02])
    first = lengths(table, pose)
    assert len(pickled) == 1 and len(_entries(store)) == 1
    moved = lengths(table, pose + 1.0)  # the same table, other values
    assert len(pickled) == 1
    assert not np.allclose(moved, first)
    np.testing.assert_array_equal(lengths(table, pose), first)
    renamed = dataclasses.replace(table, name="renamed")  # a static field: another program
    np.testing.assert_array_equal(lengths(renamed, pose), first)
    assert len(pickled) == 2 and len(_entries(store)) == 2
    # a number that is not an array is part of the program: another number in its place
    # (the same pytree structure) must not find the program of the first
    eig = _jit.jit(jt._linalg.largest_eigval_small)
    Q = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    S = jnp.asarray(Q @ np.diag([1.0, 0.95, 0.5]) @ Q.T)
    assert abs(float(eig(S, 12)) - 1.0) < 1e-12  # a new program: pickled
    assert abs(float(eig(S, 12)) - 1.0) < 1e-12  # the same objects: a repeat
    assert len(pickled) == 3 and len(_entries(store)) == 3
    assert abs(float(eig(S, 1)) - 1.0) > 1e-4  # one squaring: its own program
    assert len(pickled) == 4 and len(_entries(store)) == 4
    lengths(table, jnp.zeros(6, jnp.float32))  # another dtype
    assert len(pickled) == 5 and len(_entries(store)) == 5
    monkeypatch.setattr(_tracecache, "fingerprint", lambda: "another version")
    lengths(table, pose)
    assert len(pickled) == 6 and len(_entries(store)) == 6
    monkeypatch.setenv(_tracecache.ENV, "0")  # the plain program gives the same numbers
    np.testing.assert_allclose(lengths(table, pose), first, rtol=0, atol=1e-12)


def test_a_number_where_an_earlier_call_had_an_array_is_another_program(store):
    """The repeat check meets a Python number at a leaf where the earlier call had an array
    (a design whose tolerance was set as a float, after one set as an array): it makes the
    key again and gives the number's result, where it once raised on the number's missing
    dtype."""
    f = _jit.jit(jt._linalg.computed_once)
    assert float(f(np.asarray(2.0))) == 2.0
    assert float(f(np.asarray(2.0))) == 2.0  # a repeat
    assert float(f(3.0)) == 3.0
    assert float(f(np.asarray(4.0))) == 4.0


def test_device_arrays_run_the_program_compiled_for_host_arrays(table, store):
    """A stored program's caller, compiled for host arrays, runs uncommitted device arrays
    as they are (no copy back to the host and over again) and an array committed to a
    device as a host array (its placement would compile the caller again): the same
    numbers, nothing compiled."""
    from conftest import compiled_programs

    lengths = _jit.jit(jt._kinematics.leg_lengths)
    pose = np.array([10.0, 0.0, 5.0, 0.01, 0.0, 0.02])
    first = lengths(table, pose)
    (key,) = _tracecache._MEMORY
    run, template = _tracecache._MEMORY[key]
    received = []

    def spy(*args):
        received.append(args)
        return run(*args)

    _tracecache._MEMORY[key] = (spy, template)
    on_device = jnp.asarray(pose)
    committed = jax.device_put(pose, jax.devices()[0])
    assert not on_device.committed and committed.committed
    with compiled_programs() as names:
        for x in (on_device, committed, pose.copy()):
            np.testing.assert_array_equal(lengths(table, x), first)
    assert names == []
    assert len(received) == 3 and all(len(a) == len(received[0]) for a in received)
    passed = [args[-1] for args in received]  # the pose: the last of (table, pose)
    assert passed[0] is on_device  # as it is
    assert isinstance(passed[1], np.ndarray)  # the committed one as a host array
    np.testing.assert_array_equal(passed[1], pose)


def test_code_from_outside_jaxtable_is_traced_as_before(table, store):
    # the function itself, or a function among the static arguments, from a test module:
    # pickle would store it by name, and its code is not in the fingerprint
    x = jnp.linspace(0.0, 1.0, 5)
    np.testing.assert_allclose(_jit.jit(_outside)(x), 2 * np.sin(np.linspace(0, 1, 5)))
    out = jt._batch.run_batch(lambda shared, q: q[:3] * shared, 2.0, _poses(4))
    np.testing.assert_allclose(out, 2.0 * _poses(4)[:, :3])
    # a transformed jaxtable function carries the function's name, not its code
    R = _jit.jit(jax.vmap(jt._rotation.rotation_matrix))(jnp.zeros((2, 3)))
    np.testing.assert_allclose(R, np.broadcast_to(np.eye(3), (2, 3, 3)), atol=1e-15)
    assert _entries(store) == []


def test_a_program_that_cannot_be_exported_is_traced_as_before(store, monkeypatch):
    def refuse(*_a, **_k):
        raise RuntimeError("no export here")

    monkeypatch.setattr(_tracecache, "_export", refuse)
    f = _jit.jit(jt._rotation.rotation_matrix)  # the module's own function: eligible
    np.testing.assert_allclose(f(jnp.zeros(3)), np.eye(3), atol=1e-15)
    np.testing.assert_allclose(f(jnp.zeros(3)), np.eye(3), atol=1e-15)  # remembered as refused
    assert _entries(store) == [] and len(_tracecache._REFUSED) == 1


def test_a_module_function_under_further_wrappers_is_stored(store, monkeypatch):
    """A module's name may hold `_jit.jit`'s wrapper inside other decorators that keep
    `__wrapped__` (a type checker's, as the suite's import hooks put around every function):
    the function is still the module's own, and its program is stored."""

    def checked(fn):
        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            return fn(*args, **kwargs)

        return wrapper

    plain = inspect.unwrap(jt._rotation.rotation_matrix)
    compiled = _jit.jit(plain)
    monkeypatch.setattr(jt._rotation, "rotation_matrix", checked(checked(compiled)))
    np.testing.assert_allclose(compiled(jnp.zeros(3)), np.eye(3), atol=1e-15)
    assert len(_entries(store)) == 1 and not _tracecache._REFUSED


def test_a_program_that_calls_lapack_kernels_is_stored(table, store, traces):
    """A Levenberg-Marquardt fit (optimistix; lineax's QR solve calls LAPACK's ormqr, which
    JAX does not promise to keep stable across versions, and stored programs are keyed on
    the jaxlib version) is stored like the others, and a new process loads it instead of
    tracing it (every process traced it twice before: for the refused export, then for the
    plain call)."""
    from jaxtable._calibration.fit import fit, setup
    from jaxtable._calibration.simulate import plan_random

    # test_calibration's damped Gauss-Newton case, whose LM reference compiles this program
    true = jt.perturb_table(table, seed=2)
    data = jt.simulate(table, true, plan_random(8, 4), jt.tracker6(), seed=2)
    st = setup(table, data, compensated=True)
    first = fit(st, method="levenberg_marquardt", noise="fixed")
    names = {run.__name__ for run, _ in _tracecache._MEMORY.values()}
    assert {"_levenberg_marquardt", "_block_jacobian"} <= names and not _tracecache._REFUSED
    _tracecache._MEMORY.clear()  # as in a new process: only the stored entries are left
    _tracecache._REPEATS.clear()
    traces.clear()
    again = fit(st, method="levenberg_marquardt", noise="fixed")
    assert "flat" not in traces, traces  # loaded, not traced (compiled under their names)
    loaded = {run.__name__ for run, _ in _tracecache._MEMORY.values()}
    assert {"_levenberg_marquardt", "_block_jacobian"} <= loaded
    assert first.converged and again.steps == first.steps
    np.testing.assert_array_equal(again.value, first.value)


def test_a_broken_entry_is_replaced(table, store):
    q = _poses(6)
    first = jt.actuator_command(table, q)
    (entry,) = store.glob(f"*{_tracecache.SUFFIX}")
    entry.write_bytes(b"half-written by another process")
    _tracecache._MEMORY.clear()
    np.testing.assert_array_equal(jt.actuator_command(table, q), first)
    assert entry.stat().st_size > 1000  # exported and written again


def test_the_store_keeps_under_its_size_limit(table, store, monkeypatch):
    jt.actuator_command(table, _poses(5))
    (oldest,) = store.glob(f"*{_tracecache.SUFFIX}")
    monkeypatch.setattr(_tracecache, "MAX_BYTES", oldest.stat().st_size + 10)
    jt.actuator_command(table, _poses(5), compensated=False)
    assert not oldest.exists() and len(_entries(store)) == 1  # the newest one stays


def test_on_beside_the_compilation_cache_off_by_the_environment(monkeypatch):
    monkeypatch.delenv(_tracecache.ENV, raising=False)
    tmp_path = Path(jax.config.jax_compilation_cache_dir)  # the suite's (conftest.py)
    assert _tracecache.directory() == tmp_path / "traced"
    monkeypatch.setenv(_tracecache.ENV, "0")
    assert _tracecache.directory() is None
    for bad in ("off", "2", "yes"):
        monkeypatch.setenv(_tracecache.ENV, bad)
        with pytest.raises(ValueError, match=_tracecache.ENV):
            _tracecache.directory()
