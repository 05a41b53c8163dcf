"""LAS/LAZ files through laspy (LAZ with its ``lazrs`` backend), read and written in chunks.

A LAS file holds object-space (registered, often map) coordinates as scaled integers. The scan's
pose (Xs, Ys, Zs, omega, phi, kappa) comes from a poses file or from the header: tlsjax stores it
as a variable-length record (VLR) with user id ``tlsjax`` and record id 1 holding six
little-endian float64 (:func:`pose_vlr`). With a pose the reader takes the points to scanner
space, ``x = R (X - S)``; without one they are taken as scanner space (and a median range of
kilometres is reported as map coordinates).

Before laspy sees a file its fixed header is checked by hand (signature, header size, the count
of VLRs against the bytes they may occupy, point count against the file size for uncompressed
files): laspy trusts these numbers and, given a garbage VLR count, tries to read a billion
records instead of failing.
"""

from __future__ import annotations

import os
import struct

import numpy as np

from .._optional import require
from ._raw_scan import RawScan

#: Points per chunk when reading or correcting a LAS/LAZ file.
LAS_CHUNK = 1 << 20
POSE_USER_ID = "tlsjax"
POSE_RECORD_ID = 1
_VLR_HEADER = 54  # bytes of one VLR header (LAS 1.0-1.4)


def _laspy():
    return require("laspy", "reading and writing LAS/LAZ")


def check_las_header(source: str) -> None:
    """Refuse a file whose fixed LAS header is inconsistent, with one line naming the cause."""
    size = os.path.getsize(source)
    with open(source, "rb") as fh:
        head = fh.read(375)
    if len(head) < 227 or head[:4] != b"LASF":
        raise ValueError(
            f"{source}: not a LAS/LAZ file (no 'LASF' signature and full header; {size} bytes)"
        )
    major, minor = head[24], head[25]
    (header_size,) = struct.unpack_from("<H", head, 94)
    (offset, n_vlr) = struct.unpack_from("<II", head, 96)
    fmt = head[104]
    (rec_len,) = struct.unpack_from("<H", head, 105)
    (n_legacy,) = struct.unpack_from("<I", head, 107)
    compressed = bool(fmt & 0x80 or fmt & 0x40)
    n_points = n_legacy
    if (major, minor) >= (1, 4) and len(head) >= 255:
        (n_points,) = struct.unpack_from("<Q", head, 247)
        n_points = n_points or n_legacy
    where = f"{source}: LAS {major}.{minor} header"
    if major != 1 or minor > 4:
        raise ValueError(f"{where}: version {major}.{minor} is not LAS 1.0-1.4")
    if header_size < 227 or header_size > size:
        raise ValueError(f"{where}: header size {header_size} is invalid")
    if offset < header_size or offset > size:
        raise ValueError(
            f"{where}: offset to point data {offset} is outside {header_size}..{size} bytes"
        )
    if n_vlr * _VLR_HEADER > offset - header_size:
        raise ValueError(
            f"{where}: claims {n_vlr} variable-length records, but only "
            f"{offset - header_size} bytes lie between the header and the points (corrupt count)"
        )
    if not compressed and n_points * rec_len > size - offset:
        raise ValueError(
            f"{where}: claims {n_points} points of {rec_len} bytes, but the file holds "
            f"{size - offset} bytes of point data (truncated or corrupt)"
        )


def pose_vlr(pose):
    """The tlsjax VLR that stores a scan pose (Xs, Ys, Zs, omega, phi, kappa) in a LAS header."""
    laspy = _laspy()
    data = struct.pack("<6d", *np.asarray(pose, dtype=np.float64))
    return laspy.VLR(POSE_USER_ID, POSE_RECORD_ID, "scan pose: X Y Z omega phi kappa", data)


def pose_from_header(header, source: str):
    """The pose stored by :func:`pose_vlr`, or None."""
    for vlr in list(header.vlrs) + list(getattr(header, "evlrs", None) or []):
        if getattr(vlr, "user_id", "") == POSE_USER_ID and vlr.record_id == POSE_RECORD_ID:
            data = bytes(getattr(vlr, "record_data", b""))
            if len(data) != 48:
                raise ValueError(
                    f"{source}: tlsjax pose record holds {len(data)} bytes, expected 48"
                )
            return np.array(struct.unpack("<6d", data))
    return None


def _laspy_call(source, what, fn, *args, **kw):
    """Run a laspy call; any failure but a missing library becomes one line naming the file."""
    try:
        return fn(*args, **kw)
    except ImportError:
        raise
    except Exception as err:  # laspy's LaspyException, lazrs errors, struct errors
        text = str(err).splitlines()[0] if str(err) else type(err).__name__
        if "LazBackend" in text or "lazrs" in text.lower():
            require("lazrs", "reading and writing LAZ")
        raise ValueError(f"{source}: {what}: {text}") from None


def open_las(source: str):
    """A laspy reader of ``source`` after :func:`check_las_header`."""
    laspy = _laspy()
    check_las_header(source)
    return _laspy_call(source, "not a readable LAS/LAZ file", laspy.open, source)


def iter_las_chunks(reader, source: str, chunk: int | None = None):
    """Yield the point records of a laspy reader chunk by chunk, errors as one line."""
    it = _laspy_call(source, "cannot read the points", reader.chunk_iterator, chunk or LAS_CHUNK)
    while True:
        pts = _laspy_call(source, "points unreadable", next, it, None)
        if pts is None:
            return
        yield pts


def read_las(source: str, stem: str) -> list[RawScan]:
    """One LAS/LAZ file as one :class:`RawScan` (object frame; pose from the tlsjax VLR)."""
    with open_las(source) as reader:
        header = reader.header
        pose = pose_from_header(header, source)
        parts = [
            np.stack([np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)], axis=1)
            for p in iter_las_chunks(reader, source)
        ]
    pts = np.concatenate(parts) if parts else np.zeros((0, 3))
    if len(pts) == 0:
        raise ValueError(f"{source}: the LAS/LAZ file holds no points")
    if len(pts) != header.point_count:
        raise ValueError(f"{source}: {len(pts)} points read, the header says {header.point_count}")
    return [RawScan(stem, pts, pose, object_frame=True)]


def write_las(path, points, pose=None, *, attributes=None, scale: float = 1e-4) -> None:
    """Write object-space points (n, 3) [m] as LAS (or LAZ by the extension), point format 3
    (intensity, colour, GPS time), with the scan ``pose`` stored in the tlsjax VLR when given.
    ``attributes``: optional dict of standard dimensions (e.g. ``intensity``, ``red``).
    ``scale`` [m]: coordinate resolution (0.1 mm)."""
    laspy = _laspy()
    X = np.asarray(points, dtype=np.float64)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.scales = np.full(3, scale)
    header.offsets = np.floor(X.min(axis=0)) if len(X) else np.zeros(3)
    if pose is not None:
        header.vlrs.append(pose_vlr(pose))
    las = laspy.LasData(header)
    las.x, las.y, las.z = X[:, 0], X[:, 1], X[:, 2]
    for k, v in (attributes or {}).items():
        las[k] = v
    from ._outputs import atomic_output

    with atomic_output(path) as tmp:
        las.write(tmp)
