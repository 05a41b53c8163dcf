"""Plots of a calibration for model identification (Chow et al. 2013, figs. 2-13; Lichti &
Licht 2006, figs. 1-3): residuals of each observation group against range, horizontal
direction and elevation angle, and the correlation matrix of the APs.

Host side, matplotlib with the Agg backend; lengths in mm, angles in arc seconds, abscissae in
m and degrees, units in every label.
"""

from __future__ import annotations

import os

import numpy as np

ARCSEC = np.pi / 648000.0
GROUP_LABELS = ("range residual [mm]", 'horizontal direction residual ["]', 'elevation angle residual ["]')
GROUP_FACTORS = (1e3, 1.0 / ARCSEC, 1.0 / ARCSEC)
ABSCISSAE = (("range [m]", 1.0), ("horizontal direction [deg]", 180.0 / np.pi), ("elevation angle [deg]", 180.0 / np.pi))


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_residuals(result, path, *, title: str | None = None):
    """3 x 3 grid: residuals ``v = F + Delta - l`` of range, hz and el (rows) against the
    observed range, horizontal direction and elevation angle (columns). Writes PNG or SVG by
    the file name's extension and returns the path."""
    plt = _pyplot()
    l = np.asarray(result.network.observations)
    v = np.asarray(result.residuals)
    fig, axes = plt.subplots(3, 3, figsize=(12, 9), sharey="row")
    for g in range(3):
        for c, (xlabel, xf) in enumerate(ABSCISSAE):
            ax = axes[g, c]
            ax.plot(l[:, c] * xf, v[:, g] * GROUP_FACTORS[g], ".", ms=2, alpha=0.6)
            ax.axhline(0.0, color="k", lw=0.5)
            if g == 2:
                ax.set_xlabel(xlabel)
            if c == 0:
                ax.set_ylabel(GROUP_LABELS[g])
    fig.suptitle(title or f"Residuals after self-calibration (APs: {' '.join(result.ap_names) or 'none'})")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def plot_ap_correlations(result, path):
    """Absolute correlations among the APs (datum invariant block of the cofactor matrix)."""
    plt = _pyplot()
    C = np.asarray(result.ap_covariance, dtype=float)
    s = np.sqrt(np.diag(C))
    with np.errstate(invalid="ignore", divide="ignore"):
        R = np.abs(C / np.outer(s, s))
    n = len(result.ap_names)
    fig, ax = plt.subplots(figsize=(1.0 + 0.35 * max(n, 4), 0.8 + 0.35 * max(n, 4)))
    im = ax.imshow(R, vmin=0.0, vmax=1.0, cmap="viridis")
    ax.set_xticks(range(n), result.ap_names, rotation=90)
    ax.set_yticks(range(n), result.ap_names)
    fig.colorbar(im, ax=ax, label="|correlation| [-]")
    ax.set_title("AP correlations (non-estimable APs blank)")
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


def _save(fig, path):
    os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
    fig.savefig(path, dpi=110)
