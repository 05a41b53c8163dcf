"""Independent references for the tests: a dense Gauss-Newton with a bordered normal matrix.

The oracle writes the point model out by hand (no tlsjax model code), forms the dense Jacobian
of the whole (small) network by ``jax.jacfwd``, and imposes inner constraints on the targets
with the textbook constraint matrix ``G = [I, -[X]x]`` in a bordered system (Koch 1999).
"""

import jax
import jax.numpy as jnp
import numpy as np
from scipy import stats

ARCSEC = np.pi / 180 / 3600
#: Baarda's delta0 for alpha0 = 0.1 %, power 80 % (SPEC section 7), from scipy directly.
DELTA0 = stats.norm.ppf(1 - 0.001 / 2) + stats.norm.ppf(0.8)


def _R(w, p, k):
    c, s = jnp.cos, jnp.sin
    R1 = jnp.array([[1, 0, 0], [0, c(w), s(w)], [0, -s(w), c(w)]])
    R2 = jnp.array([[c(p), 0, -s(p)], [0, 1, 0], [s(p), 0, c(p)]])
    R3 = jnp.array([[c(k), s(k), 0], [-s(k), c(k), 0], [0, 0, 1]])
    return R3 @ R2 @ R1


# Hybrid-scanner bases written out independently of the registry.
BASES = {
    "A0": (0, lambda r, t, a: jnp.ones_like(r)),
    "A1": (0, lambda r, t, a: r),
    "B6": (1, lambda r, t, a: 1 / jnp.cos(a) - 1),
    "B7": (1, lambda r, t, a: jnp.tan(a)),
    "C0": (2, lambda r, t, a: jnp.ones_like(r)),
}


def dense_residuals(x, net, aps, n_t, n_s):
    """Whitened residuals of the whole network as one vector, written out by hand: rows in
    network order (range, hz, el per observation), then the levelling rows."""
    T = x[: 3 * n_t].reshape(n_t, 3)
    E = x[3 * n_t : 3 * n_t + 6 * n_s].reshape(n_s, 6)
    A = x[3 * n_t + 6 * n_s :]
    l = jnp.asarray(net.observations)
    ti, si = np.asarray(net.target_index), np.asarray(net.scan_index)
    R = jax.vmap(lambda e: _R(*e[3:]))(E)  # (s, 3, 3)
    p = jnp.einsum("nij,nj->ni", R[si], T[ti] - E[si, :3])
    rho = jnp.linalg.norm(p, axis=1)
    th = jnp.mod(jnp.arctan2(p[:, 1], p[:, 0]), 2 * np.pi)
    al = jnp.arctan2(p[:, 2], jnp.hypot(p[:, 0], p[:, 1]))
    F = [rho, th, al]
    for k, name in enumerate(aps):
        g, b = BASES[name]
        F[g] = F[g] + A[k] * b(l[:, 0], l[:, 1], l[:, 2])
    d = jnp.stack(F, axis=1) - l
    d = d.at[:, 1:].set(jnp.arctan2(jnp.sin(d[:, 1:]), jnp.cos(d[:, 1:])))
    res = [(d / jnp.asarray(net.sigmas)).reshape(-1)]
    lw = np.where(np.isfinite(net.levelling_sigma), 1 / net.levelling_sigma, 0.0)
    for s in range(n_s):
        # Compensator: the object-space vertical seen in scanner space, g = R e3, read as
        # omega = asin(g_y) and phi = asin(-g_x / cos(omega)).
        g = R[s][:, 2]
        reading = [jnp.arcsin(g[1]), jnp.arcsin(-g[0] / jnp.sqrt(1 - g[1] ** 2))]
        for c in range(2):
            if lw[s, c] > 0:
                res.append(((reading[c] - net.levelling[s, c]) * lw[s, c])[None])
    return jnp.concatenate(res)


def dense_oracle(net, aps, x0, iterations=8):
    """Gauss-Newton with a bordered normal matrix; returns x, Qxx (inner constraints on the
    targets), redundancy numbers (whitened), v^T P v and the degrees of freedom."""
    n_t, n_s = len(net.targets), len(net.scans)
    f = jax.jit(lambda x: dense_residuals(x, net, aps, n_t, n_s))
    J_f = jax.jit(jax.jacfwd(f))
    levelled = np.isfinite(net.levelling_sigma).all(axis=1).any()
    cols = [0, 1, 2, 5] if levelled else list(range(6))
    x = np.asarray(x0, dtype=float)
    u = x.size
    for _ in range(iterations):
        J = np.asarray(J_f(x))
        e = np.asarray(f(x))
        G = _constraints(x, n_t, u, cols)
        N = J.T @ J
        B = np.block([[N, G], [G.T, np.zeros((G.shape[1], G.shape[1]))]])
        rhs = np.concatenate([-J.T @ e, np.zeros(G.shape[1])])
        x = x + np.linalg.solve(B, rhs)[:u]
    J = np.asarray(J_f(x))
    e = np.asarray(f(x))
    G = _constraints(x, n_t, u, cols)
    B = np.block([[J.T @ J, G], [G.T, np.zeros((G.shape[1], G.shape[1]))]])
    Q = np.linalg.inv(B)[:u, :u]
    redundancy = 1 - np.einsum("ij,jk,ik->i", J, Q, J)
    dof = J.shape[0] - u + len(cols)
    return x, Q, redundancy, float(e @ e), dof


def _constraints(x, n_t, u, cols):
    G = np.zeros((u, 6))
    for t in range(n_t):
        X = x[3 * t : 3 * t + 3]
        G[3 * t : 3 * t + 3, :3] = np.eye(3)
        G[3 * t : 3 * t + 3, 3:] = -np.array([[0, -X[2], X[1]], [X[2], 0, -X[0]], [-X[1], X[0], 0]])
    return G[:, cols]


def perturbed_start(res, target_scale, eop_shift=0.0, ap_factor=1.0, seed=0):
    """A start for the oracle near a structured solution: targets moved orthogonally to the
    rigid motions (so the inner-constraint datum, defined relative to the start, is the same),
    poses shifted, APs scaled."""
    X = res.target_xyz
    G = np.zeros((X.size, 6))
    for t in range(X.shape[0]):
        G[3 * t : 3 * t + 3, :3] = np.eye(3)
        G[3 * t : 3 * t + 3, 3:] = [
            [0, X[t, 2], -X[t, 1]],
            [-X[t, 2], 0, X[t, 0]],
            [X[t, 1], -X[t, 0], 0],
        ]
    d = np.random.default_rng(seed).normal(scale=target_scale, size=X.size)
    d -= G @ np.linalg.lstsq(G, d, rcond=None)[0]
    return np.concatenate(
        [X.reshape(-1) + d, res.eops.reshape(-1) + eop_shift, res.ap_values * ap_factor]
    )


# --- The rigorous Gauss-Helmert model of plane networks, dense (SPEC sections 4 and 6) --------


def _g_plane(plane, eop, aps, names, l):
    """``g = n . (R^T x(l - Delta(l)) + S) - d`` of one point, hybrid bases of ``BASES``."""
    corr = [l[0], l[1], l[2]]
    for k, name in enumerate(names):
        grp, b = BASES[name]
        corr[grp] = corr[grp] - aps[k] * b(l[0], l[1], l[2])
    rho, th, al = corr
    x = rho * jnp.array([jnp.cos(al) * jnp.cos(th), jnp.cos(al) * jnp.sin(th), jnp.sin(al)])
    return plane[:3] @ (_R(*eop[3:]).T @ x + eop[:3]) - plane[3]


def _compensator(eop):
    g = _R(*eop[3:])[:, 2]
    return jnp.stack([jnp.arcsin(g[1]), jnp.arcsin(-g[0] / jnp.sqrt(1 - g[1] ** 2))])


def dense_gauss_helmert(net, names, x0, pseudo=(), iterations=40, tol=1e-10, datum=None):
    """The textbook rigorous Gauss-Helmert adjustment of a (small) plane network, dense.

    Unknowns ``x = (planes (k, 4), eops (s, 6), APs)``; observations ``L``: the three of every
    plane point, then the pseudo-observations (the levelling readings of ``net`` as compensator
    readings, then ``pseudo``: (f(x) -> scalar, observed value, sigma) each). Conditions
    ``g(x, L + v) = 0``: one per point, ``f(x) - (l + v) = 0`` per pseudo-observation. Each
    iteration linearises at ``(x, L + v)`` (Lenzmann & Lenzmann 2004; Neitzel 2010):
    ``A dx + B v_new + w = 0``, ``w = g(x, L + v) - B v``, and solves the bordered normal
    equations ``[[A^T M^-1 A, C^T, G], [C, 0, 0], [G^T, 0, 0]]`` with ``M = B Sigma B^T``, the
    hard unit-normal constraints ``C dx = -(|n|^2 - 1)`` and the inner constraints on the planes
    ``G^T dx = 0``; ``v_new = -Sigma B^T M^-1 (A dx + w)``; until dx and v settle (``|dx| <
    tol`` and ``|v_new - v| / sigma < tol (1 + max |v| / sigma)``, i.e. to rounding).

    Returns a dict: ``x``, ``Q`` (bordered inverse, inner-constraint cofactor), ``v`` and ``r``
    (residuals and redundancy numbers ``diag(Q_vv P)`` of all observations, points first),
    ``vtpv``, ``dof = c - u + h + d``, ``iterations``. ``datum``: the rigid motions (columns of
    tx, ty, tz, rx, ry, rz) of the inner constraints (default: all six, or without rx and ry
    when a scan is levelled).
    """
    pl, sc = jnp.asarray(net.plane_index), jnp.asarray(net.plane_scan_index)
    n_pl, n_s, n_a = len(net.planes), len(net.scans), len(names)
    m = len(pl)
    lw = np.isfinite(net.levelling_sigma)
    lev = [(s, c) for s in range(n_s) for c in range(2) if lw[s, c]]
    p_obs = [net.levelling[s, c] for s, c in lev] + [o for _, o, _ in pseudo]
    p_sig = [net.levelling_sigma[s, c] for s, c in lev] + [s_ for _, _, s_ in pseudo]
    L = np.concatenate([np.asarray(net.plane_observations).reshape(-1), p_obs])
    sig = np.concatenate([np.asarray(net.plane_sigmas).reshape(-1), p_sig])
    Sigma = np.diag(sig**2)
    u = 4 * n_pl + 6 * n_s + n_a

    def unpack(x):
        return (
            x[: 4 * n_pl].reshape(n_pl, 4),
            x[4 * n_pl : 4 * n_pl + 6 * n_s].reshape(n_s, 6),
            x[4 * n_pl + 6 * n_s :],
        )

    def g_all(x, Lh):
        P, E, A = unpack(x)
        pts = Lh[: 3 * m].reshape(m, 3)
        g = [jax.vmap(lambda i: _g_plane(P[pl[i]], E[sc[i]], A, names, pts[i]))(jnp.arange(m))]
        f = [_compensator(E[s])[c] for s, c in lev] + [fn(x) for fn, _, _ in pseudo]
        if f:
            g.append(jnp.stack(f) - Lh[3 * m :])
        return jnp.concatenate(g)

    def h_all(x):
        return jnp.sum(unpack(x)[0][:, :3] ** 2, axis=1) - 1.0

    levelled = lw.all(axis=1).any()
    cols = list(datum) if datum is not None else [0, 1, 2, 5] if levelled else list(range(6))

    def datum(x):
        # Rigid motion of object space: translation t changes d by n . t, rotation w turns n.
        P = np.asarray(unpack(x)[0])
        G = np.zeros((u, 6))
        for k in range(n_pl):
            n = P[k, :3]
            G[4 * k + 3, :3] = n
            G[4 * k : 4 * k + 3, 3:] = -np.array(
                [[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]]
            )
        return G[:, cols]

    gx = jax.jit(g_all)
    A_f = jax.jit(jax.jacfwd(g_all, argnums=0))
    B_f = jax.jit(jax.jacfwd(g_all, argnums=1))
    C_f = jax.jit(jax.jacfwd(h_all))
    x = np.asarray(x0, dtype=float).copy()
    v = np.zeros_like(L)
    for it in range(1, iterations + 1):
        done = it
        Lh = L + v
        A, B = np.asarray(A_f(x, Lh)), np.asarray(B_f(x, Lh))
        w = np.asarray(gx(x, Lh)) - B @ v
        Mi = np.linalg.inv(B @ Sigma @ B.T)
        C, G = np.asarray(C_f(x)), datum(x)
        K = np.vstack([C, G.T])
        N = np.block([[A.T @ Mi @ A, K.T], [K, np.zeros((K.shape[0], K.shape[0]))]])
        rhs = np.concatenate([-A.T @ Mi @ w, -np.asarray(h_all(x)), np.zeros(G.shape[1])])
        dx = np.linalg.solve(N, rhs)[:u]
        v_new = -Sigma @ B.T @ Mi @ (A @ dx + w)
        x = x + dx
        scale = 1.0 + np.max(np.abs(v_new) / sig)
        settled = np.max(np.abs(v_new - v) / sig) < tol * scale and np.max(np.abs(dx)) < tol
        v = v_new
        if settled:
            break
    Q = np.linalg.inv(N)[:u, :u]
    Qvv = Sigma @ B.T @ Mi @ (B @ Sigma @ B.T - A @ Q @ A.T) @ Mi @ B @ Sigma
    r = np.diag(Qvv) / sig**2
    vtpv = float(np.sum(v**2 / sig**2))
    dof = len(w) - u + n_pl + len(cols)
    return dict(x=x, Q=Q, v=v, r=r, vtpv=vtpv, dof=dof, iterations=done, n_points=m)


def tiny_planes(rng, n: int):
    """A small valid extracted-planes object (two scans, one patch each on one plane x = 5 m,
    n points), for tests of the planes file and its readers."""
    import tlsjax as tj

    half = n // 2
    return tj.ExtractedPlanes(
        scans=("S1", "S2"),
        patch_scan=np.array([0, 1]),
        patch_normal=np.array([[1.0, 0, 0], [1.0, 0, 0]]),
        patch_distance=np.array([5.0, 5.0]),
        patch_rms=np.full(2, 1e-3),
        patch_inliers=np.array([half, n - half]),
        patch_plane=np.array([0, 0]),
        point_patch=np.repeat([0, 1], [half, n - half]),
        point_index=np.arange(n),
        observations=np.column_stack([np.full(n, 5.0), rng.uniform(-0.3, 0.3, (n, 2))]),
        incidence=np.zeros(n),
        poses=np.zeros((2, 6)),
        planes=np.array([[1.0, 0, 0, 5.0]]),
    )


def same_run(cli_doc: dict, api_doc: dict) -> None:
    """The JSON ``tlsjax calibrate`` wrote equals ``self_calibrate(...).to_dict()`` of the same
    network, model and options, but for what only the command knows or what differs between
    two runs: the time and the command line in ``provenance``, and ``settings.inputs`` (how
    the command read the files)."""

    def comparable(doc):
        doc = {**doc, "provenance": dict(doc["provenance"]), "settings": dict(doc["settings"])}
        for key in ("created_utc", "command"):
            doc["provenance"].pop(key)
        doc["settings"].pop("inputs")
        return doc

    a, b = comparable(cli_doc), comparable(api_doc)
    assert set(a) == set(b), set(a) ^ set(b)
    for key in a:
        assert a[key] == b[key], key


def printed_is_summary(stdout: str, summary: str) -> None:
    """What ``tlsjax calibrate`` printed is what reading decided (lines naming the files), the
    result's ``summary()``, then one line per file written."""
    head, found, tail = stdout.partition(summary + "\n")
    assert found, "the summary is not in the output"
    assert all(".csv" in line or ".npz" in line for line in head.splitlines()), head
    assert all(line.startswith("wrote ") for line in tail.splitlines()), tail
