"""Small dense least-squares fits of many targets at once (vmapped Levenberg-Marquardt).

A sphere or a checkerboard is a fit of 4 to 6 unknowns to a few hundred to a few thousand
points. Candidates are fitted :data:`FIT_BATCH` at a time in one vmapped, compiled call.
Shapes are static: each candidate's points are padded (or thinned) to :data:`FIT_POINTS` rows
with weight zero, and the batch to :data:`FIT_BATCH`; a call whose candidates all have fewer
points runs on the smallest of :data:`ROW_BUCKETS` that holds them, and a last batch of at most
:data:`SMALL_BATCH` candidates on that many rows, so that a few compiled programs per kind of
target serve every scan (the padded rows weigh zero: they change no sum), and a scan of small
targets does not pay for 16 candidates of 2,048 points (four 536-point checkerboards: 0.09 ->
0.01 s a call); trimming outliers between calls changes weights, never shapes.

Written here rather than with optimistix, which the guide prefers for small dense fits,
because batching is what these fits need and optimistix does it badly on the CPU: a vmapped
``optx.least_squares`` (GaussNewton or LevenbergMarquardt) runs its while loop and lineax's
QR per batch member as a loop with both branches of every ``cond``; measured 2026-11-25 on 2
busy cores for 16 checkerboard fits of 2,048 points (10 steps each): vmapped optimistix
2.5-4.8 s, optimistix under ``lax.map`` 1.9 s, one at a time 16 x 0.024-0.077 s, and this loop
0.16 s (the Jacobians are the same ``jax.jacfwd``); optimistix also compiled for 4-10 s per
shape against about 2 s. The loop is Levenberg-Marquardt with a fixed number of steps
(static shapes, no data-dependent control flow): the step ``(J^T J + mu diag(J^T J)) dx =
-J^T r`` is taken where it lowers the cost (then mu / 10) and refused otherwise (mu x 10).
Each fit returns the solution, the weighted residuals and ``J^T J`` at the solution, from
which the caller forms ``s0^2 (J^T J)^-1`` with its own redundancy.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import jit

#: Rows of every fit: candidates with more points are thinned to this many (seeded).
FIT_POINTS = 2048
#: Candidates per compiled call.
FIT_BATCH = 16
#: A last call with at most this many candidates runs on this many (module docstring).
SMALL_BATCH = 4
#: Point rows a call runs on: the smallest that holds every candidate's used rows.
ROW_BUCKETS = (256, 512, 1024, FIT_POINTS)


def pad(arrays, rng, size: int = FIT_POINTS):
    """The rows of one candidate padded (or thinned at random, ``rng``) to ``size``: the
    gathered ``arrays``, a mask of the real rows, and the indices taken."""
    n = len(arrays[0])
    idx = np.sort(rng.choice(n, size, replace=False)) if n > size else np.arange(n)
    take = np.concatenate([idx, np.zeros(size - len(idx), dtype=np.int64)])
    return [np.asarray(a)[take] for a in arrays], np.arange(size) < len(idx), idx


@functools.partial(jit, static_argnames=("residual", "max_steps"))
def _solve(residual, y0, args, max_steps):
    jac = jax.jacfwd(residual)

    def one(y, a):
        def step(_, state):
            y, mu, cost, moved = state
            r, J = residual(y, a), jac(y, a)
            N = J.T @ J
            dx = -jnp.linalg.solve(N + mu * jnp.diag(jnp.diag(N) + 1e-30), J.T @ r)
            trial = y + dx
            new = jnp.sum(residual(trial, a) ** 2)
            better = jnp.isfinite(new) & (new <= cost)
            size = jnp.max(jnp.abs(dx) / (1.0 + jnp.abs(y)))
            return (
                jnp.where(better, trial, y),
                jnp.where(better, mu / 10.0, mu * 10.0),
                jnp.where(better, new, cost),
                jnp.where(better, size, moved),
            )

        cost0 = jnp.sum(residual(y, a) ** 2)
        y, mu, cost, moved = jax.lax.fori_loop(
            0, max_steps, step, (y, jnp.asarray(1e-3), cost0, jnp.asarray(jnp.inf))
        )
        J = jac(y, a)
        ok = jnp.isfinite(cost) & jnp.all(jnp.isfinite(y)) & ((moved < 1e-6) | (mu > 1e6))
        return y, residual(y, a), J.T @ J, ok

    return jax.vmap(one)(y0, args)


def _rows(x, a: int, b: int, size: int, points: int | None):
    """Rows a..b of x, padded to ``size`` with copies of row a; with ``points``, an array with
    a point axis (axis 1 of :data:`FIT_POINTS` rows) keeps its first ``points`` rows."""
    x = np.asarray(x)
    if points is not None and x.ndim >= 2 and x.shape[1] == FIT_POINTS:
        x = x[:, :points]
    return np.concatenate([x[a:b], np.repeat(x[a : a + 1], size - (b - a), axis=0)])


def fit_batch(residual, y0, args, max_steps: int = 32, rows: int | None = None):
    """Fit every row of ``y0`` (k, p) with its ``args`` (tuple of arrays with leading axis k):
    (values (k, p), residuals (k, n), normal matrices (k, p, p), converged (k,)), as numpy.
    Runs :data:`FIT_BATCH` rows per call, the last call padded with copies of its first row
    (to :data:`SMALL_BATCH` where it holds that few). ``rows``: how many leading rows of the
    point axis (axis 1 of the arguments with :data:`FIT_POINTS` rows) any candidate uses, the
    rest weighing zero; the fits then run on the smallest of :data:`ROW_BUCKETS` that holds
    them, and the residuals have that many columns (module docstring).
    ``max_steps``: Levenberg-Marquardt steps (fixed; converged means the last step taken
    moved every unknown by less than 1e-6 of its size, or no step lowers the cost any more)."""
    y0 = np.asarray(y0, dtype=np.float64)
    points = None if rows is None else next(n for n in ROW_BUCKETS if n >= min(rows, FIT_POINTS))
    out = []
    with jax.default_device(host_device()):
        for a in range(0, len(y0), FIT_BATCH):
            b = min(len(y0), a + FIT_BATCH)
            size = SMALL_BATCH if b - a <= SMALL_BATCH else FIT_BATCH
            res = _solve(
                residual,
                jnp.asarray(_rows(y0, a, b, size, None)),
                tuple(jnp.asarray(_rows(x, a, b, size, points)) for x in args),
                max_steps,
            )
            out.append([np.asarray(o)[: b - a] for o in res])
    return tuple(np.concatenate(parts) for parts in zip(*out))


def host_device():
    """The CPU device the fits run on whatever JAX's default device (None: JAX runs without its
    CPU backend, e.g. ``JAX_PLATFORMS=cuda``; then the default). A batch of 16 fits of 2,048
    points is far too small to gain from an accelerator, whose transfers would cost more than
    the fit; and on an H200 (jax 0.11.2, CUDA 13) the compiled fit stopped with an XLA runtime
    error ("Reshape input and output shapes must be the same, got 1 -> 1x32") that the same
    program on the CPU does not raise (2026-11-27)."""
    try:
        return jax.devices("cpu")[0]
    except RuntimeError:
        return None


def covariance(residuals, normal, n_used, n_unknowns):
    """``s0^2 (J^T J)^-1`` per fit with ``s0^2 = r^T r / (n - u)``, and s0^2; NaN where the
    normal matrix is singular or there is no redundancy."""
    dof = np.asarray(n_used) - n_unknowns
    s02 = np.where(dof > 0, np.sum(residuals**2, axis=1) / np.maximum(dof, 1), np.nan)
    cov = np.full(normal.shape, np.nan)
    for i, N in enumerate(normal):
        if np.isfinite(s02[i]) and np.all(np.isfinite(N)) and np.linalg.cond(N) < 1e14:
            cov[i] = s02[i] * np.linalg.inv(N)
    return cov, s02
