"""Plots of a calibration for model identification (Chow et al. 2013, figs. 2-13; Lichti &
Licht 2006, figs. 1-3): residuals of each observation group against range, horizontal
direction and elevation angle, and the correlation matrix of the APs.

Host side, matplotlib with the Agg backend; lengths in mm, angles in arc seconds, abscissae in
m and degrees, units in every label.
"""

from __future__ import annotations

import math
import os

import numpy as np

from .._units import ARCSEC, display_unit

GROUP_LABELS = (
    "range residual [mm]",
    'horizontal direction residual ["]',
    'elevation angle residual ["]',
)
GROUP_FACTORS = (1e3, 1.0 / ARCSEC, 1.0 / ARCSEC)
ABSCISSAE = (
    ("range [m]", 1.0),
    ("horizontal direction [deg]", 180.0 / np.pi),
    ("elevation angle [deg]", 180.0 / np.pi),
)


def _pyplot():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def plot_residuals(
    result,
    path,
    *,
    title: str | None = None,
    overlay: bool = True,
    compare=None,
    mask=None,
    scanner=None,
):
    """3 x 3 grid: residuals ``v = F + Delta - l`` of range, hz and el (rows) against the
    observed range, horizontal direction and elevation angle (columns), as in Chow et al. 2013
    figs. 2-13 and Lichti & Licht 2006 figs. 1-3. Writes PNG or SVG by the file name's
    extension and returns the path.

    ``overlay``: where an estimated AP of a row's group depends only on that column's variable
    (or is constant), the panel shows the residuals *without* that term, ``v - Delta_c(l)``
    (approximately what an adjustment without it would leave), and the fitted AP curve
    ``-Delta_c`` as a line, so the term's signal and its fit are seen together; other panels
    show plain residuals. ``compare``: another result of the same observations (e.g. without
    APs), drawn in grey behind. ``mask`` (n, 3) bool: observations used in the adjustment
    (e.g. ``SelfCalibration.mask``; default all); the others (removed by data snooping) are
    drawn as red crosses. A plane network plots its points, the removed ones (weight 0 in
    ``plane_used``) as red crosses at their residuals at the final unknowns
    (:func:`tlsjax.self_calibrate` fills them in). ``scanner``: the :class:`Scanner` of the calibration (architecture and unit
    lengths enter some bases, e.g. B6 and A3/A4; default hybrid).
    """
    plt = _pyplot()
    l, v, used = _rows(result)
    if mask is not None and np.shape(mask) == used.shape:
        # The target rows' mask; a plane network's plot takes the removed points from the
        # result (``plane_used``, their residuals at the final unknowns).
        used = np.asarray(mask, dtype=bool)
    curves = _ap_curves(result, scanner) if overlay else {}
    grey = None if compare is None else _rows(compare)[1]
    # Own y scale per panel: an overlay panel (residuals without a term) spans far more than a
    # plain one, and a shared scale would flatten the plain residuals to a line.
    fig, axes = plt.subplots(3, 3, figsize=(12, 9))
    for g in range(3):
        for c, (xlabel, xf) in enumerate(ABSCISSAE):
            ax = axes[g, c]
            if grey is not None:
                label = f"APs: {' '.join(compare.ap_names) or 'none'}"
                ax.plot(
                    l[:, c] * xf, grey[:, g] * GROUP_FACTORS[g], ".", ms=2, color="0.7", label=label
                )
            _residual_panel(
                ax, result, l[:, c] * xf, v[:, g], used[:, g], curves.get((g, c)), g, xf
            )
            if curves.get((g, c)) is not None or grey is not None or (~used[:, g]).any():
                ax.legend(fontsize=7, loc="upper right", markerscale=3)
            if g == 2:
                ax.set_xlabel(xlabel)
            if c == 0:
                ax.set_ylabel(GROUP_LABELS[g])
    fig.suptitle(
        title or f"Residuals after self-calibration (APs: {' '.join(result.ap_names) or 'none'})"
    )
    fig.tight_layout()
    _save(fig, path)
    plt.close(fig)
    return path


#: Above this many points a residual panel draws their density (hexagonal bins, log count)
#: instead of one marker per point: 100,000 plane points as dots are a blob.
DENSE_POINTS = 5000


def _residual_panel(ax, result, x, v, used, curve, g, xf):
    """One panel of :func:`plot_residuals`: the residuals of group ``g`` (without the AP terms
    of ``curve`` when it is given, and that fitted curve as a line) against abscissa ``x``; the
    observations not used as red crosses. Dense panels (more than :data:`DENSE_POINTS` used
    points) show the point density; the y scale is set by the used points (and the curve), so
    removed observations never set it: those beyond it are drawn at the panel's edge and
    counted in the legend."""
    f = GROUP_FACTORS[g]
    y = v if curve is None else v - curve["at_obs"]
    label = (
        f"without {' '.join(curve['terms'])}"
        if curve is not None
        else f"APs: {' '.join(result.ap_names) or 'none'}"
    )
    xu, yu = x[used], y[used] * f
    if xu.size > DENSE_POINTS:
        ax.hexbin(xu, yu, gridsize=(90, 45), bins="log", mincnt=1, cmap="Blues", linewidths=0)
        ax.plot([], [], "s", color="tab:blue", ms=4, label=f"{label} ({xu.size:,} points, density)")
    else:
        ax.plot(xu, yu, ".", ms=2, alpha=0.6, label=label)
    lim = _y_limits(yu, None if curve is None else -curve["y"] * f)
    if lim is not None:
        ax.set_ylim(*lim)
    if (~used).any():
        yr = y[~used] * f
        out = 0 if lim is None else int(np.sum((yr < lim[0]) | (yr > lim[1])))
        if lim is not None:
            yr = np.clip(yr, *lim)
        text = f"removed ({int((~used).sum())}" + (
            f", {out} beyond the axis, at its edge)" if out else ")"
        )
        ax.plot(x[~used], yr, "x", ms=5, color="tab:red", label=text, clip_on=False)
    if curve is not None:
        label = f"fitted {' + '.join(curve['terms'])}"
        ax.plot(curve["x"] * xf, -curve["y"] * f, "-", color="tab:orange", lw=1.5, label=label)
    ax.axhline(0.0, color="k", lw=0.5)


def _y_limits(y, curve=None):
    """y range of a residual panel: the 0.05 and 99.95 percentiles of the used residuals (and
    the curve's range), widened by 10 %; None without finite values."""
    parts = [np.asarray(y, dtype=float)]
    if curve is not None:
        parts.append(np.asarray(curve, dtype=float))
    allv = np.concatenate([p[np.isfinite(p)] for p in parts])
    if not allv.size:
        return None
    yf = parts[0][np.isfinite(parts[0])]
    lo, hi = np.percentile(yf, [0.05, 99.95]) if yf.size else (allv.min(), allv.max())
    if curve is not None and np.isfinite(parts[1]).any():
        lo, hi = min(lo, np.nanmin(parts[1])), max(hi, np.nanmax(parts[1]))
    lo, hi = min(lo, 0.0), max(hi, 0.0)
    pad = 0.1 * (hi - lo) if hi > lo else max(abs(hi), 1.0)
    return float(lo - pad), float(hi + pad)


def _rows(result):
    """Observations, residuals and used-mask of the rows to plot: the target observations, or
    for a plane network the plane points (Gauss-Helmert residuals, SPEC section 4)."""
    net = result.network
    if net.observations.shape[0] == 0 and getattr(result, "planes", ()):
        return (
            np.asarray(net.plane_observations),
            np.asarray(result.plane_residuals),
            np.asarray(result.plane_used),
        )
    v = np.asarray(result.residuals)
    used = np.ones_like(v, dtype=bool) if result.used is None else np.asarray(result.used)
    return np.asarray(net.observations), v, used


def _ap_curves(result, scanner=None):
    """Per (group, abscissa): the estimated terms of that group whose basis depends only on
    that abscissa (constants included), their sum at the observations and along a grid."""
    from .._model._aps import GROUP_INDEX, get_ap

    net = result.network
    if net is None or len(net.instruments) != 1 or not len(result.ap_names):
        return {}
    if scanner is None:
        from .._model._scanner import Scanner

        scanner = Scanner(aps=())
    l = _rows(result)[0]
    rng = np.random.default_rng(0)
    probe = l[rng.choice(len(l), min(len(l), 50), replace=False)]
    out = {}
    for c in range(3):
        grid_1d = np.linspace(l[:, c].min(), l[:, c].max(), 200)
        for name, value in zip(result.ap_names, result.ap_values):
            if not np.isfinite(value):
                continue
            term = get_ap(name)
            g = GROUP_INDEX[term.group]
            deps = _dependencies(term, probe, scanner)
            if deps - {c}:
                continue
            d = out.setdefault(
                (g, c),
                {
                    "terms": [],
                    "at_obs": np.zeros(len(l)),
                    "x": grid_1d,
                    "y": np.zeros_like(grid_1d),
                },
            )
            d["terms"].append(name)
            d["at_obs"] = d["at_obs"] + value * _basis(term, l, scanner)
            grid = np.tile(np.median(l, axis=0), (len(grid_1d), 1))
            grid[:, c] = grid_1d
            d["y"] = d["y"] + value * _basis(term, grid, scanner)
    # A panel whose only terms are constants shows nothing a constant line would not; keep it
    # (it is the offset the term removes) only in the first column.
    for g, c in list(out):
        if (
            all(not _dependencies(get_ap(n), probe, scanner) for n in out[(g, c)]["terms"])
            and c != 0
        ):
            del out[(g, c)]
    return out


def _basis(term, l, scanner):
    return np.asarray(term.basis(l[:, 0], l[:, 1], l[:, 2], scanner), dtype=float) * np.ones(len(l))


def _dependencies(term, probe, scanner):
    base = _basis(term, probe, scanner)
    deps = set()
    for c in range(3):
        q = probe.copy()
        q[:, c] = q[:, c] * 0.9 + 0.01
        if not np.allclose(_basis(term, q, scanner), base, rtol=1e-12, atol=1e-15):
            deps.add(c)
    return deps


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
    """Save ``fig`` atomically (a temporary file renamed when complete; the folder created if
    missing), as PNG unless the name ends in another format matplotlib writes."""
    from .._io._outputs import atomic_output

    ext = os.path.splitext(os.fspath(path))[1].lower().lstrip(".")
    fmt = ext if ext in fig.canvas.get_supported_filetypes() else "png"
    with atomic_output(path) as tmp:
        fig.savefig(tmp, dpi=110, format=fmt)


def plot_monte_carlo(result, path=None):
    """Monte Carlo result (:func:`tlsjax.monte_carlo`): histograms of ``(estimate - truth)`` per AP with the formal normal density; PNG if
    ``path``. Returns the matplotlib figure."""
    plt = _pyplot()

    ok = result.ok
    na = len(result.ap_names)
    cols = min(na, 4)
    rows = int(math.ceil(na / cols)) + 1
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False)
    for k, name in enumerate(result.ap_names):
        ax = axes[k // cols][k % cols]
        f, u = display_unit(result.ap_units[k])
        d = (result.ap_values[ok, k] - result.true_aps[ok, k]) * f
        sig = float(np.sqrt(np.mean(result.ap_sigmas[ok, k] ** 2))) * f
        ax.hist(d, bins=30, density=True, color="0.7")
        x = np.linspace(d.min(), d.max(), 200) if d.size else np.zeros(1)
        ax.plot(x, np.exp(-0.5 * (x / sig) ** 2) / (sig * np.sqrt(2 * np.pi)), "k-", lw=1)
        ax.set_xlabel(f"{name} estimate - truth [{u}]")
        ax.set_ylabel(f"density [1/{u}]", fontsize=8)
        ax.set_title(
            f"{name}: emp/formal {np.std(d, ddof=1) / sig:.3f}" if d.size > 1 else name, fontsize=9
        )
    for k in range(na, cols * (rows - 1)):
        axes[k // cols][k % cols].axis("off")
    ax = axes[-1][0]
    ax.hist(result.sigma0_sq[ok], bins=30, color="0.7")
    ax.set_xlabel("s0^2 [-]")
    ax.set_ylabel("realisations")
    ax = axes[-1][1] if cols > 1 else None
    if ax is not None:
        sm = result.to_dict()["aps"]
        power = [sm[n]["power"] for n in result.ap_names]
        ax.bar(range(na), [np.nan if p is None else p for p in power], color="0.5")
        ax.set_xticks(range(na))
        ax.set_xticklabels(result.ap_names, rotation=90, fontsize=7)
        ax.set_ylabel(f"power (|t| > t_crit, level {result.t_test_level:g}) [-]")
    for k in range(2, cols):
        axes[-1][k].axis("off")
    fig.tight_layout()
    if path is not None:
        _save(fig, path)
    return fig


def plot_sensitivity(sensitivity, path=None):
    """``d AP / d l`` of every observation (:func:`tlsjax.ap_sensitivity`), one panel per AP:
    AP sigmas per observation sigma against the observation's row, by observation group."""
    plt = _pyplot()
    s = sensitivity
    na = len(s.ap_names)
    cols = min(na, 2)
    rows = math.ceil(na / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(6 * cols, 2.8 * rows), squeeze=False)
    idx = np.arange(s.values.shape[0])
    for k, name in enumerate(s.ap_names):
        ax = axes.flat[k]
        for g, label in enumerate(("range", "hz", "el")):
            ax.scatter(idx, s.values[:, g, k], s=6, label=label)
        ax.set_title(f"d {name} / d l")
        ax.set_xlabel("observation (network row)")
        ax.set_ylabel("AP sigmas per obs. sigma [-]")
        ax.axhline(0.0, color="0.6", lw=0.5)
    for ax in list(axes.flat)[na:]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.tight_layout()
    if path:
        _save(fig, path)
    return fig
