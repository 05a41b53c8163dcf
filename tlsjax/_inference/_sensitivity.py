"""Sensitivity of the APs to every observation: ``d AP / d l`` by implicit differentiation.

For each observation i and AP k, ``S_ik = (d a_k / d l_i) sigma_i / sigma_k``: how many a priori
AP sigmas the estimate of AP k moves when observation i changes by one a priori sigma
(``sigma_k = sqrt(Q_kk)``, sigma0 = 1). It is computed by reverse mode through the converged
adjustment (:func:`tlsjax.differentiable_adjustment`: one adjoint solve per AP, never a dense
Jacobian). In the Gauss-Markov model it equals Baarda's external reliability per unit error,
``Q_(a, u_i) J_i^T P_i sigma_i / sigma_a`` (``ap_influence`` of the quality pass), up to the
terms that the linear formula leaves out: the second-order part of the Hessian and the
dependence of the AP bases on the observation itself (both of the order of the residuals and
of the APs, ~1e-3 relative); the tests check the agreement.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import Adjustment, analyze
from .._adjustment._implicit import differentiable_adjustment, network_inputs
from .._jit import jit
from .._summary import to_json_value

GROUPS = ("range", "hz", "el")


@dataclasses.dataclass(frozen=True, eq=False)
class Sensitivity:
    """``values`` (n, 3, a): AP sigmas per observation sigma (module docstring) of the target
    rows in network order; ``influence`` (n, 3, a): the quality pass's external reliability for
    comparison; ``scans``, ``targets`` (n,) names per row; ``ap_names``."""

    values: np.ndarray
    influence: np.ndarray
    scans: tuple
    targets: tuple
    ap_names: tuple

    def summary(self, top: int = 20, ap: str | None = None) -> str:
        """The ``top`` observations with the largest |influence| (on ``ap``, or on any AP)."""
        v = self.values
        k = None if ap is None else self.ap_names.index(ap)
        score = np.abs(v).max(axis=2) if k is None else np.abs(v[:, :, k])
        order = np.argsort(score.reshape(-1))[::-1][:top]
        head = f"{'scan':>6} {'target':>8} {'obs':>5} " + " ".join(f"{n:>8}" for n in self.ap_names)
        lines = [
            "d AP / d l in AP sigmas per observation sigma (largest first)",
            head,
            "-" * len(head),
        ]
        for flat in order:
            i, g = divmod(int(flat), 3)
            row = " ".join(f"{x:8.3f}" for x in v[i, g])
            lines.append(f"{self.scans[i]:>6} {self.targets[i]:>8} {GROUPS[g]:>5} {row}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Strict JSON: the AP names, the largest influence on each AP and where it comes from
        (:meth:`largest`), and ``values`` per target row (n, 3, a: rows in network order, range,
        hz, el, the APs in ``ap_names`` order)."""
        return to_json_value(
            {
                "units": "AP sigmas per observation sigma",
                "ap_names": list(self.ap_names),
                "largest": self.largest(),
                "scans": list(self.scans),
                "targets": list(self.targets),
                "values": self.values,
            }
        )

    def largest(self) -> dict:
        """Per AP: the largest |influence| and the observation (scan, target, group) it comes from."""
        out = {}
        for k, name in enumerate(self.ap_names):
            a = np.abs(self.values[:, :, k])
            i, g = np.unravel_index(int(np.argmax(a)), a.shape)
            out[name] = {
                "influence": float(self.values[i, g, k]),
                "scan": self.scans[i],
                "target": self.targets[i],
                "group": GROUPS[g],
            }
        return out


def ap_sensitivity(network_or_adjustment, model=None) -> Sensitivity:
    """``d AP / d l`` of every target observation, in AP sigmas per observation sigma."""
    adj = (
        network_or_adjustment
        if isinstance(network_or_adjustment, Adjustment)
        else analyze(network_or_adjustment, model)
    )
    f = differentiable_adjustment(adj)
    theta = network_inputs(adj)
    est = f(theta)
    jac = jit(jax.jacrev(lambda obs: f(_with_obs(theta, obs)).aps))(theta.observations)
    d = np.diagonal(np.asarray(est.ap_covariance)) / float(est.sigma0) ** 2
    sa = np.sqrt(np.clip(d, 0.0, None))
    S = np.transpose(np.asarray(jac), (1, 2, 0)) * np.asarray(theta.sigmas)[:, :, None]
    S = np.where(sa > 0, S / np.where(sa > 0, sa, 1.0), 0.0)
    net = adj.network
    return Sensitivity(
        values=S,
        influence=np.asarray(est.ap_influence),
        scans=tuple(net.scans[j] for j in net.scan_index),
        targets=tuple(net.targets[t] for t in net.target_index),
        ap_names=adj.plan.ap_labels,
    )


def _with_obs(theta, obs):
    return dataclasses.replace(theta, observations=jnp.asarray(obs))
