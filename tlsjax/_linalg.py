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

# Contractions over small axes are written out as sums of elementwise products: XLA fuses them
# with their neighbours into one loop, where ``jnp.sum`` over a small axis or a tiny einsum is
# a reduction or batched-dot kernel of its own (each 10-80 us on the CPU at these shapes,
# measured; PERFORMANCE.md).
UNROLL_MAX = 8


def small_sum(x, axis: int):
    """``x.sum(axis)`` over a small static axis, as a chain of adds (of an input: a computed
    ``x`` would be materialised before it is sliced; write such sums over slices of its
    operands instead, as :func:`outer` does)."""
    terms = [lax.index_in_dim(x, i, axis, keepdims=False) for i in range(x.shape[axis])]
    return sum(terms[1:], terms[0])


def outer(a, b):
    """(..., k, i) x (..., k, j) -> (..., i, j): ``sum_k a_ki b_kj``."""
    if a.shape[-2] == 0:
        return jnp.zeros(
            jnp.broadcast_shapes(a.shape[:-2], b.shape[:-2]) + (a.shape[-1], b.shape[-1]), a.dtype
        )
    if a.shape[-2] > UNROLL_MAX:
        return jnp.sum(a[..., :, :, None] * b[..., :, None, :], axis=-3)
    return sum(a[..., k, :, None] * b[..., k, None, :] for k in range(a.shape[-2]))


def matvec_t(a, e):
    """(..., k, i), (..., k) -> (..., i): ``sum_k a_ki e_k``."""
    if a.shape[-2] == 0:
        return jnp.zeros(jnp.broadcast_shapes(a.shape[:-2], e.shape[:-1]) + a.shape[-1:], a.dtype)
    if a.shape[-2] > UNROLL_MAX:
        return jnp.sum(a * e[..., :, None], axis=-2)
    return sum(a[..., k, :] * e[..., k, None] for k in range(a.shape[-2]))


def bmm(a, b):
    """(..., i, k) x (..., k, j) -> (..., i, j), a batch of small matrix products."""
    return outer(jnp.swapaxes(a, -1, -2), b)


def mm(a, b):
    """``a[..., k] b[k, ...]`` as one matrix product over all of a's leading axes (a plain GEMM:
    no batch axes, no transposed operands)."""
    k = a.shape[-1]
    if k == 0:
        return jnp.zeros(a.shape[:-1] + b.shape[1:], jnp.result_type(a, b))
    out = a.reshape(-1, k) @ b.reshape(k, -1)
    return out.reshape(a.shape[:-1] + b.shape[1:])


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


def constrained_spd_inverse(A, E=None):
    """``E (E^T A E)^-1 E^T`` for a batch of small SPD blocks ``A[..., p, p]`` whose unknowns
    obey hard linear constraints with null-space basis ``E[..., p, q]`` (None: no constraints,
    ``A^-1``). It solves ``A dx = b`` subject to ``dx = E delta`` exactly (the bordered system of
    the constraints, eliminated), so a plane block's inverse leaves its unit normal's length
    unchanged to first order; with the Schur formulas it is the generalised inverse of the
    constrained normal equations (Koch 1999, sec. 3.4)."""
    if E is None:
        return spd_inverse(A)
    Et = jnp.swapaxes(E, -1, -2)
    return E @ spd_inverse(Et @ A @ E) @ Et


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


def estimable_cholesky_damped(A, damping, fixed, tol, n_check: int):
    """The in-order rank-revealing Cholesky of :func:`rank_revealing_cholesky` of ``A`` and
    the Cholesky of ``A + damping I`` with the same columns held (the rank is judged on the
    undamped matrix; a damped one has no new dependencies), with the last ``n_check`` columns
    (the APs) tested against *all* other columns, not only the ones before them.

    The in-order pivot of column j is ``1 - R^2`` of j regressed on the columns before it; a
    near dependency on columns *after* j stays hidden (A1 without an independent scale: the
    scale motion explains A1's column up to the other APs' corrections, which come later). On
    the unit-diagonal matrix, ``1 / (A^-1)_jj`` is ``1 - R^2`` of column j regressed on every
    other column (and, with A the scaled Schur complement, on the eliminated primitives too): a
    ratio, independent of the parameters' units and of their order. The checked column with the
    smallest such value below ``tol`` is held fixed and the matrix refactorised, until none is
    (backward elimination, at most once per checked column; in practice zero or one round).
    Returns (L, dependent, pivots, L_damped), the pivots of the checked columns being their
    ``1 - R^2`` against all others.

    The common case (no free column dependent) is one library Cholesky: with the held columns
    replaced by unit columns its squared diagonal is the in-order pivot, and as the checked
    columns come last, ``(A^-1)_jj`` of them are the squared column norms of the inverse of
    L's trailing block alone (:func:`triangular_inverse`). Only when a test fails does the
    column loop run (:func:`_estimable_loop`, a ``lax.cond``; under ``vmap`` both branches run;
    written by hand because LAPACK has no in-order rank-revealing Cholesky). Measured on the
    Chow room's 40 x 40 system: the column loops were about a third of an adjustment's
    kernels."""
    n = A.shape[0]
    free = ~fixed
    eye = jnp.eye(n, dtype=A.dtype)
    check = jnp.arange(n) >= n - n_check
    A0 = jax.lax.stop_gradient(A)
    Ah = jnp.where(free[:, None] & free[None, :], A, 0.0) + jnp.where(fixed, 1.0, 0.0) * eye
    L = jnp.linalg.cholesky(Ah)
    piv = jnp.diagonal(L) ** 2
    if n_check:
        W = triangular_inverse(jax.lax.stop_gradient(L)[n - n_check :, n - n_check :])
        q = jnp.sum(W**2, axis=0)
        r2 = jnp.concatenate([piv[: n - n_check], 1.0 / jnp.where(q > 0, q, 1.0)])
    else:
        r2 = piv
    ok = jnp.all(jnp.isfinite(L)) & jnp.all(fixed | ((piv > tol) & (r2 > tol)))

    def fast():
        damped = jnp.where(fixed, 0.0, 1.0) * eye
        Ld = lax.cond(damping > 0, lambda: jnp.linalg.cholesky(Ah + damping * damped), lambda: L)
        return L, fixed, jnp.where(check & free, r2, piv), Ld

    return lax.cond(ok, fast, lambda: _estimable_loop(A, A0, damping, fixed, tol, check))


def _estimable_loop(A, A0, damping, fixed, tol, check):
    """The backward elimination of :func:`estimable_cholesky_damped` when a column is found
    dependent: per round the in-order loop of :func:`rank_revealing_cholesky` with the columns
    held so far and the inverse's diagonal, holding the weakest checked column, until none is
    below ``tol``.

    The column loop is written once (a round per held column, the first with none added): each
    copy of it made the compiled adjustment about 0.15 s longer to compile, for a branch that
    rarely runs. The factors returned are the library Cholesky of ``A`` with the dependent
    columns replaced by unit columns, the same factor the column loop makes (to rounding),
    differentiable in ``A``."""
    n = A.shape[0]
    eye = jnp.eye(n, dtype=A.dtype)

    # Which columns to hold is a decision, not a differentiable quantity: it is taken on the
    # value of A (a while loop, which reverse mode could not transpose), and the factors
    # returned come from the differentiable factorisation with those columns held.
    def weakest(held, r2):
        free = check & ~held
        j = jnp.argmin(jnp.where(free, r2, jnp.inf))
        return j, free[j] & (r2[j] <= tol)

    def body(carry):
        held, _, _, r2, rounds = carry
        held = jnp.where(rounds >= 0, held.at[weakest(held, r2)[0]].set(True), held)
        L, dep, piv = rank_revealing_cholesky(A0, held, tol)
        q = jnp.sum(triangular_inverse(L) ** 2, axis=0)  # diag(A^-1) of the independent cols
        r2 = jnp.where(dep, 0.0, 1.0 / jnp.where(q > 0, q, 1.0))
        return held, dep, piv, r2, rounds + 1

    def cond(carry):
        held, _, _, r2, rounds = carry
        return (rounds < 0) | (weakest(held, r2)[1] & (rounds < n))

    zeros = jnp.zeros(n, dtype=A.dtype)
    init = (jnp.asarray(fixed), jnp.asarray(fixed), zeros, zeros, jnp.asarray(-1))
    held, dep, piv, r2, _ = jax.lax.while_loop(cond, body, init)
    keep = ~dep
    Ah = jnp.where(keep[:, None] & keep[None, :], A, 0.0) + jnp.where(dep, 1.0, 0.0) * eye
    L = jnp.linalg.cholesky(Ah)
    Ld = jnp.linalg.cholesky(Ah + damping * jnp.where(dep, 0.0, 1.0) * eye)
    # The pivots of the columns held, as the factorisation with them held reports them: 1 (a
    # unit column) when they are all the dependent ones, else their in-order pivots.
    piv = jnp.where(jnp.all(dep == held) & held, 1.0, piv)
    return L, dep, jnp.where(check & ~dep, r2, piv), Ld


#: Blocks of at most this many columns are inverted by :func:`triangular_inverse` with one
#: library triangular solve; larger ones are split in two.
TRIANGULAR_LEAF = 16


def triangular_inverse(L):
    """``L^-1`` of a lower-triangular ``L[..., n, n]`` by the block formula
    ``[[A, 0], [B, C]]^-1 = [[A^-1, 0], [-C^-1 B A^-1, C^-1]]``, recursively down to blocks of
    at most :data:`TRIANGULAR_LEAF` columns, each one LAPACK triangular solve.

    Written by hand because XLA's CPU triangular solve with a matrix right-hand side calls
    OpenBLAS's ``trsm``, which runs multithreaded from about 32 columns on, and its threads
    spin on a shared 2-core machine (measured at 40 x 40: 15 us alone, 1.4-7.9 ms under
    load); a ``fori_loop`` over rows costs several kernels per row, and an unrolled
    elementwise inverse one kernel per entry (XLA does not fuse scalar chains). This is three
    solves and four matrix products at n = 40."""
    n = L.shape[-1]
    if n <= TRIANGULAR_LEAF:
        eye = jnp.broadcast_to(jnp.eye(n, dtype=L.dtype), L.shape)
        return lax.linalg.triangular_solve(L, eye, left_side=True, lower=True)
    half = (n + 1) // 2
    h = (half + TRIANGULAR_LEAF - 1) // TRIANGULAR_LEAF * TRIANGULAR_LEAF  # whole leaves
    Ai = triangular_inverse(L[..., :h, :h])
    Ci = triangular_inverse(L[..., h:, h:])
    low = -(Ci @ (L[..., h:, :h] @ Ai))
    top = jnp.concatenate([Ai, jnp.zeros(L.shape[:-2] + (h, n - h), L.dtype)], axis=-1)
    return jnp.concatenate([top, jnp.concatenate([low, Ci], axis=-1)], axis=-2)


def small_spd_solve(A, B):
    """``A^-1 B`` for one small SPD matrix (the datum's d x d normal matrix) by LAPACK's
    Cholesky and two triangular solves: seven kernels, where an LU solve runs a pivot loop
    and an unrolled inverse one kernel per entry."""
    return jax.scipy.linalg.cho_solve((jnp.linalg.cholesky(A), True), B)


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
    """``(L L^T)^-1`` from the Cholesky factor (:func:`triangular_inverse`)."""
    Li = triangular_inverse(L)
    return Li.T @ Li
