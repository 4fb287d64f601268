import jax
import jax.numpy as jnp
import numpy as np
import pytest
from conftest import quick_jit

from jaxtable._linalg import (
    cond_small,
    extreme_eigvals_psd,
    inv_normal_small,
    inv_small,
    largest_eigval_small,
    matmul_small,
    solve_small,
)


def test_small_kernels_match_numpy():
    # eagerly, every op compiles on its own (~3000 in cond_small)
    cond, solve, inv, matmul = (
        quick_jit(f) for f in (cond_small, solve_small, inv_small, matmul_small)
    )
    rng = np.random.default_rng(0)
    for _ in range(20):
        A = rng.normal(size=(6, 6))
        B = rng.normal(size=(6, 4))
        np.testing.assert_allclose(
            np.asarray(solve(A, B)), np.linalg.solve(A, B), rtol=1e-10, atol=1e-12
        )
        np.testing.assert_allclose(np.asarray(inv(A)) @ A, np.eye(6), atol=1e-10)
        c = np.linalg.cond(A)  # cond_small's promise: ~5e-15 cond² (JᵀJ squares it)
        assert abs(float(cond(A)) / c - 1) < 1e-14 * c**2, c
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
def test_extreme_eigenvalues_by_bisection_whatever_the_gap(scale):
    """Tridiagonalisation, bisection and a Newton step: λ_max to 1e-11 of itself for spectra
    spanning 30 decades, at any overall scale, also when the two largest are 1e-4 apart or
    tied (where repeated squaring is only good to the gap); λ_min to 1e-14 of the trace
    where it is simple, to 2⁻⁴² of it (the bisection's) where the two smallest tie."""
    rng = np.random.default_rng(4)
    for lam in (
        [3.0, 1.0, 1e-3, 1e-9, 1e-15, 0.0],
        [1.0, 0.999, 0.5, 0.5, 1e-30, 1e-30],
        [1.0, 1 - 1e-4, 1e-2, 1e-2, 1e-2, 1e-2],
        [1.0, 1.0, 1.0, 1.0, 1.0, 1.0],
        [1.0, 1.0, 1e-3, 1e-3, 0.0, 0.0],
        [0.0, 0.0, 0.0, 0.0, 0.0, 2.0],
        [1.0, 0.6, 0.5, 0.3, 0.2, 0.1],
        [1.0, 0.6, 0.5, 0.3, 0.1 + 1e-9, 0.1],
    ):
        for n in (6, 3, 2):
            Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
            spectrum = np.sort(lam)[-n:]
            S = (Q * (scale * spectrum)) @ Q.T
            hi, lo = np.asarray(jax.jit(extreme_eigvals_psd)(S)) / scale
            assert abs(hi / spectrum[-1] - 1) < 1e-11, (lam, n)
            tied = spectrum[1] - spectrum[0] < 1e-6 * spectrum.sum()
            tol = 2.0**-42 if tied else 1e-14
            assert abs(lo - spectrum[0]) < tol * spectrum.sum(), (lam, n)
    np.testing.assert_array_equal(np.asarray(jax.jit(extreme_eigvals_psd)(np.zeros((6, 6)))), 0)


def test_condition_number_to_its_promise_and_inf_when_singular():
    """cond_small against numpy's SVD on matrices of known singular values: within
    1e-14 cond² (its promise; JᵀJ squares the condition) up to 10⁵ whatever the ties at
    either end, and inf for a condition number of 10⁸ or an exactly singular matrix."""
    rng = np.random.default_rng(5)
    cond = quick_jit(jax.vmap(cond_small))
    J, want = [], []
    for c in (1.0, 3.0, 1e2, 1e3, 1e4, 1e5):
        for sv in (
            [1, 0.7, 0.5, 0.3, 0.2, 1 / c],
            [1, 1, 0.5, 0.3, 1 / c, 1 / c],
            [1] * 5 + [1 / c],
        ):
            U, V = (np.linalg.qr(rng.normal(size=(6, 6)))[0] for _ in range(2))
            J.append((U * np.asarray(sv, float)) @ V.T)
            want.append(max(sv) / min(sv))
    got = np.asarray(cond(np.stack(J)))
    ref = np.linalg.cond(np.stack(J))
    np.testing.assert_allclose(ref, want, rtol=1e-8)  # the matrices are what they say
    err = np.abs(got / ref - 1)
    assert np.all(err < 1e-14 * ref**2 + 1e-14), np.c_[ref, err][err >= 1e-14 * ref**2 + 1e-14]
    U, V = (np.linalg.qr(rng.normal(size=(6, 6)))[0] for _ in range(2))
    far = (U * np.array([1, 0.5, 0.4, 0.3, 0.2, 1e-8])) @ V.T
    flat = (U * np.array([1, 0.5, 0.4, 0.3, 0.2, 0.0])) @ V.T
    assert np.all(np.isinf(np.asarray(cond(np.stack([far, flat, np.zeros((6, 6))])))))


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
    got = np.asarray(cond(K))
    np.testing.assert_allclose(got, np.linalg.cond(K), rtol=1e-10)


def test_inverse_by_normal_equations_to_its_promise():
    """inv_normal_small against numpy's inverse on random 6×6 matrices: within 1e-15 cond²
    of the largest entry (its promise: AᵀA squares the condition), and NaN, not a number
    that looks right, for a singular matrix."""
    rng = np.random.default_rng(6)
    A = rng.normal(size=(500, 6, 6)) * rng.uniform(0.1, 10, (500, 1, 6))  # columns scaled
    got = np.asarray(quick_jit(jax.vmap(inv_normal_small))(A))
    ref = np.linalg.inv(A)
    err = np.abs(got - ref).max((1, 2)) / np.abs(ref).max((1, 2))
    c = np.linalg.cond(A)
    assert np.all(err < 1e-15 * c**2 + 1e-15), np.c_[c, err][err >= 1e-15 * c**2 + 1e-15]
    singular = A[0].copy()
    singular[:, 5] = singular[:, 4]
    assert np.isnan(np.asarray(quick_jit(inv_normal_small)(singular))).any()


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


def test_normal_inverse_derivative_is_the_closed_form_both_modes():
    """d(A⁻¹) = −A⁻¹ dA A⁻¹ (`inv_normal_small`'s rule), forward and reverse, against numpy's
    inverse and against central differences of numpy's inverse."""
    rng = np.random.default_rng(8)
    A = rng.normal(size=(6, 6)) + 3 * np.eye(6)
    dA = rng.normal(size=(6, 6))
    Ai = np.linalg.inv(A)
    want = -Ai @ dA @ Ai
    value, got = jax.jvp(inv_normal_small, (jnp.asarray(A),), (jnp.asarray(dA),))
    np.testing.assert_allclose(np.asarray(value), Ai, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-10, atol=1e-13)
    h = 1e-6
    fd = (np.linalg.inv(A + h * dA) - np.linalg.inv(A - h * dA)) / (2 * h)
    np.testing.assert_allclose(np.asarray(got), fd, rtol=1e-6, atol=1e-9)
    W = rng.normal(size=(6, 6))  # reverse: <W, dX> = <gA, dA>
    (gA,) = jax.vjp(inv_normal_small, jnp.asarray(A))[1](jnp.asarray(W))
    assert float(np.sum(np.asarray(gA) * dA)) == pytest.approx(float(np.sum(W * want)), rel=1e-10)


def test_largest_eigenvalue_derivative_is_the_eigenvector_form_both_modes():
    """dλ = vᵀ dS v for the unit eigenvector v of a simple largest eigenvalue
    (`largest_eigval_small`'s rule), forward and reverse, against numpy's eigenvector and
    against central differences of numpy's eigenvalue."""
    rng = np.random.default_rng(9)
    for n in (3, 6):
        Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
        S = (Q * np.linspace(0.2, 2.0, n)) @ Q.T
        dS = rng.normal(size=(n, n))
        dS = dS + dS.T
        v = np.linalg.eigh(S)[1][:, -1]
        want = v @ dS @ v
        lam, got = jax.jvp(largest_eigval_small, (jnp.asarray(S),), (jnp.asarray(dS),))
        assert float(lam) == pytest.approx(2.0, rel=1e-10)
        assert float(got) == pytest.approx(want, rel=1e-9)
        h = 1e-6
        top = [np.linalg.eigvalsh(S + sgn * h * dS)[-1] for sgn in (1, -1)]
        assert float(got) == pytest.approx((top[0] - top[1]) / (2 * h), rel=1e-6)
        g = np.asarray(jax.grad(largest_eigval_small)(jnp.asarray(S)))
        assert float(np.sum(g * dS)) == pytest.approx(want, rel=1e-9)
