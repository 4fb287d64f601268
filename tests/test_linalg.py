import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxtable._linalg import cond_small, inv_small, solve_small


def test_small_kernels_match_numpy():
    rng = np.random.default_rng(0)
    for _ in range(20):
        A = rng.normal(size=(6, 6))
        B = rng.normal(size=(6, 4))
        np.testing.assert_allclose(
            np.asarray(solve_small(A, B)), np.linalg.solve(A, B), rtol=1e-10, atol=1e-12
        )
        np.testing.assert_allclose(np.asarray(inv_small(A)) @ A, np.eye(6), atol=1e-10)
        assert abs(float(cond_small(A)) / np.linalg.cond(A) - 1) < 1e-8
    # a pivot is needed: zero leading entry
    A = np.array([[0.0, 1.0], [1.0, 0.0]])
    np.testing.assert_allclose(np.asarray(solve_small(A, np.eye(2))), A)


def test_solve_is_linear_in_b_for_reverse_mode():
    A = jnp.asarray(np.random.default_rng(1).normal(size=(6, 6)))
    b = jnp.arange(6.0)
    g = jax.grad(lambda v: jnp.sum(solve_small(A, v[:, None]) ** 2))(b)
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
