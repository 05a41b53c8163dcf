"""Per-phase timing of one Gauss-Newton iteration and of the quality pass (JAX side).

Each phase of the engine is compiled on its own and timed on the inputs it sees in the
adjustment (at the approximate values): where the time of one iteration goes. The phases:

* ``linearisation``: residual rows and Jacobian blocks of every observation (``linear_rows``);
* ``assembly``: the normal-equation sums from them (grid reshapes or segment sums);
* ``reduction``: Schur elimination of the primitives (``N_pp^-1``, ``Y``, ``K``), without
  the factorisation;
* ``factorisation``: the rank-revealing Cholesky of the reduced system;
* ``back_substitution``: the reduced solve, the primitives' updates and the datum;
* ``update_size``: the convergence test's cofactor diagonal;
* ``step_cost``: ``v^T P v`` at the new estimate (the step's acceptance);
* ``quality``: the quality pass from the last linearisation (cofactors, redundancy,
  reliability).

The sum of one iteration's phases is a lower bound of an iteration inside the loop (fusion
across phases is lost here, and so is the loop's overhead); ``iteration_sum_ms`` beside the
measured ``run_s / (iterations + 1)`` shows how much the loop adds.
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp

from tlsjax._jit import jit


def _time(fn, args, repeats):
    c = jit(fn).lower(*args).compile()
    jax.block_until_ready(c(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(c(*args))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e3, c(*args)


def phase_times(spec, problem, params, options, repeats: int = 20) -> dict:
    """Median milliseconds per phase (see the module docstring) for one (spec, problem) at
    ``params``; ``problem`` as :class:`tlsjax.Adjustment` holds it (with its layouts)."""
    from tlsjax._adjustment import _families as F
    from tlsjax._adjustment import _normal as N
    from tlsjax._adjustment import _quality as Q
    from tlsjax._adjustment._linalg import rank_revealing_cholesky

    grid = F.on_grid(problem)
    out = {}
    ap_jac = N.ap_jacobians(spec, grid, params)

    def rows(pr, p, a):
        return tuple(f.linear_rows(spec, pr, p, fi, a[fi]) for fi, f in enumerate(pr.families))

    out["linearisation"], _ = _time(rows, (grid, params, ap_jac), repeats)
    lin_ms, (blocks, rows) = _time(
        lambda pr, p, a: N.linearise_rows(spec, pr, p, a), (grid, params, ap_jac), repeats
    )
    out["assembly"] = max(lin_ms - out["linearisation"], 0.0)
    Hp, Hz = N.null_space(spec, grid.families, params)
    red_ms, red = _time(
        lambda pr, b, h: N.reduce(spec, pr, b, h, jnp.asarray(0.0), options.rank_tolerance),
        (grid, blocks, Hz),
        repeats,
    )
    out["factorisation"], _ = _time(
        lambda K, fx: rank_revealing_cholesky(K, fx, options.rank_tolerance),
        (red.Ks, grid.fixed),
        repeats,
    )
    out["reduction"] = max(red_ms - out["factorisation"], 0.0)
    out["back_substitution"], (new, dps, dz) = _time(
        lambda pr, p, b, r, hp, hz: N.solve_step(spec, pr, p, b, r, hp, hz),
        (grid, params, blocks, red, Hp, Hz),
        repeats,
    )
    out["update_size"], _ = _time(
        lambda b, r, z, d: N.update_size(b, r, z, d), (blocks, red, dz, dps), repeats
    )
    # As the loop does: Gauss-Helmert weights held at the linearisation point (its rows).
    frozen = rows if any(f.frozen_cost for f in grid.families) else None
    out["step_cost"], _ = _time(
        lambda pr, p, fr: F.cost(spec, pr, p, frozen=fr), (grid, new, frozen), repeats
    )
    lin = Q.linearisation_at(spec, grid, params, options.rank_tolerance)
    out["quality"], _ = _time(
        lambda pr, g, p, li: Q.quality_from(spec, pr, g, p, li),
        (problem, grid, params, lin),
        repeats,
    )
    out["iteration_sum_ms"] = sum(v for k, v in out.items() if k != "quality")
    return {k: round(v, 4) for k, v in out.items()}
