"""The simulations of the AP-set compatibility test (SPEC section 9, steps 2-3), as pure JAX.

One simulation draws targets over the room's faces, observes them twice from one levelled
station (in the design's architecture, scan k with set k's noise), corrects scan k with set k
(its own basis functions: architecture variant, unit lengths, user-registered terms),
converts both to Cartesian coordinates and fits scan 2 onto scan 1 on the control points
(rigid body, Horn/Kabsch). It returns sums over its check points of everything the test needs,
so that N simulations reduce to a few small matrices (no per-point array leaves the device):

* ``T``: sum of ``d^T C^-1 d``; ``n_sig``: how many exceed the chi-square(3) quantile;
* ``G = sum F^T C^-1 F``, ``b = sum F^T C^-1 n``, ``c = sum n^T C^-1 n`` (the null's quadratic
  form, SPEC section 9 step 5, on the union columns below);
* ``Geu = sum F^T F`` and ``Kpre = sum Fpre^T Fpre``: the Euclidean size of an AP direction's
  effect after and before the rigid fit (what object space can see of it);
* ``ss``: sums of squared differences per axis.

**Union columns.** ``[J1 J2] e = F P e``: a term both sets hold with one basis moves the two
scans alike, so its column of J2 is minus its column of J1 to first
order (the two scans differ by noise), and the pair enters through ``e1 - e2`` alone. F holds
J1's columns (every term of set 1) and J2's columns of the other terms of set 2; ``P`` (host
side) maps e = (e1, e2) onto them, and the covariance of ``P e`` is the argument ``Cu``. For two
sets of one model this halves the width of every per-point product (a quarter of the work in
``G``), which is what keeps a 23-AP test within twice a 4-AP one.

Jacobians by autodiff, composed by the chain rule so that nothing is differentiated twice:
per point ``dx/dl`` and ``dx/da`` of ``x = cart(l - Delta(l; a))`` (``jax.jacfwd``), and the
12 x 6 n_c Jacobian of the fit's (R, t) with respect to the control points' coordinates
(``jax.jacfwd`` through the SVD). A check point's difference ``d = R x2 + t - x1`` then has
``J1 = -dx1/da1 + A dtheta/dx1_c dx1_c/da1``, ``J2 = R dx2/da2 + A dtheta/dx2_c dx2_c/da2``
(``A = d(R x2 + t)/d(R, t)``), and the noise covariance
``N = S1 + R S2 R^T + A P A^T`` with ``S_k = dx_k/dl Sigma_l dx_k/dl^T`` and ``P`` the
covariance of (R, t) from the control points' noise.

The instrument's own errors are not put into the simulated scans: both scans are of one mode,
so its errors would move them alike and cancel from ``d`` to first order; what is left is the
product of two AP effects (e.g. 1e-4 rad times a basis slope), far below the noise and common to
the null. (Scans of two modes, hybrid and panoramic, would not cancel: the same collimation
error moves the back half of a panoramic scan the other way. The design therefore observes both
scans in one architecture.)
"""

from __future__ import annotations

import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._linalg import spd_inverse
from .._model._aps import ap_basis_matrix, ap_corrections, on_reregistration
from .._model._geometry import cartesian_from_spherical, rigid_fit, spherical_from_cartesian
from .._simulation._batch import compile_batched

#: Relative ridge on a check point's 3 x 3 covariance: keeps ``d^T C^-1 d`` finite when the
#: noise is zero and the AP difference moves the point in fewer than three directions.
RIDGE = 1e-12


def room_vector(room) -> np.ndarray:
    """The room as an argument of the compiled simulation: (L, W, H, margin, station xyz) [m]
    (the scanner at the room's first station), so that another room does not recompile."""
    return np.array([room.length, room.width, room.height, room.margin, *room.stations[0]])


def room_points(room, u):
    """Points uniform by area over the room's six faces (margin from the edges), with the
    faces' inward normals, from uniforms ``u`` (n, 4): targets at different distances from the
    station. ``room``: :func:`room_vector`. The face is the first uniform's bin in the
    cumulative face areas."""
    L, W, H, m = room[0], room[1], room[2], room[3]
    area = jnp.stack([W * H, W * H, L * H, L * H, L * W, L * W])
    edges = jnp.cumsum(area)[:-1] / jnp.sum(area)
    value = jnp.stack([0.0 * L, L, 0.0 * W, W, 0.0 * H, H])
    axis = jnp.asarray([0, 0, 1, 1, 2, 2])
    normal = jnp.asarray(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=jnp.float64
    )
    face = jnp.sum(u[:, :1] >= edges[None, :], axis=1)
    size = jnp.stack([L, W, H])
    X = m + u[:, 1:4] * (size - 2 * m)
    X = jnp.where(jnp.arange(3)[None, :] == axis[face][:, None], value[face][:, None], X)
    return X, normal[face]


def _normals(u):
    """Standard normals (n, 2k) from uniforms (n, 2k) by Box-Muller."""
    k = u.shape[1] // 2
    r = jnp.sqrt(-2.0 * jnp.log1p(-u[:, :k]))
    phi = 2.0 * np.pi * u[:, k:]
    return jnp.concatenate([r * jnp.cos(phi), r * jnp.sin(phi)], axis=1)


def _observe(x, architecture):
    """Observations of scanner-space points in the architecture's convention (SPEC section 1)."""
    if architecture != "panoramic":
        return spherical_from_cartesian(x)
    face2 = jnp.mod(jnp.arctan2(x[..., 1], x[..., 0]), 2 * np.pi) >= np.pi
    return spherical_from_cartesian(x, face2)


def _fit_params(dst, src):
    """(R, t) of the rigid fit of ``src`` onto ``dst`` as one 12-vector (R row-major, t)."""
    R, t = rigid_fit(src, dst)
    return jnp.concatenate([R.reshape(-1), t])


def _moves(x):
    """``A = d(R x + t)/d(vec R, t)`` (3 x 12) of each point of ``x`` (p, 3)."""
    p = x.shape[0]
    eye = jnp.broadcast_to(jnp.eye(3), (p, 3, 3))
    rot = jnp.einsum("rq,ps->prqs", jnp.eye(3), x).reshape(p, 3, 9)
    return jnp.concatenate([rot, eye], axis=2)


def _corrector(scanner):
    """Per point of a noisy scan ``l = l0 + nu``: ``x = cart(l - Delta(l; a))``, ``dx/dl``
    (3 x 3), ``dx/da`` (3 x n) and the noise-free point ``x0 = x - dx/dl nu``; and ``effect(l,
    a)`` -> (x, dx/da) alone.

    The corrections are linear in ``a``: ``Delta = B(l) a`` with the basis matrix ``B =
    dDelta/da`` (:func:`~tlsjax._model._aps.ap_basis_matrix`, each basis evaluated once;
    ``jax.jacfwd`` or ``jax.jacrev`` of the corrections with respect to ``a`` cost two to three
    times as much for 23 APs, measured under vmap on the CPU). ``dx/dl`` includes the slope of
    the corrections, ``dDelta/dl`` (autodiff). ``x0`` is first order in the noise: its error,
    about ``rho sigma^2`` (5e-8 m for 20" at 10 m), is a few 1e-5 of the noise, and the bases
    are not evaluated a third time."""
    names = scanner.aps

    def correction(l, a):  # for the slope: the registry's sum is faster to differentiate
        return ap_corrections(a, names, l, scanner)

    def effect(l, a):
        B = ap_basis_matrix(names, l, scanner)
        lc = l - B @ a
        Jc = jax.jacfwd(cartesian_from_spherical)(lc)
        return cartesian_from_spherical(lc), Jc, -Jc @ B

    def point(l, nu, a):
        x, Jc, Ja = effect(l, a)
        Jl = Jc - Jc @ jax.jacfwd(correction)(l, a)
        return x, x - Jl @ nu, Jl, Ja

    def effect_only(l, a):
        x, _, Ja = effect(l, a)
        return x, Ja

    return jax.vmap(point, in_axes=(0, 0, None)), jax.vmap(effect_only, in_axes=(0, None))


def _flat(M, K):
    """``M[p] @ K`` for a stack M (p, r, q) and one K (q, s), as one matrix product."""
    return (M.reshape(-1, M.shape[-1]) @ K).reshape(M.shape[:-1] + K.shape[-1:])


def _gram(U, V):
    """``sum_p U[p]^T V[p]`` (p, r, a), (p, r, b) -> (a, b), as one matrix product (XLA lowers
    the einsum with two contracted axes several times slower)."""
    return U.reshape(-1, U.shape[-1]).T @ V.reshape(-1, V.shape[-1])


def _outer_sum(M, S, K):
    """``sum_c M[:, c] S[c] K[:, c]^T`` for M, K (a, c, 3) and S (c, 3, 3)."""
    return jnp.einsum("acj,cjk,bck->ab", M, S, K)


class _Fit:
    """The rigid fit of scan 2 onto scan 1 on the first ``nc`` points and its Jacobians."""

    def __init__(self, nc):
        self.nc = nc
        self._jac = jax.jacfwd(_fit_params, argnums=(0, 1))

    def differences(self, x1, x2):
        """Check-point differences ``R x2 + t - x1`` and R."""
        nc = self.nc
        th = _fit_params(x1[:nc], x2[:nc])
        R, t = th[:9].reshape(3, 3), th[9:]
        return x2[nc:] @ R.T + t - x1[nc:], R

    def columns(self, x1, x2, R, Ja1, Ja2):
        """``F`` (check points, 3, u): the effect of each union column on ``d`` through the
        correction, conversion and the fit; also dtheta/dx1_c, dtheta/dx2_c (12, nc, 3) and
        ``A = d(R x2 + t)/d(R, t)`` of the check points."""
        nc = self.nc
        M1, M2 = self._jac(x1[:nc], x2[:nc])
        M1, M2 = M1.reshape(12, nc, 3), M2.reshape(12, nc, 3)
        A = _moves(x2[nc:])
        F1 = -Ja1[nc:] + _flat(A, M1.reshape(12, -1) @ Ja1[:nc].reshape(nc * 3, -1))
        F2 = jnp.einsum("ij,pja->pia", R, Ja2[nc:])
        F2 = F2 + _flat(A, M2.reshape(12, -1) @ Ja2[:nc].reshape(nc * 3, -1))
        return jnp.concatenate([F1, F2], axis=2), M1, M2, A


def make_simulation(design):
    """``one(key, a1, a2, Cu, sig1, sig2, room, reference) -> dict`` of check-point sums (module
    docstring) for a :class:`~tlsjax._inference._compatibility.Design`; ``Geu`` and ``Kpre`` (at zero
    noise, on the same targets) are formed only when ``reference`` (an unbatched flag) is
    true, and are zeros otherwise. (One closure over the design, longer than a page: its steps,
    the scans, the noise covariance and the reference sums, share the design's static
    settings.)"""
    s1, s2 = design.scanner1, design.scanner2
    nc, nt = design.n_control, design.n_targets
    (point1, effect1), (point2, effect2) = _corrector(s1), _corrector(s2)
    fit = _Fit(nc)
    cols2 = np.asarray(design.columns2, dtype=int)

    def scans(key, sig1, sig2, room):
        # One flat draw per simulation: XLA compiles a multi-dimensional threefry draw many
        # times slower (measured 14 s against 1.3 s for 1,000 uniforms under vmap).
        u = jax.random.uniform(key, (nt * 10,)).reshape(nt, 10)
        X, nrm = room_points(room, u[:, :4])
        e = _normals(u[:, 4:])
        los = X - room[4:7]
        cosb = jnp.abs(jnp.sum(los * nrm, axis=1)) / jnp.linalg.norm(los, axis=1)
        unit = jnp.stack([1.0 / jnp.maximum(cosb, 0.05), jnp.ones(nt), jnp.ones(nt)], axis=1)
        nu1, nu2 = e[:, :3] * unit * sig1, e[:, 3:] * unit * sig2
        return _observe(los, design.architecture), nu1, nu2, unit * sig1, unit * sig2

    def noise_cov(Jl1, Jl2, sd1, sd2, R, M1, M2, A):
        """N: both scans' observation noise through correction, conversion and the fit."""
        S1 = jnp.einsum("pij,pj,pkj->pik", Jl1, sd1**2, Jl1)
        S2 = jnp.einsum("pij,pj,pkj->pik", Jl2, sd2**2, Jl2)
        P = _outer_sum(M1, S1[:nc], M1) + _outer_sum(M2, S2[:nc], M2)
        return S1[nc:] + R @ S2[nc:] @ R.T + _flat(A, P) @ jnp.swapaxes(A, 1, 2)

    def reference_sums(l0, a1, a2):
        """Post-fit and pre-fit Gram matrices of the union columns at zero noise."""
        x1, Ja1 = effect1(l0, a1)
        x2, Ja2 = effect2(l0, a2)
        Ja2 = Ja2[:, :, cols2]
        _, R = fit.differences(x1, x2)
        F = fit.columns(x1, x2, R, Ja1, Ja2)[0]
        Fpre = jnp.concatenate([-Ja1[nc:], Ja2[nc:]], axis=2)
        return _gram(F, F), _gram(Fpre, Fpre)

    def one(key, a1, a2, Cu, sig1, sig2, room, reference):
        l0, nu1, nu2, sd1, sd2 = scans(key, sig1, sig2, room)
        x1, x01, Jl1, Ja1 = point1(l0 + nu1, nu1, a1)
        x2, x02, Jl2, Ja2 = point2(l0 + nu2, nu2, a2)
        d, R = fit.differences(x1, x2)
        n = d - fit.differences(x01, x02)[0]  # the noise part of d: d less its noise-free value
        F, M1, M2, A = fit.columns(x1, x2, R, Ja1, Ja2[:, :, cols2])
        C = jnp.einsum("pia,pja->pij", _flat(F, Cu), F)
        C = C + noise_cov(Jl1, Jl2, sd1, sd2, R, M1, M2, A)
        tr = jnp.trace(C, axis1=1, axis2=2)
        Ci = spd_inverse(C + (RIDGE * tr / 3.0)[:, None, None] * jnp.eye(3))
        Cid, Cin = jnp.einsum("pij,pj->pi", Ci, d), jnp.einsum("pij,pj->pi", Ci, n)
        zeros = jnp.zeros((F.shape[2],) * 2)
        Geu, Kpre = jax.lax.cond(
            reference, lambda: reference_sums(l0, a1, a2), lambda: (zeros, zeros)
        )
        q = jnp.sum(d * Cid, axis=1)
        return {
            "T": jnp.sum(q),
            "n_sig": jnp.sum(q > design.critical),
            "G": _gram(F, Ci @ F),
            "b": _gram(F, Cin[:, :, None])[:, 0],
            "c": jnp.sum(n * Cin),
            "Geu": Geu,
            "Kpre": Kpre,
            "ss": jnp.sum(d * d, axis=0),
        }

    return one


def _realisation_key(seed_key, index, runs):
    """Simulation ``index % runs`` of test ``index // runs``: ``fold_in(fold_in(seed key, test),
    simulation)``, the same whatever the chunking and the number of devices."""
    return jax.random.fold_in(jax.random.fold_in(seed_key, index // runs), index % runs)


def _indexed(one):
    """``one`` of a realisation index. The AP values come as tables ``V1`` (chunk, n1), ``V2``
    (chunk, n2), one row per position in the chunk (chunks start at multiples of the chunk
    size): one test repeats its values in every row, a batch of tests gives each realisation
    its test's values, and both run through one compiled function."""

    def run(index, seed_key, runs, V1, V2, Cu, sig1, sig2, room, reference):
        pos = index % V1.shape[0]
        key = _realisation_key(seed_key, index, runs)
        return one(key, V1[pos], V2[pos], Cu, sig1, sig2, room, reference)

    return run


@functools.lru_cache(maxsize=16)
def compiled_chunk(design, chunk: int, devices: tuple):
    """One compiled chunk function per design, chunk size and devices (the cache key holds
    everything the function closes over: the design's scanners carry their AP names and the
    registration tokens of the terms). AP values, covariances, noise, room and seed are
    arguments: another test of one design, or a batch of tests, never recompiles."""
    one = _indexed(make_simulation(design))
    n1, n2 = len(design.scanner1.aps), len(design.scanner2.aps)
    u = n1 + len(design.columns2)
    consts = (
        jax.random.PRNGKey(0),
        jnp.asarray(1, dtype=jnp.int64),
        jnp.zeros((chunk, n1)),
        jnp.zeros((chunk, n2)),
        jnp.zeros((u, u)),
        jnp.zeros(3),
        jnp.zeros(3),
        jnp.zeros(7),
        jnp.asarray(False),
    )  # the order of run_tests' arguments
    return compile_batched(one, consts, chunk)


def run_tests(b, seed_key, runs: int, V1, V2, rest, *, reference=False, progress=False):
    """Realisations of ``len(V1)`` tests of ``runs`` simulations each through the compiled
    chunk function ``b`` (test k has the values ``V1[k]``, ``V2[k]``; ``rest`` = (Cu, sig1,
    sig2, room vector)); with ``reference``, the first chunk also forms the zero-noise Gram
    matrices.
    Returns the per-realisation outputs (tests * runs, ...) as numpy and the seconds."""
    from tqdm.auto import tqdm

    n = V1.shape[0] * runs
    consts = jax.device_put((seed_key, np.int64(runs)), b.replicated)
    rest = jax.device_put(tuple(rest), b.replicated)
    flags = [jax.device_put(np.asarray(f), b.replicated) for f in (False, True)]
    single = V1.shape[0] == 1
    if single:  # one test: its tables are the same for every chunk
        tables = jax.device_put(
            (np.tile(V1, (b.chunk, 1)), np.tile(V2, (b.chunk, 1))), b.replicated
        )
    parts = []
    t0 = time.perf_counter()
    starts = range(0, n, b.chunk)
    for start in tqdm(starts, desc="compatibility chunks", unit="chunk", disable=not progress):
        idx = np.arange(start, start + b.chunk, dtype=np.int64)
        if not single:
            test = np.minimum(idx, n - 1) // runs  # past the end: repeat the last (discarded)
            tables = jax.device_put((V1[test], V2[test]), b.replicated)
        flag = flags[bool(reference) and start == 0]
        out = b.compiled(jax.device_put(idx, b.batched), *consts, *tables, *rest, flag)
        parts.append(out)
    parts = [jax.tree.map(np.asarray, part) for part in parts]
    return jax.tree.map(lambda *a: np.concatenate(a)[:n], *parts), time.perf_counter() - t0


def statistic_function(design, runs: int):
    """``T(a1, a2, Cu, sig1, sig2, room, seed_key)``: the test statistic (SPEC section 9 step 4)
    as a pure, differentiable function of the two AP vectors."""
    one = make_simulation(design)
    n_check = design.n_targets - design.n_control

    def T(a1, a2, Cu, sig1, sig2, room, seed_key):
        keys = jax.vmap(lambda i: _realisation_key(seed_key, i, runs))(jnp.arange(runs))
        out = jax.vmap(one, in_axes=(0,) + (None,) * 7)(keys, a1, a2, Cu, sig1, sig2, room, False)
        return jnp.sum(out["T"]) / (runs * n_check)

    return T


on_reregistration(compiled_chunk.cache_clear)
