"""Small dense linear algebra that vectorises well under vmap.

Batched LAPACK calls run as loops on CPU (PERFORMANCE.md), so the tiny SPD blocks of the
eliminated primitives are inverted with an unrolled Cholesky written in elementwise
arithmetic, and the reduced system is factorised by an in-order, rank-revealing Cholesky that
also tells which parameters the network cannot determine.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax


def spd_inverse(A):
    """Inverse of a batch of small SPD matrices ``A[..., p, p]`` by unrolled Cholesky."""
    p = A.shape[-1]
    L = [[None] * p for _ in range(p)]
    for j in range(p):
        s = A[..., j, j] - sum(L[j][k] * L[j][k] for k in range(j))
        L[j][j] = jnp.sqrt(s)
        for i in range(j + 1, p):
            L[i][j] = (A[..., i, j] - sum(L[i][k] * L[j][k] for k in range(j))) / L[j][j]
    # Inverse of L by forward substitution, column by column.
    Li = [[None] * p for _ in range(p)]
    for j in range(p):
        for i in range(p):
            if i < j:
                Li[i][j] = jnp.zeros_like(L[0][0])
            elif i == j:
                Li[i][j] = 1.0 / L[i][i]
            else:
                Li[i][j] = -sum(L[i][k] * Li[k][j] for k in range(j, i)) / L[i][i]
    # A^-1 = L^-T L^-1
    rows = []
    for i in range(p):
        rows.append(
            jnp.stack(
                [sum(Li[k][i] * Li[k][j] for k in range(max(i, j), p)) for j in range(p)], axis=-1
            )
        )
    return jnp.stack(rows, axis=-2)


def rank_revealing_cholesky(A, fixed, tol):
    """In-order Cholesky of a unit-diagonal SPD(-ish) matrix that skips dependent columns.

    Column j is *dependent* when its pivot, ``1 - R^2`` of j regressed on the independent
    columns before it, is below ``tol``, or when ``fixed[j]``. A dependent column gets a unit
    column in L and no update, so solving with L fixes that parameter (its right-hand side must
    be zeroed). Returns (L, dependent, pivots).
    """
    n = A.shape[0]
    idx = jnp.arange(n)

    def body(j, carry):
        A, L, dep, piv = carry
        d = A[j, j]
        is_dep = fixed[j] | (d <= tol)
        col = A[:, j] / jnp.sqrt(jnp.where(is_dep, 1.0, d))
        col = jnp.where(idx > j, col, 0.0)
        col = jnp.where(is_dep, 0.0, col)
        col = col.at[j].set(jnp.where(is_dep, 1.0, jnp.sqrt(jnp.maximum(d, 0.0))))
        A = A - jnp.where(is_dep, 0.0, 1.0) * (col[:, None] * col[None, :])
        # A dependent parameter is removed: its row in the earlier columns must go too, or the
        # triangular solves would couple it back in.
        L = jnp.where(is_dep, L.at[j, :].set(0.0), L)
        return A, L.at[:, j].set(col), dep.at[j].set(is_dep), piv.at[j].set(d)

    init = (A, jnp.zeros_like(A), jnp.zeros(n, dtype=bool), jnp.zeros(n, dtype=A.dtype))
    _, L, dep, piv = lax.fori_loop(0, n, body, init)
    return L, dep, piv


def rank_revealing_cholesky_damped(A, damping, fixed, tol):
    """:func:`rank_revealing_cholesky` of ``A`` and the Cholesky of ``A + damping I`` with the
    same columns held (the rank is judged on the undamped matrix; a damped one has no new
    dependencies). Returns (L, dependent, pivots, L_damped).

    Written by hand because LAPACK has no in-order rank-revealing Cholesky, but the common
    case needs none: with the held columns replaced by unit columns, LAPACK's Cholesky
    (``potrf``) gives the same factor, and its squared diagonal is the same in-order pivot
    ``1 - R^2`` as long as no free column is dependent. That case (every pivot above ``tol``)
    takes two library calls; otherwise the column loop of :func:`_rank_revealing_loop` runs
    (measured on the 40 x 40 reduced system of the Chow room: 0.01-0.03 ms against 0.06-0.25 ms
    for the loop). Under ``vmap`` both branches run.
    """
    n = A.shape[0]
    free = ~fixed
    eye = jnp.eye(n, dtype=A.dtype)
    Ah = jnp.where(free[:, None] & free[None, :], A, 0.0) + jnp.where(fixed, 1.0, 0.0) * eye
    L = jnp.linalg.cholesky(Ah)
    piv = jnp.diagonal(L) ** 2
    ok = jnp.all(jnp.isfinite(L)) & jnp.all(fixed | (piv > tol))

    def fast():
        Ld = jnp.linalg.cholesky(Ah + damping * jnp.where(fixed, 0.0, 1.0) * eye)
        return L, fixed, piv, Ld

    return lax.cond(ok, fast, lambda: _rank_revealing_loop(A, damping, fixed, tol))


def _rank_revealing_loop(A, damping, fixed, tol):
    """The column loop behind :func:`rank_revealing_cholesky_damped`: both factors in one
    ``fori_loop`` (under ``vmap`` a ``lax.cond`` between two loops would run both)."""
    n = A.shape[0]
    idx = jnp.arange(n)

    def col(A, j, is_dep):
        d = A[j, j]
        c = A[:, j] / jnp.sqrt(jnp.where(is_dep, 1.0, d))
        c = jnp.where((idx > j) & ~is_dep, c, 0.0)
        return c.at[j].set(jnp.where(is_dep, 1.0, jnp.sqrt(jnp.maximum(d, 0.0))))

    def body(j, carry):
        A, Ad, L, Ld, dep, piv = carry
        d = A[j, j]
        is_dep = fixed[j] | (d <= tol)
        c, cd = col(A, j, is_dep), col(Ad, j, is_dep)
        keep = jnp.where(is_dep, 0.0, 1.0)
        A = A - keep * (c[:, None] * c[None, :])
        Ad = Ad - keep * (cd[:, None] * cd[None, :])
        L = jnp.where(is_dep, L.at[j, :].set(0.0), L).at[:, j].set(c)
        Ld = jnp.where(is_dep, Ld.at[j, :].set(0.0), Ld).at[:, j].set(cd)
        return A, Ad, L, Ld, dep.at[j].set(is_dep), piv.at[j].set(d)

    Ad = A + damping * jnp.eye(n, dtype=A.dtype)
    zero = jnp.zeros_like(A)
    init = (A, Ad, zero, zero, jnp.zeros(n, dtype=bool), jnp.zeros(n, dtype=A.dtype))
    _, _, L, Ld, dep, piv = lax.fori_loop(0, n, body, init)
    return L, dep, piv, Ld


def forward_substitution(L, B):
    """``L^-1 B`` for lower-triangular L, row by row in a ``fori_loop``.

    XLA's CPU triangular solve with a *matrix* right-hand side falls off a cliff at r >= 40
    (measured here: 0.01 ms for r = 28, 7.9 ms for r = 40..64); this loop takes 0.02-0.07 ms
    and gives the same numbers. Vector right-hand sides do not have the problem.
    """

    def body(i, X):
        return X.at[i].set((B[i] - L[i] @ X) / L[i, i])

    return lax.fori_loop(0, L.shape[0], body, jnp.zeros_like(B))


def cholesky_solve(L, b):
    y = jax.scipy.linalg.solve_triangular(L, b, lower=True)
    return jax.scipy.linalg.solve_triangular(L.T, y, lower=False)


def cholesky_inverse(L):
    Li = forward_substitution(L, jnp.eye(L.shape[0], dtype=L.dtype))
    return Li.T @ Li
