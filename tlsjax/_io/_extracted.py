"""What plane extraction produces and matching completes: :class:`ExtractedPlanes`, the plane
patches of a set of scans and the points kept on them, with their global planes once matched
(:func:`tlsjax.extract_planes`, :func:`tlsjax.match_planes`)."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._network import ObservationTable
from .._model._geometry import cartesian_from_spherical, rotation_matrix
from .._summary import to_json_value


@dataclasses.dataclass(frozen=True, eq=False)
class ExtractedPlanes:
    """Plane patches of a set of scans and the points kept on them.

    Per patch p: ``patch_scan[p]`` (scan index), ``patch_normal[p]`` and ``patch_distance[p]``
    in scanner space (``n . x = d``), ``patch_rms[p]`` [m] of the orthogonal distances,
    ``patch_inliers[p]`` (points after refinement, before the budget), ``patch_plane[p]`` (global
    plane index, -1 before matching). Per kept point i: ``point_patch[i]``, ``point_index[i]``
    (row in its scan's input), ``observations[i]`` (rho, theta, alpha) and ``incidence[i]``
    [rad]. After matching: ``poses`` (s, 6) and ``planes`` (g, 4) = (n, d) in object space,
    fitted to all points of each global plane.
    """

    scans: tuple
    patch_scan: np.ndarray
    patch_normal: np.ndarray
    patch_distance: np.ndarray
    patch_rms: np.ndarray
    patch_inliers: np.ndarray
    patch_plane: np.ndarray
    point_patch: np.ndarray
    point_index: np.ndarray
    observations: np.ndarray
    incidence: np.ndarray
    poses: np.ndarray | None = None
    planes: np.ndarray | None = None

    @property
    def point_plane(self) -> np.ndarray:
        """Global plane index of every kept point (-1 before matching)."""
        return self.patch_plane[self.point_patch]

    @property
    def point_scan(self) -> np.ndarray:
        return self.patch_scan[self.point_patch]

    def to_dict(self) -> dict:
        """Strict-JSON data (undefined values as None): ``scans``, ``n_patches``, ``n_points``
        and ``planes``, None before matching, else per global plane: ``plane`` (name),
        ``normal``, ``d`` [m] in object space, ``n_scans``, ``n_patches``, ``n_points``,
        ``n_inliers`` that support it, ``rms`` [m] of the kept points' orthogonal distances
        from it and ``max_patch_angle`` [rad], the largest angle between one of its patches and
        the plane."""
        planes = None if self.planes is None or self.poses is None else plane_summary(self)
        return to_json_value(
            {
                "scans": list(self.scans),
                "n_patches": int(len(self.patch_scan)),
                "n_points": int(len(self.point_patch)),
                "planes": planes,
            }
        )

    def summary(self) -> str:
        """Text: the counts, then one line per global plane once matched: the scans, patches
        and points that support it, its RMS [mm] and largest patch angle [deg]."""
        matched = self.planes is not None and self.poses is not None
        head = (
            f"{len(self.scans)} scan(s), {len(self.patch_scan)} patches, "
            f"{len(self.point_patch)} points; "
            + (f"{len(self.planes)} planes" if matched else "not matched across scans yet")
        )
        if not matched:
            return head
        rows = plane_summary(self)
        lines = [head, "plane  scans  patches   points  RMS [mm]  max patch angle [deg]"]
        lines += [
            f"{p['plane']:5s} {p['n_scans']:6d} {p['n_patches']:8d} {p['n_points']:8d} "
            f"{p['rms'] * 1e3:9.2f} {np.degrees(p['max_patch_angle']):22.2f}"
            for p in rows
        ]
        return "\n".join(lines)

    def to_table(self) -> ObservationTable:
        """Plane observations (SPEC section 11): one row per kept point of a matched plane.

        Planes are named ``P1``, ``P2``, ... in the order of ``planes``.
        """
        if self.planes is None:
            raise ValueError(
                "planes are not matched across scans yet: call match_planes(planes, poses) first"
            )
        plane = self.point_plane
        keep = plane >= 0
        scans = tuple(self.scans[s] for s in self.point_scan[keep])
        # One string object per plane, shared by its points (not one per point).
        names = [f"P{g + 1}" for g in range(len(self.planes))]
        prims = tuple(names[g] for g in plane[keep])
        return ObservationTable(
            kind="plane",
            source="<extracted planes>",
            scans=scans,
            primitives=prims,
            observations=self.observations[keep],
            sigmas=None,
            incidence=self.incidence[keep],
            instruments=None,
            rows=np.arange(2, int(keep.sum()) + 2, dtype=np.int64),
        )


def plane_summary(planes: ExtractedPlanes) -> list[dict]:
    """Per global plane of matched ``planes``: the scans, patches and points that support it,
    the RMS [m] of the kept points' orthogonal distances from it (object space) and the largest
    angle [rad] between one of its patches and the plane."""
    if planes.planes is None or planes.poses is None:
        raise ValueError("planes are not matched across scans yet: call match_planes first")
    R = np.stack([rotation_matrix(*p[3:], xp=np) for p in planes.poses])
    x = cartesian_from_spherical(planes.observations, xp=np)
    s_pt = planes.point_scan
    X = np.einsum("mji,mj->mi", R[s_pt], x) + planes.poses[s_pt, :3]
    N = np.einsum("pji,pj->pi", R[planes.patch_scan], planes.patch_normal)
    out = []
    pp = planes.point_plane
    for g, (nx, ny, nz, d) in enumerate(planes.planes):
        n = np.array([nx, ny, nz])
        members = np.flatnonzero(planes.patch_plane == g)
        r = X[pp == g] @ n - d
        cosang = np.clip(np.abs(N[members] @ n), 0.0, 1.0)
        out.append(
            {
                "plane": f"P{g + 1}",
                "normal": n.tolist(),
                "d": float(d),
                "n_scans": int(len(np.unique(planes.patch_scan[members]))),
                "n_patches": int(len(members)),
                "n_points": int(len(r)),
                "n_inliers": int(planes.patch_inliers[members].sum()),
                "rms": float(np.sqrt(np.mean(r**2))) if len(r) else float("nan"),
                "max_patch_angle": float(np.arccos(cosang.min())) if len(members) else 0.0,
            }
        )
    return out
