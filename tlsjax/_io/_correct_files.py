"""``correct_point_cloud``: a point-cloud file in, the same format out, every point corrected by
:func:`~tlsjax._io._correct.correct_points` and every other attribute kept (see that module).

Per format: LAS/LAZ are streamed chunk by chunk through laspy (the coordinate resolution is
refined to at most 0.1 mm so that the correction is not rounded away; the precision goes into
an extra-bytes dimension ``calibration_sigma`` [m]); PTX and XYZ are streamed line by line, each
line keeping its other columns (intensity, colour) as written; PLY keeps every element and
property (the precision as a ``calibration_sigma`` vertex property); E57 keeps the scans' names,
poses, intensity, colour and grid indices (pye57 writes Cartesian coordinates; fields pye57 does
not know, e.g. normals, are not carried over and are named in the notes). For PTX, XYZ and E57
the precision goes to a side file ``<output>.sigma_mm.txt``, one value [mm] per stored point.
"""

from __future__ import annotations

import copy
import dataclasses
import os

import numpy as np

from ._correct import Calibration, correct_points
from ._outputs import atomic_output, same_file
from ._point_clouds import point_cloud_format

_TEXT_CHUNK = 1 << 18  # lines per chunk of a PTX or XYZ file


@dataclasses.dataclass(frozen=True)
class CorrectedScan:
    """What correcting one scan did: points stored and corrected, the largest and RMS shift of
    a point [m], the largest propagated sigma [m] (None without precision), and notes."""

    name: str
    source: str
    output: str
    n_points: int
    n_corrected: int
    max_shift: float
    rms_shift: float
    max_sigma: float | None
    notes: tuple = ()

    def line(self) -> str:
        sig = "" if self.max_sigma is None else f", max sigma {self.max_sigma * 1e3:.3f} mm"
        return (
            f"{self.source}: scan {self.name}: {self.n_corrected} of {self.n_points} points "
            f"corrected (shift RMS {self.rms_shift * 1e3:.3f} mm, max {self.max_shift * 1e3:.3f} mm"
            f"{sig}) -> {self.output}"
        )


class _Tally:
    def __init__(self):
        self.n = self.done = 0
        self.sq = self.mx = self.smx = 0.0

    def add(self, before, after, sigma):
        valid = np.all(np.isfinite(before), axis=1) & ~np.all(before == 0.0, axis=1)
        d = np.linalg.norm(after[valid] - before[valid], axis=1)
        self.n += len(before)
        self.done += int(valid.sum())
        self.sq += float(np.sum(d * d))
        self.mx = max(self.mx, float(d.max()) if len(d) else 0.0)
        self.smx = max(self.smx, float(np.max(sigma)) if len(sigma) else 0.0)

    def scan(self, name, source, output, precision, notes=()):
        rms = float(np.sqrt(self.sq / self.done)) if self.done else 0.0
        return CorrectedScan(
            name, source, output, self.n, self.done, self.mx, rms,
            self.smx if precision else None, tuple(notes),
        )  # fmt: skip


def _progress(total, progress, desc):
    from tqdm.auto import tqdm

    return tqdm(total=total, disable=not progress, unit="pt", unit_scale=True, desc=desc)


def correct_point_cloud(
    path,
    calibration: Calibration,
    out,
    *,
    poses=None,
    precision: bool = False,
    progress: bool = False,
) -> tuple[CorrectedScan, ...]:
    """Apply ``calibration`` to every scan of the point-cloud file ``path`` (E57, PTX, PLY,
    LAS/LAZ, XYZ) and write the corrected file ``out`` in the same format.

    ``poses``: mapping scan name -> pose (6,) for LAS/LAZ files without a stored pose (their
    coordinates are object space; the correction happens in scanner space). ``precision``:
    also propagate each point's sigma from the AP covariance. ``progress``: a progress bar.
    Returns one :class:`CorrectedScan` per scan.
    """
    src, dst = os.fspath(path), os.fspath(out)
    kind = point_cloud_format(src)
    if point_cloud_format(dst) != kind and {kind, point_cloud_format(dst)} != {"las"}:
        raise ValueError(f"{dst}: the output must have the input's format ({kind})")
    if not os.path.isfile(src):
        raise FileNotFoundError(2, "No such file or directory", src)
    if same_file(src, dst) or same_file(src, dst + ".sigma_mm.txt"):
        raise ValueError(f"{dst}: the output would overwrite the input {src}")
    stem = os.path.splitext(os.path.basename(src))[0]
    poses = poses or {}
    if kind == "pcd":
        raise ValueError(f"{src}: correcting PCD files is not supported; convert to PLY")
    # Written to a temporary file (and side file) renamed when complete: an error or Ctrl-C
    # leaves no half-written output and a previous output as it was.
    with atomic_output(dst, companions=(".sigma_mm.txt",)) as tmp:
        args = (src, tmp, calibration, precision, progress)
        try:
            if kind == "las":
                scans = (_correct_las(*args, stem, poses.get(stem)),)
            elif kind in ("ptx", "xyz"):
                scans = _correct_text(*args, stem, kind)
            elif kind == "ply":
                scans = (_correct_ply(*args, stem),)
            else:
                scans = _correct_e57(*args, stem)
        except ValueError as err:
            message = str(err).replace(tmp, dst)
            raise ValueError(message if message.startswith(src) else f"{src}: {message}") from None
    return tuple(dataclasses.replace(c, output=dst) for c in scans)


# --- LAS/LAZ -----------------------------------------------------------------------------


def _correct_las(src, dst, cal, precision, progress, stem, pose):
    from ._las import _laspy, _laspy_call, iter_las_chunks, open_las, pose_from_header

    laspy = _laspy()
    with open_las(src) as reader:
        header = reader.header
        pose = pose if pose is not None else pose_from_header(header, src)
        out_header = copy.deepcopy(header)
        scales = np.minimum(np.asarray(header.scales, dtype=np.float64), 1e-4)
        span = np.maximum(
            np.abs(header.maxs - header.offsets), np.abs(header.mins - header.offsets)
        )
        if np.all(span / scales < 2**31 - 1024):  # else keep the file's resolution
            out_header.scales = scales
        name = "calibration_sigma"
        if precision and name not in out_header.point_format.dimension_names:
            out_header.add_extra_dim(
                laspy.ExtraBytesParams(name, "f4", description="sigma of corrected point [m]")
            )
        tally, bar = _Tally(), _progress(header.point_count, progress, stem)
        with _laspy_call(dst, "cannot write", laspy.open, dst, mode="w", header=out_header) as w:
            for pts in iter_las_chunks(reader, src):
                X = np.stack([np.asarray(pts.x), np.asarray(pts.y), np.asarray(pts.z)], axis=1)
                Xc, sig = correct_points(X, cal, pose=pose, precision=precision)
                rec = laspy.ScaleAwarePointRecord.zeros(len(X), header=out_header)
                for dim in pts.point_format.dimension_names:
                    if dim not in ("X", "Y", "Z"):
                        rec[dim] = pts[dim]
                rec.x, rec.y, rec.z = Xc[:, 0], Xc[:, 1], Xc[:, 2]
                if precision:
                    rec[name] = sig.astype(np.float32)
                w.write_points(rec)
                tally.add(X, Xc, sig)
                bar.update(len(X))
        bar.close()
    notes = [] if pose is not None else [f"{src}: no scan pose: coordinates taken as scanner space"]
    return tally.scan(stem, src, dst, precision, notes)


# --- PTX and XYZ (text) ------------------------------------------------------------------


def _rewrite_lines(lines, first_line, src, cal, precision, tally, fout, sig_out, comments):
    """Correct a block of text lines (x y z [more columns]) and write them."""
    from ._point_clouds import _numeric_block

    data = [
        k
        for k, ln in enumerate(lines)
        if not (comments and (not ln.strip() or ln.lstrip().startswith(("#", "//"))))
    ]
    X = _numeric_block([lines[k] for k in data], first_line, src) if data else np.zeros((0, 3))
    Xc, sig = correct_points(X, cal, precision=precision)
    tally.add(X, Xc, sig)
    new = list(lines)
    for j, k in enumerate(data):
        fields = lines[k].replace(",", " ").split(None, 3)
        rest = " " + fields[3] if len(fields) > 3 else ""
        if np.array_equal(Xc[j], X[j]):
            continue  # unchanged point (no return): keep the line as written
        new[k] = f"{Xc[j, 0]:.6f} {Xc[j, 1]:.6f} {Xc[j, 2]:.6f}{rest}"
    fout.write("\n".join(new) + "\n")
    if sig_out is not None:
        np.savetxt(sig_out, sig * 1e3, fmt="%.4f")


def _take(fin, n):
    lines = []
    for _ in range(n):
        ln = fin.readline()
        if not ln:
            break
        lines.append(ln.rstrip("\r\n"))
    return lines


def _correct_text(src, dst, cal, precision, progress, stem, kind):
    """PTX (scan by scan: the 10 header lines copied, the point lines corrected) or XYZ."""
    results = []
    sig_out = open(dst + ".sigma_mm.txt", "w", encoding="utf-8") if precision else None
    bar = _progress(None, progress, stem)
    try:
        with open(src, encoding="utf-8") as fin, open(dst, "w", encoding="utf-8") as fout:
            line_no, k = 1, 0
            while True:
                if kind == "xyz":
                    n, tally = None, _Tally()
                else:
                    head = _take(fin, 10)
                    while head and not head[0].strip():  # blank lines between scans
                        fout.write("\n")
                        line_no += 1
                        head = head[1:] + _take(fin, 1)
                    if not head:
                        break
                    if len(head) < 10:
                        raise ValueError(f"{src}, line {line_no}: PTX header needs 10 lines")
                    try:
                        n = int(head[0].split()[0]) * int(head[1].split()[0])
                    except (ValueError, IndexError):
                        raise ValueError(
                            f"{src}, line {line_no}: PTX scan must start with columns and rows"
                        ) from None
                    fout.write("\n".join(head) + "\n")
                    line_no += 10
                    tally = _Tally()
                left = n
                while left is None or left > 0:
                    lines = _take(fin, _TEXT_CHUNK if left is None else min(left, _TEXT_CHUNK))
                    if not lines:
                        if left:
                            raise ValueError(f"{src}, line {line_no}: PTX scan ends early")
                        break
                    _rewrite_lines(
                        lines, line_no, src, cal, precision, tally, fout, sig_out, kind == "xyz"
                    )
                    line_no += len(lines)
                    left = None if left is None else left - len(lines)
                    bar.update(len(lines))
                k += 1
                if kind == "xyz":
                    results.append(tally.scan(stem, src, dst, precision))
                    break
                results.append(tally.scan(f"{stem}_{k}", src, dst, precision))
    finally:
        bar.close()
        if sig_out is not None:
            sig_out.close()
    if kind == "ptx" and len(results) == 1:
        results[0] = dataclasses.replace(results[0], name=stem)
    return tuple(results)


# --- PLY -----------------------------------------------------------------------------------


def _correct_ply(src, dst, cal, precision, progress, stem):
    from ._ply import _plyfile, read_ply_data

    plyfile = _plyfile()
    data, vertex = read_ply_data(src)
    arr = np.array(vertex.data)  # a copy: the input is memory-mapped read-only
    X = np.stack([arr[c].astype(np.float64) for c in "xyz"], axis=1)
    bar = _progress(len(X), progress, stem)
    Xc, sig = correct_points(X, cal, precision=precision, on_chunk=bar.update)
    bar.close()
    for i, c in enumerate("xyz"):
        arr[c] = Xc[:, i]
    notes = []
    if arr.dtype["x"].itemsize < 8:
        notes.append(f"{src}: coordinates are single precision in the file (about 1e-7 relative)")
    if precision:
        import numpy.lib.recfunctions as rfn

        if "calibration_sigma" in arr.dtype.names:
            arr["calibration_sigma"] = sig
        else:
            arr = rfn.append_fields(arr, "calibration_sigma", sig.astype("<f4"), usemask=False)
    elements = [
        plyfile.PlyElement.describe(arr, "vertex", comments=list(vertex.comments))
        if e.name == "vertex"
        else e
        for e in data.elements
    ]
    out = plyfile.PlyData(
        elements, text=data.text, byte_order=data.byte_order,
        comments=list(data.comments), obj_info=list(data.obj_info),
    )  # fmt: skip
    out.write(dst)
    tally = _Tally()
    tally.add(X, Xc, sig)
    return tally.scan(stem, src, dst, precision, notes)


# --- E57 -----------------------------------------------------------------------------------

_CART = ("cartesianX", "cartesianY", "cartesianZ")
_SPH = ("sphericalRange", "sphericalAzimuth", "sphericalElevation", "sphericalInvalidState")


def _e57_scan_out(e57, header, src, k, cal, precision, bar):
    from ._e57 import _e57_call

    fields = list(header.point_fields)
    data = _e57_call(src, f"scan {k + 1}: points unreadable", e57.read_scan_raw, k, True)
    dropped = [f for f in fields if f not in data]
    if all(f in data for f in _CART):
        X = np.stack([data[f].astype(np.float64) for f in _CART], axis=1)
        state = data.get("cartesianInvalidState")
    else:
        r, az, el = (data[f].astype(np.float64) for f in _SPH[:3])
        X = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
        state = data.get("sphericalInvalidState")
        if state is not None:
            data["cartesianInvalidState"] = state
        dropped += [f for f in _SPH if f in data]
    for f in _SPH:
        data.pop(f, None)
    valid = np.ones(len(X), dtype=bool) if state is None else np.asarray(state) == 0
    Xc, sig = X.copy(), np.zeros(len(X))
    Xc[valid], sig[valid] = correct_points(X[valid], cal, precision=precision, on_chunk=bar.update)
    for i, f in enumerate(_CART):
        data[f] = Xc[:, i]
    return data, X, Xc, sig, valid, dropped


def _correct_e57(src, dst, cal, precision, progress, stem):
    from ._e57 import _e57_call, open_e57

    e57 = open_e57(src)
    results = []
    try:
        n_scans = int(_e57_call(src, "cannot count the scans", lambda: e57.scan_count))
        if n_scans == 0:
            raise ValueError(f"{src}: the E57 file holds no scans")
        writer = open_e57(dst, mode="w")
        sig_out = open(dst + ".sigma_mm.txt", "w", encoding="utf-8") if precision else None
        try:
            for k in range(n_scans):
                header = _e57_call(src, f"scan {k + 1}: unreadable header", e57.get_header, k)
                name = f"{stem}_{k + 1}" if n_scans > 1 else stem
                bar = _progress(int(header.point_count), progress, name)
                data, X, Xc, sig, valid, dropped = _e57_scan_out(
                    e57, header, src, k, cal, precision, bar
                )
                bar.close()
                kw = {}
                if header.has_pose():
                    kw = dict(rotation=header.rotation, translation=header.translation)
                try:
                    label = header.node["name"].value()
                except Exception:  # the name is optional in E57
                    label = name
                _e57_call(dst, "cannot write", writer.write_scan_raw, data, name=label, **kw)
                if sig_out is not None:
                    np.savetxt(sig_out, sig * 1e3, fmt="%.4f")
                tally = _Tally()
                tally.add(np.where(valid[:, None], X, 0.0), Xc * valid[:, None], sig)
                notes = [f"{src}: scan {name}: fields not carried over: {', '.join(dropped)}"]
                results.append(tally.scan(name, src, dst, precision, notes if dropped else ()))
        finally:
            writer.close()
            if sig_out is not None:
                sig_out.close()
    finally:
        e57.close()
    return tuple(results)
