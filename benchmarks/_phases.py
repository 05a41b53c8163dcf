"""Per-phase timing of one Gauss-Newton iteration and of the quality pass (JAX side).

Each phase of the engine is compiled on its own and timed on the inputs it sees in the
adjustment (at the approximate values): where the time of one iteration goes. The phases:

* ``linearisation``: residual rows and Jacobian blocks of every observation (``linear_rows``);
* ``assembly``: the normal-equation sums from them (grid reshapes or segment sums);
* ``reduction``: Schur elimination of the primitives (``N_pp^-1``, ``Y``, ``K``), without
  the factorisation;
* ``factorisation``: the rank-revealing Cholesky of the reduced system;
* ``back_substitution``: the reduced solve, the primitives' updates and the datum;
* ``step_cost``: ``v^T P v`` at the new estimate (the step's acceptance);
* ``quality``: the quality pass from the last linearisation (cofactors, redundancy,
  reliability).

The sum of one iteration's phases is not the time of an iteration inside the loop: each phase
here pays the dispatch of one compiled call (about 0.05 ms), which the loop does not, and loses
the fusion across phases. ``iteration_sum_ms`` beside the measured ``run_s / (iterations + 1)``
shows the difference (2026-11-24, 4-AP Chow room: 1.17 against 0.67 ms).

:func:`arithmetic` puts the work beside the time: XLA's cost analysis of each phase's
compiled program (floating-point operations, and bytes its kernels read and write), summed
over the passes of one run, and the machine's dense float64 matrix-product rate measured in
the same process. A loop body counts once in XLA's cost analysis, so the per-column loops of
the rank-revealing factorisation (about r^3/3 flops for r reduced unknowns) are under-counted:
at r = 40 to 60, a few ten thousand flops per pass.
"""

from __future__ import annotations

import statistics
import time

import jax
import jax.numpy as jnp

from tlsjax._jit import jit


def _cost(compiled) -> tuple[float, float]:
    """(flops, bytes accessed) of a compiled program by XLA's cost analysis."""
    d = compiled.cost_analysis()
    d = d[0] if isinstance(d, list) else d
    return float(d.get("flops", 0.0)), float(d.get("bytes accessed", 0.0))


def _time(fn, args, repeats, costs, name):
    c = jit(fn).lower(*args).compile()
    costs[name] = _cost(c)
    jax.block_until_ready(c(*args))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(c(*args))
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts) * 1e3, c(*args)


def phase_times(spec, problem, params, options, repeats: int = 20, costs: dict | None = None):
    """Median milliseconds per phase (see the module docstring) for one (spec, problem) at
    ``params``; ``problem`` as :class:`tlsjax.Adjustment` holds it (with its layouts).
    ``costs``: a dict to fill with each phase's (flops, bytes accessed), for :func:`arithmetic`."""
    from tlsjax._adjustment import _families as F
    from tlsjax._adjustment import _normal as N
    from tlsjax._adjustment import _quality as Q
    from tlsjax._linalg import estimable_cholesky_damped

    grid = F.on_grid(problem)
    out, raw = {}, {}
    ap_jac = N.ap_jacobians(spec, grid, params)

    def rows(pr, p, a):
        return tuple(f.linear_rows(spec, pr, p, fi, a[fi]) for fi, f in enumerate(pr.families))

    out["linearisation"], _ = _time(rows, (grid, params, ap_jac), repeats, raw, "linearisation")
    lin_ms, (blocks, rows) = _time(
        lambda pr, p, a: N.linearise_rows(spec, pr, p, a),
        (grid, params, ap_jac),
        repeats,
        raw,
        "linearise_rows",
    )
    out["assembly"] = max(lin_ms - out["linearisation"], 0.0)
    Hp, Hz = N.null_space(spec, grid.families, params)
    red_ms, red = _time(
        lambda pr, b, h: N.reduce(spec, pr, b, h, jnp.asarray(0.0), options.rank_tolerance),
        (grid, blocks, Hz),
        repeats,
        raw,
        "reduce",
    )
    # What the engine runs: the library Cholesky and the AP test, the column loop only when a
    # column is dependent (:func:`tlsjax._linalg.estimable_cholesky_damped`).
    out["factorisation"], _ = _time(
        lambda K, fx: estimable_cholesky_damped(
            K, jnp.asarray(0.0), fx, options.rank_tolerance, spec.n_aps
        ),
        (red.Ks, grid.fixed),
        repeats,
        raw,
        "factorisation",
    )
    out["reduction"] = max(red_ms - out["factorisation"], 0.0)
    out["back_substitution"], (new, _, _) = _time(
        lambda pr, p, b, r, hp, hz: N.solve_step(spec, pr, p, b, r, hp, hz),
        (grid, params, blocks, red, Hp, Hz),
        repeats,
        raw,
        "back_substitution",
    )
    # As the loop does: v^T P v with one Gauss-Helmert update of the residuals (planes).
    out["step_cost"], _ = _time(
        lambda pr, p, st: F.cost_and_state(spec, pr, p, st),
        (grid, new, F.initial_state(grid)),
        repeats,
        raw,
        "step_cost",
    )
    lin = Q.linearisation_at(spec, grid, params, options.rank_tolerance)
    out["quality"], _ = _time(
        lambda pr, g, p, li: Q.quality_from(spec, pr, g, p, li),
        (problem, grid, params, lin),
        repeats,
        raw,
        "quality",
    )
    out["iteration_sum_ms"] = sum(v for k, v in out.items() if k != "quality")
    if costs is not None:
        # The same split as the times: assembly = linearise_rows - rows, reduction = reduce -
        # factorisation.
        sub = lambda a, b: tuple(max(x - y, 0.0) for x, y in zip(raw[a], raw[b]))
        costs.update({k: v for k, v in raw.items() if k not in ("linearise_rows", "reduce")})
        costs["assembly"] = sub("linearise_rows", "linearisation")
        costs["reduction"] = sub("reduce", "factorisation")
    return {k: round(v, 4) for k, v in out.items()}


#: Phases of every pass of the loop (the last one included) and of every step.
PASS_PHASES = ("linearisation", "assembly", "reduction", "factorisation")
STEP_PHASES = ("back_substitution", "step_cost")


def matmul_gflops(n: int = 1000, repeats: int = 10) -> float:
    """The machine's dense float64 matrix-product rate in GFlop/s (XLA's dot, on the cores
    the process has): what the CPU reaches on large, regular work."""
    a = jnp.ones((n, n)) * 0.5
    c = jit(lambda x: x @ x).lower(a).compile()
    jax.block_until_ready(c(a))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(c(a))
        ts.append(time.perf_counter() - t0)
    return 2.0 * n**3 / min(ts) / 1e9


def arithmetic(costs: dict, passes: int, steps: int, seconds: float, gflops: float, quality=True):
    """Work of ``passes`` linearisations with their reduction, ``steps`` solves with their
    cost and (``quality``) one quality pass, from :func:`phase_times`' ``costs``, beside the
    measured ``seconds``: the achieved GFlop/s, and the time the same flops take at the
    matrix-product rate ``gflops``."""
    total = lambda i: (
        passes * sum(costs[k][i] for k in PASS_PHASES)
        + steps * sum(costs[k][i] for k in STEP_PHASES)
        + (costs["quality"][i] if quality else 0.0)
    )
    flops, nbytes = total(0), total(1)
    return {
        "per_phase": {
            k: {"mflop": round(f / 1e6, 4), "mb_accessed": round(b / 1e6, 4)}
            for k, (f, b) in costs.items()
        },
        "passes": passes,
        "steps": steps,
        "quality_pass": quality,
        "mflop": round(flops / 1e6, 3),
        "mb_accessed": round(nbytes / 1e6, 3),
        "seconds": seconds,
        "achieved_gflops": round(flops / seconds / 1e9, 3),
        "matmul_gflops": round(gflops, 2),
        "ms_at_matmul_rate": round(1e3 * flops / (gflops * 1e9), 4),
        "method": "XLA cost analysis per phase (a loop body counts once: the factorisation's "
        "per-column loops are under-counted), summed over the passes",
    }
