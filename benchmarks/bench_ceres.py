"""tlsjax against its peers, a C++ program on Ceres Solver and scipy ``least_squares``, side by
side in one run, in alternating rounds.

Usage::

    benchmarks/setup_ceres                     # once: installs libceres-dev, builds the peer
    python benchmarks/bench_ceres.py           # writes benchmarks/results/ceres.json
    python benchmarks/bench_ceres.py --rounds 7 --repeats 30 --runs 1000 --cases physical

The peer (``benchmarks/ceres/peer.cc``, built by ``setup_ceres`` or here on first use; skipped
with a message where it cannot be built) is what a bundle-adjustment engineer would write:
one AutoDiffCostFunction per observation, DENSE_SCHUR with the targets eliminated first,
Levenberg-Marquardt from a huge trust radius, tolerances 1e-10, the problem built once and
re-solved, the AP covariance from the Schur complement. It reads the data this script writes
(``benchmarks/_ceres.py``), so both solve the same observations from the same start.

Cases (the simulated Chow et al. 2013 room: 120 targets, 6 scans, 4 levelled and 2 rolled by
+-45 deg, hybrid scanner, 2,168 observations; ``tj.simulate(seed=0)``), per AP set:

* **one adjustment with the AP covariance**: the peer on 1 thread from tlsjax's approximate
  values (each solve timed with its covariance; the problem built once) against
  ``adj.solve()`` (the compiled adjustment with its quality and the result's assembly), the
  compiled call alone (``adj.run()``), and the public ``tj.calibrate`` (plan, approximate
  values, compiled call, result) on the same network again (``calibrate``: its plan and
  approximate values memoised per network's data) and on a new network object with the same
  data (``calibrate_first``: both computed);
* **Monte Carlo**: ``--runs`` realisations of tlsjax's simulator (the same noisy observations
  and levelling readings for both), each started at the truth: the peer looped over them on 2
  threads (one Problem per thread), against ``tj.monte_carlo`` on the JAX devices (one per
  core on the CPU; the compile reported apart).

The scipy peer (``bench_point.ScipyPeer``: trf with the exact sparse Jacobian pattern,
tolerances 1e-10, S1's Xs, Ys, Zs, kappa held; the APs do not depend on the datum) solves the
single adjustment from the same start in the same rounds; for the Monte Carlo only its time per
adjustment times the runs is given (an estimate, marked as such).

tlsjax's time is reported by phase: compile (trace and lower apart from XLA's compile, and the
first ``adj.solve()``, which compiles the call ``calibrate`` uses), the public ``calibrate``
split into its plan, approximate values and compiled solve with the result's assembly, and one
pass of the compiled adjustment split into its kernels (``_phases.phase_times``).

Where the peer cannot be built (no Ceres, no compiler), the JSON says why under ``ceres`` and
every case runs without it (``"ceres": {"skipped": ...}``), scipy and tlsjax still measured.

**Quiet machine only.** A ratio measured while other processes compete for the cores says
nothing (peers and tlsjax suffer unequally). Before every round the one-minute load average
must be at most ``--max-load`` (default 1.25 per core: 2.5 on 2 cores); while it is higher the
benchmark says so and waits (``--wait`` seconds in all, default 900), and when the machine does
not get quiet it stops with exit code 3 and writes no ratio. Each round records the load
average before it and the share of the cores that other processes used during it.

**The command line, in new processes**: ``tlsjax calibrate`` of the demo room (the README's
command, without plots) with an empty compilation cache and again (re-run), and ``import
tlsjax``, each the wall time of a new process (``cli`` in the JSON).

Rounds alternate the sides (Ceres, scipy, tlsjax, ...), so all see the same load of this
shared machine; medians over all rounds. The JSON records the date, the machine, the jax version, the JAX
device, the load average of every round, the ratios (peer time / tlsjax time) and the checks that both
reached the same estimates (APs in tlsjax's sigmas, sigmas, s0^2, iterations).
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import os
import sys
import tempfile
import time
from pathlib import Path


def _host_devices():
    """One JAX CPU device per core unless ``--devices`` says otherwise (read at backend start)."""
    from tlsjax._cli._common import available_cpus, use_host_devices

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--devices", type=int, default=available_cpus())
    use_host_devices(p.parse_known_args()[0].devices)


_host_devices()

import jax  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
import _ceres  # noqa: E402
from _common import loadavg, stats, write_results  # noqa: E402
from _phases import phase_times  # noqa: E402
from bench_point import ScipyPeer, machine_info  # noqa: E402

import tlsjax as tj  # noqa: E402
from tlsjax._adjustment._calibrate import _run  # noqa: E402
from tlsjax._simulation._montecarlo import (  # noqa: E402
    MonteCarloOptions,
    _draw_many,
    _simulator,
    monte_carlo,
)

CASES = {"physical": "A0 B6 B7 C0", "chow2013-noscale": "chow2013-noscale"}


def _uptime():
    import subprocess

    try:
        return subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    except OSError:
        return None


class NotQuiet(RuntimeError):
    """The machine did not get quiet enough to measure a ratio."""


def _cpu_busy() -> float | None:
    """CPU seconds all processes of the machine have used (``/proc/stat``), or None."""
    try:
        with open("/proc/stat") as f:
            fields = [float(x) for x in f.readline().split()[1:]]
    except OSError:
        return None
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0.0)
    return (sum(fields) - idle) / os.sysconf("SC_CLK_TCK")


def _own_cpu() -> float:
    import resource

    me, kids = (
        resource.getrusage(resource.RUSAGE_SELF),
        resource.getrusage(resource.RUSAGE_CHILDREN),
    )
    return me.ru_utime + me.ru_stime + kids.ru_utime + kids.ru_stime


class Quiet:
    """The load guard: :meth:`wait` before a round (the one-minute load average at most
    ``max_load``, waiting up to ``budget`` seconds in all, else :class:`NotQuiet`), and
    :meth:`round` as a context that records the load before it and the share of the machine's
    cores that other processes used during it."""

    def __init__(self, max_load: float, budget: float):
        self.max_load, self.budget, self.waited = max_load, budget, 0.0
        self.rounds: list[dict] = []

    def wait(self) -> float:
        while True:
            load = os.getloadavg()[0]
            if load <= self.max_load:
                return load
            if self.waited >= self.budget:
                raise NotQuiet(
                    f"load average {load:.2f} above {self.max_load:.2f} for {self.waited:.0f} s: "
                    "no ratio is written (rerun on a quiet machine, or raise --wait)"
                )
            print(f"# load average {load:.2f} > {self.max_load:.2f}: waiting", file=sys.stderr)
            time.sleep(30.0)
            self.waited += 30.0

    @contextlib.contextmanager
    def round(self):
        load = self.wait()
        busy0, own0, t0 = _cpu_busy(), _own_cpu(), time.perf_counter()
        yield
        wall = time.perf_counter() - t0
        entry = {"loadavg_before": load, "wall_s": wall}
        busy1 = _cpu_busy()
        if busy0 is not None and busy1 is not None:
            others = max(busy1 - busy0 - (_own_cpu() - own0), 0.0)
            entry["others_cpu_share"] = others / (wall * (os.cpu_count() or 1))
        self.rounds.append(entry)


def _cli_times(tmp: str) -> dict:
    """Wall time of ``import tlsjax`` and of ``tlsjax calibrate`` of the demo room in new
    processes: with an empty compilation cache (first) and again (re-run)."""
    import subprocess

    env = dict(os.environ, TLSJAX_CACHE_DIR=os.path.join(tmp, "cache"), JAX_PLATFORMS="cpu")
    # As a user's Python runs: bytecode written and read (a sandbox that sets
    # PYTHONDONTWRITEBYTECODE compiles tlsjax's 200 modules from source on every import).
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    py = sys.executable
    obs, scans = os.path.join(tmp, "observations.csv"), os.path.join(tmp, "scans.csv")
    script = os.path.join(os.path.dirname(py), "tlsjax")  # the console script users run
    tool = (
        [script]
        if os.path.exists(script)
        else [py, "-c", "from tlsjax._cli import console; console()"]
    )
    # The demo room (tlsjax demo): seed 0, two scans rolled, the 23-term model in the data.
    subprocess.run(
        [*tool, "simulate", "--out", obs, "--scans-out", scans, "--aps", "chow2013-noscale"],
        env=env, check=True, capture_output=True,
    )  # fmt: skip
    argv = [*tool, "calibrate", obs, "--scans", scans, "--aps", "chow2013-noscale"]
    argv += ["--json", os.path.join(tmp, "cal.json"), "--quiet"]

    def wall(cmd):
        t = time.perf_counter()
        subprocess.run(cmd, env=env, check=True, capture_output=True)
        return time.perf_counter() - t

    out = {
        "command": "tlsjax calibrate observations.csv --scans scans.csv --aps chow2013-noscale "
        "--json cal.json --quiet (the demo room: tlsjax simulate --aps chow2013-noscale)"
    }
    wall([py, "-c", "import tlsjax"])  # writes the bytecode of a fresh checkout
    out["import_tlsjax_s"] = min(wall([py, "-c", "import tlsjax"]) for _ in range(3))
    out["calibrate_first_s"] = wall(argv)
    out["calibrate_rerun_s"] = [wall(argv) for _ in range(3)]
    return out


def _median(xs):
    return float(np.median(xs)) if len(xs) else float("nan")


def _compile_phases(adj, opts) -> dict:
    """Trace and lower, and XLA's compile, of the compiled adjustment (ahead of time)."""
    plan = adj.plan
    t0 = time.perf_counter()
    lowered = _run.lower(plan.spec, plan.problem, adj.initial, opts.arrays(), opts.full_covariance)
    t1 = time.perf_counter()
    lowered.compile()
    return {"trace_and_lower_s": t1 - t0, "xla_compile_s": time.perf_counter() - t1}


def _calibrate_phases(net, model, opts) -> dict:
    """The public calibrate's phases on a network object met for the first time (its plan and
    approximate values not yet memoised): plan, approximate values, compiled solve and result."""
    net = dataclasses.replace(net)  # the same data in a new object: nothing memoised
    t0 = time.perf_counter()
    adj = tj.analyze(net, model, opts)
    t1 = time.perf_counter()
    jax.block_until_ready(adj.initial)
    t2 = time.perf_counter()
    adj.solve()
    t3 = time.perf_counter()
    return {"plan": t1 - t0, "approximate_values": t2 - t1, "solve_and_result": t3 - t2}


def _scipy(net, scanner, start, repeats) -> tuple[list, object, object]:
    """The scipy peer from the same start: wall times, solution, peer."""
    peer = ScipyPeer(net, scanner, fixed_scan=0)
    peer.prepare()
    kw = dict(ftol=1e-10, xtol=1e-10, gtol=1e-10, tr_options=dict(atol=1e-12, btol=1e-12))
    times, sol = [], None
    for _ in range(repeats):
        t = time.perf_counter()
        sol = peer.solve(start[0], start[1], max_nfev=1000, **kw)
        times.append(time.perf_counter() - t)
    return times, sol, peer


def single(binary, net, model, args, tmp) -> dict:
    """One adjustment with the AP covariance: the peers (Ceres on 1 thread, scipy) and tlsjax,
    alternately; without ``binary`` scipy and tlsjax only."""
    scanner = model.scanner
    opts = tj.SolverOptions(full_covariance=False)
    adj = tj.analyze(net, model, opts)
    p0 = adj.initial
    targets = np.zeros((len(net.targets), 3))
    targets[adj.plan.family_targets[0][:, 0]] = np.asarray(p0.prims[0])
    problem = os.path.join(tmp, "single.bin")
    start = (targets, np.asarray(p0.eops), np.zeros(len(scanner.aps)))
    obs, lev = net.observations[None], net.levelling[None]
    if binary is not None:
        _ceres.write_problem(problem, net, scanner, start, obs, lev)
    t0 = time.perf_counter()
    res = adj.solve()  # the first call compiles
    compile_s = time.perf_counter() - t0
    compile_phases = _compile_phases(adj, opts)
    times = {k: [] for k in ("ceres", "scipy", "solve", "run", "calibrate", "calibrate_first")}
    phases = {"plan": [], "approximate_values": [], "solve_and_result": []}
    got = {}

    def one_round():
        got["peer"] = None
        if binary is not None:
            got["peer"] = _ceres.run(binary, "single", problem, repeats=args.repeats, threads=1)
            times["ceres"] += got["peer"]["wall_s"]
        t_sc, got["sol"], got["sc_peer"] = _scipy(net, scanner, start, args.scipy_repeats)
        times["scipy"] += t_sc
        for k, v in _calibrate_phases(net, model, opts).items():
            phases[k].append(v)
        for _ in range(args.repeats):
            t = time.perf_counter()
            got["res"] = adj.solve()
            times["solve"].append(time.perf_counter() - t)
            t = time.perf_counter()
            jax.block_until_ready(adj.run())
            times["run"].append(time.perf_counter() - t)
        for _ in range(max(args.repeats // 4, 1)):
            t = time.perf_counter()
            tj.calibrate(net, model, opts)
            times["calibrate"].append(time.perf_counter() - t)
            # The first calibration of a network object: its plan and approximate values
            # computed (a repeated one finds them memoised per network's data).
            fresh = dataclasses.replace(net)
            t = time.perf_counter()
            tj.calibrate(fresh, model, opts)
            times["calibrate_first"].append(time.perf_counter() - t)

    for _ in range(args.rounds):
        with args.quiet.round():
            one_round()
    loads = args.quiet.rounds[-args.rounds :]
    peer, sol, sc_peer, res = got["peer"], got["sol"], got["sc_peer"], got["res"]
    med = {k: _median(v) for k, v in times.items()}
    _, _, ap_sc = sc_peer.unpack(sol.x, start[1])
    costs = {}
    out = {
        "times_s": {k: stats(v) for k, v in times.items() if v},
        "tlsjax_compile_s": compile_s,
        "tlsjax_compile_phases_s": compile_phases,
        "calibrate_phases_s": {k: stats(v) for k, v in phases.items()},
        "pass_phases_ms": phase_times(
            adj.plan.spec, adj.plan.problem, p0, opts.arrays(), 20, costs
        ),
        "ratio_scipy_over_solve": med["scipy"] / med["solve"],
        "ratio_calibrate_over_solve": med["calibrate"] / med["solve"],
        "ratio_calibrate_first_over_solve": med["calibrate_first"] / med["solve"],
        "iterations": {"tlsjax": int(res.iterations), "scipy_nfev": int(sol.nfev)},
        "checks": {
            "max_ap_diff_sigma_scipy": float(np.max(np.abs(ap_sc - res.ap_values) / res.ap_sigmas)),
            "scipy_status": int(sol.status),
            "s0sq_tlsjax": float(res.sigma0**2),
        },
        "loadavg": loads,
    }
    if peer is None:
        out["ceres"] = {"skipped": "the peer was not built (see the top-level ceres entry)"}
        return out
    last = peer["results"][-1]
    cov = np.asarray(last["ap_covariance"]).reshape(len(scanner.aps), -1)
    sig_c = np.sqrt(np.diag(cov))
    out["ratio_ceres_over_solve"] = med["ceres"] / med["solve"]
    out["ratio_ceres_over_run"] = med["ceres"] / med["run"]
    out["iterations"].update(
        ceres_iterations=last["iterations"], ceres_linear_solves=last["linear_solves"]
    )
    out["checks"].update(
        max_ap_diff_sigma=float(np.max(np.abs(last["aps"] - res.ap_values) / res.ap_sigmas)),
        max_ap_sigma_ratio_minus_1=float(np.max(np.abs(sig_c / res.ap_sigmas - 1))),
        s0sq_ceres=last["s0sq"],
        ceres_converged=bool(last["converged"]),
    )
    return out


def montecarlo(binary, sim, model, args, tmp, scipy_single_s: float) -> dict:
    """Monte Carlo: the peer on 2 threads and ``tj.monte_carlo``, alternately, same draws;
    scipy as an estimate from its single adjustment (``scipy_single_s``)."""
    scanner = model.scanner
    truth = sim.truth()
    net = truth.network
    draws = _draw_many(_simulator(truth, None), np.int64(args.seed), jax.numpy.arange(args.runs))
    l_t, _, lev, _, _, true_aps = (np.asarray(a) for a in draws)
    true = dict(zip(sim.scanner.aps, np.asarray(true_aps[0])))
    start = (truth.targets, truth.eops, np.array([true.get(a, 0.0) for a in scanner.aps]))
    problem = os.path.join(tmp, "mc.bin")
    if binary is not None:
        _ceres.write_problem(problem, net, scanner, start, l_t, lev)
    options = MonteCarloOptions(runs=args.runs, seed=args.seed, progress=False)
    t0 = time.perf_counter()
    mc = monte_carlo(sim, model, options)
    compile_s = time.perf_counter() - t0 - mc.run_s
    times = {"ceres": [], "tlsjax": []}
    peer = None
    for _ in range(args.rounds):
        with args.quiet.round():
            if binary is not None:
                peer = _ceres.run(binary, "mc", problem, threads=args.peer_threads)
                times["ceres"] += peer["wall_s"]
            t = time.perf_counter()
            mc = monte_carlo(sim, model, options)
            times["tlsjax"].append(time.perf_counter() - t)
    loads = args.quiet.rounds[-args.rounds :]
    base = {
        "runs": args.runs,
        "tlsjax_s": stats(times["tlsjax"]),
        "tlsjax_compile_s": compile_s,
        "tlsjax_run_s_last": mc.run_s,
        "tlsjax_chunk_size": mc.chunk_size,
        "tlsjax_devices": mc.n_devices,
        "tlsjax_successful": int(np.sum(mc.ok)),
        "tlsjax_chord_iterations_mean": float(np.mean(mc.iterations)),
        "scipy_estimate_s": {
            "value": args.runs * scipy_single_s,
            "how": "runs x the median scipy single adjustment of this case (not run 1,000 times)",
        },
        "loadavg": loads,
    }
    if binary is None:
        return {
            **base,
            "times_s": {"tlsjax": stats(times["tlsjax"])},
            "ceres": {"skipped": "the peer was not built"},
        }
    aps = np.array([r["aps"] for r in peer["results"]])
    s0sq = np.array([r["s0sq"] for r in peer["results"]])
    dev = np.abs(aps - mc.ap_values) / mc.ap_sigmas
    med = {k: _median(v) for k, v in times.items()}
    return {
        **base,
        "times_s": {k: stats(v) for k, v in times.items()},
        "ceres_threads": args.peer_threads,
        "ratio_ceres_over_tlsjax": med["ceres"] / med["tlsjax"],
        "iterations": {
            "tlsjax_chord_mean": float(np.mean(mc.iterations)),
            "ceres_iterations_mean": float(np.mean([r["iterations"] for r in peer["results"]])),
            "ceres_linear_solves_mean": float(
                np.mean([r["linear_solves"] for r in peer["results"]])
            ),
        },
        "checks": {
            "tlsjax_successful": int(np.sum(mc.ok)),
            "ceres_converged": int(sum(r["converged"] for r in peer["results"])),
            "max_ap_diff_sigma": float(np.nanmax(dev)),
            "median_ap_diff_sigma": float(np.nanmedian(dev)),
            "max_s0sq_rel_diff": float(np.nanmax(np.abs(s0sq / mc.sigma0_sq - 1))),
        },
        "loadavg": loads,
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "ceres.json"))
    p.add_argument("--cases", default=",".join(CASES))
    p.add_argument("--rounds", type=int, default=5, help="alternating rounds per case")
    p.add_argument("--repeats", type=int, default=20, help="adjustments per side and round")
    p.add_argument("--runs", type=int, default=1000, help="Monte Carlo realisations")
    p.add_argument("--scipy-repeats", type=int, default=2, help="scipy solves per round")
    p.add_argument("--peer-threads", type=int, default=2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--devices", type=int, help="JAX CPU devices (default: one per core)")
    p.add_argument("--no-montecarlo", action="store_true")
    p.add_argument("--no-cli", action="store_true", help="skip the command-line timings")
    p.add_argument(
        "--no-peer", action="store_true", help="neither build nor run the Ceres peer (tlsjax only)"
    )
    p.add_argument(
        "--max-load",
        type=float,
        default=1.25 * (os.cpu_count() or 1),
        help="largest one-minute load average a round may start at (default 1.25 per core)",
    )
    p.add_argument("--wait", type=float, default=900.0, help="seconds to wait for a quiet machine")
    args = p.parse_args(argv)
    args.quiet = Quiet(args.max_load, args.wait)
    try:
        return _main(args)
    except NotQuiet as exc:
        print(f"bench_ceres: {exc}", file=sys.stderr)
        return 3


def _main(args) -> int:
    out = {
        "date_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "jax_version": jax.__version__,
        "tlsjax_version": tj.__version__,
        "max_load": args.max_load,
        "machine": machine_info(),
        "device": str(jax.devices()[0].device_kind),
        "devices": [str(d) for d in jax.devices()],
        "loadavg_start": loadavg(),
        "shared_machine": "other processes may run beside this benchmark: see loadavg",
        "uptime": _uptime(),
        "args": {k: v for k, v in vars(args).items() if k != "quiet"},
    }
    binary, why = (None, "--no-peer") if args.no_peer else _ceres.build()
    out["ceres"] = {"binary": str(binary)} if binary is not None else {"skipped": why}
    if binary is None:
        print(f"# Ceres peer skipped: {why}")
    sim = tj.simulate(seed=0, architecture="hybrid", tilted=True)
    out["cases"] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.cases.split(","):
            model = tj.CalibrationModel(tj.Scanner(architecture="hybrid", aps=CASES[name]))
            why = _ceres.supported(model.scanner) if binary is not None else ""
            if why:
                print(f"# {name}: Ceres peer skipped: {why}")
            peer = None if why else binary
            case = {"single": single(peer, sim.network, model, args, tmp)}
            print(f"# {name} single: {case['single']['times_s']}")
            if not args.no_montecarlo:
                sc = case["single"]["times_s"]["scipy"]["median"]
                case["montecarlo"] = montecarlo(peer, sim, model, args, tmp, sc)
                print(f"# {name} Monte Carlo: {case['montecarlo']['times_s']}")
            out["cases"][name] = case
        if not args.no_cli:
            with args.quiet.round():
                out["cli"] = _cli_times(tmp)
            out["cli"]["round"] = args.quiet.rounds[-1]
            print(f"# command line: {out['cli']}")
    out["rounds"] = args.quiet.rounds
    out["loadavg_end"] = loadavg()
    out["uptime_end"] = _uptime()
    write_results(out, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
