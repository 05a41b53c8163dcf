"""Sum the suite's profile per test file: ``TLSJAX_TEST_PROFILE=DIR ./scripts/test -o
enable_assertion_pass_hook=true`` writes DIR/profile-<worker>.json (tests/conftest.py); then
``python scripts/suite_profile.py DIR`` prints per file the tests, wall seconds, XLA compiles and
their seconds, tracing and lowering seconds, persistent-cache reads and asserts passed, and the
most costly tests. With ``--write-fast FILE [BUDGET]``: the quick subset (``-m fast``, tests/conftest.py)
of every test file's cheapest test and then the cheapest others, up to BUDGET CPU seconds
(default 240: under 3 minutes on 2 cores with the workers' start)."""

import json
import sys
from collections import defaultdict
from pathlib import Path

KEYS = ("wall_s", "cpu_s", "compiles", "compile_s", "trace_s", "lower_s", "cache_reads", "asserts")


def main(folder: str, top: int = 25) -> None:
    tests = {}
    for path in sorted(Path(folder).glob("profile-*.json")):
        tests.update(json.loads(path.read_text()))
    files = defaultdict(lambda: defaultdict(float))
    for node, rec in tests.items():
        f = files[node.split("::")[0]]
        f["tests"] += 1
        for k in KEYS:
            f[k] += rec.get(k, 0)
    head = f"{'file':38s} {'tests':>5s} " + " ".join(f"{k:>11s}" for k in KEYS)
    print(head)
    total = defaultdict(float)
    for name, f in sorted(files.items(), key=lambda kv: -kv[1]["wall_s"]):
        print(f"{name[-38:]:38s} {int(f['tests']):5d} " + " ".join(f"{f[k]:11.1f}" for k in KEYS))
        for k, v in f.items():
            total[k] += v
    print(f"{'total':38s} {int(total['tests']):5d} " + " ".join(f"{total[k]:11.1f}" for k in KEYS))
    print(f"\nmost costly {top} tests (CPU s, wall s, compiles):")
    cost = lambda rec: rec.get("cpu_s", rec.get("wall_s", 0))
    for node, rec in sorted(tests.items(), key=lambda kv: -cost(kv[1]))[:top]:
        print(f"{cost(rec):8.1f} {rec.get('wall_s', 0):8.1f} {rec.get('compiles', 0):4d}  {node}")


def write_fast(folder: str, path: str, budget: float = 240.0) -> None:
    tests = {}
    for p in sorted(Path(folder).glob("profile-*.json")):
        tests.update(json.loads(p.read_text()))
    cost = {n: r.get("cpu_s", r.get("wall_s", 0.0)) for n, r in tests.items()}
    by_file = defaultdict(list)
    for n in sorted(cost, key=cost.get):
        by_file[n.split("::")[0]].append(n)
    chosen = [names[0] for names in by_file.values() if cost[names[0]] < 0.2 * budget]
    spent = sum(cost[n] for n in chosen)
    for n in sorted(cost, key=cost.get):
        if n not in chosen and spent + cost[n] <= budget:
            chosen.append(n)
            spent += cost[n]
    header = (
        f"# The quick subset (-m fast): {len(chosen)} of {len(tests)} tests, {spent:.0f} CPU s "
        f"measured; regenerate with scripts/suite_profile.py PROFILE --write-fast {path}\n"
    )
    Path(path).write_text(header + "".join(f"{n}\n" for n in sorted(chosen)))
    print(f"{len(chosen)} tests, {spent:.0f} CPU s -> {path}")


if __name__ == "__main__":
    if "--write-fast" in sys.argv:
        i = sys.argv.index("--write-fast")
        write_fast(sys.argv[1], *sys.argv[i + 1 : i + 2], *map(float, sys.argv[i + 2 : i + 3]))
    else:
        main(*sys.argv[1:2])
