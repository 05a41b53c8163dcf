"""A picture per scan of the targets extracted from it."""

from __future__ import annotations

import os
import re

import numpy as np

from ._plots import _pyplot, _save

_MARKERS = {"sphere": "o", "checkerboard": "s", "circle": "D"}


def plot_targets(targets, scan, path) -> None:
    """Panorama of scan ``scan`` (name or index) of :class:`~tlsjax.ExtractedTargets`:
    horizontal direction against elevation angle (hybrid, degrees) of its thinned voxel cloud
    in grey (normalised intensity, or range without intensity), the accepted targets as green
    markers with their names, the rejected candidates as red crosses."""
    plt = _pyplot()
    j = targets.scans.index(scan) if isinstance(scan, str) else int(scan)
    theta, alpha, value, what = targets.previews[j]
    fig, ax = plt.subplots(figsize=(14, 5.5))
    lo, hi = np.nanpercentile(value, [1, 99]) if len(value) else (0.0, 1.0)
    ax.scatter(
        np.degrees(theta), np.degrees(alpha), c=value, s=float(np.clip(4e4 / max(len(value), 1), 0.2, 4.0)),
        cmap="gray", vmin=lo, vmax=hi,
        rasterized=True, linewidths=0,
    )  # fmt: skip
    rows = np.flatnonzero(targets.scan_index == j)
    X = targets.centre[rows]
    rho = np.linalg.norm(X, axis=1)
    th = np.degrees(np.mod(np.arctan2(X[:, 1], X[:, 0]), 2 * np.pi))
    al = np.degrees(np.arcsin(np.clip(X[:, 2] / np.maximum(rho, 1e-12), -1, 1)))
    for i, t, a in zip(rows, th, al):
        if targets.accepted[i]:
            ax.plot(t, a, _MARKERS.get(targets.kind[i], "o"), mfc="none", mec="lime", ms=9, mew=1.5)
            ax.annotate(str(targets.names[i]) or "?", (t, a), xytext=(4, 4),
                        textcoords="offset points", color="lime", fontsize=7)  # fmt: skip
        else:
            ax.plot(t, a, "x", color="red", ms=4, mew=0.8)
    n_acc = int(targets.accepted[rows].sum())
    ax.set_title(
        f"scan {targets.scans[j]}: {n_acc} targets accepted (green), "
        f"{len(rows) - n_acc} candidates rejected (red); background: {what}"
    )
    ax.set_xlabel("horizontal direction [deg]")
    ax.set_ylabel("elevation angle [deg]")
    ax.set_xlim(0, 360)
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)


def picture_name(scan: str) -> str:
    """File name of the picture of scan ``scan``: its name with characters other than letters,
    digits, ``_.-`` replaced by ``_``, then ``.png``."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", scan) + ".png"


def target_picture_names(targets) -> list[str]:
    """The file names :func:`plot_all_targets` writes, one per scan of ``targets`` (a
    :class:`tlsjax.TargetMatching` or :class:`tlsjax.ExtractedTargets`), so that a caller can
    check the folder before any picture is drawn."""
    return [picture_name(name) for name in targets.scans]


def plot_all_targets(targets, folder) -> list[str]:
    """:func:`plot_targets` for every scan into ``folder/<scan>.png``; returns the paths."""
    os.makedirs(folder, exist_ok=True)
    paths = []
    for j, name in enumerate(target_picture_names(targets)):
        path = os.path.join(folder, name)
        plot_targets(targets, j, path)
        paths.append(path)
    return paths
