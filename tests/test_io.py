"""Observation and scan CSV files (SPEC section 11): units, round trips and error messages.

Private imports: ``ObservationTable``, the table type the readers return, and the unit-suffix
parser of the CSV grammar (``_io._csv``).
"""

import math
import re

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import ObservationTable, read_observations, read_scans, write_observations

DEG = math.pi / 180.0
GON = math.pi / 200.0
ARCSEC = DEG / 3600.0


def write(tmp_path, text, name="obs.csv"):
    path = tmp_path / name
    path.write_text(text)
    return path


def where(path, line, column=None):
    """Regex for the location prefix of an error message."""
    text = f"{path}, line {line}" + (f", column {column}" if column else "")
    return re.escape(text)


GOOD = """scan,target,range_m,hz_deg,el_deg
S1,T1,10.0,45.0,10.0
S1,T2,12.5,90.0,-5.0
S2,T1,11.0,180.0,100.0
"""


# --------------------------------------------------------------------------------------------
# Units
# --------------------------------------------------------------------------------------------


@pytest.mark.internal
@pytest.mark.parametrize(
    "header, expected",
    [
        ("hz_deg", ("hz", "deg", DEG)),
        ("el_rad", ("el", "rad", 1.0)),
        ("hz_gon", ("hz", "gon", GON)),
        ("sigma_hz_arcsec", ("sigma_hz", "arcsec", ARCSEC)),
        ("range_mm", ("range", "mm", 1e-3)),
        ("sigma_range_m", ("sigma_range", "m", 1.0)),
        ("incidence_deg", ("incidence", "deg", DEG)),
        ("sigma_omega_arcsec", ("sigma_omega", "arcsec", ARCSEC)),
    ],
)
def test_parse_unit_column(header, expected):
    from tlsjax._io._csv import parse_unit_column

    q, u, f = parse_unit_column(header)
    assert (q, u) == expected[:2]
    assert f == pytest.approx(expected[2], rel=1e-15)


@pytest.mark.internal
def test_unit_factors_against_hand_values():
    from tlsjax._io._csv import parse_unit_column

    assert 200.0 * parse_unit_column("hz_gon")[2] == pytest.approx(math.pi, rel=1e-15)
    assert 3600.0 * parse_unit_column("hz_arcsec")[2] == pytest.approx(DEG, rel=1e-15)
    assert 1500.0 * parse_unit_column("range_mm")[2] == pytest.approx(1.5, rel=1e-15)
    assert 180.0 * parse_unit_column("el_deg")[2] == pytest.approx(math.pi, rel=1e-15)


@pytest.mark.internal
@pytest.mark.parametrize(
    "header, message",
    [
        ("hz", "missing unit suffix"),
        ("range_km", "unknown unit suffix '_km'"),
        ("range_deg", "length"),
        ("hz_mm", "angle"),
    ],
)
def test_parse_unit_column_errors(header, message):
    from tlsjax._io._csv import parse_unit_column

    with pytest.raises(ValueError, match=message):
        parse_unit_column(header)


def test_read_converts_units(tmp_path):
    path = write(
        tmp_path,
        "scan,target,range_mm,hz_gon,el_arcsec,sigma_range_mm,sigma_hz_arcsec,sigma_el_deg,"
        "incidence_deg\n"
        "S1,T1,1500,200,3600,0.5,20,0.01,30\n",
    )
    t = read_observations(path)
    np.testing.assert_allclose(t.observations, [[1.5, math.pi, DEG]], rtol=1e-15)
    np.testing.assert_allclose(t.sigmas, [[0.5e-3, 20 * ARCSEC, 0.01 * DEG]], rtol=1e-15)
    np.testing.assert_allclose(t.incidence, [30 * DEG], rtol=1e-15)
    assert t.observations.dtype == np.float64


def test_read_basic_table(tmp_path):
    path = write(tmp_path, GOOD)
    t = read_observations(path)
    assert isinstance(t, ObservationTable)
    assert t.kind == "target"
    assert t.source == str(path)
    assert t.scans == ("S1", "S1", "S2")
    assert t.primitives == ("T1", "T2", "T1")
    assert t.sigmas is None and t.incidence is None and t.instruments is None
    np.testing.assert_array_equal(t.rows, [2, 3, 4])
    np.testing.assert_allclose(t.observations[:, 0], [10.0, 12.5, 11.0])
    np.testing.assert_allclose(
        t.observations[:, 1], np.array([45.0, 90.0, 180.0]) * DEG, rtol=1e-15
    )
    # el is not wrapped: panoramic elevations live in [-pi/2, 3pi/2).
    np.testing.assert_allclose(
        t.observations[:, 2], np.array([10.0, -5.0, 100.0]) * DEG, rtol=1e-15
    )


def test_names_stripped_quoting_and_blank_lines(tmp_path):
    path = write(
        tmp_path,
        " scan , target ,range_m,hz_deg,el_deg,instrument\n"
        '  S 1 ,"T,1",10,0,0, scanner A \n'
        "\n"
        "S2,T2,10,0,0,B\n",
    )
    t = read_observations(path)
    assert t.scans == ("S 1", "S2")
    assert t.primitives == ("T,1", "T2")
    assert t.instruments == ("scanner A", "B")
    np.testing.assert_array_equal(t.rows, [2, 4])


def test_hz_wrapping(tmp_path):
    path = write(
        tmp_path,
        "scan,target,range_m,hz_deg,el_deg\nS1,T1,10,-10,-10\nS1,T2,10,370,0\n"
        "S1,T3,10,360,0\nS1,T4,10,-1e-30,0\n",
    )
    t = read_observations(path)
    np.testing.assert_allclose(
        t.observations[:3, 1], np.array([350.0, 10.0, 0.0]) * DEG, rtol=1e-14, atol=1e-15
    )
    assert np.all((t.observations[:, 1] >= 0) & (t.observations[:, 1] < 2 * math.pi))
    assert t.observations[0, 2] == pytest.approx(-10 * DEG)


def test_partial_sigma_columns_are_nan(tmp_path):
    path = write(
        tmp_path,
        "scan,target,range_m,hz_deg,el_deg,sigma_hz_arcsec\nS1,T1,10,0,0,15\nS1,T2,10,0,0,\n",
    )
    t = read_observations(path)
    assert t.sigmas.shape == (2, 3)
    assert np.isnan(t.sigmas[:, 0]).all() and np.isnan(t.sigmas[:, 2]).all()
    assert t.sigmas[0, 1] == pytest.approx(15 * ARCSEC)
    assert np.isnan(t.sigmas[1, 1])


def test_header_case_and_bom(tmp_path):
    path = tmp_path / "obs.csv"
    path.write_bytes("\ufeffScan,Target,Range_M,HZ_deg,El_Deg\nS1,T1,10,0,0\n".encode("utf-8"))
    t = read_observations(path)
    assert t.kind == "target" and t.scans == ("S1",)


# --------------------------------------------------------------------------------------------
# Planes
# --------------------------------------------------------------------------------------------


def test_plane_file(tmp_path):
    path = write(
        tmp_path,
        "scan,plane,range_m,hz_rad,el_rad\nS1,P1,5,0.1,0.2\nS1,P1,5.1,0.15,0.2\nS2,P1,4,1,0\n",
        "planes.csv",
    )
    t = read_observations(path)
    assert t.kind == "plane"
    assert t.primitives == ("P1", "P1", "P1")  # many points per (scan, plane) are fine
    np.testing.assert_allclose(t.observations[1], [5.1, 0.15, 0.2])


def test_mixed_targets_and_planes(tmp_path):
    path = write(tmp_path, "scan,target,plane,range_m,hz_deg,el_deg\nS1,T1,P1,1,0,0\n")
    with pytest.raises(
        ValueError, match=where(path, 1, "plane") + ".*may not mix targets and planes"
    ):
        read_observations(path)


# --------------------------------------------------------------------------------------------
# Round trips
# --------------------------------------------------------------------------------------------


def random_table(kind="target", n=40, with_extras=True, seed=0):
    rng = np.random.default_rng(seed)
    obs = np.column_stack(
        [
            rng.uniform(0.5, 80.0, n),
            rng.uniform(0, 2 * np.pi, n),
            rng.uniform(-np.pi / 2, 3 * np.pi / 2, n),
        ]
    )
    sig = np.column_stack(
        [rng.uniform(1e-4, 2e-3, n), rng.uniform(1, 30, n) * ARCSEC, rng.uniform(1, 30, n) * ARCSEC]
    )
    sig[3, 1] = np.nan  # a missing cell round-trips as NaN
    prims = tuple(f"{kind[0].upper()}{i}" for i in range(n))
    return ObservationTable(
        kind=kind,
        source="mem",
        scans=tuple(f"S{i % 3}" for i in range(n)),
        primitives=prims,
        observations=obs,
        sigmas=sig if with_extras else None,
        incidence=rng.uniform(0, 1.4, n) if with_extras else None,
        instruments=tuple("scanner, A" if i % 2 else "B" for i in range(n))
        if with_extras
        else None,
        rows=np.arange(2, n + 2),
    )


@pytest.mark.parametrize("length_unit", ["m", "mm"])
@pytest.mark.parametrize("angle_unit", ["rad", "deg", "gon", "arcsec"])
def test_round_trip(tmp_path, length_unit, angle_unit):
    table = random_table()
    path = tmp_path / "out.csv"
    write_observations(path, table, length_unit=length_unit, angle_unit=angle_unit)
    header = path.read_text().splitlines()[0].split(",")
    assert f"range_{length_unit}" in header and f"hz_{angle_unit}" in header
    back = read_observations(path)
    assert back.kind == "target"
    assert back.scans == table.scans and back.primitives == table.primitives
    assert back.instruments == table.instruments
    np.testing.assert_allclose(back.observations, table.observations, rtol=1e-12)
    np.testing.assert_allclose(back.sigmas, table.sigmas, rtol=1e-12)  # NaN == NaN here
    np.testing.assert_allclose(back.incidence, table.incidence, rtol=1e-12)
    np.testing.assert_array_equal(back.rows, np.arange(2, len(table) + 2))


def test_round_trip_plane_without_extras(tmp_path):
    table = random_table(kind="plane", with_extras=False)
    path = tmp_path / "planes.csv"
    write_observations(path, table)
    back = read_observations(path)
    assert back.kind == "plane"
    assert back.sigmas is None and back.incidence is None and back.instruments is None
    np.testing.assert_allclose(back.observations, table.observations, rtol=1e-12)


def test_write_rejects_bad_units(tmp_path):
    with pytest.raises(ValueError, match="length_unit"):
        write_observations(tmp_path / "x.csv", random_table(), length_unit="deg")
    with pytest.raises(ValueError, match="angle_unit"):
        write_observations(tmp_path / "x.csv", random_table(), angle_unit="mm")


# --------------------------------------------------------------------------------------------
# Errors: every message names the file, the line and (where it applies) the column
# --------------------------------------------------------------------------------------------

HEAD = "scan,target,range_m,hz_deg,el_deg\n"


@pytest.mark.parametrize(
    "text, line, column, message",
    [
        # header problems
        (
            "scan,target,range,hz_deg,el_deg\nS1,T1,1,0,0\n",
            1,
            "range",
            "missing unit suffix.*_m, _mm",
        ),
        (
            "scan,target,range_km,hz_deg,el_deg\nS1,T1,1,0,0\n",
            1,
            "range_km",
            "unknown unit suffix '_km'.*_m, _mm",
        ),
        (
            "scan,target,range_m,hz_furlong,el_deg\nS1,T1,1,0,0\n",
            1,
            "hz_furlong",
            "_rad, _deg, _gon, _arcsec",
        ),
        ("scan,target,range_deg,hz_deg,el_deg\nS1,T1,1,0,0\n", 1, "range_deg", "length.*angle"),
        ("scan,target,range_m,hz_deg,el_m\nS1,T1,1,0,0\n", 1, "el_m", "angle.*length"),
        ("scan,target,range_m,hz_deg\nS1,T1,1,0\n", 1, "el_<unit>", "missing required column"),
        ("target,range_m,hz_deg,el_deg\nT1,1,0,0\n", 1, "scan", "missing required column"),
        ("scan,range_m,hz_deg,el_deg\nS1,1,0,0\n", 1, "target", "missing required column.*plane"),
        ("scan,target,range_m,hz_deg,hz_rad,el_deg\nS1,T1,1,0,0,0\n", 1, "hz_rad", "given twice"),
        # row problems
        (HEAD + "S1,T1,1,0,0\nS1,T2,1,0\n", 3, None, "expected 5 fields, found 4"),
        (HEAD + "S1,T1,1,0,0,7\n", 2, None, "expected 5 fields, found 6"),
        (HEAD + "S1,T1,1,0,0\nS1,T2,1,abc,0\n", 3, "hz_deg", "'abc' is not a number"),
        (HEAD + "S1,T1,1,0,nan\n", 2, "el_deg", "not a finite number"),
        (HEAD + "S1,T1,inf,0,0\n", 2, "range_m", "not a finite number"),
        (HEAD + "S1,T1,1,,0\n", 2, "hz_deg", "empty value"),
        (HEAD + "S1,T1,0,0,0\n", 2, "range_m", "range must be positive"),
        (HEAD + "S1,T1,-2,0,0\n", 2, "range_m", "range must be positive"),
        (HEAD + " ,T1,1,0,0\n", 2, "scan", "empty scan name"),
        (HEAD + "S1,,1,0,0\n", 2, "target", "empty target name"),
        (
            HEAD + "S1,T1,1,0,0\nS2,T1,1,0,0\nS1,T1,2,0,0\n",
            4,
            "target",
            r"duplicate.*lines 2 and 4",
        ),
        (
            "scan,target,range_m,hz_deg,el_deg,sigma_range_mm\nS1,T1,1,0,0,0\n",
            2,
            "sigma_range_mm",
            "sigma must be positive",
        ),
        (
            "scan,target,range_m,hz_deg,el_deg,sigma_hz_arcsec\nS1,T1,1,0,0,-3\n",
            2,
            "sigma_hz_arcsec",
            "sigma must be positive",
        ),
        (
            "scan,target,range_m,hz_deg,el_deg,sigma_el_arcsec\nS1,T1,1,0,0,x\n",
            2,
            "sigma_el_arcsec",
            "not a number",
        ),
        (
            "scan,target,range_m,hz_deg,el_deg,incidence_deg\nS1,T1,1,0,0,inf\n",
            2,
            "incidence_deg",
            "not a finite",
        ),
        (
            "scan,target,range_m,hz_deg,el_deg,instrument\nS1,T1,1,0,0,\n",
            2,
            "instrument",
            "empty instrument",
        ),
    ],
)
def test_observation_errors(tmp_path, text, line, column, message):
    path = write(tmp_path, text)
    with pytest.raises(ValueError, match=where(path, line, column) + ".*" + message):
        read_observations(path)


def test_unknown_columns_are_named(tmp_path):
    path = write(
        tmp_path, "scan,target,range_m,hz_deg,el_deg,sigma_rnage_mm,comment\nS1,T1,1,0,0,1,x\n"
    )
    with pytest.raises(
        ValueError, match=where(path, 1) + ".*unknown column.*'sigma_rnage_mm', 'comment'"
    ):
        read_observations(path)


def test_levelling_column_in_observation_file_is_unknown(tmp_path):
    path = write(tmp_path, "scan,target,range_m,hz_deg,el_deg,omega_deg\nS1,T1,1,0,0,1\n")
    with pytest.raises(ValueError, match="unknown column.*'omega_deg'"):
        read_observations(path)


def test_empty_file(tmp_path):
    path = write(tmp_path, "")
    with pytest.raises(ValueError, match=where(path, 1) + ".*empty file"):
        read_observations(path)
    path = write(tmp_path, "\n\n", "blank.csv")
    with pytest.raises(ValueError, match=where(path, 1) + ".*empty file"):
        read_observations(path)


def test_header_only(tmp_path):
    path = write(tmp_path, HEAD)
    with pytest.raises(ValueError, match=where(path, 2) + ".*no data rows"):
        read_observations(path)


def test_wrong_delimiter(tmp_path):
    path = write(tmp_path, "scan;target;range_m;hz_deg;el_deg\nS1;T1;1;0;0\n")
    with pytest.raises(ValueError, match=where(path, 1) + ".*delimiter must be ','"):
        read_observations(path)


def test_line_numbers_after_multiline_field(tmp_path):
    path = write(tmp_path, HEAD + 'S1,"T\n1",1,0,0\nS1,T2,1,bad,0\n')
    with pytest.raises(ValueError, match=where(path, 4, "hz_deg")):
        read_observations(path)


# --------------------------------------------------------------------------------------------
# Scans file
# --------------------------------------------------------------------------------------------


def test_read_scans(tmp_path):
    path = write(
        tmp_path,
        "scan,omega_deg,phi_gon,sigma_omega_arcsec,sigma_phi_arcsec\n"
        "S1,0.01,-0.02,10,12\n"
        "S2,,,5,5\n"
        "S3,0.5,0.5,,\n",
        "scans.csv",
    )
    scans = read_scans(path)
    assert set(scans) == {"S1", "S2"}  # S3 is not levelled
    assert scans["S1"]["omega"] == pytest.approx(0.01 * DEG, rel=1e-15)
    assert scans["S1"]["phi"] == pytest.approx(-0.02 * GON, rel=1e-15)
    assert scans["S1"]["sigma_omega"] == pytest.approx(10 * ARCSEC, rel=1e-15)
    assert scans["S1"]["sigma_phi"] == pytest.approx(12 * ARCSEC, rel=1e-15)
    assert scans["S2"]["omega"] == 0.0 and scans["S2"]["phi"] == 0.0


def test_read_scans_without_sigmas_levels_nothing(tmp_path):
    # Levelling angles without sigma columns are refused (issue 13: they were dropped silently).
    path = write(tmp_path, "scan,omega_rad,phi_rad\nS1,0.001,0.002\n", "scans.csv")
    with pytest.raises(ValueError, match=where(path, 2, "omega_rad") + ".*no sigma columns"):
        read_scans(path)
    path = write(tmp_path, "scan,omega_rad,phi_rad\nS1,,\n", "empty.csv")
    assert read_scans(path) == {}
    path = write(tmp_path, "scan\n", "only.csv")
    assert read_scans(path) == {}


@pytest.mark.parametrize(
    "text, line, column, message",
    [
        (
            "scan,sigma_omega_arcsec,sigma_phi_arcsec\nS1,1,1\nS2,1,1\nS1,2,2\n",
            4,
            "scan",
            "duplicate scan.*lines 2 and 4",
        ),
        (
            "scan,omega,sigma_omega_arcsec,sigma_phi_arcsec\nS1,0,1,1\n",
            1,
            "omega",
            "missing unit suffix",
        ),
        ("scan,omega_mm,sigma_omega_arcsec,sigma_phi_arcsec\nS1,0,1,1\n", 1, "omega_mm", "angle"),
        (
            "scan,omega_deg,sigma_omega_arcsec,sigma_phi_arcsec\nS1,x,1,1\n",
            2,
            "omega_deg",
            "'x' is not a number",
        ),
        (
            "scan,sigma_omega_arcsec,sigma_phi_arcsec\nS1,0,1\n",
            2,
            "sigma_omega_arcsec",
            "sigma must be positive",
        ),
        (
            "scan,sigma_omega_arcsec,sigma_phi_arcsec\nS1,1,nan\n",
            2,
            "sigma_phi_arcsec",
            "not a finite",
        ),
        (
            "scan,sigma_omega_arcsec,sigma_phi_arcsec\nS1,1,\n",
            2,
            "sigma_phi_arcsec",
            "both or neither",
        ),
        ("scan,sigma_omega_arcsec\nS1,1\n", 1, "sigma_omega_arcsec", "sigma_phi_<unit>"),
        ("scan,sigma_omega_arcsec,sigma_phi_arcsec\n,1,1\n", 2, "scan", "empty scan name"),
        (
            "scan,sigma_omega_arcsec,sigma_phi_arcsec\nS1,1,1,1\n",
            2,
            None,
            "expected 3 fields, found 4",
        ),
        (
            "omega_deg,sigma_omega_arcsec,sigma_phi_arcsec\n0,1,1\n",
            1,
            "scan",
            "missing required column",
        ),
    ],
)
def test_scan_errors(tmp_path, text, line, column, message):
    path = write(tmp_path, text, "scans.csv")
    with pytest.raises(ValueError, match=where(path, line, column) + ".*" + message):
        read_scans(path)


def test_scan_unknown_column(tmp_path):
    path = write(
        tmp_path, "scan,heading_deg,sigma_omega_arcsec,sigma_phi_arcsec\nS1,0,1,1\n", "scans.csv"
    )
    with pytest.raises(ValueError, match=where(path, 1) + ".*unknown column.*'heading_deg'"):
        read_scans(path)
    path = write(tmp_path, "", "empty.csv")
    with pytest.raises(ValueError, match=where(path, 1) + ".*empty file"):
        read_scans(path)


# --------------------------------------------------------------------------------------------
# Issue 13: file-system failures and angle ranges at the boundary
# --------------------------------------------------------------------------------------------


def test_a_directory_or_binary_file_is_one_line(tmp_path):
    with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path))}: is a directory, not a CSV"):
        read_observations(tmp_path)
    with pytest.raises(ValueError, match="is a directory, not a CSV"):
        read_scans(tmp_path)
    with pytest.raises(ValueError, match="is a directory, not a plane file"):
        tj.read_network(planes=tmp_path)
    binary = tmp_path / "scan.e57"
    binary.write_bytes(bytes(range(256)) * 4)
    with pytest.raises(ValueError, match="scan.e57, line 1: not a text CSV file"):
        read_observations(binary)
    with pytest.raises(FileNotFoundError):
        read_observations(tmp_path / "missing.csv")


@pytest.mark.parametrize(
    "row, column, message",
    [
        ("S1,T1,10,720,0", "hz_deg", r"hz = 720 \(720 deg\) is two turns or more"),
        ("S1,T1,10,-725,0", "hz_deg", "hz = -725 .*two turns or more"),
        ("S1,T1,10,10,-120", "el_deg", r"el = -120 \(-120 deg\) is below -90 deg"),
        ("S1,T1,10,10,270", "el_deg", "el = 270 .*not below 270 deg"),
    ],
)
def test_angles_beyond_any_scanner_are_refused_before_wrapping(tmp_path, row, column, message):
    path = write(tmp_path, HEAD + row + "\n")
    with pytest.raises(ValueError, match=where(path, 2, column) + ": " + message):
        read_observations(path)


def test_degrees_in_a_radian_column_are_caught(tmp_path):
    path = write(
        tmp_path, "scan,target,range_m,hz_rad,el_rad\nS1,T1,10,0.5,0.1\nS1,T2,9,126.03,-7.05\n"
    )
    with pytest.raises(ValueError, match=where(path, 3, "hz_rad") + ".*two turns"):
        read_observations(path)


def test_elevation_past_the_zenith_needs_a_panoramic_file(tmp_path):
    rows = "".join(
        f"S{j},T{t},{5 + t},{20 * t + 100 * j},{-10 + 3 * t}\n" for j in (1, 2) for t in range(6)
    )
    path = write(tmp_path, HEAD + rows.replace("S2,T5,10,300,5", "S2,T5,10,300,95"))
    with pytest.raises(ValueError, match=where(path, 13) + ": el of scan S2, target T5 = 95 deg"):
        tj.read_network(path)
    with pytest.raises(ValueError, match=where(path, 13) + ".*a hybrid scanner observes"):
        tj.read_network(path, architecture="hybrid")


def test_a_repeated_plane_point_is_refused_with_both_lines(tmp_path):
    """Issue 39 item 7: one row of a plane file repeated would count one observation twice,
    and the thinning of ``tlsjax calibrate`` would hide it: the reader names both lines."""
    rows = ["scan,plane,range_m,hz_deg,el_deg", "S1,P1,5.0,10.0,-20.0", "S1,P1,5.1,11.0,-20.0"]
    rows += ["S2,P1,5.0,10.0,-20.0", "S1,P1,5.1,11.0,-20.0"]  # same values in S2: not a repeat
    path = tmp_path / "planes.csv"
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(
        ValueError, match=r"line 5: duplicate point of plane 'P1' in scan 'S1' \(lines 3 and 5"
    ):
        tj.read_planes(path)
    path.write_text("\n".join(rows[:4]) + "\n")
    assert len(tj.read_planes(path)) == 3
