"""BLAS pools at one thread while jaxtable fits and diagnoses, the caller's setting after."""

import sys
import types

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from threadpoolctl import threadpool_info, threadpool_limits

import jaxtable as jt
from jaxtable import _threads
from jaxtable._threads import ENV, blas_threads, one_blas_thread

# numpy's and scipy's OpenBLAS (jaxlib's LAPACK kernels call scipy's) are both loaded
np.linalg.svd(np.ones((3, 3)))
scipy.linalg.svd(np.ones((3, 3)))
jnp.linalg.svd(jnp.ones((3, 3)))


def _blas_threads() -> list[int]:
    return [p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"]


@pytest.fixture
def two_threads():
    """Every BLAS pool at 2 threads around the test (the suite's machine has 2 cores)."""
    with threadpool_limits(limits=2, user_api="blas"):
        if not _blas_threads() or set(_blas_threads()) != {2}:
            pytest.skip("no BLAS pool that takes 2 threads")
        yield


@one_blas_thread
def _seen(fail=False):
    seen = _blas_threads()
    if fail:
        raise RuntimeError("inside")
    return seen


def test_pools_are_one_thread_inside_and_restored_after(two_threads, monkeypatch):
    monkeypatch.delenv(ENV, raising=False)
    assert len(_blas_threads()) >= 2  # numpy's and scipy's
    assert set(_seen()) == {1}
    assert set(_blas_threads()) == {2}
    with pytest.raises(RuntimeError, match="inside"):
        _seen(fail=True)
    assert set(_blas_threads()) == {2}  # restored after an exception too


def test_the_environment_sets_the_count_or_turns_it_off(two_threads, monkeypatch):
    monkeypatch.setenv(ENV, "off")
    assert blas_threads() is None and set(_seen()) == {2}
    monkeypatch.setenv(ENV, "3")
    assert blas_threads() == 3
    for bad in ("0", "-1", "two"):
        monkeypatch.setenv(ENV, bad)
        with pytest.raises(ValueError, match=ENV):
            _seen()
    assert set(_blas_threads()) == {2}


def test_a_call_inside_another_leaves_the_pools_to_its_caller(two_threads, monkeypatch):
    """A fit inside a diagnosis: the inner call neither looks for the libraries again nor
    restores the pools when it returns; the outer call restores them."""
    monkeypatch.delenv(ENV, raising=False)
    found = []
    pools = _threads._pools
    monkeypatch.setattr(_threads, "_pools", lambda: found.append(1) or pools())

    @one_blas_thread
    def outer():
        inner = _seen()
        return inner, _blas_threads()

    inner, after_inner = outer()
    assert set(inner) == {1} and set(after_inner) == {1}
    assert set(_blas_threads()) == {2}
    assert len(found) == 1  # the outer call only
    assert set(_seen()) == {1} and len(found) == 2  # a call on its own sets them again


def test_the_libraries_are_looked_for_again_after_an_import(monkeypatch):
    first = _threads._pools()
    assert _threads._pools() is first
    monkeypatch.setitem(sys.modules, "jaxtable_test_new_module", types.ModuleType("x"))
    again = _threads._pools()
    assert again is not first
    assert {lib.filepath for lib in again.lib_controllers} == {
        lib.filepath for lib in first.lib_controllers
    }


@pytest.mark.parametrize(
    "fn",
    [
        jt.fit,
        jt.calibrate,
        jt.heldout_rms,
        jt.select_poses,
        jt.compare_with_random,
        jt.posterior,
        jt.validate,
        jt.optimize_design,
        jt.pareto_front,
        jt.diagnose,
        jt.discrimination_plan,
        jt.residual_gp,
        jt.detection_power,
        jt.structure_test,
    ],
    ids=lambda f: f.__name__,
)
def test_public_fitting_functions_run_with_one_blas_thread(fn):
    wrapper_code = one_blas_thread(lambda: None).__code__
    f, codes = fn, []
    while f is not None:  # through the test suite's own annotation-checking wrappers
        codes.append(getattr(f, "__code__", None))
        f = getattr(f, "__wrapped__", None)
    assert wrapper_code in codes, fn.__name__


def test_a_fit_sees_one_thread(two_threads, monkeypatch, table):
    """Inside a real calibration the pools are at one thread (seen by the noise model's
    host code, which every fit calls)."""
    import jaxtable._calibration.fit as fit_module

    seen = []
    original = fit_module.group_scales

    def spy(*a, **k):
        seen.append(_blas_threads())
        return original(*a, **k)

    monkeypatch.delenv(ENV, raising=False)
    monkeypatch.setattr(fit_module, "group_scales", spy)
    true = jt.perturb_table(table, 3, joint_sigma=0.0, zero_sigma=0.05)
    data = jt.simulate(table, true, jt.plan_random(30, 3), jt.tracker6(), seed=3)
    cal = jt.calibrate(table, data, ("zero_lengths",))
    assert cal.converged
    assert seen and all(set(s) == {1} for s in seen), seen
    assert set(_blas_threads()) == {2}
