"""Matching extracted targets across scans: by a user's target list, or by geometry alone.

The poses of the scans are unknown, but the distance between two targets is the same in every
scan that sees both (up to noise and the uncalibrated scanner's distortion: ``tolerance +
relative_tolerance x distance``). Registration of a set A of centres onto a set B:

1. **Hypotheses** from triangles: triplets of A (sides of at least ``min_side``), and every
   triplet of B of the same kinds whose three sides agree within the tolerance; each gives a
   rigid motion (Horn's closed form, ``_model._geometry.rigid_fit``).
2. **Consensus**: each motion maps A into B's frame; its support is the number of A's
   centres with a centre of B of the same kind within the tolerance (all hypotheses at once,
   vectorised).
3. **Decision**: the best motion, refitted to its inliers, is accepted when it is supported by
   at least ``min_common`` targets and no essentially different motion (rotated by more than
   1 deg or shifted by more than the tolerance) is supported nearly as well (at least the
   ``ambiguity`` share of the best, and at least as many targets as the best where that is 3
   or 4): a symmetric layout is reported as ambiguous, never guessed.
4. **Three targets.** Three centres fix a motion; a fourth checks it. Without the fourth,
   the distances are the only guard, so a placement on exactly three needs (a) their three
   distances to agree within the tighter ``tolerance_3 + relative_tolerance_3 x distance``
   (the distances between targets of a field check agree to a few millimetres even before a
   calibration: DVW-Merkblatt 7-2014's limits are 2-4 mm), and (b) a chance match to be
   improbable among the centres at hand: the expected number of false triangle matches (an
   *a contrario* number of false alarms, Desolneux, Moisan and Morel 2008, ch. 5) must not
   exceed ``max_chance``. A false triangle match needs a pair of A to match a pair of B
   (truly, when two targets are shared, or by chance) and a third centre of B to lie, by
   chance, at A's third centre's two distances from the pair: on a circle about the pair's
   axis. With B's centres spread uniformly over their bounding box (volume V, each side at
   least 2 m), a centre lies within ``t_1``, ``t_2`` of the distances ``d_1``, ``d_2`` from a
   pair ``L`` apart with probability ``2 t_1 2 t_2 x 2 pi d_1 d_2 / (L V)`` (the circle's
   tube; at most the shell ``4 pi d_1^2 2 t_1 / V``), so
   ``E = sum over matching pairs (i k, j l) and third centres m of A of P(d_im, d_km) x
   (number of B's other centres of m's kind)``. Every real pair match enters, true or
   chance, so the scans' own structure (shared targets, walls) is counted, not modelled;
   each triangle enters once per side, which errs on the safe side (by about 2 on walls,
   more elsewhere: tests/test_field_check.py counts chance placements against it). In random
   hall layouts, 94-98 % of scans of 3 targets sharing all 3 with a set of 3 or 4 are placed
   and 73-78 % of 6 sharing 3 with 6; the rest are reported as undecided, with the figure,
   rather than placed on what may be a coincidence; of scans sharing only 2 targets, about
   1-2 in 1,000 on walls are still placed on a chance third. A placement on 4 or more needs a
   fourth centre to coincide as well, which the tolerance makes negligible.

Scans are joined one at a time onto the growing set of global targets, the best-supported
scan first; a scan's centres without a partner become new targets, so targets seen by only
some scans, and false detections (which find no partner), are handled alike. Then every scan
is matched once more against the final set. A centre within the tolerance of two global
targets, or two centres of one scan on one target, are left unnamed and reported. Without a
list, targets seen in fewer than ``min_scans`` scans are not named (they cannot help a
calibration and are most likely false detections).

With a target list (name -> approximate coordinates in any frame, e.g. from a total station),
each scan is registered onto the list the same way and takes the names of its partners.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from .._model._geometry import angles_from_matrix, rigid_fit
from .._summary import Settings, to_json_value
from ._targets import ExtractedTargets


@dataclasses.dataclass(frozen=True)
class TargetMatchingOptions(Settings):
    """Thresholds of :func:`match_targets` (lengths in metres).

    ``tolerance`` + ``relative_tolerance`` x distance: how far two distances between the same
    targets, or a mapped centre and its partner, may differ (noise plus the uncalibrated
    scanner's distortion, about a centimetre at 10 m for 3' angular errors). ``min_common``:
    targets a scan must share with the others (or the list) to be placed (at least 3, which
    fix a motion). A placement on exactly 3 needs their distances to agree within
    ``tolerance_3 + relative_tolerance_3 x distance`` and the expected number of chance
    triangle matches among the scan's and the others' centres to be at most ``max_chance``
    (module docstring, step 4). ``ambiguity``: a different motion supported by at least this
    share of the best one's targets makes the scan ambiguous. ``min_side``: shortest triangle
    side used for hypotheses. ``max_triangles``: triangles of A tried (drawn with ``seed``).
    ``min_scans``: scans a target needs to get a name when no list is given.
    """

    tolerance: float = 0.02
    relative_tolerance: float = 2e-3
    min_common: int = 3
    tolerance_3: float = 0.005
    relative_tolerance_3: float = 5e-4
    max_chance: float = 1e-2
    ambiguity: float = 0.75
    min_side: float = 0.5
    max_triangles: int = 300
    min_scans: int = 2
    seed: int = 0

    def __post_init__(self):
        for name in ("tolerance", "min_side", "tolerance_3"):
            if not getattr(self, name) > 0:
                raise ValueError(f"TargetMatchingOptions.{name} must be positive")
        if not (self.relative_tolerance >= 0 and self.relative_tolerance_3 >= 0):
            raise ValueError("TargetMatchingOptions.relative_tolerance(_3) must be >= 0")
        if self.min_common < 3:
            raise ValueError("TargetMatchingOptions.min_common must be at least 3")
        if not 0 < self.max_chance < 1:
            raise ValueError("TargetMatchingOptions.max_chance must be in (0, 1)")
        if not 0 < self.ambiguity <= 1:
            raise ValueError("TargetMatchingOptions.ambiguity must be in (0, 1]")
        if self.max_triangles < 1 or self.min_scans < 1:
            raise ValueError("TargetMatchingOptions.max_triangles and min_scans must be >= 1")


@dataclasses.dataclass(frozen=True, eq=False)
class TargetMatching:
    """What :func:`match_targets` did: per scan its ``status`` ("reference", "placed",
    "ambiguous", "undecided" (3 common targets where a chance triangle is not improbable),
    "too few common targets", "no targets"), ``n_common`` targets matched, the
    RMS [m] of its rigid fit and its ``pose`` (6,) in the matching frame (that of the first
    scan or of the list; NaN when not placed); ``targets`` name -> coordinates (3,) in that
    frame; ``messages``: every ambiguity and conflict, one line each."""

    status: dict
    n_common: dict
    rms: dict
    pose: dict
    targets: dict
    messages: tuple

    def summary(self) -> str:
        lines = [
            f"{s}: {self.status[s]}, {self.n_common[s]} common targets, fit RMS "
            f"{self.rms[s] * 1e3:.1f} mm"
            for s in self.status
        ]
        return "\n".join(lines + list(self.messages))

    def to_dict(self) -> dict:
        """Strict JSON: per scan its status, common targets, fit RMS [m] and pose (6,); the
        targets' coordinates [m] in the matching frame; the messages."""
        return to_json_value(
            {
                "scans": {
                    s: {
                        "status": self.status[s],
                        "n_common": self.n_common[s],
                        "rms": self.rms[s],
                        "pose": self.pose[s],
                    }
                    for s in self.status
                },
                "targets": self.targets,
                "messages": list(self.messages),
            }
        )


@dataclasses.dataclass
class _Registration:
    status: str
    R: np.ndarray | None = None
    t: np.ndarray | None = None
    pairs: tuple = ()
    rms: float = np.nan
    support: int = 0
    second: int = 0
    chance: float = 0.0
    misfit: float = 0.0


def _tol(d, options):
    return options.tolerance + options.relative_tolerance * np.asarray(d)


def _triangles(X, rng, options):
    """Up to ``max_triangles`` index triplets of X with every side >= min_side, drawn at random
    (all of them when there are few)."""
    n = len(X)
    if n < 3:
        return np.zeros((0, 3), dtype=np.int64)
    D = np.linalg.norm(X[:, None] - X[None], axis=2)
    if n <= 14:
        tri = np.array(list(itertools.combinations(range(n), 3)))
    else:
        tri = np.sort(
            np.stack([rng.choice(n, 3, replace=False) for _ in range(4 * options.max_triangles)]), 1
        )
        tri = np.unique(tri, axis=0)
    ok = (D[tri[:, 0], tri[:, 1]] >= options.min_side) & (
        D[tri[:, 0], tri[:, 2]] >= options.min_side
    )
    ok &= D[tri[:, 1], tri[:, 2]] >= options.min_side
    tri = tri[ok]
    return tri[rng.permutation(len(tri))[: options.max_triangles]]


def _hypotheses(A, ka, B, kb, tri, options):
    """Rigid motions (R (h, 3, 3), t (h, 3)) of A onto B from the triangles ``tri`` of A and
    the triplets of B with equal sides."""
    DA = np.linalg.norm(A[:, None] - A[None], axis=2)
    DB = np.linalg.norm(B[:, None] - B[None], axis=2)
    same = ka[:, None] == kb[None, :]  # (nA, nB)
    src, dst = [], []
    for i, k, m in tri:
        jl = np.argwhere(
            (np.abs(DB - DA[i, k]) <= _tol(DA[i, k], options)) & same[i][:, None] & same[k][None, :]
        )
        jl = jl[jl[:, 0] != jl[:, 1]]
        if not len(jl):
            continue
        ok_p = (
            (np.abs(DB[jl[:, 0]] - DA[i, m]) <= _tol(DA[i, m], options))
            & (np.abs(DB[jl[:, 1]] - DA[k, m]) <= _tol(DA[k, m], options))
            & same[m][None, :]
        )
        for (j, l), p in zip(jl, ok_p):
            for pp in np.flatnonzero(p):
                if pp != j and pp != l:
                    src.append(A[[i, k, m]])
                    dst.append(B[[j, l, pp]])
    if not src:
        return np.zeros((0, 3, 3)), np.zeros((0, 3))
    src, dst = np.asarray(src), np.asarray(dst)
    cs, cd = src.mean(axis=1), dst.mean(axis=1)
    H = np.einsum("hki,hkj->hij", src - cs[:, None], dst - cd[:, None])
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(np.einsum("hji,hkj->hik", Vt, U)))
    Dm = np.tile(np.eye(3), (len(H), 1, 1))
    Dm[:, 2, 2] = d
    R = np.einsum("hji,hjk,hlk->hil", Vt, Dm, U)
    return R, cd - np.einsum("hij,hj->hi", R, cs)


def _tol_3(d, options):
    return options.tolerance_3 + options.relative_tolerance_3 * np.asarray(d)


def _chance(A, ka, B, kb, options):
    """Expected number of chance triangle matches of A with B (module docstring, step 4), at
    the tolerance of a placement on 3 targets. B with more than 60 centres: infinite (3
    common targets never decide among so many)."""
    if len(B) > 60:
        return float("inf")
    DA = np.linalg.norm(A[:, None] - A[None], axis=2)
    DB = np.linalg.norm(B[:, None] - B[None], axis=2)
    V = float(np.prod(np.maximum(np.ptp(B, axis=0), 2.0)))
    counts = {int(c): int(n) for c, n in zip(*np.unique(kb, return_counts=True))}
    total = 0.0
    for i, k in itertools.combinations(range(len(A)), 2):
        L = DA[i, k]
        match = np.abs(DB - L) <= _tol_3(L, options)
        match &= (kb[:, None] == ka[i]) & (kb[None, :] == ka[k])
        np.fill_diagonal(match, False)
        if not match.any():
            continue
        jl = np.argwhere(match)
        for m in range(len(A)):
            if m in (i, k):
                continue
            d1, d2 = DA[i, m], DA[k, m]
            t1, t2 = 2 * _tol_3(d1, options), 2 * _tol_3(d2, options)
            p = min(
                t1 * t2 * 2 * np.pi * d1 * d2 / (max(L, 1e-9) * V),
                4 * np.pi * d1**2 * t1 / V,
                1.0,
            )
            others = counts.get(int(ka[m]), 0) - np.sum((kb[jl] == ka[m]).astype(np.int64), axis=1)
            total += p * float(np.maximum(others, 0).sum())
    return total


def _support(R, t, A, ka, B, kb, options):
    """Per motion: number of A's centres with a same-kind centre of B within the tolerance
    (``tolerance + relative_tolerance x`` the centre's range in its scan)."""
    from scipy.spatial import cKDTree  # at first use: it is slow to import

    tree = cKDTree(B)
    tol = _tol(np.linalg.norm(A, axis=1), options)
    Y = np.einsum("hij,nj->hni", R, A) + t[:, None, :]
    d, j = tree.query(Y.reshape(-1, 3), distance_upper_bound=tol.max())
    d, j = d.reshape(len(R), len(A)), np.minimum(j, len(B) - 1).reshape(len(R), len(A))
    return np.sum((d <= tol[None, :]) & (kb[j] == ka[None, :]), axis=1)


def _pairs(R, t, A, ka, B, kb, options):
    """One-to-one partners (mutual nearest, same kind, within the tolerance) of A in B under a
    motion, and the indices of A's centres within the tolerance of two of B's (ambiguous)."""
    Y = A @ R.T + t
    D = np.linalg.norm(Y[:, None] - B[None], axis=2)
    D[ka[:, None] != kb[None, :]] = np.inf
    near = D <= _tol(np.linalg.norm(A, axis=1), options)[:, None]
    pairs, ambiguous = [], []
    for i in range(len(A)):
        cand = np.flatnonzero(near[i])
        if len(cand) > 1:
            ambiguous.append(i)
        elif len(cand) == 1 and np.argmin(D[:, cand[0]]) == i:
            pairs.append((i, int(cand[0])))
    return pairs, ambiguous


def register(A, ka, B, kb, options, rng) -> _Registration:
    """Rigid registration of centres A (kinds ka) onto B (kinds kb) by distance consensus
    (module docstring)."""
    if min(len(A), len(B)) < 3:
        return _Registration("too few common targets")
    tri = _triangles(A, rng, options)
    R, t = _hypotheses(A, ka, B, kb, tri, options)
    if not len(R):
        return _Registration("too few common targets")
    sup = _support(R, t, A, ka, B, kb, options)
    best = int(np.argmax(sup))
    # Refit the best motion to its partners, twice.
    Rb, tb = R[best], t[best]
    pairs = []
    for _ in range(2):
        pairs, _ = _pairs(Rb, tb, A, ka, B, kb, options)
        if len(pairs) < 3:
            break
        i, j = np.asarray(pairs).T
        Rb, tb = rigid_fit(A[i], B[j], xp=np)
    n = len(pairs)
    # Different motions: rotated by > 1 deg from the best, or moving A's centroid by > tol.
    cA = A.mean(axis=0)
    cosang = (np.einsum("hij,ij->h", R, Rb) - 1.0) / 2.0
    moved = np.linalg.norm((R @ cA + t) - (Rb @ cA + tb), axis=1)
    other = (cosang < np.cos(np.radians(1.0))) | (moved > 2 * options.tolerance)
    second = int(sup[other].max()) if other.any() else 0
    reg = _Registration("placed", Rb, tb, tuple(pairs), support=n, second=second)
    # A rival is a tie where the best rests on 3 or 4 targets (a 3-target rival of a 4-target
    # fit needs the fourth partner to be a coincidence), else the ambiguity share of the best.
    if n < options.min_common:
        reg.status = "too few common targets"
    elif second >= max(options.ambiguity * n, min(n, 4)):
        reg.status = "ambiguous"
    elif n == 3:
        i, j = np.asarray(pairs).T
        da = np.linalg.norm(A[i][:, None] - A[i][None], axis=2)
        db = np.linalg.norm(B[j][:, None] - B[j][None], axis=2)
        reg.misfit = float(np.max(np.abs(da - db) - _tol_3(da, options)))
        reg.chance = _chance(A, ka, B, kb, options)
        if reg.misfit > 0 or reg.chance > options.max_chance:
            reg.status = "undecided"
    if n:
        i, j = np.asarray(pairs).T
        reg.rms = float(np.sqrt(np.mean(np.sum((A[i] @ Rb.T + tb - B[j]) ** 2, axis=1))))
    return reg


def _not_placed(scan, reg, onto, options) -> str | None:
    """The message of a registration that was not accepted for its ambiguity, or None."""
    if reg.status == "ambiguous":
        return (
            f"scan {scan}: two different placements {onto} are supported by {reg.support} and "
            f"{reg.second} targets: ambiguous, not named"
        )
    if reg.status == "undecided" and reg.misfit > 0:
        return (
            f"scan {scan}: placed {onto} by 3 common targets only, whose distances disagree by "
            f"{reg.misfit * 1e3:.1f} mm more than the tolerance of 3 (tolerance_3 + "
            "relative_tolerance_3 x distance): 3 cannot decide, not named (a target list, or a "
            "fourth target seen by this scan and another, can)"
        )
    if reg.status == "undecided":
        return (
            f"scan {scan}: placed {onto} by 3 common targets only, and among these centres a "
            f"chance match of 3 is expected {reg.chance:.2g} times (limit "
            f"{options.max_chance:g}): 3 cannot decide, not named (a target list, or a fourth "
            "target seen by this scan and another, can)"
        )
    return None


def _kind_codes(kind, size):
    """Integer codes: targets match only targets of the same kind and nominal size."""
    labels = [f"{k}:{round(float(s) * 1e4)}" for k, s in zip(kind, size)]
    table = {lab: c for c, lab in enumerate(sorted(set(labels)))}
    return np.array([table[lab] for lab in labels], dtype=np.int64)


def _pose(R, t):
    """EOP of a scan whose centres x map into the frame by ``X = R x + t``: ``x = R^T (X -
    t)``, so SPEC section 1's rotation is R^T and S = t."""
    return np.concatenate([t, angles_from_matrix(R.T)])


def _assign(targets, options, scan_sets, frame_R, frame_t, G, kG, names_g, messages):
    """Names of every accepted detection from the final motions (one-to-one per scan)."""
    names = np.full(len(targets), "", dtype=object)
    for s, (idx, X, k) in scan_sets.items():
        if frame_R.get(s) is None or not len(idx):
            continue
        pairs, amb = _pairs(frame_R[s], frame_t[s], X, k, G, kG, options)
        for i, j in pairs:
            names[idx[i]] = names_g[j]
        for i in amb:
            messages.append(
                f"scan {targets.scans[s]}: the {targets.kind[idx[i]]} at "
                f"{np.round(targets.centre[idx[i]], 3).tolist()} m lies within the tolerance of "
                "two targets: ambiguous, not named"
            )
    return names


def match_targets(
    targets,
    options: TargetMatchingOptions | None = None,
    *,
    target_list=None,
) -> ExtractedTargets:
    """Name the accepted detections of :func:`~tlsjax.extract_targets` consistently across
    scans (module docstring). ``target_list``: optional mapping name -> (x, y, z) [m] (or
    name -> (x, y, z, kind) with kind "sphere", "checkerboard", "circle"), e.g. from
    :func:`~tlsjax.read_reference`. Returns the targets with ``names`` filled in and
    ``matching`` (:class:`TargetMatching`)."""
    options = options or TargetMatchingOptions()
    rng = np.random.default_rng(options.seed)
    codes = _kind_codes(targets.kind, targets.size)
    scan_sets = {}
    for s in range(len(targets.scans)):
        idx = np.flatnonzero(targets.accepted & (targets.scan_index == s))
        scan_sets[s] = (idx, targets.centre[idx], codes[idx])
    messages = []
    if target_list is not None:
        result = _match_to_list(targets, options, rng, scan_sets, target_list, messages)
    else:
        result = _match_by_geometry(targets, options, rng, scan_sets, messages)
    names, status, n_common, rms, pose, coords = result
    matching = TargetMatching(
        {targets.scans[s]: status[s] for s in scan_sets},
        {targets.scans[s]: n_common.get(s, 0) for s in scan_sets},
        {targets.scans[s]: rms.get(s, np.nan) for s in scan_sets},
        {targets.scans[s]: pose.get(s, np.full(6, np.nan)) for s in scan_sets},
        coords,
        tuple(messages),
    )
    return dataclasses.replace(targets, names=names, matching=matching)


def _list_kinds(targets, idx, kinds):
    """Kind codes of the detections idx and of the list: by kind name where the list gives a
    kind for every target, else one code for all (a list without kinds matches any kind)."""
    if any(k is None for k in kinds):
        return np.zeros(len(idx), dtype=np.int64), np.zeros(len(kinds), dtype=np.int64)
    table = {k: c for c, k in enumerate(sorted(set(kinds) | {str(k) for k in targets.kind}))}
    return (
        np.array([table[str(targets.kind[i])] for i in idx], dtype=np.int64),
        np.array([table[k] for k in kinds], dtype=np.int64),
    )


def _match_to_list(targets, options, rng, scan_sets, target_list, messages):
    names_g = list(target_list)
    rows = [list(target_list[name]) for name in names_g]
    G = np.array([[float(v) for v in r[:3]] for r in rows]).reshape(-1, 3)
    kinds = [str(r[3]) if len(r) > 3 and r[3] else None for r in rows]
    frame_R, frame_t, status, n_common, rms, pose = {}, {}, {}, {}, {}, {}
    kG = np.zeros(len(G), dtype=np.int64)
    for s, (idx, X, _) in scan_sets.items():
        if not len(idx):
            status[s] = "no targets"
            continue
        kX, kG = _list_kinds(targets, idx, kinds)
        scan_sets[s] = (idx, X, kX)
        reg = register(X, kX, G, kG, options, rng)
        status[s], n_common[s], rms[s] = reg.status, reg.support, reg.rms
        if reg.status == "placed":
            frame_R[s], frame_t[s] = reg.R, reg.t
            pose[s] = _pose(reg.R, reg.t)
        elif note := _not_placed(targets.scans[s], reg, "on the target list", options):
            messages.append(note)
    names = _assign(targets, options, scan_sets, frame_R, frame_t, G, kG, names_g, messages)
    _conflicts(targets, names, messages)
    return names, status, n_common, rms, pose, dict(zip(names_g, G))


def _conflicts(targets, names, messages):
    """Two detections of one scan with one name: both unnamed."""
    for s in range(len(targets.scans)):
        idx = np.flatnonzero((targets.scan_index == s) & (names != ""))
        seen = {}
        for i in idx:
            seen.setdefault(names[i], []).append(i)
        for name, rows in seen.items():
            if len(rows) > 1:
                for i in rows:
                    names[i] = ""
                messages.append(
                    f"scan {targets.scans[s]}: {len(rows)} detections match target {name}: "
                    "ambiguous, none named"
                )


def _match_by_geometry(targets, options, rng, scan_sets, messages):
    sizes = {s: len(v[0]) for s, v in scan_sets.items()}
    status = {s: "no targets" for s in scan_sets}
    n_common, rms, pose = {}, {}, {}
    frame_R, frame_t = {}, {}
    if not any(sizes.values()):
        return np.full(len(targets), "", dtype=object), status, n_common, rms, pose, {}
    ref = max(sizes, key=lambda s: sizes[s])
    idx, X, k = scan_sets[ref]
    G, kG, members = list(X), list(k), [[(ref, i)] for i in range(len(X))]
    frame_R[ref], frame_t[ref] = np.eye(3), np.zeros(3)
    status[ref], n_common[ref], rms[ref], pose[ref] = "reference", len(X), 0.0, np.zeros(6)
    todo = {s for s in scan_sets if s != ref and sizes[s]}
    while todo:
        regs = {
            s: register(
                scan_sets[s][1], scan_sets[s][2], np.asarray(G), np.asarray(kG), options, rng
            )
            for s in sorted(todo)
        }
        placed = [s for s, r in regs.items() if r.status == "placed"]
        if not placed:
            for s, r in regs.items():
                status[s], n_common[s], rms[s] = r.status, r.support, r.rms
                if note := _not_placed(targets.scans[s], r, "onto the other scans", options):
                    messages.append(note)
            break
        s = max(placed, key=lambda q: regs[q].support)
        r = regs[s]
        todo.discard(s)
        frame_R[s], frame_t[s] = r.R, r.t
        status[s], n_common[s], rms[s], pose[s] = "placed", r.support, r.rms, _pose(r.R, r.t)
        _, Xs, ks = scan_sets[s]
        matched = dict(r.pairs)
        for i in range(len(Xs)):
            Y = r.R @ Xs[i] + r.t
            if i in matched:
                g = matched[i]
                members[g].append((s, i))
                G[g] = G[g] + (Y - G[g]) / len(members[g])
            else:
                G.append(Y)
                kG.append(ks[i])
                members.append([(s, i)])
    G, kG = np.asarray(G), np.asarray(kG)
    # Final pass: every placed scan against the final set (a target first seen by a later scan).
    counts = np.zeros(len(G), dtype=np.int64)
    for s in frame_R:
        pairs, _ = _pairs(frame_R[s], frame_t[s], scan_sets[s][1], scan_sets[s][2], G, kG, options)
        for _, j in pairs:
            counts[j] += 1
    keep = counts >= options.min_scans
    names_g = np.full(len(G), "", dtype=object)
    order = np.flatnonzero(keep)
    for n, j in enumerate(order):
        names_g[j] = f"T{n + 1:03d}"
    names = _assign(targets, options, scan_sets, frame_R, frame_t, G, kG, names_g, messages)
    _conflicts(targets, names, messages)
    coords = {names_g[j]: G[j] for j in order}
    return names, status, n_common, rms, pose, coords
