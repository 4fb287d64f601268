import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtable._linalg import (
    cond_small,
    inv_small,
    largest_eigval_psd,
    largest_eigval_small,
    matmul_small,
    solve_small,
)


def test_small_kernels_match_numpy():
    # eagerly, every op compiles on its own (~3000 in cond_small)
    cond, solve, inv, matmul = (
        jax.jit(f) for f in (cond_small, solve_small, inv_small, matmul_small)
    )
    rng = np.random.default_rng(0)
    for _ in range(20):
        A = rng.normal(size=(6, 6))
        B = rng.normal(size=(6, 4))
        np.testing.assert_allclose(
            np.asarray(solve(A, B)), np.linalg.solve(A, B), rtol=1e-10, atol=1e-12
        )
        np.testing.assert_allclose(np.asarray(inv(A)) @ A, np.eye(6), atol=1e-10)
        assert abs(float(cond(A)) / np.linalg.cond(A) - 1) < 1e-8
        assert abs(float(cond(A, np.linalg.inv(A))) / np.linalg.cond(A) - 1) < 1e-8
        for a, b in [((6, 6), (6, 6)), ((6, 3), (3, 3)), ((3, 6), (6, 5)), ((6, 6), (6,))]:
            A, B = rng.normal(size=a), rng.normal(size=b)
            np.testing.assert_allclose(np.asarray(matmul(A, B)), A @ B, rtol=1e-13, atol=1e-13)
    # a pivot is needed: zero leading entry
    A = np.array([[0.0, 1.0], [1.0, 0.0]])
    np.testing.assert_allclose(np.asarray(solve_small(A, np.eye(2))), A)


@pytest.mark.parametrize("scale", [1e-30, 1.0, 1e30])
def test_largest_eigenvalue_over_a_wide_range(scale):
    """Repeated squaring with the trace taken every fourth square: the largest eigenvalue of
    S = Q diag(λ) Qᵀ to 1e-10 for spectra spanning 30 decades, at any overall scale; when the
    two largest are less than 1 % apart (1e-3, 1e-4, a tie), to within their gap."""
    Q = np.linalg.qr(np.random.default_rng(3).normal(size=(6, 6)))[0]
    for lam in (
        [3.0, 1.0, 1e-3, 1e-9, 1e-15, 0.0],
        [1.0, 0.999, 0.5, 0.5, 1e-30, 1e-30],
        [1.0, 1 - 1e-4, 1e-2, 1e-2, 1e-2, 1e-2],
        [1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
    ):
        S = (Q * (scale * np.asarray(lam))) @ Q.T
        gap = 1 - lam[1] / lam[0]
        tol = 1e-10 if gap >= 0.01 else max(gap, 1e-14)  # the docstring's promise
        assert abs(float(largest_eigval_small(S)) / (scale * lam[0]) - 1) < tol, lam


@pytest.mark.parametrize("scale", [1e-30, 1.0, 1e30])
def test_largest_eigenvalue_by_bisection_whatever_the_gap(scale):
    """Tridiagonalisation and bisection: the largest eigenvalue to 1e-11 for spectra spanning
    30 decades, at any overall scale, also when the two largest are 1e-4 apart or tied
    (where repeated squaring is only good to the gap)."""
    rng = np.random.default_rng(4)
    for lam in (
        [3.0, 1.0, 1e-3, 1e-9, 1e-15, 0.0],
        [1.0, 0.999, 0.5, 0.5, 1e-30, 1e-30],
        [1.0, 1 - 1e-4, 1e-2, 1e-2, 1e-2, 1e-2],
        [1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
        [1.0, 1.0, 1e-3, 1e-3, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 0.0, 2.0],
    ):
        for n in (6, 3, 2):
            Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
            S = (Q * (scale * np.sort(lam)[-n:])) @ Q.T
            got = float(jax.jit(largest_eigval_psd)(S)) / (scale * max(lam))
            assert abs(got - 1) < 1e-11, (lam, n)
    assert float(jax.jit(largest_eigval_psd)(np.zeros((6, 6)))) == 0.0


def test_condition_number_of_workspace_jacobians_matches_numpy(table):
    """The error map's condition number at 5000 workspace poses against numpy's SVD: 1e-10
    (repeated squaring, used before, was up to 3e-6 off at 5 of these poses, where two
    singular values of the symmetric table nearly tie)."""
    import jax
    from conftest import random_poses

    from jaxtable._analysis.sensitivities import budget_jacobians_one

    K = np.asarray(
        jax.jit(jax.vmap(lambda q: budget_jacobians_one(table, q)[1]))(
            jnp.asarray(random_poses(5000, 8))
        )
    )
    cond = jax.jit(jax.vmap(cond_small))  # eagerly, every op compiled on its own
    got = np.asarray(cond(K, np.linalg.inv(K)))
    np.testing.assert_allclose(got, np.linalg.cond(K), rtol=1e-10)
    np.testing.assert_allclose(np.asarray(cond(K)), np.linalg.cond(K), rtol=1e-10)


def test_solve_is_linear_in_b_for_reverse_mode():
    A = jnp.asarray(np.random.default_rng(1).normal(size=(6, 6)))
    b = jnp.arange(6.0)
    g = jax.jit(jax.grad(lambda v: jnp.sum(solve_small(A, v[:, None]) ** 2)))(b)
    x = np.linalg.solve(np.asarray(A), np.asarray(b))
    np.testing.assert_allclose(np.asarray(g), 2 * np.linalg.solve(np.asarray(A).T, x), rtol=1e-10)


def test_cholesky_and_generalized_eigenvalue_match_scipy():
    from scipy.linalg import eigh

    from jaxtable._linalg import cholesky_small, smallest_generalized_eigval

    rng = np.random.default_rng(3)
    A, B = rng.normal(size=(6, 6)), rng.normal(size=(6, 6))
    K, M = A @ A.T + 0.5 * np.eye(6), B @ B.T + 0.1 * np.eye(6)
    np.testing.assert_allclose(
        np.asarray(cholesky_small(jnp.asarray(K))), np.linalg.cholesky(K), rtol=1e-12, atol=1e-12
    )
    lam = float(smallest_generalized_eigval(jnp.asarray(K), jnp.asarray(M)))
    assert lam == pytest.approx(eigh(K, M, eigvals_only=True)[0], rel=1e-9)


def test_solve_derivatives_in_a_and_b_equal_the_closed_form_both_modes():
    """d(A⁻¹B) = A⁻¹ (dB − dA A⁻¹B), forward and reverse, against numpy's solves; and a
    pivoting matrix's derivative against central differences."""
    rng = np.random.default_rng(2)
    A, B = rng.normal(size=(6, 6)), rng.normal(size=(6, 3))
    X = np.linalg.solve(A, B)
    dA, dB = rng.normal(size=(6, 6)), rng.normal(size=(6, 3))
    want = np.linalg.solve(A, dB - dA @ X)
    _, got = jax.jvp(solve_small, (jnp.asarray(A), jnp.asarray(B)), (dA, dB))
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-9, atol=1e-12)
    # reverse: <W, dX> = <gA, dA> + <gB, dB> for a cotangent W
    W = rng.normal(size=(6, 3))
    _, vjp = jax.vjp(solve_small, jnp.asarray(A), jnp.asarray(B))
    gA, gB = vjp(jnp.asarray(W))
    lhs = np.sum(W * want)
    assert float(np.sum(gA * dA) + np.sum(gB * dB)) == pytest.approx(lhs, rel=1e-9)
    # a matrix that needs pivoting (zero leading entry), derivative in A by differences
    A[0, 0] = 0.0
    h = 1e-6
    fd = (np.linalg.solve(A + h * dA, B) - np.linalg.solve(A - h * dA, B)) / (2 * h)
    _, got = jax.jvp(solve_small, (jnp.asarray(A), jnp.asarray(B)), (dA, np.zeros_like(B)))
    np.testing.assert_allclose(np.asarray(got), fd, rtol=1e-6, atol=1e-8)
