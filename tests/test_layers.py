"""The layer rule of ``tlsjax/__init__.py``'s docstring, read from the code (issue 39 item 4):
every import of a tlsjax module goes down the list of layers, never up or sideways; the modules
of one subpackage import each other without circles; ``tlsjax calibrate`` uses the public API
only. And the rule of the tests (item 5): a test module imports private modules only where it
checks an internal mechanism, and then says so (``pytest.mark.internal``, its docstring naming
them); the console script's entry point ``tlsjax._cli.main`` is the command line's public
door.

The imports are read with :mod:`ast` (module level and inside functions alike), so a lazy
import does not hide an upward one.
"""

import ast
import pathlib

import tlsjax

ROOT = pathlib.Path(tlsjax.__file__).parent
#: The layers of the package docstring, lowest first.
LAYERS = (
    ("_version",),
    ("_units", "_stats", "_jit", "_optional", "_summary", "_linalg", "_pytree"),
    ("_model",),
    ("_adjustment",),
    ("_simulation", "_io"),
    ("_inference", "_design", "_clouds"),
    ("_report",),
    ("_workflow",),
    ("__init__",),
    ("_cli",),
)
LAYER = {unit: k for k, units in enumerate(LAYERS) for unit in units}


def _modules():
    """Dotted name -> (path, is a package's __init__) of every module of tlsjax."""
    out = {}
    for path in ROOT.rglob("*.py"):
        parts = path.relative_to(ROOT.parent).with_suffix("").parts
        package = parts[-1] == "__init__"
        out[".".join(parts[:-1] if package else parts)] = (path, package)
    return out


def _imports(name, path, package):
    """(target module, at module level) of every tlsjax import in one module."""
    tree = ast.parse(path.read_text(), str(path))
    top = {id(n) for n in tree.body}
    here = name.split(".") if package else name.split(".")[:-1]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = here[: len(here) - node.level + 1] if node.level else []
            target = ".".join(base + ([node.module] if node.module else []))
            if not node.module:  # from . import _x
                out += [(f"{target}.{a.name}", id(node) in top) for a in node.names]
            else:
                out.append((target, id(node) in top))
        elif isinstance(node, ast.Import):
            out += [(a.name, id(node) in top) for a in node.names]
    return [(t, level) for t, level in out if t == "tlsjax" or t.startswith("tlsjax.")]


def _unit(module):
    parts = module.split(".")
    return "__init__" if len(parts) == 1 else parts[1]


def test_imports_go_down_the_layers_of_the_package_docstring():
    modules = _modules()
    assert set(LAYER) >= {_unit(m) for m in modules}, "a module outside the layer list"
    upward = []
    for name, (path, package) in modules.items():
        for target, _ in _imports(name, path, package):
            a, b = _unit(name), _unit(target)
            if a == b or (a == "_cli" and b == "__init__"):
                continue
            if not LAYER[b] < LAYER[a]:
                upward.append(f"{name} -> {target}")
    assert not upward, upward


def test_no_import_circles_within_a_subpackage():
    modules = _modules()
    graph = {m: set() for m in modules}
    for name, (path, package) in modules.items():
        for target, at_top in _imports(name, path, package):
            if at_top and target in modules and _unit(target) == _unit(name) and target != name:
                graph[name].add(target)
    done, stack, cycles = set(), [], []

    def visit(m):
        if m in stack:
            cycles.append(stack[stack.index(m) :] + [m])
            return
        if m in done:
            return
        stack.append(m)
        for t in sorted(graph[m]):
            visit(t)
        stack.pop()
        done.add(m)

    for m in sorted(graph):
        visit(m)
    assert not cycles, cycles


#: The command-line modules that use the public API only (all of them; _checks, _common and
#: _progress hold argument checks and messages and import nothing of tlsjax).
PUBLIC_COMMANDS = (
    "__init__",
    "_calibrate",
    "_compare",
    "_correct",
    "_design",
    "_extract",
    "_extract_targets",
    "_field_check",
    "_montecarlo",
    "_report",
    "_simulate",
    "_targets",
)


def test_commands_use_the_public_api_only():
    modules = _modules()
    for command in PUBLIC_COMMANDS:
        name = "tlsjax._cli" if command == "__init__" else f"tlsjax._cli.{command}"
        imported = _imports(name, *modules[name])
        private = [t for t, _ in imported if _unit(t) not in ("__init__", "_cli")]
        assert not private, (name, private)


TESTS = ROOT.parent / "tests"


def _private(node) -> set:
    """The private tlsjax modules an import statement imports (the console script's entry
    ``tlsjax._cli.main`` aside)."""
    if isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("tlsjax._"):
        if node.module != "tlsjax._cli" or {a.name for a in node.names} - {"main"}:
            return {node.module}
    elif isinstance(node, ast.Import):
        return {a.name for a in node.names if a.name.startswith("tlsjax._")}
    return set()


def _internal(node) -> bool:
    """``pytestmark = pytest.mark.internal`` at module level, or ``@pytest.mark.internal``."""
    if isinstance(node, ast.Assign):
        names = [getattr(t, "id", None) for t in node.targets]
        return names == ["pytestmark"] and ast.unparse(node.value) == "pytest.mark.internal"
    decorators = getattr(node, "decorator_list", ())
    return any(ast.unparse(d) == "pytest.mark.internal" for d in decorators)


def test_private_imports_only_in_tests_marked_internal():
    """A private import stands only in a test module marked ``internal`` or in a test marked
    ``internal``, and the module's docstring says why; a mark without a private import under
    it is stale."""
    wrong = []
    for path in sorted(TESTS.glob("test_*.py")):
        tree = ast.parse(path.read_text())
        module_mark = any(_internal(n) for n in tree.body)
        top = set().union(*(_private(n) for n in tree.body))
        doc = ast.get_docstring(tree) or ""
        inner = set()
        for f in tree.body:
            found = set().union(*(_private(n) for n in ast.walk(f)))
            if isinstance(f, (ast.Import, ast.ImportFrom)) or not found:
                if _internal(f) and not isinstance(f, ast.Assign):
                    wrong.append(f"{path.name}: {f.name} marked internal, imports nothing private")
                continue
            inner |= found
            if not (module_mark or _internal(f)):
                wrong.append(f"{path.name}: {getattr(f, 'name', '?')} imports {sorted(found)}")
        if top and not module_mark:
            wrong.append(f"{path.name}: {sorted(top)} at module level without the module's mark")
        if module_mark and not top | inner:
            wrong.append(f"{path.name}: marked internal, imports nothing private")
        if (top | inner) and "Private" not in doc:
            wrong.append(f"{path.name}: the docstring does not say what is imported privately")
    assert not wrong, wrong


def test_import_leaves_the_heavy_optional_libraries_for_their_use():
    """``import tlsjax`` (the CLI's and every notebook's first step, issue 37) loads JAX and
    numpy, not the libraries that only some tasks need: each costs a third of a second or more
    at import (equinox 0.14 s: tlsjax._pytree has what tlsjax used of it). Checked in a fresh
    interpreter."""
    import subprocess
    import sys

    heavy = ("scipy", "open3d", "laspy", "pye57", "matplotlib", "optimistix", "optax", "pandas")
    heavy += ("equinox",)
    code = "import sys, tlsjax; print(' '.join(sorted(sys.modules)))"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-2000:]
    loaded = {m.split(".")[0] for m in proc.stdout.split()}
    assert "jax" in loaded and "tlsjax" in loaded
    assert not loaded & set(heavy), sorted(loaded & set(heavy))
