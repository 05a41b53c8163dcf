"""Property-based hostile input (issue 28 item 6): malformed observation tables, result JSON,
point clouds and plane files thrown at the readers and the commands. The outcome is always a
valid result, a clear one-line error (ValueError naming the file; exit code 2) or a result code
(exit 1); never a traceback (exit 3) and never a modified input.

The profile is the fixed, derandomised one of ``conftest.py``; each test draws a modest number
of examples so that CI stays fast (mutations keep the network's shape where they can, so the
adjustments that do run reuse one compiled program).

Private imports: ``tlsjax._cli.main`` (the console script) and the PTX/XYZ writers that
build the point-cloud files the readers are given.
"""

import contextlib
import hashlib
import io
import json
import os
import tempfile

import numpy as np
import pytest
from helpers import tiny_planes
from hypothesis import given, settings
from hypothesis import strategies as st

import tlsjax as tj
from tlsjax._cli import main
from tlsjax._io._point_clouds import write_ptx, write_xyz

pytestmark = pytest.mark.internal

N_TARGETS = 24

CELLS = ["", " ", "abc", "nan", "inf", "-inf", "-1", "0", "1e300", "1e-300", "1,5", '"', "720",
         "-95", "3.2", "S1", "T001", "\x00", "1e5"]  # fmt: skip
HEADERS = ["range", "range_km", "range_m", "range_mm", "hz_deg", "hz_rad", "el_gon", "target",
           "plane", "scan", "sigma_hz_m", "incidence_deg", "instrument", "x", "", "range_m "]  # fmt: skip
JSON_VALUES = st.recursive(
    st.none() | st.booleans() | st.integers(-(10**20), 10**20) | st.floats(allow_nan=False)
    | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=4), inner, max_size=3),
    max_leaves=6,
)  # fmt: skip


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("props") / "not_written_by_tlsjax"
    d.mkdir()
    argv = ["simulate", "--out", d / "obs.csv", "--scans-out", d / "scans.csv", "--targets"]
    assert main([str(a) for a in argv + [N_TARGETS, "--seed", "3"]]) == 0
    assert main(["calibrate", str(d / "obs.csv"), "--no-vce", "--json", str(d / "cal.json")]) == 0
    rng = np.random.default_rng(1)
    x = rng.normal(size=(60, 3)) * 3.0 + [5.0, 1.0, 0.5]
    write_xyz(d / "c.xyz", x)
    write_ptx(d / "c.ptx", [(x, None)])
    tj.write_ply(d / "c.ply", x)
    tj.write_las(d / "c.las", x, np.zeros(6))
    tj.write_extracted_planes(d / "p.npz", tiny_planes(rng, 20))
    return d


def _digest(path) -> str:
    with open(path, "rb") as fh:
        return hashlib.sha256(fh.read()).hexdigest()


def _cli(argv):
    """Exit code and stderr of one command run in this process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            code = main([str(a) for a in argv])
        except SystemExit as exc:
            code = exc.code
    return code, err.getvalue()


def _assert_outcome(code, err, command):
    """A valid result (0), a result code (1) or one clear error line (2); never exit 3."""
    assert code in (0, 1, 2), (code, err)
    assert "internal error" not in err and "Traceback" not in err, err
    if code == 2:
        errors = [x for x in err.splitlines() if ": error:" in x]
        assert len(errors) == 1 and errors[0].startswith(f"tlsjax {command}: error:"), err


def _assert_clear(exc: BaseException, source: str):
    message = str(exc)
    assert isinstance(exc, ValueError), f"{type(exc).__name__}: {message}"
    assert "\n" not in message and os.path.basename(source) in message, message


@contextlib.contextmanager
def _folder():
    with tempfile.TemporaryDirectory() as d:
        yield d


# --- observation tables ---------------------------------------------------------------------


@st.composite
def mutated_table(draw, text):
    """The simulated target CSV with one to three mutations that a person or a program makes."""
    lines = [x for x in text.splitlines() if not x.startswith("#")]  # header first
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["cell", "header", "drop_field", "duplicate", "cut", "noise"]))
        i = draw(st.integers(1, len(lines) - 1))
        fields = lines[i].split(",")
        if kind == "cell":
            fields[draw(st.integers(0, len(fields) - 1))] = draw(st.sampled_from(CELLS))
            lines[i] = ",".join(fields)
        elif kind == "header":
            head = lines[0].split(",")
            head[draw(st.integers(0, len(head) - 1))] = draw(st.sampled_from(HEADERS))
            lines[0] = ",".join(head)
        elif kind == "drop_field":
            del fields[draw(st.integers(0, len(fields) - 1))]
            lines[i] = ",".join(fields)
        elif kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "cut":  # the file ends inside its last line
            lines[-1] = lines[-1][: draw(st.integers(0, len(lines[-1])))]
        else:
            lines.insert(i, draw(st.text(max_size=12)))
    return "\n".join(lines) + "\n"


@contextlib.contextmanager
def _table_file(text):
    """``text`` written to a CSV in a fresh folder (surrogates kept as invalid UTF-8); the
    file must be unchanged when the block ends."""
    with _folder() as d:
        path = os.path.join(d, "obs.csv")
        with open(path, "w", encoding="utf-8", errors="surrogatepass") as fh:
            fh.write(text)
        before = _digest(path)
        yield d, path
        assert _digest(path) == before


@settings(max_examples=40)
@given(data=st.data())
def test_malformed_tables_at_the_reader(files, data):
    text = data.draw(mutated_table((files / "obs.csv").read_text()))
    with _table_file(text) as (_, path):
        try:
            net = tj.read_network(path)
        except Exception as exc:  # noqa: BLE001 - any class but a clear ValueError fails
            _assert_clear(exc, path)
        else:
            assert np.all(np.isfinite(net.observations)) and np.all(net.sigmas > 0)


@settings(max_examples=12)
@given(data=st.data())
def test_malformed_tables_at_calibrate(files, data):
    text = data.draw(mutated_table((files / "obs.csv").read_text()))
    with _table_file(text) as (d, path):
        code, err = _cli(["calibrate", path, "--no-vce", "--json", os.path.join(d, "c.json")])
        _assert_outcome(code, err, "calibrate")


# --- result JSON ----------------------------------------------------------------------------


@st.composite
def mutated_json(draw, doc):
    """The calibration JSON with a value somewhere replaced or removed, or another document."""
    doc = json.loads(json.dumps(doc))
    if draw(st.integers(0, 9)) == 0:
        return draw(JSON_VALUES)
    for _ in range(draw(st.integers(1, 3))):
        node, key = doc, None
        for _ in range(4):  # walk down a few levels, then change what is there
            if isinstance(node, dict) and node:
                key = draw(st.sampled_from(sorted(node)))
            elif isinstance(node, list) and node:
                key = draw(st.integers(0, len(node) - 1))
            else:
                key = None
                break
            if isinstance(node[key], (dict, list)) and draw(st.booleans()):
                node = node[key]
                continue
            break
        if key is None:
            continue
        if isinstance(node, dict) and draw(st.booleans()):
            del node[key]
        else:
            node[key] = draw(JSON_VALUES)
    return doc


@settings(max_examples=30)
@given(data=st.data())
def test_malformed_json_at_readers_and_commands(files, data):
    doc = data.draw(mutated_json(json.loads((files / "cal.json").read_text())))
    with _folder() as d:
        path = os.path.join(d, "cal.json")
        with open(path, "w") as fh:
            json.dump(doc, fh)
        before, cloud = _digest(path), _digest(files / "c.xyz")
        for read in (tj.Calibration.from_json, tj.APSet.from_json):
            try:
                read(path)
            except Exception as exc:  # noqa: BLE001 - any other class fails the test
                _assert_clear(exc, path)
        code, err = _cli(["report", path, "--html", os.path.join(d, "r.html")])
        _assert_outcome(code, err, "report")
        argv = ["correct", path, files / "c.xyz", "--out", os.path.join(d, "out")]
        _assert_outcome(*_cli(argv), "correct")
        assert _digest(path) == before and _digest(files / "c.xyz") == cloud


# --- point clouds and plane files -------------------------------------------------------------


@st.composite
def mutated_bytes(draw, raw: bytes):
    kind = draw(st.sampled_from(["cut", "flip", "insert", "empty"]))
    if kind == "empty":
        return b""
    i = draw(st.integers(0, max(len(raw) - 1, 0)))
    if kind == "cut":
        return raw[:i]
    if kind == "flip":
        return raw[:i] + bytes([raw[i] ^ draw(st.integers(1, 255))]) + raw[i + 1 :]
    return raw[:i] + draw(st.binary(min_size=1, max_size=16)) + raw[i:]


@contextlib.contextmanager
def _bytes_file(raw: bytes, name: str):
    """``raw`` written to ``name`` in a fresh folder; the file must be unchanged at the end."""
    with _folder() as d:
        path = os.path.join(d, name)
        with open(path, "wb") as fh:
            fh.write(raw)
        yield d, path
        with open(path, "rb") as fh:
            assert fh.read() == raw


@settings(max_examples=40)
@given(data=st.data(), fmt=st.sampled_from(["xyz", "ptx", "ply", "las"]))
def test_malformed_clouds_at_the_reader_and_correct(files, data, fmt):
    raw = data.draw(mutated_bytes((files / f"c.{fmt}").read_bytes()))
    with _bytes_file(raw, f"c.{fmt}") as (d, path):
        try:
            tj.read_point_clouds(path)
        except Exception as exc:  # noqa: BLE001
            _assert_clear(exc, path)
        argv = ["correct", files / "cal.json", path, "--out", os.path.join(d, "out")]
        _assert_outcome(*_cli(argv), "correct")


@settings(max_examples=25)
@given(data=st.data())
def test_malformed_plane_files(files, data):
    raw = data.draw(mutated_bytes((files / "p.npz").read_bytes()))
    with _bytes_file(raw, "p.npz") as (_, path):
        try:
            tj.read_planes(path)
        except Exception as exc:  # noqa: BLE001
            _assert_clear(exc, path)
        _assert_outcome(*_cli(["calibrate", "--planes", path, "--no-screen"]), "calibrate")


@settings(max_examples=25)
@given(
    key=st.sampled_from(
        [
            "patch_scan",
            "patch_normal",
            "point_patch",
            "observations",
            "planes",
            "poses",
            "incidence",
            "patch_plane",
            "scans",
        ]
    ),  # fmt: skip
    value=st.sampled_from(
        [
            np.zeros(0),
            np.zeros((3, 5)),
            np.array([-7]),
            np.array(["x"]),
            np.full((2, 4), np.nan),
            np.arange(100),
            np.array(3.0),
        ]
    ),  # fmt: skip
)
def test_inconsistent_plane_arrays(files, key, value):
    with np.load(files / "p.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays[key] = value
    with _folder() as d:
        path = os.path.join(d, "p.npz")
        np.savez(path, **arrays)
        try:
            tj.read_planes(path)
        except Exception as exc:  # noqa: BLE001
            _assert_clear(exc, path)


# --- vendor target lists and reference surveys ----------------------------------------------

LISTS = os.path.join(os.path.dirname(__file__), "data", "target_lists")
LIST_CELLS = ["", "abc", "nan", "inf", "1e300", "-0", "0", "1,5", "1.5.3", "T001", "\x00", ";"]


@st.composite
def mutated_list(draw, text):
    """A vendor target list with one to three mutations: a cell, a dropped or duplicated line,
    noise, a cut, a changed header."""
    lines = text.splitlines()
    for _ in range(draw(st.integers(1, 3))):
        kind = draw(st.sampled_from(["cell", "drop", "duplicate", "cut", "noise", "header"]))
        i = draw(st.integers(0, len(lines) - 1))
        if kind == "cell":
            fields = lines[i].replace("\t", " ").replace(";", " ").replace(",", " ").split()
            if fields:
                fields[draw(st.integers(0, len(fields) - 1))] = draw(st.sampled_from(LIST_CELLS))
            lines[i] = " ".join(fields)
        elif kind == "drop" and len(lines) > 1:
            del lines[i]
        elif kind == "duplicate":
            lines.insert(i, lines[i])
        elif kind == "cut":
            lines = lines[: i + 1]
            lines[-1] = lines[-1][: draw(st.integers(0, len(lines[-1])))]
        elif kind == "header":
            lines[0] = draw(st.sampled_from(["", "x y z", "Name X[km] Y Z", "#", "a,b,c,d,e"]))
        else:
            lines.insert(i, draw(st.text(max_size=12)))
    return "\n".join(lines) + "\n"


@settings(max_examples=30)
@given(
    data=st.data(),
    layout=st.sampled_from(["cyclone_", "cloudcompare_", "scene_", "riscan_tpl_socs_", ""]),
)
def test_malformed_target_lists_at_the_readers_and_import(layout, data):
    """A mutated Station1 list beside an intact Station2 list: read_target_list,
    read_reference and import-targets give a table, a clear error naming the mutated file, or
    exit 1/2; the lists are never modified."""
    ext = ".pts" if not layout else (".txt" if layout in ("cyclone_", "cloudcompare_") else ".csv")
    with open(os.path.join(LISTS, f"{layout}Station1{ext}"), encoding="utf-8") as fh:
        text = data.draw(mutated_list(fh.read()))
    with _folder() as d:
        one, two = os.path.join(d, f"Station1{ext}"), os.path.join(d, f"Station2{ext}")
        with open(one, "w", encoding="utf-8", errors="surrogatepass") as fh:
            fh.write(text)
        with open(os.path.join(LISTS, f"{layout}Station2{ext}"), "rb") as src:
            with open(two, "wb") as fh:
                fh.write(src.read())
        before = _digest(one)
        for read in (lambda: tj.read_target_list([one, two], "hybrid").observations,
                     lambda: np.array(list(tj.read_reference(one).values()))):  # fmt: skip
            try:
                values = read()
            except Exception as exc:  # noqa: BLE001 - any class but a clear ValueError fails
                _assert_clear(exc, one)
            else:  # what is read is finite and within a laser scan's reach
                assert np.all(np.isfinite(values)) and np.all(np.abs(values) <= 1e4)
        argv = ["import-targets", one, two, "--architecture", "panoramic"]
        _assert_outcome(*_cli(argv + ["--out", os.path.join(d, "obs.csv")]), "import-targets")
        assert _digest(one) == before
