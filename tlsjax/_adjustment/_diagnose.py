"""Naming what a non-estimable AP is confounded with (SPEC section 7).

The rank-revealing Cholesky of :mod:`._linalg` finds *that* an AP column depends on the others;
this module says *on what*. A dependency is a null vector of the reduced normal matrix K, but
it is defined only up to the rigid-motion null space of the free network, so the partner one
reads off it depends on the datum. The papers' tables report correlations in the
inner-constraint datum on the object-space primitives (SPEC section 6), so the dependency is
expressed in that datum too:

* the AP gets a vanishing ridge ``eps K_jj`` so that its cofactor exists, the other dependent
  columns are held fixed;
* the datum is closed by the inner constraints on the targets written in the reduced unknowns:
  a reduced update ``z`` moves the targets by ``dp = -N_pp^-1 N_pz z`` (homogeneous part of the
  back-substitution), so ``G^T dp = 0`` reads ``C z = 0`` with ``C = sum_i H_p,i^T N_pp,i^-1
  N_pz,i``;
* the bordered system ``[[K + eps e_j e_j^T, C^T], [C, 0]]`` is inverted; the AP's largest
  absolute correlation in that cofactor matrix names its partner (it tends to 1 as eps -> 0).

A dependency that is a change of network scale (A1 without scale bars or control) is reported
as such: the AP's null vector then moves every scan position radially.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._linalg import spd_inverse
from ._normal import linearise, null_space

RIDGE = 1e-9


@functools.partial(jax.jit, static_argnums=0)
def _reduced_system(spec, problem, params):
    """Raw reduced normal matrix K, target-datum constraint C (d, r) and the datum columns Hz."""
    blocks = linearise(spec, problem, params)
    Hp, Hz = null_space(spec, params)
    K = blocks.Nzz
    C = jnp.zeros((Hz.shape[1], K.shape[0]))
    for Npp, Npz, H in zip(blocks.Npp, blocks.Npz, Hp):
        Y = jnp.sum(spd_inverse(Npp)[..., :, :, None] * Npz[..., None, :, :], axis=-2)
        K = K - jnp.einsum("npr,npq->rq", Npz, Y)
        C = C + jnp.einsum("npd,npr->dr", H, Y)
    return K, C, Hz


def confounded_partners(
    spec, problem, params, dependent: np.ndarray, fixed: np.ndarray, columns
) -> dict:
    """For each reduced column j in ``columns``: (partner index, |corr|, scale_like)."""
    K, C, Hz = (np.asarray(a) for a in _reduced_system(spec, problem, params))
    r = K.shape[0]
    d = np.sqrt(np.clip(np.diag(K), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    Ks = K / np.outer(d, d)
    Cs = C / d[None, :]
    ns = spec.n_scans
    out = {}
    for j in columns:
        keep = ~(dependent | fixed)
        keep[j] = True
        idx = np.flatnonzero(keep)
        A = Ks[np.ix_(idx, idx)].copy()
        jj = int(np.flatnonzero(idx == j)[0])
        A[jj, jj] += RIDGE
        B = Cs[:, idx] if Hz.shape[1] else np.zeros((0, len(idx)))
        M = np.block([[A, B.T], [B, np.zeros((B.shape[0], B.shape[0]))]])
        Q = np.linalg.pinv(M, hermitian=True)[: len(idx), : len(idx)]
        s = np.sqrt(np.clip(np.diag(Q), 1e-300, None))
        corr = Q[jj] / (s[jj] * s)
        corr[jj] = 0.0
        k = int(np.argmax(np.abs(corr)))
        # The AP's own uncertainty direction, back in unscaled reduced coordinates.
        v = np.zeros(r)
        v[idx] = Q[jj] / d[idx]
        out[j] = (int(idx[k]), float(abs(corr[k])), _is_scale(v, params, ns))
    return out


def _is_scale(v, params, ns) -> bool:
    """True when the scan-position part of the null direction is a radial expansion."""
    S = np.asarray(params.eops)[:, :3]
    radial = (S - S.mean(axis=0)).reshape(-1)
    pos = v[: 6 * ns].reshape(ns, 6)[:, :3].reshape(-1)
    pos = pos - np.tile(pos.reshape(ns, 3).mean(axis=0), ns)
    den = np.linalg.norm(pos) * np.linalg.norm(radial)
    return bool(den > 0 and abs(pos @ radial) / den > 0.9)
