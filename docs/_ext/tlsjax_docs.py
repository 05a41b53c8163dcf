"""Sphinx extension of the tlsjax documentation.

- ``.. tlsjax-api:: NAME NAME ...`` documents public names of ``tlsjax`` (autodoc), and the build
  fails (a warning under ``-W``) when a public name of ``tlsjax/__init__.py`` is documented on no
  page, twice, or has no docstring; data names take the ``#:`` comment of their defining module.
- ``{bench}`FILE:KEY.PATH[*FACTOR][:FORMAT][ UNIT]``` inserts one figure from
  ``benchmarks/results/FILE`` at build time (``FILE:?KEY.PATH...``: "not measured" where the
  file lacks the key: fields that a later version of a benchmark writes), and ``{bench-source}`FILE``` says when, where and
  under what load it was measured (what the file does not record is said as "not measured"):
  no figure of speed or accuracy is typed into a page, so none goes stale.
- "SPEC section N" in a docstring becomes a link to that section of the concepts pages, and
  ``|x|`` (an absolute value) is not read as a reST substitution.
- ``.. tlsjax-cli::`` shows ``tlsjax ...`` command lines and runs them at build (doctest).
- The committed notebooks are copied into ``docs/notebooks/`` (ignored by git) for myst-nb.
"""

from __future__ import annotations

import ast
import importlib
import inspect
import json
import pathlib
import re
import shutil

from docutils import nodes
from docutils.statemachine import StringList
from sphinx.pycode import ModuleAnalyzer
from sphinx.util import logging
from sphinx.util.docutils import SphinxDirective

LOG = logging.getLogger(__name__)
DOCS = pathlib.Path(__file__).resolve().parents[1]
ROOT = DOCS.parent
RESULTS = ROOT / "benchmarks" / "results"

#: Where each numbered SPEC section lives among the concepts pages (document, label).
SPEC_SECTIONS = {
    1: "spec-1",
    2: "spec-2",
    3: "spec-3",
    4: "spec-4",
    5: "spec-5",
    6: "spec-6",
    7: "spec-7",
    8: "spec-8",
    9: "spec-9",
    10: "spec-10",
    11: "spec-11",
    12: "spec-12",
    13: "spec-13",
}


# --- public names -----------------------------------------------------------------------------


def public_names() -> dict[str, str]:
    """Public name -> defining module, read from the imports of ``tlsjax/__init__.py``."""
    tree = ast.parse((ROOT / "tlsjax" / "__init__.py").read_text())
    out = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom) and node.level == 1 and node.module:
            for alias in node.names:
                name = alias.asname or alias.name
                if not name.startswith("_"):
                    out[name] = "tlsjax." + node.module
    return out


def _data_doc(module: str, name: str) -> str:
    docs = ModuleAnalyzer.for_module(module).find_attr_docs()
    return "\n".join(docs.get(("", name), [])).strip()


class ApiDirective(SphinxDirective):
    """Autodoc entries for the public names given as arguments, in that order."""

    required_arguments = 1
    final_argument_whitespace = True
    has_content = False

    def run(self):
        import tlsjax

        names = self.arguments[0].split()
        where = self.env.docname
        seen = self.env.domaindata.setdefault("tlsjax_api", {})
        modules = public_names()
        lines = []
        for name in names:
            if name not in modules:
                LOG.warning(f"tlsjax-api: {name} is not a public name of tlsjax", location=where)
                continue
            seen.setdefault(name, []).append(where)
            obj = getattr(tlsjax, name)
            if inspect.isclass(obj):
                lines += [f".. autoclass:: tlsjax.{name}"]
                # Members inherited from tlsjax's own bases (the settings' to_dict/from_dict,
                # a result's fields of the pipeline) are part of the class's API.
                bases = [b for b in obj.__mro__[1:] if b is not object]
                if bases and all(b.__module__.startswith("tlsjax.") for b in bases):
                    lines += ["   :inherited-members:"]
                lines += [""]
            elif callable(obj):
                lines += [f".. autofunction:: tlsjax.{name}", ""]
            else:
                text = _data_doc(modules[name], name)
                if not text:
                    LOG.warning(f"public name tlsjax.{name} has no docstring", location=where)
                lines += [f".. py:data:: tlsjax.{name}", ""]
                lines += ["   " + x for x in text.splitlines()] + [""]
                continue
            if not (obj.__doc__ or "").strip():
                LOG.warning(f"public name tlsjax.{name} has no docstring", location=where)
        node = nodes.section()
        node.document = self.state.document
        self.state.nested_parse(StringList(lines, source=where), self.content_offset, node)
        return node.children


def _check_api(app, env):
    seen = env.domaindata.get("tlsjax_api", {})
    for name in sorted(public_names()):
        pages = seen.get(name, [])
        if not pages:
            LOG.warning(f"public name tlsjax.{name} is documented on no page (docs/api/)")
        elif len(set(pages)) > 1 or len(pages) > 1:
            LOG.warning(f"public name tlsjax.{name} is documented more than once: {pages}")


def _purge(app, env, docname):
    seen = env.domaindata.get("tlsjax_api", {})
    for name in list(seen):
        seen[name] = [d for d in seen[name] if d != docname]


def _merge(app, env, docnames, other):
    seen = env.domaindata.setdefault("tlsjax_api", {})
    for name, pages in other.domaindata.get("tlsjax_api", {}).items():
        seen.setdefault(name, []).extend(pages)


# --- "SPEC section N" in docstrings ---------------------------------------------------------------

_SPEC = re.compile(r"SPEC section (\d+)")
# The docstrings write absolute values as |x|, which reST reads as a substitution.
_BARS = re.compile(r"(?<![\\`])\|([^|`\s][^|`]*?)\|(?![_`])")


def _escape_bars(line: str) -> str:
    parts = line.split("``")
    for i in range(0, len(parts), 2):  # outside ``literals`` only
        parts[i] = _BARS.sub(r"\\|\1\\|", parts[i])
    return "``".join(parts)


def _link_spec(app, what, name, obj, options, lines):
    for i, line in enumerate(lines):
        line = _escape_bars(line)
        lines[i] = _SPEC.sub(
            lambda m: (
                f":ref:`SPEC section {m.group(1)} <{SPEC_SECTIONS[int(m.group(1))]}>`"
                if int(m.group(1)) in SPEC_SECTIONS
                else m.group(0)
            ),
            line,
        )


def cli_parser():
    """``tlsjax._cli.build_parser()`` for sphinx-argparse, whose help texts are read as reST:
    absolute values ``|x|`` escaped as in the docstrings."""
    import argparse

    from tlsjax._cli import build_parser

    def walk(parser):
        if parser.description:
            parser.description = _escape_bars(parser.description)
        for action in parser._actions:
            if action.help and action.help is not argparse.SUPPRESS:
                action.help = _escape_bars(action.help)
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    choice.help = _escape_bars(choice.help or "")
                for sub in action.choices.values():
                    walk(sub)

    parser = build_parser()
    walk(parser)
    return parser


# --- benchmark figures ----------------------------------------------------------------------------

_BENCH = re.compile(
    r"^(?P<file>[\w.-]+\.json):(?P<optional>\?)?(?P<path>[^*:\s?]+)(\*(?P<factor>[0-9.eE+-]+))?"
    r"(:(?P<fmt>[^\s]+))?(\s+(?P<unit>.+))?$"
)


def load_result(name: str):
    path = RESULTS / name
    if not path.is_file():
        raise ValueError(f"benchmarks/results/{name} does not exist")
    return json.loads(path.read_text())


def lookup(data, dotted: str):
    """``a.b.0.c`` in nested dicts and lists; keys may contain spaces written as ``~``; a list of
    numbers followed by ``median`` gives its median (as the benchmarks' dicts of times do)."""
    cur = data
    for part in dotted.split("."):
        part = part.replace("~", " ")
        if isinstance(cur, list) and part == "median":
            values = sorted(float(x) for x in cur)
            if not values:
                raise KeyError(dotted)
            mid = len(values) // 2
            cur = values[mid] if len(values) % 2 else (values[mid - 1] + values[mid]) / 2
        elif isinstance(cur, list):
            cur = cur[int(part)]
        else:
            cur = cur[part]
    return cur


def bench_value(spec: str) -> str:
    m = _BENCH.match(spec.strip())
    if not m:
        raise ValueError(f"bench: cannot read {spec!r} (FILE:KEY.PATH[*FACTOR][:FORMAT][ UNIT])")
    try:
        value = lookup(load_result(m["file"]), m["path"])
    except (KeyError, IndexError):
        if m["optional"]:
            return "not measured"
        raise
    if m["factor"]:
        value = float(value) * float(m["factor"])
    text = format(value, m["fmt"]) if m["fmt"] else str(value)
    return f"{text} {m['unit']}" if m["unit"] else text


def _find(data, pred, depth=0):
    """First (key, value) in ``data`` (three levels, the top first) whose key satisfies ``pred``."""
    if not isinstance(data, dict):
        return None
    for k, v in data.items():
        if pred(k):
            return k, v
    if depth < 2:
        for v in data.values():
            hit = _find(v, pred, depth + 1)
            if hit:
                return hit
    return None


def provenance(name: str) -> str:
    """When, where and under what load ``benchmarks/results/NAME`` was measured."""
    data = load_result(name)
    date = _find(data, lambda k: k in ("date", "date_utc", "measured", "timestamp", "datetime"))
    machine = data.get("machine")
    if isinstance(machine, dict):
        bits = [
            machine.get("cpu_model"),
            f"{machine['cpu_count']} CPU cores" if machine.get("cpu_count") else None,
            f"{machine['cpus']} CPUs"
            if machine.get("cpus") and not machine.get("cpu_count")
            else None,
            machine.get("jax_backend")
            and f"JAX {machine.get('jax_version', '')} on {machine['jax_backend']}",
        ]
        machine = ", ".join(b for b in bits if b) or machine.get("platform")
    if not machine and data.get("cpus"):
        machine = f"{data['cpus']} CPUs"
    load = _find(data, lambda k: k.startswith(("loadavg", "load_average")))
    rounds = [r.get("loadavg_before") for r in data.get("rounds") or [] if isinstance(r, dict)]
    rounds = [x for x in rounds if isinstance(x, (int, float))]
    load_text = None
    if rounds:  # the load each measured round started at (bench_ceres.py waits for a quiet one)
        load_text = f"{min(rounds):.2g}-{max(rounds):.2g} at the start of its {len(rounds)} rounds"
        if isinstance(data.get("max_load"), (int, float)):
            load_text += f" (at most {data['max_load']:.2g} allowed)"
    elif load:
        v = load[1]
        load_text = ", ".join(f"{x:.2g}" for x in v) if isinstance(v, list) else str(v)
    command = data.get("command")
    versions = [f"tlsjax {data['tlsjax_version']}"] if data.get("tlsjax_version") else []
    if data.get("jax_version") and "JAX" not in str(machine):
        versions.append(f"JAX {data['jax_version']}")
    if versions and machine:
        machine = f"{machine} ({', '.join(versions)})"
    parts = [
        f"measured {date[1]}" if date else "date not measured" + _committed(name),
        f"on {machine}" if machine else "machine not measured",
        f"load average {load_text}" if load_text else "load average not measured",
    ]
    text = "; ".join(parts) + f" (benchmarks/results/{name}"
    return text + (f", {command})" if command else ")")


def _committed(name: str) -> str:
    """`` (file committed YYYY-MM-DD)`` from git, when the file is tracked; else nothing."""
    import subprocess

    try:
        out = subprocess.run(
            ["git", "log", "-1", "--format=%cs", "--", f"benchmarks/results/{name}"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=10,
        ).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""
    return f" (file committed {out})" if out else ""


def bench_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    try:
        value = bench_value(text)
    except (ValueError, KeyError, IndexError, TypeError) as exc:
        msg = inliner.reporter.warning(f"bench: {text}: {exc!r}", line=lineno)
        return [inliner.problematic(rawtext, rawtext, msg)], [msg]
    return [nodes.Text(value)], []


def bench_source_role(name, rawtext, text, lineno, inliner, options=None, content=None):
    try:
        value = provenance(text.strip())
    except (ValueError, json.JSONDecodeError) as exc:
        msg = inliner.reporter.warning(f"bench-source: {text}: {exc}", line=lineno)
        return [inliner.problematic(rawtext, rawtext, msg)], [msg]
    return [nodes.emphasis(value, value)], []


# --- command lines run at build -------------------------------------------------------------------


class CliDirective(SphinxDirective):
    """A ``tlsjax ...`` command line shown as a console block and run by the doctest builder in
    the page's namespace (in this process: the compiled programs are shared with the Python
    examples). One command per paragraph; a trailing backslash continues a line. The option
    ``:exit: N`` gives the expected exit status (default 0)."""

    has_content = True
    option_spec = {"exit": int}

    def run(self):
        commands, current = [], []
        for line in list(self.content) + [""]:
            if not line.strip():
                if current:
                    commands.append(" ".join(current))
                current = []
                continue
            current.append(line.strip().removesuffix("\\").strip())
        for cmd in commands:
            if not cmd.startswith("tlsjax "):
                raise self.error(f"tlsjax-cli: a command starts with 'tlsjax ': {cmd!r}")
        shown = "\n\n".join("$ " + "\n".join(self._wrap(c)) for c in commands)
        expected = self.options.get("exit", 0)
        test = "\n".join(f"_tlsjax_cli({c[len('tlsjax ') :]!r}, {expected})" for c in commands)
        node = nodes.literal_block(shown, shown, testnodetype="testcode", groups=["default"])
        node["test"] = test
        node["language"] = "console"
        self.set_source_info(node)
        return [node]

    @staticmethod
    def _wrap(cmd: str, width: int = 78) -> list[str]:
        lines, cur = [], ""
        for word in cmd.split(" "):
            if cur and len(cur) + 1 + len(word) > width:
                lines.append(cur + " \\")
                cur = "    " + word
            else:
                cur = f"{cur} {word}" if cur else word
        return lines + [cur]


#: Defined in every page's doctest namespace (``doctest_global_setup`` imports it).
def run_cli(args: str, expected: int = 0) -> None:
    """Run ``tlsjax ARGS`` in this process; its output is kept out of the doctest's (a page
    shows the command, not figures that change with every release) and shown on failure.
    Wildcards (``S1/*.txt``) are expanded in sorted order, as a shell does."""
    import contextlib
    import glob
    import io
    import shlex

    from tlsjax._cli import main

    argv = []
    for word in shlex.split(args):
        matches = sorted(glob.glob(word)) if glob.has_magic(word) else []
        argv += matches or [word]
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        try:
            rc = main(argv)
        except SystemExit as exc:  # argparse errors exit
            rc = exc.code
    if rc != expected:
        tail = "\n".join(out.getvalue().splitlines()[-15:])
        raise AssertionError(f"tlsjax {args}: exit status {rc}, expected {expected}:\n{tail}")


# --- notebooks ----------------------------------------------------------------------------------------


def _copy_notebooks(app):
    dest = DOCS / "notebooks"
    dest.mkdir(exist_ok=True)
    for src in sorted((ROOT / "notebooks").glob("[0-9][0-9]_*.ipynb")):
        out = dest / src.name
        if not out.exists() or out.read_bytes() != src.read_bytes():
            shutil.copyfile(src, out)


def _time_doctest_pages(app):
    # TLSJAX_DOCS_TIMINGS=1: the seconds each page's examples take, wall and CPU of this
    # process (to keep the build fast).
    import os
    import time

    if app.builder.name != "doctest" or not os.environ.get("TLSJAX_DOCS_TIMINGS"):
        return
    inner = app.builder.test_doc

    def timed(docname, doctree):
        t0, c0 = time.perf_counter(), time.process_time()
        try:
            return inner(docname, doctree)
        finally:
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            if wall > 0.05:
                print(f"docs: {docname} examples {wall:.1f} s ({cpu:.1f} CPU s)", flush=True)

    app.builder.test_doc = timed


def setup(app):
    app.connect("builder-inited", _time_doctest_pages)
    app.add_directive("tlsjax-api", ApiDirective)
    app.add_directive("tlsjax-cli", CliDirective)
    app.add_role("bench", bench_role)
    app.add_role("bench-source", bench_source_role)
    app.connect("builder-inited", _copy_notebooks)
    app.connect("autodoc-process-docstring", _link_spec)
    app.connect("env-check-consistency", _check_api)
    app.connect("env-purge-doc", _purge)
    app.connect("env-merge-info", _merge)
    importlib.import_module("tlsjax")
    return {"version": "1", "parallel_read_safe": True, "parallel_write_safe": True}
