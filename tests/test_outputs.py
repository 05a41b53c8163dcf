"""Strict, atomic outputs (issue 13): NaN and infinities become null, a failed write leaves no
half file, unwritable paths are refused before any work, a failed adjustment reports no
numbers.

Private imports: the strict JSON writer and the result JSON's handling of undetermined
parameters are private mechanisms; geometry helpers build a network.
"""

import json
import math
import os

import numpy as np
import pytest
from strict_json import load_strict

import tlsjax as tj
from tlsjax import rotation_matrix, spherical_from_cartesian


@pytest.mark.internal
def test_to_json_value_nulls_what_is_undefined():
    from tlsjax._io._json import dumps_strict, to_json_value

    value = to_json_value(
        {
            "nan": float("nan"),
            "inf": np.inf,
            "ninf": -np.float32(np.inf),
            "arr": np.array([1.0, np.nan, 3.0]),
            "i": np.int64(7),
            "b": np.bool_(True),
            "t": (1, np.float64(2.5)),
            5: "key",
            "code": tj.ResultCode.NOT_ESTIMABLE,
        }
    )
    assert value == {
        "nan": None,
        "inf": None,
        "ninf": None,
        "arr": [1.0, None, 3.0],
        "i": 7,
        "b": True,
        "t": [1, 2.5],
        "5": "key",
        "code": 2,
    }
    assert type(value["i"]) is int and type(value["b"]) is bool
    # Lists of plain floats (the fast path) and of mixed values: the same rules.
    assert to_json_value([[1.5, math.inf], (2.0, -0.0), [math.nan, np.float64(3.0)]]) == [
        [1.5, None],
        [2.0, -0.0],
        [None, 3.0],
    ]
    assert to_json_value(()) == [] and to_json_value([0.5, 2.0]) == [0.5, 2.0]
    text = dumps_strict({"x": [math.nan, 1e308 * 10]})
    assert json.loads(text) == {"x": [None, None]} and "NaN" not in text
    with pytest.raises(TypeError, match="object"):
        to_json_value({"x": object()})


@pytest.mark.internal
def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    from tlsjax._io._json import write_json_file

    path = tmp_path / "out.json"
    write_json_file(path, {"a": 1})
    with pytest.raises(TypeError):
        write_json_file(path, {"a": object()})  # refused before anything is written
    assert load_strict(path) == {"a": 1}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.json"]
    write_json_file(tmp_path / "new" / "deep.json", {"v": float("nan")})
    assert load_strict(tmp_path / "new" / "deep.json") == {"v": None}
    mode = os.stat(path).st_mode & 0o777
    assert mode & 0o044, oct(mode)  # readable by others like any file (umask), not private


@pytest.mark.internal
def test_unwritable_paths_are_refused(tmp_path):
    from tlsjax._io._json import check_output_dir, check_output_file, write_json_file

    afile = tmp_path / "afile"
    afile.write_text("x")
    with pytest.raises(ValueError, match="--json .*is a directory"):
        check_output_file(tmp_path, "--json ")
    with pytest.raises(ValueError, match="afile is a file, not a directory"):
        check_output_file(afile / "x.json")
    with pytest.raises(ValueError, match="afile is a file, not a directory"):
        check_output_file(afile / "sub" / "x.json")
    with pytest.raises(ValueError, match="is a file, not a directory"):
        check_output_dir(afile, "--plots ")
    with pytest.raises(ValueError, match="afile is a file"):
        check_output_dir(afile / "sub")
    with pytest.raises(ValueError, match="cannot be written"):
        write_json_file(afile / "x.json", {"a": 1})
    if os.path.isdir("/proc/self"):  # a file system where nothing can be created
        with pytest.raises(ValueError, match="/proc"):
            check_output_file("/proc/tlsjax-test.json")
    check_output_file(tmp_path / "new" / "ok.json")  # a folder to be created is fine
    check_output_dir(tmp_path / "plots")
    assert not (tmp_path / "new").exists() and not (tmp_path / "plots").exists()


@pytest.fixture(scope="module")
def rank_defect():
    """A network in which scan S7 sees four collinear targets only: its rotation about that
    line is undetermined (a rank defect beyond the datum)."""
    sim = tj.simulate(tj.Room(n_targets=24), aps="none", noise=False, seed=1)
    net = sim.network
    X = np.array([[3.0 + 2 * k, 5.5, 2.9] for k in range(4)])

    def observe(eop):
        R = np.asarray(rotation_matrix(*eop[3:], xp=np))
        l = spherical_from_cartesian((X - eop[:3]) @ R.T, xp=np)
        l[:, 1] = np.mod(l[:, 1], 2 * np.pi)
        return l

    scans = [net.scans[j] for j in net.scan_index] + ["S1"] * 4 + ["S7"] * 4
    targets = [net.targets[t] for t in net.target_index] + [f"L{k}" for k in range(4)] * 2
    obs = np.vstack(
        [
            net.observations,
            observe(sim.true_eops[0]),
            observe(np.array([7.0, 4.0, 1.5, 0.0, 0.0, 0.4])),
        ]
    )
    net = tj.make_network(scans, targets, obs)
    # The approximate values refuse such a scan with a ValueError (test_approx.py); started
    # from the truth, the adjustment itself must find the defect and withhold the numbers.
    truth_t = dict(zip(sim.network.targets, sim.true_targets))
    truth_t.update({f"L{k}": X[k] for k in range(4)})
    truth_s = dict(zip(sim.network.scans, sim.true_eops))
    truth_s["S7"] = np.array([7.0, 4.0, 1.5, 0.0, 0.0, 0.4])
    initial = (
        np.array([truth_t[t] for t in net.targets]),
        np.array([truth_s[s] for s in net.scans]),
    )
    return tj.calibrate(net, tj.CalibrationModel(tj.Scanner(aps="A0")), initial=initial)


def test_a_failed_adjustment_reports_no_numbers(rank_defect, tmp_path):
    res = rank_defect
    assert res.result == tj.ResultCode.RANK_DEFICIENT and "S7" in res.message
    path = tmp_path / "rank.json"
    tj.write_json(res, path)
    d = load_strict(path)
    assert d["estimates"].startswith("withheld") and "S7" in d["estimates"]
    assert d["sigma0"] is None and d["ap_covariance"] is None
    assert all(v is None for a in d["aps"].values() for v in (a["value"], a["sigma"], a["t"]))
    for scan in d["eops"].values():
        assert all(scan[k] is None and scan["sigma"][k] is None for k in ("Xs", "kappa"))
    assert d["rank_deficient"] == list(res.rank_deficient)
    table = res.summary()
    assert "no estimates" in table and "mm" not in table.splitlines()[-1]


@pytest.mark.internal
def test_undetermined_scan_parameters_are_null_in_a_valid_result(rank_defect):
    from tlsjax._adjustment._json import _undetermined

    assert _undetermined(rank_defect) == {
        (n.split("[")[1].rstrip("]"), n.split("[")[0]) for n in rank_defect.rank_deficient
    }
