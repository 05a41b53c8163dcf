"""Target centres from point clouds: spheres and planar contrast targets (issue 33).

Per scan, two streamed passes (``_voxels``): the first builds a voxel cloud, on which the
candidates are found (spheres by a curvature-filtered Hough vote, ``_spheres``; checkerboards
and circles by dark and bright patches of the target's size, ``_contrast``); the second
collects the points near each candidate, to which the precise fits go. A scan is never held
whole.

Each centre, in scanner space with its covariance, becomes an observation of the scan's
architecture, ``rho = |c|``, ``theta = atan2(y, x)``, ``alpha = atan2(z, hypot(x, y))`` (a
panoramic scanner's back half folded into its second face, SPEC section 1), with the covariance
propagated by the Jacobian of that conversion (autodiff). The sigma columns of the target CSV
are the square roots of its diagonal; the correlations, which the CSV cannot carry, are kept in
:attr:`ExtractedTargets.observation_covariance`.

Candidates that fail a check are kept with the reason and never enter the CSV: too few points,
fit RMS, radius misfit, coverage (partial or occluded), incidence, pattern contrast or shape,
or (panoramic scanners) points on both sides of the face boundary, which the two faces'
systematic errors would tear apart.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import numpy as np

from .._adjustment._network import DEFAULT_SIGMA_ANGLE, DEFAULT_SIGMA_RANGE, ObservationTable
from .._io._point_clouds import observations_from_points
from .._io._scan_chunks import CHUNK_POINTS, ScanChunks, open_scans, scan_from_observations
from .._jit import jit
from .._model._geometry import spherical_from_cartesian
from .._model._scanner import ARCHITECTURES
from .._summary import Settings, to_json_value
from .._units import DEG
from . import _spheres
from ._voxels import crop, intensity_normaliser, voxelise

KINDS = ("sphere", "checkerboard", "circle")


@dataclasses.dataclass(frozen=True)
class TargetExtractionOptions(Settings):
    """What to look for and when to reject it (lengths in metres, angles in radians).

    ``spheres``: nominal radii of the sphere targets (e.g. ``(0.0725, 0.1)``);
    ``sphere_model``: the fit whose centre is reported: "offset" (radius known, plus a range
    offset shared by the sphere's points, so that a rangefinder offset of the uncalibrated
    scanner, which magnifies a sphere by ``A0 / D``, does not bias the centre), "known" (radius
    known) or "free" (radius free); the radius misfit is judged from the free fit always. ``checkerboards``, ``circles``: look for 2 x 2
    checkerboards and white discs on a dark ground, of side (plate) ``pattern_size``;
    ``circle_radius`` of the disc (None: any from 0.1 to 0.45 of the size).
    ``size_tolerance``: how far (relative) a target's real size may be from the one given: the
    size is a prior, not a gate (a candidate's extent is tested against the size widened by it,
    and a sphere's fitted radius against the nominal one). ``voxel_size`` of the candidate
    search (None: the smallest of 2 cm, a quarter of the smallest radius and an eighth of the
    pattern). ``sigma_range``/``sigma_angle``: a priori point sigmas (SPEC section 5) for the
    sphere fit's weights. Rejection, from the scan's own noise where no limit is given (the
    median thickness of the voxels there, ``_voxels``): a candidate patch thicker than 3 times
    the noise of its points, a planar target bending from its plane by more than that noise, a
    sphere whose fit RMS exceeds 3 times it (``max_rms``, when given, is a fixed limit [m] on
    both instead); fewer than ``min_points``; a sphere's fitted radius off the nominal by more
    than ``max_radius_misfit`` [m] when given, else by more than ``size_tolerance`` of it (a
    sphere of another size); coverage below ``min_coverage``; planar targets seen at more than
    ``max_incidence``, with a contrast below ``min_contrast`` (bright minus dark, in units of the
    scan's median intensity at that range) or a pattern residual above ``max_pattern_rms`` of
    the contrast.
    ``min_votes``: sphere votes a candidate needs. ``chunk_points``: points per streamed chunk.
    ``seed``: thinning of fits beyond 2,048 points.
    """

    spheres: tuple = ()
    checkerboards: bool = False
    circles: bool = False
    sphere_model: str = "offset"
    pattern_size: float = 0.15
    circle_radius: float | None = None
    voxel_size: float | None = None
    sigma_range: float = DEFAULT_SIGMA_RANGE
    sigma_angle: float = DEFAULT_SIGMA_ANGLE
    min_points: int = 30
    max_rms: float | None = None
    max_radius_misfit: float | None = None
    size_tolerance: float = 0.3
    min_coverage: float = 0.6
    max_incidence: float = 75.0 * DEG
    min_contrast: float = 0.3
    max_pattern_rms: float = 0.25
    dark_threshold: float = 0.5
    min_votes: int = 8
    chunk_points: int = CHUNK_POINTS
    seed: int = 0

    def __post_init__(self):
        radii = tuple(float(r) for r in np.atleast_1d(np.asarray(self.spheres, dtype=float)))
        for r in radii:
            if not (np.isfinite(r) and 0.005 <= r <= 1.0):
                raise ValueError(f"sphere radius {r} m is not in [0.005, 1] m")
        object.__setattr__(self, "spheres", radii)
        positive = (
            "pattern_size",
            "sigma_range",
            "sigma_angle",
            "min_contrast",
            "max_pattern_rms",
            "dark_threshold",
        )
        for name in positive + ("max_rms", "max_radius_misfit"):
            v = getattr(self, name)
            if v is not None and not (np.isfinite(v) and v > 0):
                raise ValueError(f"TargetExtractionOptions.{name} must be positive, got {v}")
        if not 0.0 <= self.size_tolerance < 1.0:
            raise ValueError(f"size_tolerance must be in [0, 1), got {self.size_tolerance}")
        if self.voxel_size is not None and not (0 < self.voxel_size <= 0.2):
            raise ValueError(f"voxel_size must be in (0, 0.2] m, got {self.voxel_size}")
        if self.sphere_model not in ("offset", "known", "free"):
            raise ValueError(
                f"sphere_model {self.sphere_model!r} is not one of 'offset', 'known', 'free'"
            )
        if not 0.0 <= self.min_coverage <= 1.0:
            raise ValueError(f"min_coverage must be in [0, 1], got {self.min_coverage}")
        if not 0.0 < self.max_incidence < np.pi / 2:
            raise ValueError("max_incidence must be in (0, 90 deg)")
        if self.circle_radius is not None and not 0 < self.circle_radius < self.pattern_size / 2:
            raise ValueError(
                f"circle_radius must be in (0, pattern_size / 2), got {self.circle_radius}"
            )
        for name in ("min_points", "min_votes", "chunk_points"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"TargetExtractionOptions.{name} must be a positive integer")

    @property
    def voxel(self) -> float:
        """The voxel edge of the candidate search [m]."""
        if self.voxel_size is not None:
            return float(self.voxel_size)
        sizes = [0.02] + [r / 4.0 for r in self.spheres]
        if self.checkerboards or self.circles:
            sizes.append(self.pattern_size / 8.0)
        return float(min(sizes))


_FIELDS = (
    "scan_index",
    "kind",
    "size",
    "centre",
    "covariance",
    "observations",
    "observation_covariance",
    "n_points",
    "rms",
    "incidence",
    "coverage",
    "radius_fit",
    "radius_sigma",
    "plane_offset",
    "contrast_bias",
    "pattern_rms",
    "contrast",
    "accepted",
    "reason",
    "names",
)


@dataclasses.dataclass(frozen=True, eq=False)
class ExtractedTargets:
    """Every target candidate of a set of scans, accepted or rejected with its reason.

    Per detection i: ``scan_index[i]`` into ``scans``; ``kind[i]`` ("sphere",
    "checkerboard", "circle"); ``size[i]`` the nominal radius or pattern size [m]; ``centre``
    (k, 3) in scanner space [m] with ``covariance`` (k, 3, 3); ``observations`` (k, 3) =
    (rho [m], theta [rad], alpha [rad]) in ``architecture`` with ``observation_covariance``;
    ``n_points`` used, fit ``rms`` [m] (radial for spheres, of the plane for planar targets),
    ``incidence`` [rad] (0 for spheres), ``coverage`` in [0, 1]; spheres: ``radius_fit`` and
    ``radius_sigma`` [m]; planar targets: ``plane_offset`` [m] (the intensity-weighted centroid
    of the points, along the line of sight, from the plane fitted to them: the range bias of
    contrast centroiding, Lichti & Licht 2006 section 5.3), ``contrast_bias`` [m] (range of the
    dark points minus the bright ones, from the plane), ``pattern_rms`` (intensity residual of
    the pattern fit over the contrast) and ``contrast``; ``accepted[i]`` and ``reason[i]``
    ("" when accepted); ``names[i]`` the target name after :func:`~tlsjax.match_targets` ("" before,
    or when unmatched). ``previews``: per scan (theta, alpha, value) of a thinned voxel cloud
    for the pictures; ``notes``: what was skipped and why; ``matching``: the report of
    :func:`~tlsjax.match_targets` (None before).
    """

    scans: tuple
    architecture: str
    poses: tuple
    scan_index: np.ndarray
    kind: np.ndarray
    size: np.ndarray
    centre: np.ndarray
    covariance: np.ndarray
    observations: np.ndarray
    observation_covariance: np.ndarray
    n_points: np.ndarray
    rms: np.ndarray
    incidence: np.ndarray
    coverage: np.ndarray
    radius_fit: np.ndarray
    radius_sigma: np.ndarray
    plane_offset: np.ndarray
    contrast_bias: np.ndarray
    pattern_rms: np.ndarray
    contrast: np.ndarray
    accepted: np.ndarray
    reason: np.ndarray
    names: np.ndarray
    previews: tuple = ()
    notes: tuple = ()
    matching: object = None

    def __len__(self) -> int:
        return len(self.scan_index)

    @classmethod
    def from_centres(
        cls, scans, scan_index, centres, *, kind=None, size=None, covariance=None,
        architecture: str = "hybrid",
    ) -> ExtractedTargets:  # fmt: skip
        """Detections made elsewhere (e.g. a vendor's target export): scanner-space
        ``centres`` (k, 3) [m] of scans ``scans[scan_index[i]]``, all accepted; ``kind`` (k,)
        (default "sphere") and nominal ``size`` (k,) [m] (default 0) keep kinds apart in
        :func:`~tlsjax.match_targets`; ``covariance`` (k, 3, 3) (default 1 mm^2 I)."""
        X = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
        k = len(X)
        recs = [[] for _ in scans]
        kind = ["sphere"] * k if kind is None else list(kind)
        size = np.zeros(k) if size is None else np.asarray(size, dtype=np.float64)
        C = np.tile(np.eye(3) * 1e-6, (k, 1, 1)) if covariance is None else np.asarray(covariance)
        for i, j in enumerate(np.asarray(scan_index, dtype=np.int64)):
            recs[j].append({"kind": kind[i], "size": size[i], "centre": X[i], "covariance": C[i],
                            "n_points": 0, "reason": ""})  # fmt: skip
        return _assemble(scans, architecture, [None] * len(scans), recs, [], [])

    @property
    def sigmas(self) -> np.ndarray:
        """(k, 3) standard deviations of the observations [m, rad, rad]."""
        return np.sqrt(np.einsum("kii->ki", self.observation_covariance))

    def select(self, mask) -> ExtractedTargets:
        """The detections where ``mask`` is true (same scans)."""
        mask = np.asarray(mask)
        return dataclasses.replace(self, **{f: getattr(self, f)[mask] for f in _FIELDS})

    def table(self) -> list[dict]:
        """The per-target table: one dict per detection with its scan, name, kind, nominal
        size, observation and sigmas, scanner-space centre, points used, fit RMS, incidence,
        coverage, radius fit, plane offset, contrast bias, and accepted/reason (SI units)."""
        rows = []
        sig = self.sigmas
        for i in range(len(self)):
            rows.append(
                {
                    "scan": self.scans[self.scan_index[i]],
                    "target": str(self.names[i]),
                    "kind": str(self.kind[i]),
                    "size_m": float(self.size[i]),
                    "range_m": float(self.observations[i, 0]),
                    "hz_rad": float(self.observations[i, 1]),
                    "el_rad": float(self.observations[i, 2]),
                    "sigma_range_m": float(sig[i, 0]),
                    "sigma_hz_rad": float(sig[i, 1]),
                    "sigma_el_rad": float(sig[i, 2]),
                    "x_m": float(self.centre[i, 0]),
                    "y_m": float(self.centre[i, 1]),
                    "z_m": float(self.centre[i, 2]),
                    "n_points": int(self.n_points[i]),
                    "rms_m": float(self.rms[i]),
                    "incidence_rad": float(self.incidence[i]),
                    "coverage": float(self.coverage[i]),
                    "radius_fit_m": float(self.radius_fit[i]),
                    "radius_sigma_m": float(self.radius_sigma[i]),
                    "plane_offset_m": float(self.plane_offset[i]),
                    "contrast_bias_m": float(self.contrast_bias[i]),
                    "pattern_rms": float(self.pattern_rms[i]),
                    "contrast": float(self.contrast[i]),
                    "accepted": bool(self.accepted[i]),
                    "reason": str(self.reason[i]),
                }
            )
        return rows

    def summary(self) -> str:
        """The detections per scan and kind, accepted and rejected (with the reasons), and the
        notes."""
        lines = [
            f"{len(self)} target candidate(s) in {len(self.scans)} scan(s), {self.architecture}"
        ]
        for j, scan in enumerate(self.scans):
            rows = self.scan_index == j
            for kind in sorted(set(self.kind[rows].tolist())):
                k = rows & (self.kind == kind)
                ok = int((k & self.accepted).sum())
                lines.append(f"  {scan}: {kind}: {ok} accepted, {int(k.sum()) - ok} rejected")
        reasons = sorted(set(str(r) for r in self.reason[~self.accepted]))
        lines += [f"  rejected: {r}" for r in reasons if r]
        if self.matching is not None:
            lines.append(self.matching.summary())
        return "\n".join(lines + [f"note: {n}" for n in self.notes])

    def to_dict(self) -> dict:
        """Strict JSON: the scans, the architecture, one record per detection (:meth:`table`,
        SI units), the matching's report and the notes."""
        return to_json_value(
            {
                "scans": list(self.scans),
                "architecture": self.architecture,
                "targets": self.table(),
                "matching": None if self.matching is None else self.matching.to_dict(),
                "notes": list(self.notes),
            }
        )

    def to_table(self) -> ObservationTable:
        """The target observations (SPEC section 11) of the accepted, named detections, with
        their sigmas; no incidence column (the sigmas are the centres' own, already)."""
        keep = self.accepted & (self.names != "")
        if not keep.any():
            raise ValueError(
                "no accepted and matched target: nothing to write (see the per-target table)"
            )
        idx = np.flatnonzero(keep)
        return ObservationTable(
            kind="target",
            source="<extracted targets>",
            scans=tuple(self.scans[self.scan_index[i]] for i in idx),
            primitives=tuple(str(self.names[i]) for i in idx),
            observations=self.observations[idx],
            sigmas=self.sigmas[idx],
            incidence=None,
            instruments=None,
            rows=np.arange(2, len(idx) + 2, dtype=np.int64),
            architecture=self.architecture,
        )


@jit
def _spherical_jacobians(X):
    return jax.vmap(jax.jacfwd(spherical_from_cartesian))(X)


def centre_observations(centres, covariances, architecture: str):
    """Observations (k, 3) of scanner-space centres in ``architecture`` and their covariance
    ``J C J^T`` (J the Jacobian of the hybrid conversion by autodiff; the fold into a panoramic
    scanner's second face, ``(theta - pi, pi - alpha)``, flips the sign of the elevation row,
    which leaves the covariance's diagonal unchanged)."""
    X = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    if not len(X):
        return np.zeros((0, 3)), np.zeros((0, 3, 3))
    obs = observations_from_points(X, architecture)
    pad = (-len(X)) % 64  # one compiled size per 64 targets
    J = np.array(_spherical_jacobians(np.concatenate([X, np.ones((pad, 3))])))[: len(X)]
    if architecture == "panoramic":
        face2 = obs[:, 2] > np.pi / 2
        J[face2, 1:, :] *= np.array([1.0, -1.0])[:, None]
    C = np.einsum("kij,kjl,kml->kim", J, np.asarray(covariances), J)
    return obs, C


def _empty_record(kind, size, centre, reason, n=0):
    return {
        "kind": kind,
        "size": float(size),
        "centre": np.asarray(centre, dtype=np.float64),
        "covariance": np.full((3, 3), np.nan),
        "n_points": n,
        "rms": np.nan,
        "incidence": np.nan,
        "coverage": 0.0,
        "reason": reason,
    }


#: A sphere's fit RMS may reach this many times the noise of the scan's points there (the
#: radial residuals of a true sphere are that noise; a pipe or a curved bump that voted for a
#: centre leaves 1.2-3 times it in a real plant room, pye57's pump scan).
SPHERE_RMS_SIGMAS = 2.0


def _judge_sphere(rec, options: TargetExtractionOptions):
    """The first failed check of a sphere fit, or ""."""
    if rec["n_points"] < options.min_points:
        return f"too few points ({rec['n_points']} < {options.min_points})"
    if not rec["converged"] or not np.all(np.isfinite(rec["covariance"])):
        return "the fit did not converge"
    if options.max_rms is not None:
        if rec["rms"] > options.max_rms:
            return f"fit RMS {rec['rms'] * 1e3:.2f} mm > max_rms {options.max_rms * 1e3:.2f} mm"
    elif rec["rms"] > SPHERE_RMS_SIGMAS * rec["noise"]:
        return (
            f"fit RMS {rec['rms'] * 1e3:.2f} mm > {SPHERE_RMS_SIGMAS:.0f} x the points' noise "
            f"{rec['noise'] * 1e3:.2f} mm there (not a sphere of this radius)"
        )
    n = max(rec["n_points"], 7)
    trend_limit = max(0.5, 2.0 * np.sqrt(6.0 / n)) * rec["noise"]
    if options.max_rms is None and not rec["trend"] <= trend_limit:
        return (
            f"residuals with a shape: their quadratic trend over the sphere has an RMS of "
            f"{rec['trend'] * 1e3:.2f} mm > {trend_limit * 1e3:.2f} mm (half the points' noise, "
            "or twice what noise leaves): not a sphere"
        )
    miss = rec["radius_fit"] - rec["size"]
    limit = (
        options.max_radius_misfit
        if options.max_radius_misfit is not None
        else options.size_tolerance * rec["size"]
    )
    if not abs(miss) <= limit:
        return (
            f"radius {rec['radius_fit'] * 1e3:.1f} mm differs from the nominal "
            f"{rec['size'] * 1e3:.1f} mm by {miss * 1e3:+.1f} mm (limit {limit * 1e3:.1f} mm)"
        )
    if rec["coverage"] < options.min_coverage:
        return (
            f"coverage {rec['coverage']:.2f} of the visible hemisphere < {options.min_coverage:.2f}"
            " (partial or occluded sphere)"
        )
    return ""


def _face_boundary(rec, architecture):
    """True when a panoramic scanner saw the target's points in both faces."""
    P = rec.get("points")
    if architecture != "panoramic" or P is None or not len(P):
        return False
    return bool(P[:, 1].min() < 0.0 < P[:, 1].max())


def _scan_spheres(scan, vox, options, rng, bar):
    """Sphere records of one scan (accepted or not)."""
    normal, kappa, offset = _spheres.local_surfaces(vox)
    radii = np.asarray(options.spheres)
    starts, which, _ = _spheres.sphere_candidates(
        normal, kappa, offset, vox.centroid, radii, options.min_votes
    )
    if not len(starts):
        return []
    crops = crop(scan, starts, 1.5 * radii[which] + 0.02, chunk=options.chunk_points, bar=bar)
    recs = _spheres.fit_spheres([p for p, _ in crops], starts, radii[which], options, rng)
    # Imported here: scipy.spatial takes a third of a second, and most runs never find targets
    # in clouds (issue 37: import tlsjax in under 0.8 s).
    from scipy.spatial import cKDTree

    tree = cKDTree(vox.centroid)
    for rec, R in zip(recs, radii[which]):
        # The points' noise there: the within-voxel spread along the radius, pooled over the
        # voxels on the sphere (a voxel of a quarter radius holds a cap whose points spread
        # about R / 400 along it, 0.2 mm at R = 7 cm: below any scanner's noise at the
        # sphere's range); the a priori range sigma where no voxel holds 2 points.
        near = np.asarray(tree.query_ball_point(rec["centre"], 1.2 * R), dtype=np.int64)
        radial = vox.centroid[near] - rec["centre"]
        radial /= np.maximum(np.linalg.norm(radial, axis=1), 1e-12)[:, None]
        rec["noise"] = vox.noise(near, radial) if len(near) else np.nan
        if not np.isfinite(rec["noise"]):
            rec["noise"] = options.sigma_range
        # Toward the limb the angular noise moves points along the sphere's normal by
        # rho sigma_a sin(beta) (2.7 mm at 28 m for 20"), which a voxel of a quarter radius,
        # holding one or two points at that range, does not measure: the fit's residuals
        # carry it, so the noise they are judged by does too (a priori sigma_angle: the
        # scan's angle noise cannot be told from its points).
        if rec.get("points") is not None and len(rec["points"]):
            lateral = _spheres.radial_sigma(rec["points"], rec["centre"], 0.0, options.sigma_angle)
            rec["noise"] = float(np.hypot(rec["noise"], np.sqrt(np.mean(lateral**2))))
        # A sphere of another of the given radii votes for this one's too: take the nearest.
        rec["size"] = float(radii[np.argmin(np.abs(radii - rec["radius_fit"]))])
        rec["reason"] = _judge_sphere(rec, options)
    return _dedupe(recs)


def _dedupe(recs):
    """Detections of one target closer than half its size: keep the accepted one with the
    smallest RMS; the others are marked duplicates."""
    order = sorted(
        range(len(recs)),
        key=lambda i: (recs[i]["reason"] != "", np.nan_to_num(recs[i]["rms"], nan=1e9)),
    )
    kept = []
    for i in order:
        r = recs[i]
        dup = next(
            (
                k
                for k in kept
                if np.linalg.norm(recs[k]["centre"] - r["centre"])
                < 0.5 * max(r["size"], recs[k]["size"])
            ),
            None,
        )
        if dup is None:
            kept.append(i)
        elif r["reason"] == "" or r["kind"] == recs[dup]["kind"]:
            r["reason"] = r["reason"] or "duplicate of a better fit of the same target"
            r["duplicate"] = True
    return [recs[i] for i in range(len(recs)) if not recs[i].get("duplicate")]


def _preview(vox, normalise, max_points=150_000, seed=0):
    """(theta, alpha, value, what) of a thinned voxel cloud for the pictures: the normalised
    intensity where the scan has one, else the range."""
    P, inten = vox.centroid, vox.intensity
    if len(P) > max_points:
        take = np.random.default_rng(seed).choice(len(P), max_points, replace=False)
        P, inten = P[take], inten[take]
    obs = spherical_from_cartesian(P, xp=np)
    if normalise is None:
        return obs[:, 1], obs[:, 2], obs[:, 0], "range"
    return obs[:, 1], obs[:, 2], normalise(inten, obs[:, 0]), "intensity"


def _extract_scan(scan: ScanChunks, options, architecture, rng, bar):
    vox = voxelise(scan, options.voxel, chunk=options.chunk_points, bar=bar)
    normalise = (
        intensity_normaliser(vox.intensity_sample, vox.range_sample) if vox.has_intensity else None
    )
    notes = []
    recs = []
    if options.spheres:
        recs += _scan_spheres(scan, vox, options, rng, bar)
    if options.checkerboards or options.circles:
        if normalise is None:
            notes.append(
                f"{scan.source}: scan {scan.name}: no intensity, so no checkerboards or circles"
            )
        else:
            from . import _contrast

            recs = _dedupe(
                recs + _contrast.scan_planar_targets(scan, vox, normalise, options, rng, bar)
            )
    for rec in recs:
        if rec["reason"] == "" and _face_boundary(rec, architecture):
            rec["reason"] = "points in both faces of the panoramic scanner (face boundary)"
    return recs, _preview(vox, normalise, seed=options.seed), notes


def _assemble(names, architecture, poses, per_scan, previews, notes) -> ExtractedTargets:
    rows = [(j, r) for j, recs in enumerate(per_scan) for r in recs]
    k = len(rows)
    get = lambda key, default=np.nan: np.array([r.get(key, default) for _, r in rows], dtype=float)
    centres = np.array([r["centre"] for _, r in rows]).reshape(k, 3)
    cov = np.array([r["covariance"] for _, r in rows]).reshape(k, 3, 3)
    obs, ocov = centre_observations(centres, np.nan_to_num(cov), architecture)
    ocov[~np.all(np.isfinite(cov), axis=(1, 2))] = np.nan
    reason = np.array([r["reason"] for _, r in rows], dtype=object).reshape(k)
    return ExtractedTargets(
        scans=tuple(names),
        architecture=architecture,
        poses=tuple(poses),
        scan_index=np.array([j for j, _ in rows], dtype=np.int64),
        kind=np.array([r["kind"] for _, r in rows], dtype=object).reshape(k),
        size=get("size"),
        centre=centres,
        covariance=cov,
        observations=obs,
        observation_covariance=ocov,
        n_points=get("n_points", 0).astype(np.int64),
        rms=get("rms"),
        incidence=get("incidence"),
        coverage=get("coverage"),
        radius_fit=get("radius_fit"),
        radius_sigma=get("radius_sigma"),
        plane_offset=get("plane_offset"),
        contrast_bias=get("contrast_bias"),
        pattern_rms=get("pattern_rms"),
        contrast=get("contrast"),
        accepted=reason == "",
        reason=reason,
        names=np.full(k, "", dtype=object),
        previews=tuple(previews),
        notes=tuple(notes),
    )


def _run(sources: Sequence[ScanChunks], options, architecture, progress):
    from tqdm.auto import tqdm

    if architecture not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {architecture!r} is not one of {ARCHITECTURES}")
    if not (options.spheres or options.checkerboards or options.circles):
        raise ValueError(
            "nothing to look for: give sphere radii (spheres=...), checkerboards or circles"
        )
    names = [s.name for s in sources]
    if len(set(names)) != len(names):
        raise ValueError(f"scan names are not unique: {names}")
    rng = np.random.default_rng(options.seed)
    per_scan, previews, notes = [], [], []
    for s in sources:
        total = None if s.n_stored is None else 2 * s.n_stored
        with tqdm(total=total, disable=not progress, unit="pt", unit_scale=True) as bar:
            bar.set_description(f"targets of scan {s.name}")
            recs, preview, note = _extract_scan(s, options, architecture, rng, bar)
        per_scan.append(recs)
        previews.append(preview)
        notes += note
    return _assemble(names, architecture, [s.pose for s in sources], per_scan, previews, notes)


def extract_targets(
    scans: Sequence,
    options: TargetExtractionOptions | None = None,
    *,
    intensity: Sequence | None = None,
    names: Sequence[str] | None = None,
    architecture: str = "hybrid",
    progress: bool = False,
) -> ExtractedTargets:
    """Find the target centres in scans held in memory (see the module docstring).

    ``scans``: one (n_j, 3) array of observations (rho [m], theta [rad], alpha [rad]) per scan,
    in ``architecture`` (as :func:`~tlsjax.extract_planes` takes them); ``intensity``: one
    (n_j,) array per scan (needed for checkerboards and circles); ``names``: scan names
    (default S1, S2, ...). Files: :func:`extract_targets_from_files`.
    """
    options = options or TargetExtractionOptions()
    names = tuple(names) if names is not None else tuple(f"S{j + 1}" for j in range(len(scans)))
    if len(names) != len(scans):
        raise ValueError(f"{len(names)} scan names for {len(scans)} scans")
    if intensity is not None and len(intensity) != len(scans):
        raise ValueError(f"{len(intensity)} intensity arrays for {len(scans)} scans")
    sources = [
        scan_from_observations(n, o, None if intensity is None else intensity[j])
        for j, (n, o) in enumerate(zip(names, scans))
    ]
    return _run(sources, options, architecture, progress)


def extract_targets_from_files(
    paths: Sequence,
    options: TargetExtractionOptions | None = None,
    *,
    architecture: str = "hybrid",
    poses=None,
    columns: str | None = None,
    progress: bool = False,
) -> ExtractedTargets:
    """Find the target centres in point-cloud files (E57, PTX, LAS/LAZ, PLY, PCD, and text:
    XYZ, TXT, ASC, CSV, PTS), every scan of each file, streamed in chunks
    (``options.chunk_points``): two passes per scan, and only the points near candidates
    held. ``poses``: scan name -> pose (replacing the files'). Intensity is taken by name
    (a text file's header, E57/LAS/PLY fields); ``columns`` names the columns of text files
    without a header, e.g. "x,y,z,r,g,b,intensity" (unnamed columns beyond x y z intensity are
    refused, never guessed)."""
    sources = [s for p in paths for s in open_scans(p, poses=poses, columns=columns)]
    return _run(sources, options or TargetExtractionOptions(), architecture, progress)
