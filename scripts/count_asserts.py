"""Static count of the checks in the test suite: ``assert`` statements, ``numpy.testing``
assertions and ``pytest.raises``/``pytest.warns`` blocks, per file and in total (parsed, so
strings and comments do not count). Usage: ``python scripts/count_asserts.py [tests/]`` or, for
another revision, ``git show REV:tests/x.py | python scripts/count_asserts.py -``."""

import ast
import sys
from pathlib import Path


def counts(source: str) -> dict:
    out = {"assert": 0, "np.testing": 0, "raises/warns": 0}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Assert):
            out["assert"] += 1
        elif isinstance(node, ast.Call):
            name = ast.unparse(node.func)
            if ".testing.assert_" in name or name.startswith("assert_allclose"):
                out["np.testing"] += 1
            elif name in ("pytest.raises", "pytest.warns"):
                out["raises/warns"] += 1
    return out


def main(args):
    if args == ["-"]:
        print(counts(sys.stdin.read()))
        return
    root = Path(args[0] if args else "tests")
    total = {"assert": 0, "np.testing": 0, "raises/warns": 0}
    for path in sorted(root.glob("*.py")):
        c = counts(path.read_text())
        for k in total:
            total[k] += c[k]
        print(f"{path.name:40s} {c['assert']:5d} {c['np.testing']:5d} {c['raises/warns']:5d}")
    print(f"{'total':40s} {total['assert']:5d} {total['np.testing']:5d} {total['raises/warns']:5d}")


if __name__ == "__main__":
    main(sys.argv[1:])
