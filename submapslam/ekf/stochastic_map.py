"""Stochastic map: one stacked state ``X = [x_r, x_1 ... x_n]`` with the full covariance.

``x_r = (x, y, theta)`` is the planar robot pose in the world frame, ``x_k = (x, y)`` point
features. Every prediction and update keeps all robot-feature and feature-feature
cross-covariances (the seed's eq. 5.71-5.72). Measurements are range-bearing in the robot
frame. Matching has the seed's three outcomes:

* matched prediction and observation -> EKF update, ``n_s += 1``;
* unexpected observation -> a new feature, state and covariance augmented with the correct
  cross-covariances;
* unobserved prediction (a feature in sensor range that was predicted but not seen) ->
  ``n_u += 1``.

Each feature's credibility is ``c = 1 - exp(-(n_s/a - n_u/b))`` clamped to [0, 1] (eq. 5.70);
a feature whose credibility falls below a threshold is removed (its rows and columns dropped,
which is the exact marginalisation of a Gaussian). The seed's counts never forget: a feature
seen ``n_s`` times needs ``(b/a) n_s`` misses before it goes. ``memory < 1`` (config
``ekf.credibility.memory``) multiplies both counts by ``memory`` each time the feature is
matched or missed, so credibility weighs about the last ``1 / (1 - memory)`` chances to see
it and a vanished feature goes after a bounded number of misses however long it was seen.

``first_estimate_jacobians=True`` is the FEJ-EKF of Huang, Mourikis & Roumeliotis (2008): the
same filter, but the Jacobians are evaluated at the robot's predicted positions and each
feature's first estimate, so the linearised system keeps the unobservable global pose
unobservable and the filter stays consistent longer (NEES study in BENCHMARKS.md). It needs
first estimates that are roughly right: after long blind stretches it can diverge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..config import CredibilityParams, check_credibility_rates

CHI2_2DOF_999 = 13.82   # match gate
NEW_FEATURE_D2 = 25.0   # an unknown observation founds a new feature only beyond this distance


def credibility(n_s: float, n_u: float, a: float, b: float) -> float:
    """Seed eq. 5.70, clamped to [0, 1]; ``a`` and ``b`` must be > 0 (else :class:`ConfigError`)."""
    check_credibility_rates(a, b)
    return float(np.clip(1.0 - np.exp(-(n_s / a - n_u / b)), 0.0, 1.0))


def wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def _jacobians(robot_xy: np.ndarray, feature_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Range-bearing Jacobians ``(2, 3)`` w.r.t. the robot ``(x, y, theta)`` and ``(2, 2)`` w.r.t.
    the feature ``(x, y)``, evaluated at the given world positions."""
    dx, dy = feature_xy - robot_xy
    q = dx * dx + dy * dy
    r = np.sqrt(q)
    Hr = np.array([[-dx / r, -dy / r, 0.0], [dy / q, -dx / q, -1.0]])
    Hf = np.array([[dx / r, dy / r], [-dy / q, dx / q]])
    return Hr, Hf


@dataclass
class MatchReport:
    """What one observation step did: indices into the observation list / feature ids."""

    matched: list[tuple[int, int]] = field(default_factory=list)  # (observation index, feature id)
    new: list[tuple[int, int]] = field(default_factory=list)      # (observation index, new feature id)
    unobserved: list[int] = field(default_factory=list)          # feature ids predicted but not seen
    removed: list[int] = field(default_factory=list)             # feature ids removed (credibility)
    ambiguous: list[int] = field(default_factory=list)           # observations between the two gates


class StochasticMap:
    """Full-covariance EKF-SLAM over a planar robot and 2D point features."""

    def __init__(self, pose: np.ndarray, pose_cov: np.ndarray | None = None,
                 credibility_params: CredibilityParams | None = None, max_range: float = np.inf,
                 fov: float = 2 * np.pi, gate: float = CHI2_2DOF_999,
                 new_feature_d2: float = NEW_FEATURE_D2, first_estimate_jacobians: bool = False) -> None:
        self.x = np.asarray(pose, dtype=np.float64).reshape(3).copy()
        self.P = np.zeros((3, 3)) if pose_cov is None else np.asarray(pose_cov, dtype=np.float64).copy()
        self.ids: list[int] = []          # feature id per state slot
        self.n_s: list[float] = []
        self.n_u: list[float] = []
        self.n_seen: list[int] = []       # times matched (never forgotten; for min_observations)
        self.n_chances: list[int] = []    # times matched or missed (never forgotten; for min_chances)
        self.cred = credibility_params or CredibilityParams()
        self.max_range = max_range
        self.fov = fov
        self.gate = gate
        self.new_feature_d2 = new_feature_d2
        self._next_id = 0
        # First-estimates Jacobians (Huang, Mourikis & Roumeliotis 2008): linearise at the
        # robot's predicted position and each feature's first estimate, so the filter does not
        # gain spurious information about the unobservable global heading.
        self.fej = first_estimate_jacobians
        self._first_xy: dict[int, np.ndarray] = {}       # feature id -> position at initialisation
        self._prior_xy = self.x[:2].copy()               # robot position before the last update

    # ------------------------------------------------------------------ state access
    @property
    def n(self) -> int:
        return len(self.ids)

    @property
    def pose(self) -> np.ndarray:
        return self.x[:3].copy()

    def feature(self, fid: int) -> tuple[np.ndarray, np.ndarray]:
        """Mean ``(2,)`` and covariance ``(2, 2)`` of feature ``fid``."""
        k = self._slot(fid)
        return self.x[k:k + 2].copy(), self.P[k:k + 2, k:k + 2].copy()

    def credibility_of(self, fid: int) -> float:
        i = self.ids.index(fid)
        return credibility(self.n_s[i], self.n_u[i], self.cred.a, self.cred.b)

    def _slot(self, fid: int) -> int:
        return 3 + 2 * self.ids.index(fid)

    # ------------------------------------------------------------------ prediction
    def predict(self, u: np.ndarray, Q: np.ndarray) -> None:
        """Motion ``u = (dx, dy, dtheta)`` in the robot frame with covariance ``Q (3, 3)``.

        Only the robot rows/columns change: ``P_rr = F P_rr F^T + G Q G^T``, ``P_rm = F P_rm``.
        """
        x, y, th = self.x[:3]
        dx, dy, dth = u
        c, s = np.cos(th), np.sin(th)
        self.x[:3] = [x + c * dx - s * dy, y + s * dx + c * dy, wrap(th + dth)]
        if self.fej:  # position change measured from the previous *predicted* position
            d = self.x[:2] - self._prior_xy
            F = np.array([[1, 0, -d[1]], [0, 1, d[0]], [0, 0, 1]])
            self._prior_xy = self.x[:2].copy()
        else:
            F = np.array([[1, 0, -s * dx - c * dy], [0, 1, c * dx - s * dy], [0, 0, 1]])
        G = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
        P = self.P
        P[:3, :3] = F @ P[:3, :3] @ F.T + G @ Q @ G.T
        if self.n:
            P[:3, 3:] = F @ P[:3, 3:]
            P[3:, :3] = P[:3, 3:].T

    # ------------------------------------------------------------------ measurement model
    def _h(self, k: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Predicted range-bearing of the feature at slot ``k`` and its Jacobians w.r.t. robot, feature."""
        dx, dy = self.x[k] - self.x[0], self.x[k + 1] - self.x[1]
        z = np.array([np.hypot(dx, dy), wrap(np.arctan2(dy, dx) - self.x[2])])
        return (z, *_jacobians(self.x[:2], self.x[k:k + 2]))

    def _innovation(self, k: int, z: np.ndarray, R: np.ndarray):
        zh, Hr, Hf = self._h(k)
        if self.fej:
            Hr, Hf = _jacobians(self._prior_xy, self._first_xy[self.ids[(k - 3) // 2]])
        nu = np.array([z[0] - zh[0], wrap(z[1] - zh[1])])
        Prr, Prf, Pff = self.P[:3, :3], self.P[:3, k:k + 2], self.P[k:k + 2, k:k + 2]
        S = Hr @ Prr @ Hr.T + Hr @ Prf @ Hf.T + Hf @ Prf.T @ Hr.T + Hf @ Pff @ Hf.T + R
        return nu, S, Hr, Hf

    def _update(self, k: int, z: np.ndarray, R: np.ndarray) -> None:
        nu, S, Hr, Hf = self._innovation(k, z, R)
        PHt = self.P[:, :3] @ Hr.T + self.P[:, k:k + 2] @ Hf.T  # (N, 2), H is sparse
        K = PHt @ np.linalg.inv(S)
        self.x += K @ nu
        self.x[2] = wrap(self.x[2])
        self.P -= K @ S @ K.T
        self.P = 0.5 * (self.P + self.P.T)

    def _augment(self, z: np.ndarray, R: np.ndarray, fid: int | None) -> int:
        x, y, th = self.x[:3]
        r, b = z
        a = th + b
        m = np.array([x + r * np.cos(a), y + r * np.sin(a)])
        Gr = np.array([[1, 0, -r * np.sin(a)], [0, 1, r * np.cos(a)]])
        Gz = np.array([[np.cos(a), -r * np.sin(a)], [np.sin(a), r * np.cos(a)]])
        N = len(self.x)
        P = np.zeros((N + 2, N + 2))
        P[:N, :N] = self.P
        P[N:, :N] = Gr @ self.P[:3, :]
        P[:N, N:] = P[N:, :N].T
        P[N:, N:] = Gr @ self.P[:3, :3] @ Gr.T + Gz @ R @ Gz.T
        self.P = P
        self.x = np.concatenate([self.x, m])
        if fid is None:
            fid = self._next_id
        self._next_id = max(self._next_id, fid + 1)
        self.ids.append(fid)
        self._first_xy[fid] = m.copy()
        self.n_s.append(1.0)
        self.n_u.append(0.0)
        self.n_seen.append(1)
        self.n_chances.append(1)
        return fid

    def remove(self, fid: int) -> None:
        """Marginalise a feature out: drop its two rows and columns (exact for a Gaussian)."""
        i = self.ids.index(fid)
        k = 3 + 2 * i
        keep = np.r_[0:k, k + 2:len(self.x)]
        self.x = self.x[keep]
        self.P = self.P[np.ix_(keep, keep)]
        del self.ids[i], self.n_s[i], self.n_u[i], self.n_seen[i], self.n_chances[i]
        self._first_xy.pop(fid, None)

    def _predicted_in_view(self) -> set[int]:
        """Ids of the features whose predicted range-bearing lies inside the sensor's range and FOV."""
        if not self.n:
            return set()
        d = self.x[3:].reshape(-1, 2) - self.x[:2]
        bearing = wrap(np.arctan2(d[:, 1], d[:, 0]) - self.x[2])
        inside = (np.hypot(d[:, 0], d[:, 1]) <= self.max_range) & (np.abs(bearing) <= self.fov / 2)
        return {fid for fid, ok in zip(self.ids, inside) if ok}

    # ------------------------------------------------------------------ the matching step
    def observe(self, observations: np.ndarray, R: np.ndarray, ids: list[int | None] | None = None) -> MatchReport:
        """One matching step with ``observations (M, 2)`` range-bearing and covariance ``R (2, 2)``.

        ``ids`` gives known association (a feature id per observation, None = unknown);
        otherwise nearest-neighbour association: matched inside the chi-square gate (99.9 %),
        a new feature beyond ``new_feature_d2``, ignored in between (so the gate's own 0.1 %
        misses do not duplicate features).
        """
        obs = np.asarray(observations, dtype=np.float64).reshape(-1, 2)
        report = MatchReport()
        predicted = self._predicted_in_view()
        seen: set[int] = set()
        for m, z in enumerate(obs):
            fid = None if ids is None else ids[m]
            if fid is not None and fid in self.ids:
                target = fid
            elif fid is None and self.n:
                target, d2 = self._associate(z, R, seen)
                if target is None and d2 < self.new_feature_d2:
                    report.ambiguous.append(m)  # between the gates: neither matched nor new
                    continue
            else:
                target = None
            if target is None:
                new_id = self._augment(z, R, fid)
                report.new.append((m, new_id))
                seen.add(new_id)
                continue
            self._update(self._slot(target), z, R)
            i = self.ids.index(target)
            lam = self.cred.memory
            self.n_s[i] = lam * self.n_s[i] + 1
            self.n_u[i] *= lam
            self.n_seen[i] += 1
            self.n_chances[i] += 1
            seen.add(target)
            report.matched.append((m, target))
        for fid in sorted(predicted - seen):
            if fid in self.ids:
                i = self.ids.index(fid)
                self.n_u[i] = self.cred.memory * self.n_u[i] + 1
                self.n_s[i] *= self.cred.memory
                self.n_chances[i] += 1
                report.unobserved.append(fid)
        for fid in list(self.ids):
            i = self.ids.index(fid)
            if self.n_seen[i] >= self.cred.min_observations and self.n_chances[i] >= self.cred.min_chances and \
                    credibility(self.n_s[i], self.n_u[i], self.cred.a, self.cred.b) < self.cred.remove_below:
                self.remove(fid)
                report.removed.append(fid)
        return report

    def _associate(self, z: np.ndarray, R: np.ndarray, taken: set[int]) -> tuple[int | None, float]:
        """Nearest feature by Mahalanobis distance: ``(id or None if beyond the gate, distance^2)``."""
        best, best_d2 = None, np.inf
        for fid in self.ids:
            if fid in taken:
                continue
            nu, S, _, _ = self._innovation(self._slot(fid), z, R)
            d2 = float(nu @ np.linalg.solve(S, nu))
            if d2 < best_d2:
                best, best_d2 = fid, d2
        return (best if best_d2 < self.gate else None), best_d2

    # ------------------------------------------------------------------ export
    def landmarks(self) -> list[dict]:
        """``M = {z_t, Sigma_t, c_t}``: one dict per feature."""
        out = []
        for i, fid in enumerate(self.ids):
            k = 3 + 2 * i
            C = self.P[k:k + 2, k:k + 2]
            out.append({"id": fid, "x": float(self.x[k]), "y": float(self.x[k + 1]), "var_xx": float(C[0, 0]),
                        "var_xy": float(C[0, 1]), "var_yy": float(C[1, 1]),
                        "credibility": credibility(self.n_s[i], self.n_u[i], self.cred.a, self.cred.b)})
        return out
