"""Small dense linear algebra (n ≈ 6) in plain jnp, for batched per-pose kernels.

Why not `jnp.linalg`: on CPU its LAPACK custom calls split a batch over XLA's shared thread
pool and block until the pieces finish. When one compiled program holds two independent
LAPACK calls (say an LU and an SVD), both can run at once, each holding a pool thread while it
waits for the other pieces: on a 2-core machine the program then deadlocks (seen here with
jax 0.10.2 in about one run in two). These kernels are ordinary fused element-wise code, with
no custom call; at n = 6 they are as fast.
"""

import jax
import jax.numpy as jnp
from jaxtyping import ArrayLike, Float


def computed_once(x):
    """`x` unchanged (x / 1, exactly), as a division, so that XLA computes it once per kernel.

    XLA's fusion prices arithmetic as cheap and recomputes a cheap value inside every fusion
    that reads it; a division it never duplicates, so its result is written once and read
    where needed. For values that many later expressions share: the Householder
    projections of `tridiagonal_small` (recomputed each about five times), the error map's
    Jacobian rows. Not for kernels that fuse into one loop anyway (the attitude's sines and
    cosines in the pose -> command map: 5 % slower that way). The divisor is computed from
    `x`, so it is not a constant XLA could fold away (and the result is not linear in `x`:
    not for a value reverse mode must transpose)."""
    return x / (1.0 + 0.0 * x)


def lu_small(A: Float[ArrayLike, "n n"]):
    """PA = LU with partial pivoting, unrolled over the n columns. Returns (LU, perm): the
    unit-lower multipliers below the diagonal, U on and above it; `perm` the row order
    (as floats).

    Row swaps are written as one-hot arithmetic rather than indexed updates, so under `vmap`
    the whole factorisation stays element-wise (no gathers or scatters): inside the forward
    solve's Newton loop a gather of the pivot row made forward kinematics 25 % slower, though
    the factorisation alone runs 1.7× faster that way (6×6, batches of 8192)."""
    n = A.shape[0]
    rows = jnp.arange(n)
    perm = rows.astype(A.dtype)
    M = jnp.asarray(A)
    for k in range(n):
        p = jnp.argmax(jnp.where(rows >= k, jnp.abs(M[:, k]), -1.0))
        at_p = (rows == p).astype(M.dtype)
        at_k = (rows == k).astype(M.dtype)
        row_p = at_p @ M
        d = row_p - M[k]
        M = M + (at_k - at_p)[:, None] * d[None, :]
        perm_p = at_p @ perm
        perm = perm + (at_k - at_p) * (perm_p - perm[k])
        f = jnp.where(rows > k, M[:, k] / M[k, k], 0.0)
        M = M - f[:, None] * jnp.where(rows > k, M[k], 0.0)[None, :]
        M = M.at[:, k].set(jnp.where(rows > k, f, M[:, k]))
    return M, perm


def lu_solve_small(LU, perm, B: Float[ArrayLike, "n k"]) -> Float[ArrayLike, "n k"]:
    """Solve A X = B from `lu_small(A)`; linear in B (so it transposes for reverse mode).

    B's rows are permuted by index (one gather under `vmap`): the one-hot product it replaces
    was a reduction over rows that cost twice the factorisation in a 6×6 inverse; forward
    kinematics runs 15–28 % faster with the gather (paired runs, 10⁶ poses)."""
    n = LU.shape[0]
    rows = jnp.arange(n)
    X = jnp.asarray(B)[perm.astype(jnp.int32)]
    for k in range(n):
        X = X - jnp.where(rows > k, LU[:, k], 0.0)[:, None] * X[k][None, :]
    for k in range(n - 1, -1, -1):
        X = X.at[k].set(X[k] / LU[k, k])
        X = X - jnp.where(rows < k, LU[:, k], 0.0)[:, None] * X[k][None, :]
    return X


@jax.custom_jvp
def solve_small(A: Float[ArrayLike, "n n"], B: Float[ArrayLike, "n k"]) -> Float[ArrayLike, "n k"]:
    """A⁻¹ B by Gaussian elimination with partial pivoting.

    Differentiated by its rule, d(A⁻¹B) = A⁻¹ (dB − dA·X) with the factorisation reused
    (linear in the tangents, so reverse mode transposes it), not through the elimination:
    one more pair of triangular solves per tangent instead of the derivative of every
    pivoting and elimination step (fewer operations to trace, compile and run wherever a
    model differentiates a solve, e.g. the compliance effect's statics inside the forward
    solve)."""
    return lu_solve_small(*lu_small(A), B)


@solve_small.defjvp
def _solve_small_jvp(primals, tangents):
    A, B = primals
    dA, dB = tangents
    LU, perm = lu_small(A)
    X = lu_solve_small(LU, perm, B)
    return X, lu_solve_small(LU, perm, dB - dA @ X)


def inv_small(A: Float[ArrayLike, "n n"]) -> Float[ArrayLike, "n n"]:
    return solve_small(A, jnp.eye(A.shape[0], dtype=A.dtype))


def matmul_small(
    A: Float[ArrayLike, "n k"], B: Float[ArrayLike, "k ..."]
) -> Float[ArrayLike, "n ..."]:
    """A @ B for a small matrix A and a matrix or vector B, as a sum of k outer products
    (element-wise code). Under `vmap`, `A @ B` is a batched dot that XLA's CPU backend runs
    as one tiny product per batch row; this form fuses with its neighbours instead: the
    error map's kernel (condition number: 24 products of 6×6 matrices) 8.0 → 3.4 µs a pose.
    Not everywhere faster: `lu_small`'s one-hot row selection stays a dot (written out, forward
    kinematics was 20 % slower)."""
    A, B = jnp.asarray(A), jnp.asarray(B)
    if B.ndim == 1:
        return matmul_small(A, B[:, None])[:, 0]
    out = A[:, 0][:, None] * B[0][None, :]
    for k in range(1, A.shape[1]):
        out = out + A[:, k][:, None] * B[k][None, :]
    return out


def largest_eigval_small(S: Float[ArrayLike, "n n"], squarings: int = 12) -> Float[ArrayLike, ""]:
    """Largest eigenvalue of a symmetric positive semi-definite matrix: repeated squaring
    (S^(2^k), normalised by its trace) isolates the dominant eigenvector, whose Rayleigh
    quotient is the eigenvalue (error quadratic in the eigenvector's, so ~1e-9 relative or
    better unless the two largest eigenvalues differ by less than ~1 %, where any vector of
    their span gives the value to that precision anyway).

    The trace is taken before the first squaring and after every fourth: with trace 1 every
    eigenvalue is in [0, 1] and the largest ≥ 1/n, so four squarings keep it above n⁻¹⁶
    (no overflow, no underflow of what matters) and skip three passes over the batch
    (6×6: 1.8 → 1.1 µs for the condition number's two eigenvalues)."""
    M = S / jnp.trace(S)
    for i in range(squarings):
        M = matmul_small(M, M)
        if (i + 1) % 4 == 0 or i == squarings - 1:
            M = M / jnp.trace(M)
    k = jnp.argmax(jnp.sum(M**2, axis=0))
    v = M[:, k]
    return (v @ matmul_small(S, v)) / (v @ v)


def tridiagonal_small(S: Float[ArrayLike, "n n"]):
    """Householder reduction of a symmetric matrix to tridiagonal form Qᵀ S Q (same
    eigenvalues), unrolled over the n − 2 reflections. Returns (a (n,), b (n − 1,)): the
    diagonal and the off-diagonal.

    Written on scalar entries of the lower triangle (a list of lists), so that under `vmap`
    it is one element-wise expression per entry: with slices of the matrix it ran 3× slower
    (6×6, batches of 8192)."""
    n = S.shape[0]
    A = [[S[i, j] for j in range(i + 1)] for i in range(n)]  # A[i][j], j ≤ i
    a, b = [], []
    for k in range(n - 2):  # reflection I − 2 v vᵀ on rows/columns k+1.., taking x to α e₁
        x = [A[i][k] for i in range(k + 1, n)]
        alpha = -jnp.where(x[0] >= 0, 1.0, -1.0) * jnp.sqrt(sum(xi * xi for xi in x))
        v = [x[0] - alpha] + x[1:]
        norm = jnp.sqrt(sum(vi * vi for vi in v))
        # v of unit length (zero where x is): every product below stays of the size of the
        # matrix (with v unnormalised and β = 2/|v|², a nearly diagonal matrix made products of
        # 1e-17 and 1e33 that the compiled program got wrong)
        v = [vi / jnp.where(norm > 0, norm, 1.0) for vi in v]
        m = len(v)

        def entry(i, j):  # trailing block, symmetric
            return A[k + 1 + max(i, j)][k + 1 + min(i, j)]

        p = [computed_once(2.0 * sum(entry(i, j) * v[j] for j in range(m))) for i in range(m)]
        vp = sum(vi * pi for vi, pi in zip(v, p))
        w = [computed_once(pi - vp * vi) for pi, vi in zip(p, v)]
        a.append(A[k][k])
        b.append(alpha)
        for i in range(m):
            for j in range(i + 1):
                A[k + 1 + i][k + 1 + j] = entry(i, j) - v[i] * w[j] - w[i] * v[j]
    return jnp.stack(a + [A[n - 2][n - 2], A[n - 1][n - 1]]), jnp.stack(b + [A[n - 1][n - 2]])


BISECTIONS = 40
"""Steps of `largest_eigval_psd`'s bisection: the bracket starts at most 2 λ wide, so the
midpoint is within λ / 2⁴⁰ ≈ 1e-12 λ."""


def largest_eigval_psd(S: Float[ArrayLike, "n n"]) -> Float[ArrayLike, ""]:
    """Largest eigenvalue λ of a symmetric positive semi-definite matrix to ~1e-12 relative
    (rounding in the reduction aside), whatever the gap to the next one: Householder
    tridiagonalisation (`tridiagonal_small`) of S / tr S, then bisection on λ with the
    leading minors of x I − T (x > λ exactly when all are positive; three-term recurrence,
    no divisions). The bracket is [max aᵢ, max(aᵢ + |bᵢ₋₁| + |bᵢ|)] (a diagonal entry is at
    most λ; Gershgorin), at most 2 λ wide since |bᵢ| ≤ √(aᵢ aᵢ₊₁) for S ⪰ 0.

    Not differentiable (the bisection has no derivative): for maps of fixed matrices, e.g.
    the error map's condition number. The bisection is a `fori_loop` (the six-minor
    recurrence unrolled inside): written out as 40 unrolled steps, the error map's kernel
    compiled ~1.2 s slower on a small grid and ran ~20 % slower on large ones, the same
    numbers. The loop carries the bracket's lower end and width, so each step has one
    output that reads the recurrence: carrying both ends, XLA computed the recurrence once
    for each (the error map with its condition number, 2²⁰ poses, two pairs of runs:
    7.2–7.4 → 8.4–8.6×10⁵ poses/s). `largest_eigval_small` is the differentiable one
    (design criteria), by repeated squaring: slower, and only as exact as the gap allows
    (the error map's condition number that way was up to 5e-6 off numpy's at 10,000 workspace
    poses, where two singular values of a symmetric table nearly tie; this way 2e-13)."""
    S = jax.lax.stop_gradient(jnp.asarray(S))
    scale = jnp.trace(S)
    a, b = tridiagonal_small(S / jnp.where(scale > 0, scale, 1.0))
    b2, ab, zero = b * b, jnp.abs(b), jnp.zeros(1, S.dtype)
    lo = jnp.max(a)
    hi = jnp.max(a + jnp.concatenate([ab, zero]) + jnp.concatenate([zero, ab]))

    def bisect(_, carry):  # the bracket is [lo, lo + w]
        lo, w = carry
        w = 0.5 * w
        x = lo + w
        prev, minor = 1.0, x - a[0]
        above = minor > 0
        for i in range(1, a.shape[0]):
            prev, minor = minor, (x - a[i]) * minor - b2[i - 1] * prev
            above = above & (minor > 0)
        return jnp.where(above, lo, x), w

    lo, w = jax.lax.fori_loop(0, BISECTIONS, bisect, (lo, hi - lo))
    return scale * (lo + 0.5 * w)


def cond_small(J: Float[ArrayLike, "n n"], J_inv=None) -> Float[ArrayLike, ""]:
    """2-norm condition number σ_max / σ_min of a square matrix (n ≥ 2), from the largest
    eigenvalues of JᵀJ and of its inverse J⁻¹J⁻ᵀ (`largest_eigval_psd`, ~1e-11 relative
    against numpy's SVD): `J_inv` when the caller has J⁻¹, else by elimination. Not
    differentiable."""
    J = jnp.asarray(J)
    J_inv = inv_small(J) if J_inv is None else jnp.asarray(J_inv)
    pair = jnp.stack([matmul_small(J.T, J), matmul_small(J_inv, J_inv.T)])
    return jnp.sqrt(jnp.prod(jax.vmap(largest_eigval_psd)(pair)))


def cholesky_small(S: Float[ArrayLike, "n n"]) -> Float[ArrayLike, "n n"]:
    """Lower-triangular L with L Lᵀ = S for a symmetric positive definite S, unrolled over
    the n columns (element-wise code, no LAPACK call)."""
    n = S.shape[0]
    rows = jnp.arange(n)
    L = jnp.zeros_like(S)
    for k in range(n):
        d = jnp.sqrt(S[k, k] - L[k] @ L[k])
        col = (S[:, k] - L @ L[k]) / d
        L = L.at[:, k].set(jnp.where(rows > k, col, jnp.where(rows == k, d, 0.0)))
    return L


def smallest_generalized_eigval(
    K: Float[ArrayLike, "n n"], M: Float[ArrayLike, "n n"]
) -> Float[ArrayLike, ""]:
    """Smallest λ of K x = λ M x (K, M symmetric positive definite): with M = L Lᵀ it is
    1 / λ_max(Lᵀ K⁻¹ L)."""
    L = cholesky_small(M)
    return 1.0 / largest_eigval_small(L.T @ solve_small(K, L))
