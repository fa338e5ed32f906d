"""The uncertainty a run reports: calibrated anchor covariances and per-scan pose covariances.

Covariances are ``(6, 6)`` in GTSAM's Pose3 tangent order ``(rx, ry, rz, tx, ty, tz)`` [rad, m],
right perturbations in the pose's own frame: ``T_true = T_est Exp(xi)``, ``xi ~ N(0, Sigma)``.

The graph's marginals are not calibrated: against the truth of the Monte Carlo worlds
(``tools/bench_calibration.py``) their variances are off by factors that differ per axis, and the
worlds disagree with the real logs. A run (2D or 3D) that measured its own odometry noise
(:class:`OdometryNoise`, from the registrations between consecutive submaps) reports its
estimate's covariance under that noise instead. Other runs (short, merged) report ``D Sigma D``, ``D = diag(sqrt(scale))``,
``scale`` per axis chosen by one rule, a conservative envelope: the larger of the mean
``(e/sigma)^2`` of the anchors on the Monte Carlo worlds it was fitted on (2D: rectangle, 2 laps,
seeds 0-19; 3D: terrain city along KITTI 05, 200 scans, seeds 0-11) and the mean ``(e/sigma)^2``
of the raw covariances on a real log against its reference (2D: Intel against its corrected log;
3D: the Livox loop against FAST-LIO2): the most overconfident of them ends at 1, none above. The
synthetic 2D world is far easier than Intel (anchors 50-100x inside their raw sigma, Intel at
1.6-1.7 in x and y), so the real log sets the 2D scale; in 3D the Livox loop sets yaw and y.
Figures and the checks on worlds the scales were not fitted on: BENCHMARKS.md, "Calibrated
covariances". For a graph whose every factor's information were divided by a common per-axis
factor the estimate would not move and the marginals would scale the same way; with per-axis
factors and rotations between anchors this is an approximation (exact for yaw-only rotations when
x and y share one factor). The graph, its estimate and the gates that read its covariances are
untouched.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .config import BackendConfig
from .geometry import rotation_angle, so3_log

#: variance scale per axis (GTSAM order: roll, pitch, yaw, x, y, z) of planar runs. Rectangle
#: Monte Carlo: yaw 0.01, x 0.02, y 0.01; Intel raw: yaw 0.26, x 1.62, y 1.69 -> Intel's (roll,
#: pitch and z are pinned in planar runs and keep their pinned sigma)
COVARIANCE_SCALE_PLANAR = (1.0, 1.0, 0.26, 1.62, 1.69, 1.0)
#: variance scale per axis (GTSAM order) of 3D runs. Terrain city 05 Monte Carlo (with the odometry
#: edges' measured tilt, TiltDrift): roll 0.66, pitch 1.72, yaw 0.01, x 0.34, y 0.03, z 1.83; Livox
#: loop raw: roll 0.22, pitch 0.09, yaw 0.16, x 0.18, y 0.96, z 0.25 -> yaw and y from the Livox
#: loop, the rest from the Monte Carlo
COVARIANCE_SCALE_3D = (0.66, 1.72, 0.16, 0.34, 0.96, 1.83)


def covariance_scale(config: BackendConfig, planar: bool) -> np.ndarray:
    """``(6,)`` variance scale per axis (GTSAM order): the config's, else the fitted default."""
    if config.covariance_scale is not None:
        return np.asarray(config.covariance_scale, dtype=np.float64)
    return np.asarray(COVARIANCE_SCALE_PLANAR if planar else COVARIANCE_SCALE_3D, dtype=np.float64)


def calibrate(covariances: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """``(..., 6, 6)`` covariances (GTSAM order, each in its pose's frame) scaled per axis:
    ``D Sigma D`` with ``D = diag(sqrt(scale))``; correlations are kept."""
    d = np.sqrt(np.asarray(scale, dtype=np.float64))
    return np.asarray(covariances, dtype=np.float64) * np.outer(d, d)


def odometry_information(T_i_j: np.ndarray, distance: float, planar: bool, config: BackendConfig,
                         tilt_sigma: float | None = None) -> np.ndarray:
    """Information ``(6, 6)`` (GTSAM order) of an odometry edge between consecutive anchors.

    Drift model of scan-to-map odometry: translation sigma ``odometry_drift`` of the distance
    travelled plus a floor; rotation sigma ``odometry_drift_deg_per_m`` per metre plus a
    fraction of the turned angle plus a floor (:meth:`BackendConfig.rotation_drift`). 3D:
    ``tilt_sigma`` [rad], when given and smaller, replaces the model's roll and pitch sigma
    (:class:`TiltDrift`: what the run's own odometry achieves). For planar logs z, roll and
    pitch are pinned (they are not observable and must not drift).
    """
    angle = rotation_angle(T_i_j)
    per_m, turn = config.rotation_drift(planar)
    s_t = config.odometry_sigma_floor_m + config.odometry_drift * distance
    s_r = np.deg2rad(config.odometry_sigma_floor_deg) + np.deg2rad(per_m) * distance + turn * angle
    sig = np.array([s_r, s_r, s_r, s_t, s_t, s_t])
    if planar:
        sig[[0, 1, 5]] = 1e-4
    elif tilt_sigma is not None:
        sig[[0, 1]] = min(s_r, tilt_sigma)
    return np.diag(1.0 / sig**2)


def tilt_no_tighter_than_yaw(information: np.ndarray) -> np.ndarray:
    """A 3D odometry edge's ``(6, 6)`` information (GTSAM order) with its roll and pitch variance
    raised to its yaw variance where smaller (correlations' covariance terms kept): the edge's
    rotation weighed by one model again, undoing :class:`TiltDrift`'s tightening."""
    cov = np.linalg.inv(0.5 * (information + information.T))
    for axis in (0, 1):
        cov[axis, axis] += max(cov[2, 2] - cov[axis, axis], 0.0)
    return np.linalg.inv(0.5 * (cov + cov.T))


class TiltDrift:
    """How far the run's own odometry tilts (roll and pitch) between consecutive anchors,
    estimated from the run itself.

    The drift model of :func:`odometry_information` is one sigma for all three rotations, sized
    for a 16-ring sensor on a town drive. A denser sensor holds roll and pitch ten times better,
    and the ground priors, weighed against that loose model, then bend a good odometry towards a
    flat world (terrain 00, 64 rings: odometry 0.12 m, graph 0.18 m). Each odometry edge is
    registered submap to submap anyway (the covariance shaping); the tilt by which that
    registration corrects the odometry is a sample of the odometry's tilt error, but not the
    whole of it: the two share the sensor's bias (on the flat city the 16-ring odometry pitches
    0.11 deg per 12 m the same way every time, which no registration between its own submaps
    sees), and on the terrain cities the true error was 1.5-4x the correction's RMS per axis.
    Per edge ``d^2 / distance`` [rad^2 / m] of roll and pitch; the robust variance per metre is
    the samples' median over chi-square(1)'s median (0.455). An edge's tilt sigma is
    ``factor`` times its square root times ``sqrt(distance)``, at least ``floor``; None until
    ``min_edges`` edges were measured. (``backend.odometry_tilt_factor``: 3 by default; 2 let the
    flat city's bias through, BENCHMARKS.md.)
    """

    def __init__(self, factor: float, min_edges: int = 5, floor_rad: float = float(np.deg2rad(0.01))) -> None:
        self.factor = factor
        self.min_edges = min_edges
        self.floor_rad = floor_rad
        self.samples: list[float] = []  # per edge and axis: d^2 / distance [rad^2 / m]

    @staticmethod
    def correction(T_odometry: np.ndarray, T_registered: np.ndarray) -> np.ndarray:
        """``(2,)`` roll and pitch [rad] by which the registration's ``(4, 4)`` ``T_prev_new``
        turns the odometry's, in the new anchor's frame."""
        return so3_log(T_odometry[:3, :3].T @ T_registered[:3, :3])[:2]

    def add(self, correction: np.ndarray, distance: float) -> None:
        """One edge's :meth:`correction` ``(2,)`` [rad] over ``distance`` [m]."""
        self.samples.extend(float(c) ** 2 / max(distance, 1.0) for c in correction)

    def per_sqrt_metre(self) -> float | None:
        """The edges' roll/pitch sigma [rad / sqrt(m)] before the floor, or None (too few edges yet)."""
        if len(self.samples) < 2 * self.min_edges:
            return None
        return self.factor * float(np.sqrt(np.median(self.samples) / 0.455))

    def sigma(self, distance: float) -> float | None:
        """Roll/pitch sigma [rad] of an edge over ``distance`` [m], or None (too few edges yet)."""
        per = self.per_sqrt_metre()
        return None if per is None else max(self.floor_rad, per * float(np.sqrt(max(distance, 1.0))))

    def summary(self) -> dict:
        """What ``summary.json`` says of it: edges measured and the sigma it gives 12 m of odometry."""
        per = self.per_sqrt_metre()
        return {"edges_measured": len(self.samples) // 2,
                "sigma_deg_over_12_m": None if per is None else round(float(np.rad2deg(self.sigma(12.0))), 4)}


class TiltChangeSpread:
    """How far the ground's tilt changes from one anchor to the next, as the run's own odometry
    and ground planes see it: the sigma the ground tilt-change prior should have.

    The prior says two consecutive anchors' ground normals are one direction in the world within
    ``floor`` (``backend.ground_tilt_change_sigma_deg``, 0.2 deg): right on a flat town, where the
    spread of what the odometry sees (a 16-ring sensor's tilt noise) is 0.17 deg per submap, too
    tight where the ground changes grade or a sensor's ground plane is rough (a narrow-field
    sensor on hilly ground: 0.83 deg), and a prior 4x too tight bends a good odometry (that drive:
    ATE 0.09 m odometry, 0.61 m graph). Per pair of anchors the angle [rad] between their ground
    normals carried through the odometry; a 2-D isotropic error of sigma has the median angle
    ``sigma sqrt(2 ln 2)``, so the spread is the median over that. The sigma is what is left of it
    once the odometry's own tilt error is taken out, at least ``floor``; None until ``min_pairs``
    pairs were seen.
    """

    def __init__(self, floor_rad: float, min_pairs: int = 5) -> None:
        self.floor_rad = floor_rad
        self.min_pairs = min_pairs
        self.angles: list[float] = []  # per pair of consecutive anchors [rad]

    @staticmethod
    def observed(up_before: np.ndarray, up: np.ndarray, T_before_anchor: np.ndarray) -> float:
        """Angle [rad] between the earlier anchor's ground normal ``up_before`` ``(3,)`` and the
        later one's ``up`` ``(3,)`` (each in its anchor's frame) carried into the earlier anchor's
        frame by the odometry ``T_before_anchor`` ``(4, 4)``."""
        c = float(np.dot(T_before_anchor[:3, :3] @ np.asarray(up, dtype=np.float64), up_before))
        return float(np.arccos(np.clip(c, -1.0, 1.0)))

    def add(self, angle_rad: float) -> None:
        """One pair's :meth:`observed` angle [rad]."""
        self.angles.append(float(angle_rad))

    def spread(self) -> float | None:
        """The pairs' robust sigma [rad] per axis, or None (fewer than ``min_pairs``)."""
        if len(self.angles) < self.min_pairs:
            return None
        return float(np.median(self.angles)) / float(np.sqrt(2.0 * np.log(2.0)))

    def sigma(self, odometry_sigma_rad: float | None = None) -> float | None:
        """The prior's sigma [rad]: the spread less the odometry's own tilt error between two
        anchors (``odometry_sigma_rad``, per axis, as the graph weighs it: the observed change is
        the ground's plus the odometry's, and the prior is there to correct the latter), at least
        ``floor_rad``; None until ``min_pairs`` pairs."""
        spread = self.spread()
        if spread is None:
            return None
        odometry = odometry_sigma_rad or 0.0
        return max(self.floor_rad, float(np.sqrt(max(spread**2 - odometry**2, 0.0))))

    def summary(self, sigma_rad: float | None) -> dict:
        """What ``summary.json`` says of it: pairs seen, their spread and ``sigma_rad``, the sigma
        the priors took last (None: no prior yet) [deg]."""
        spread = self.spread()
        return {"pairs": len(self.angles),
                "spread_deg": None if spread is None else round(float(np.rad2deg(spread)), 4),
                "sigma_deg": None if sigma_rad is None else round(float(np.rad2deg(sigma_rad)), 4)}


class LevelGroundTest:
    """Whether the ground the run drives on is level, as far as the run's own odometry can tell.

    The ground priors (level within ``ground_attitude_sigma_deg``, tilting like the anchor
    before) bet on a flat world: they hold a 16-ring odometry's pitch bias there (0.11 deg per 12 m,
    the same way every time), and on a long climb or a sag curve they bend the chain instead (a town
    along KITTI 02 with 52 m of relief: odometry 1.44 m, graph 4.32 m; a Livox-like drive along
    KITTI 09: 0.109 m, 3.73 m, with its three true closures rejected). Over a window of
    ``window`` consecutive anchors, the ground normals carried through the odometry turn by the
    ground's change of grade plus the odometry's own tilt error; the latter is at most the sum of
    the edges' tilt sigmas (:class:`TiltDrift`, which already holds 3x the registrations'
    corrections: a bias adds up linearly). The ground is level when the windows' RMS turn is at
    most the median allowance (16-ring towns, first 1,700 scans: flat 0.43, terrain along KITTI
    05 0.80, 08 1.63, 00 1.88; the 52 m-relief town 2.0; the Livox-like drive 74); None until
    ``min_windows`` windows were seen or without a tilt estimate.
    """

    def __init__(self, window: int = 3, min_windows: int = 8) -> None:
        self.window = window
        self.min_windows = min_windows
        self._ups: dict[int, np.ndarray] = {}  # submap id -> (3,) ground normal in the odometry frame
        self._distance: dict[int, float] = {}  # submap id -> [m] length of its odometry edge from id - 1

    def add(self, submap_id: int, up_odometry: np.ndarray, edge_distance: float) -> None:
        """One anchor's ground normal ``(3,)`` in the odometry frame, and the length [m] of the
        odometry edge that reached it."""
        self._ups[submap_id] = np.asarray(up_odometry, dtype=np.float64)
        self._distance[submap_id] = float(edge_distance)

    def ratio(self, edge_tilt_sigma: Callable[[float], float | None]) -> float | None:
        """The windows' RMS turn of the ground normals over the odometry's (median) allowance:
        ``edge_tilt_sigma(distance [m]) -> [rad] | None`` (:meth:`TiltDrift.sigma`). At most 1: level.
        The RMS, not the median: a few sag curves on an otherwise constant grade bend the chain too."""
        turns, allowances = [], []
        for j, up in self._ups.items():
            i = j - self.window
            if i not in self._ups or any(k not in self._distance for k in range(i + 1, j + 1)):
                continue
            sigmas = [edge_tilt_sigma(self._distance[k]) for k in range(i + 1, j + 1)]
            if any(s is None for s in sigmas):
                return None
            turns.append(float(np.arccos(np.clip(float(np.dot(up, self._ups[i])), -1.0, 1.0))))
            allowances.append(float(sum(sigmas)))
        if len(turns) < self.min_windows:
            return None
        return float(np.sqrt(np.mean(np.square(turns))) / max(float(np.median(allowances)), 1e-9))


#: 3D: the odometry's error over an edge, per axis, as a multiple of the registration's correction
#: of it (:class:`OdometryNoise`). The registration between two submaps shares the odometry's
#: scans and biases and sees a third to a half of its error: on the terrain Monte Carlo worlds
#: (KITTI 05 and 00 paths, 200 and 1,700 scans) the true edge errors' robust sigma was 2-4x the
#: corrections' on roll, pitch, x, y and z (TiltDrift takes 3 for roll and pitch). BENCHMARKS.md, "3D runs:
#: the estimate's covariance under the run's own odometry noise".
ODOMETRY_NOISE_FACTOR = 2.5
#: 3D: a loop edge's error variance over one odometry edge's of the median length. A loop is a
#: registration between two submaps like the correction of an odometry edge; against the truth its
#: error was that of one odometry edge or less (KITTI 05 terrain, 1,700 scans, 62 loops: RMS 0.005 /
#: 0.004 / 0.0002 rad, 0.029 / 0.020 / 0.043 m against the odometry edges' 0.005 / 0.004 / 0.0003,
#: 0.033 / 0.022 / 0.056)
LOOP_NOISE_SHARE = 0.25
#: 3D: a ground or wall level prior's error variance over its stated one. Until stop 52 it was 2, which
#: stood in for what the priors share: the world's up they are all measured against carries the
#: votes' errors and the odometry's start. That shared error is now its own term of the reported
#: covariances (:func:`world_up_covariance`), and the priors' own errors are within their stated
#: noise (the terrain worlds' wall verticals miss the estimate by 0.12-0.16 deg, stated 0.5). The
#: terrain Monte Carlo worlds (KITTI 05, 00 paths) and the 2.2 / 3.7 km drives keep every tilt axis
#: within [0.5, 2] / [0.33, 3] with 1 and the shared term (BENCHMARKS.md, stop 52)
PRIOR_NOISE_INFLATION = 1.0


def measured_vote_variance(residuals: np.ndarray, stated: float, min_priors: int = 8) -> float:
    """Variance [rad^2] per tilt axis of one vote for the world up (a wall vertical, a ground
    normal), from how far the run's level priors of that kind are from its estimate: their ``(n, 2)``
    residuals [rad], robust (the median of the squares over chi-square(1)'s, 0.455), pooled over
    both axes; with fewer than ``min_priors``, the priors' ``stated`` variance [rad^2] as
    :meth:`OdometryNoise.factor_covariance` takes it (times :data:`PRIOR_NOISE_INFLATION`). The
    estimate holds each anchor's tilt by its neighbours as well, so a residual is mostly the vote's
    own error (the terrain worlds' wall verticals: 0.12-0.16 deg, against the 0.5 deg the priors
    are weighed with)."""
    r = np.asarray(residuals, dtype=np.float64).reshape(-1, 2)
    if len(r) < min_priors:
        return PRIOR_NOISE_INFLATION * float(stated)
    return float(np.median(r**2) / 0.455)


def world_up_covariance(up: np.ndarray, distances: list[float], vote_variance: float,
                        tilt_variance_per_metre: float) -> np.ndarray:
    """``(3, 3)`` covariance [rad^2] of the world up the level priors share, as a small rotation in
    the world frame (none about ``up`` ``(3,)`` itself). It is the mean of votes (one wall vertical,
    or one ground normal), each seen from an anchor ``distances`` [m] along the path from the first,
    through the odometry's attitude there: per vote its own error (``vote_variance`` [rad^2] per
    tilt axis) plus the odometry's tilt random walk (``tilt_variance_per_metre`` [rad^2/m]), which
    the votes share up to the nearer one's distance. Every prior measured against this up carries
    its error, so it tilts the whole estimate relative to the first anchor; over ``r`` metres from
    there a tilt of ``e`` rad moves heights by ``r e``, which no independent factor says."""
    d = np.asarray(distances, dtype=np.float64).reshape(-1)
    n = len(d)
    shared = tilt_variance_per_metre * float(np.minimum.outer(d, d).sum()) / n**2
    u = np.asarray(up, dtype=np.float64) / np.linalg.norm(up)
    return (vote_variance / n + shared) * (np.eye(3) - np.outer(u, u))


def rank_correlation(samples: np.ndarray) -> np.ndarray:
    """``(d, d)`` correlation of the columns of ``samples`` ``(n, d)``, robust: Spearman's rank
    correlation taken to a normal's (``2 sin(pi rho / 6)``), made positive semi-definite. A column
    that never varies (a planar run's roll, pitch, z) is uncorrelated with the rest."""
    x = np.asarray(samples, dtype=np.float64)
    n, d = x.shape
    out = np.eye(d)
    live = np.flatnonzero(np.ptp(x, axis=0) > 0.0) if n >= 3 else np.zeros(0, dtype=int)
    if len(live) < 2:
        return out
    ranks = np.argsort(np.argsort(x[:, live], axis=0, kind="stable"), axis=0).astype(np.float64)
    r = 2.0 * np.sin(np.pi * np.corrcoef(ranks.T) / 6.0)
    w, v = np.linalg.eigh(r)
    r = (v * np.maximum(w, 1e-3)) @ v.T
    sd = np.sqrt(np.diag(r))
    out[np.ix_(live, live)] = r / np.outer(sd, sd)
    return out


def first_cloud_covariance(travelled: np.ndarray, per_metre: np.ndarray, jitter: np.ndarray,
                           refit_scans: range | None = None, cloud_scans: int | None = None) -> np.ndarray:
    """``(6, 6)`` covariance [rad^2, m^2] (GTSAM order, the first anchor's frame) of where
    the first submap's cloud sits relative to the first scan, the pose every output is relative to.

    Every edge into the first anchor registers against its cloud, not its first scan, so the whole
    estimate sits where that cloud is; the cloud is built from the first ``cloud_scans`` scans
    (default: all of ``travelled``), which the odometry placed with a random walk of ``per_metre``
    (covariance ``(6, 6)`` or variances ``(6,)`` per m) along the path (``travelled`` ``(M,)`` [m]:
    each scan's path from the first, nondecreasing), plus each scan's own ``jitter`` ``(6,)``. A
    registration sees about the mean of its scans' errors. ``refit_scans``: the scans (indices
    below ``M``) the first was registered again against (:class:`~submapslam.start_frame.StartFrame`):
    the frame sits at their mean error, and every scan of the cloud but the first moves by it. For
    a walk over ``L`` metres without the refit this is ``variance * L / 3``.
    """
    s = np.asarray(travelled, dtype=np.float64).reshape(-1)
    k = len(s) if cloud_scans is None else min(int(cloud_scans), len(s))
    if k < 2:
        return np.zeros((6, 6))
    weights = np.zeros(len(s) - 1)  # scans 1..M-1; the first contributes where it sits
    weights[:k - 1] = 1.0 / k
    refit = [i for i in (refit_scans or ()) if 0 < i < len(s)]
    if refit:  # the frame at the mean error of the refit scans: every scan of the cloud but the first moves by it
        weights[np.array(refit) - 1] -= (1.0 - 1.0 / k) / len(refit)
    # w^T min(s_i, s_j) w over scans 1..M-1 without the M x M matrix (a robot standing still for
    # minutes fills one submap with thousands of scans): s nondecreasing, min(s_i, s_j) is s_0
    # plus the steps up to the earlier of the two, so each step counts the square of the weights after it
    tail = np.cumsum(weights[::-1])[::-1]
    walk = float(s[0] * tail[0] ** 2 + np.diff(s) @ tail**2)
    own = float(weights @ weights)
    rate = np.asarray(per_metre, dtype=np.float64)
    rate = np.diag(rate) if rate.ndim == 1 else rate
    return rate * walk + np.diag(np.asarray(jitter, dtype=np.float64)) * own


class OdometryNoise:
    """The run's own odometry noise per axis, from the registrations between consecutive submaps,
    and the noise of every factor of the graph that follows from it (2D and 3D runs; a planar run's
    roll, pitch and z, which its registrations never move, keep the factors' stated noise).

    Each odometry edge is registered submap to submap (:meth:`GraphBuilder._registration_shaped`);
    the ``(6,)`` correction that registration makes to the odometry's relative pose (GTSAM order,
    [rad, m]) samples the odometry's error over the edge. Per axis the robust variance per metre is
    the median of ``c^2 / distance`` over chi-square(1)'s median (0.455), times
    :data:`ODOMETRY_NOISE_FACTOR` squared (the part of the error the registration shares); the axes
    keep their correlation over an edge (:func:`rank_correlation` of ``c / sqrt(distance)``, the
    edges within 4 robust sigmas on every axis: a heading error comes with a lateral one). The graph
    weighs its edges with a drift model sized for any 16-ring town (one rotation sigma of 0.2 deg and
    more for all three axes), ten to a hundred times looser in yaw than what a run achieves; the
    covariances a run reports are those of its estimate under this measured noise
    (:meth:`~submapslam.backend.pose_graph.PoseGraph.estimator_covariances`), so the graph, its
    decisions and its estimate stay as they are. None (:meth:`variance_per_metre`) until
    ``min_edges`` edges were measured.
    """

    def __init__(self, corrections: dict[int, np.ndarray], distances: dict[int, float],
                 factor: float = ODOMETRY_NOISE_FACTOR, min_edges: int = 8) -> None:
        """``corrections``: per submap id, the ``(6,)`` correction of its odometry edge from the
        previous submap; ``distances``: per submap id, that edge's length [m]."""
        ids = sorted(k for k in corrections if k in distances)
        self.distances = {k: max(float(distances[k]), 1.0) for k in ids}
        self.edges = len(ids)
        self.median_distance = float(np.median(list(self.distances.values()))) if ids else 1.0
        self._variance: np.ndarray | None = None  # (6,) per metre, once min_edges edges were measured
        self._correlation = np.eye(6)  # between the axes' errors over one edge
        if len(ids) >= min_edges:
            c = np.array([np.asarray(corrections[k], dtype=np.float64) for k in ids])
            d = np.array([self.distances[k] for k in ids])
            self._variance = factor**2 * np.median(c**2 / d[:, None], axis=0) / 0.455
            per_root_metre = c / np.sqrt(d)[:, None]
            spread = np.sqrt(np.median(per_root_metre**2, axis=0) / 0.455)
            usual = np.all(np.abs(per_root_metre) <= 4.0 * spread, axis=1)  # registrations gone wrong left out
            self._correlation = rank_correlation(per_root_metre[usual])

    def variance_per_metre(self) -> np.ndarray | None:
        """``(6,)`` variance per metre [rad^2/m, m^2/m] of the odometry, GTSAM order, or None."""
        return self._variance

    def covariance_per_metre(self) -> np.ndarray | None:
        """``(6, 6)`` covariance per metre of the odometry (GTSAM order): the axes' variances with
        their correlation over an edge (:func:`rank_correlation`), or None."""
        if self._variance is None:
            return None
        sd = np.sqrt(self._variance)
        return self._correlation * np.outer(sd, sd)

    def edge_covariance(self, distance: float) -> np.ndarray:
        """``(6, 6)`` covariance of the odometry over ``distance`` [m] (at least 1 m)."""
        return self.covariance_per_metre() * max(float(distance), 1.0)

    def factor_covariance(self, kind: str, i: int, j: int, stated: np.ndarray) -> np.ndarray:
        """The covariance of one factor's measurement as this run's noise says it is: an odometry
        edge into node ``j`` over its measured length (or the median edge's), a loop edge
        :data:`LOOP_NOISE_SHARE` of the median edge, a level prior its ``stated`` covariance times
        :data:`PRIOR_NOISE_INFLATION`, anything else (the start prior, an edge that gave way) as
        ``stated``."""
        if kind == "odometry" and stated.shape == (6, 6):
            return self._planar_kept(self.edge_covariance(self.distances.get(j, self.median_distance)), stated)
        if kind == "loop" and stated.shape == (6, 6):
            return self._planar_kept(LOOP_NOISE_SHARE * self.edge_covariance(self.median_distance), stated)
        if "prior" in kind and kind != "prior":
            return PRIOR_NOISE_INFLATION * stated
        return stated

    @staticmethod
    def _planar_kept(measured: np.ndarray, stated: np.ndarray) -> np.ndarray:
        """Axes the registration never moves (roll, pitch, z of a planar run: zero variance) keep ``stated``."""
        out = measured.copy()
        flat = np.flatnonzero(np.diag(measured) <= 0.0)
        out[flat, :] = stated[flat, :]
        out[:, flat] = stated[:, flat]
        return out

    def summary(self) -> dict:
        """What ``summary.json`` says of it: edges measured, and once measured the sigma per axis
        over 10 m and the variance per metre (GTSAM order, what the scans' covariances use)."""
        out: dict = {"edges_measured": self.edges}
        if self._variance is not None:
            sig = np.sqrt(self._variance * 10.0)
            out["sigma_over_10_m"] = {"roll_deg": round(float(np.rad2deg(sig[0])), 4),
                                      "pitch_deg": round(float(np.rad2deg(sig[1])), 4),
                                      "yaw_deg": round(float(np.rad2deg(sig[2])), 4),
                                      "x_m": round(float(sig[3]), 4), "y_m": round(float(sig[4]), 4),
                                      "z_m": round(float(sig[5]), 4)}
            out["variance_per_m"] = [float(v) for v in self._variance]
            out["correlation"] = [[round(float(v), 4) for v in row] for row in self._correlation]
        return out


def scan_jitter_variance(odometry_poses: np.ndarray, timestamps: np.ndarray | None = None) -> np.ndarray:
    """``(6,)`` variance (GTSAM order, [rad^2, m^2]) of each scan's own registration error, which
    does not add up along the drive: scan-to-map odometry places consecutive scans a few
    centimetres back and forth along the track (16 rings on a town drive: 1.2-2.2 cm), more than
    its drift per metre says over one scan. From the odometry ``(N, 4, 4)`` itself: the third
    difference of the poses (the change of the change between consecutive steps) is ``J`` times
    ``1 + 9 + 9 + 1 = 20`` for independent errors of variance ``J``, while a motion of constant
    acceleration cancels (a second difference kept the vehicle's turning in yaw: 0.03 deg per
    scan on the terrain towns, against 0.017 deg from the third); per axis its robust variance
    (median over chi-square(1)'s, 0.455) over 20. Only windows of three steps equally long in time
    (within 5 %, by ``timestamps`` ``(N,)`` [s] when given) count: a keyframe log's irregular steps
    change the motion between them (a Livox-like drive: 0.74 m along the track otherwise). Zero
    with fewer than 10 such windows."""
    from .geometry import pose_difference

    poses = np.asarray(odometry_poses, dtype=np.float64).reshape(-1, 4, 4)
    if len(poses) < 4:
        return np.zeros(6)
    valid = np.ones(len(poses) - 3, dtype=bool)
    if timestamps is not None:
        dt = np.diff(np.asarray(timestamps, dtype=np.float64)[:len(poses)])
        windows = np.stack([dt[:-2], dt[1:-1], dt[2:]], axis=1)
        valid = (windows.min(axis=1) > 0) & (windows.max(axis=1) <= 1.05 * windows.min(axis=1))
    if valid.sum() < 10:
        return np.zeros(6)
    steps = np.linalg.solve(poses[:-1], poses[1:])  # (N-1, 4, 4) T_k^-1 T_k+1
    changes = np.linalg.solve(steps[:-1], steps[1:])
    thirds = np.linalg.solve(changes[:-1], changes[1:])
    third = np.array([pose_difference(T) for T in thirds[valid]])
    return np.median(third**2, axis=0) / 0.455 / 20.0


def within_submap_covariance(T_anchor_scan: np.ndarray, distance: float, planar: bool,
                             config: BackendConfig) -> np.ndarray:
    """``(6, 6)`` covariance (GTSAM order, scan frame) of a scan's pose relative to its anchor:
    the odometry edges' drift model over ``distance`` [m] travelled since the anchor
    (:func:`odometry_information`); zero at the anchor itself."""
    if distance <= 0.0 and np.allclose(T_anchor_scan, np.eye(4)):
        return np.zeros((6, 6))
    return np.linalg.inv(odometry_information(T_anchor_scan, distance, planar, config))


def scan_covariances(result) -> np.ndarray | None:
    """``(N, 6, 6)`` covariance of every scan pose of a :class:`~submapslam.result.SlamResult`
    (GTSAM order, each in its scan's frame, right perturbation of ``result.poses[k]``).

    Its anchor's reported marginal (already calibrated by the pipeline) carried to the scan, ``Ad(T_anchor_scan^-1) Sigma
    Ad(.)^T``, plus (except for the anchor's own scan) the odometry's noise from the anchor to the
    scan: the run's measured noise when its anchors' covariances were made with it
    (``result.covariance_model["variance_per_m"]``, :class:`OdometryNoise`) and twice the scans'
    own jitter (``["scan_jitter_variance"]``, :func:`scan_jitter_variance`: the scan's and its
    anchor's), else the drift model
    scaled by the same per-axis factors as the anchors (:func:`covariance_scale`). A scan shared
    by two submaps (the last of one is the anchor of the next) takes the later submap's, i.e. its
    anchor's. None when the run has no covariances (an empty run, a failed final optimisation).

    A planar run whose scans were refined between their anchors (``result.scan_refinement``: each
    scan placed by the corrections of its submap's anchor and the next blended along the path, then
    matched again with the anchors held) counts the measured noise over
    ``d1 d2 / (d1 + d2)`` instead of ``d1``, ``d1`` and ``d2`` [m] the path from the scan to the
    submap's anchor and on to the next anchor: the variance of a random walk tied at both ends (a
    Brownian bridge), zero at either anchor and a quarter of the submap's walk midway. The last
    submap, with no anchor after it, keeps ``d1``. On the 2D worlds the scans' mean ``(e/sigma)^2``
    was 0.3-0.5, against their anchors' 0.6-0.9 (BENCHMARKS.md, "Calibrated covariances").
    """
    from .geometry import adjoint, inverse

    covs = np.asarray(result.submap_covariances, dtype=np.float64)
    if len(covs) == 0 or not np.isfinite(covs).all():
        return None
    backend = result.config.backend
    scale = covariance_scale(backend, result.planar)
    model = getattr(result, "covariance_model", None) or {}
    measured = model.get("variance_per_m")
    if measured is not None:  # with the axes' correlation over an edge when the run measured it
        sd = np.sqrt(np.asarray(measured, dtype=np.float64))
        measured = np.asarray(model.get("correlation", np.eye(6)), dtype=np.float64) * np.outer(sd, sd)
    jitter = 2.0 * np.asarray(model.get("scan_jitter_variance") or np.zeros(6), dtype=np.float64)
    bridged = bool(result.planar and getattr(result, "scan_refinement", None))
    out = np.full((len(result.poses), 6, 6), np.nan)
    for k, (idx, T_scans) in enumerate(zip(result.submap_scan_indices, result.submap_scan_poses)):
        steps = np.linalg.norm(np.diff(np.asarray(T_scans)[:, :3, 3], axis=0), axis=1)
        travelled = np.concatenate([[0.0], np.cumsum(steps)])
        tied = bridged and k + 1 < len(covs) and travelled[-1] > 0.0
        for m, (s, T, dist) in enumerate(zip(idx, T_scans, travelled)):
            A = adjoint(inverse(T))
            if m == 0:  # the anchor's own scan (a refined 2D scan may sit a few mm off it): the anchor's
                out[s] = A @ covs[k] @ A.T
                continue
            if measured is not None:
                walk = dist * (travelled[-1] - dist) / travelled[-1] if tied else max(float(dist), 1.0)
                rel = measured * walk + np.diag(jitter)
            else:
                rel = calibrate(within_submap_covariance(T, float(dist), result.planar, backend), scale)
            out[s] = A @ covs[k] @ A.T + rel
    return out


# --- localisation in a fixed map: a pose filter beside the tracker --------------------------------
# The tracker (submapslam.localization) keeps its poses; these give each one a covariance: the
# previous covariance carried through the motion between the scans, plus the motion's own noise
# (MotionNoise), replaced by what the scan's match against the map says (its point-to-line /
# point-to-point Hessian over the residual variance, divided by REGISTRATION_INFLATION, plus the
# map's own error MAP_SIGMA) along the directions the match constrains better (take_the_match).
# Directions the map does not constrain (a corridor's axis, unmapped space) keep the prediction's
# growing covariance, as the tracker keeps the prediction's pose there.

#: planar (x, y, yaw) or 3D registration information is divided by this: scan points are not
#: independent (the map's walls carry shared errors, neighbouring beams see the same bump), so
#: the Hessian over the residual variance is overconfident. Fitted on the rectangle localisation
#: world (tests/test_localization.py), checked on the rooms world: BENCHMARKS.md, "Localization".
REGISTRATION_INFLATION = 5.0
#: 1σ [m, rad] of the map itself where a scan matches it, translation and rotation: a match can
#: place the scan no better than the map's walls are placed (a built map is off by a few cm), and
#: that error does not shrink with more scan points
MAP_SIGMA = (0.01, np.deg2rad(0.04))
#: 1σ [m, m, rad] of an initial pose the user gives (or a global-search fix) before its first scan
#: is matched: x, y and yaw (3D: also z; roll and pitch at the yaw's sigma)
INITIAL_SIGMA = (0.5, 0.5, np.deg2rad(5.0))
#: variance of the axes a planar pose does not have (roll, pitch, z): pinned
PINNED_VARIANCE = 1e-10


@dataclass(frozen=True)
class MotionNoise:
    """1σ of the predicted motion between consecutive scans (wheel odometry or constant velocity),
    per component, growing with the step's length ``d`` [m] and turned angle ``a`` [rad]:
    translation ``trans_floor + trans_per_m d``, rotation ``rot_floor + rot_per_m d + rot_per_rad a``."""

    trans_floor: float = 0.005
    trans_per_m: float = 0.05
    rot_floor: float = np.deg2rad(0.1)
    rot_per_m: float = np.deg2rad(1.0)
    rot_per_rad: float = 0.05


def motion_covariance(delta: np.ndarray, planar: bool, noise: MotionNoise = MotionNoise()) -> np.ndarray:
    """``(6, 6)`` covariance (GTSAM order, frame of the step's end) of a predicted step ``delta``
    ``(4, 4)`` ``T_prev_cur``; planar: roll, pitch and z pinned."""
    d = float(np.linalg.norm(delta[:3, 3]))
    s_t = noise.trans_floor + noise.trans_per_m * d
    s_r = noise.rot_floor + noise.rot_per_m * d + noise.rot_per_rad * rotation_angle(delta)
    var = np.array([s_r, s_r, s_r, s_t, s_t, s_t]) ** 2
    if planar:
        var[[0, 1, 5]] = PINNED_VARIANCE
    return np.diag(var)


def initial_covariance(planar: bool) -> np.ndarray:
    """``(6, 6)`` covariance (GTSAM order) of a pose given without a measured accuracy: :data:`INITIAL_SIGMA`."""
    sx, sy, syaw = INITIAL_SIGMA
    var = np.array([syaw, syaw, syaw, sx, sy, sx]) ** 2
    if planar:
        var[[0, 1, 5]] = PINNED_VARIANCE
    return np.diag(var)


def propagate(P: np.ndarray, delta: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """Covariance ``(6, 6)`` of ``T_cur = T_prev delta`` (right perturbations, each pose's own frame)
    from ``P`` of ``T_prev``, plus the step's noise ``Q`` (in the frame of ``T_cur``)."""
    from .geometry import adjoint, inverse

    A = adjoint(inverse(delta))
    return A @ P @ A.T + Q


def take_the_match(P: np.ndarray, information: np.ndarray | None) -> np.ndarray:
    """Covariance of a pose the tracker took from a match with ``information`` ``(6, 6)`` where the
    match constrains it and from the prediction (covariance ``P``) where it does not.

    The tracker does not average the two (it is no filter): along each direction the match
    constrains it keeps the match, elsewhere the prediction. In the prediction's whitened frame
    (``P = L L^T``, ``L^T I L = V diag(lam) V^T``) the covariance is ``1 / max(1, lam)`` per direction:
    the match's own variance where it is the better of the two, the prediction's where not. A
    filter's ``1 / (1 + lam)`` would shrink below the match's variance in every step, though the map's
    errors that bound the match repeat from scan to scan. ``P`` itself without a match."""
    if information is None:
        return P
    L = np.linalg.cholesky(0.5 * (P + P.T))
    lam, V = np.linalg.eigh(L.T @ information @ L)
    W = L @ V
    out = (W / np.maximum(1.0, lam)) @ W.T
    return 0.5 * (out + out.T)


def planar_match_information(points: np.ndarray, normals_body: np.ndarray, residuals: np.ndarray,
                             weights: np.ndarray, min_sigma: float = 0.005) -> np.ndarray:
    """``(6, 6)`` information (GTSAM order, the scan's frame; roll, pitch and z zero) of a planar
    point-to-line match: ``J^T W J / (sigma^2 REGISTRATION_INFLATION)``.

    ``points`` ``(K, 2)`` scan points in the scan frame, ``normals_body`` ``(K, 2)`` their matched
    lines' unit normals rotated into the scan frame, ``residuals`` ``(K,)`` [m] signed point-to-line
    distances, ``weights`` ``(K,)`` robust weights. ``J = [n_x, n_y, n_y p_x - n_x p_y]`` per point
    (right perturbation ``(x, y, yaw)``); ``sigma^2`` the weighted residual variance (at least
    ``min_sigma^2``). Zero with fewer than 4 points.
    """
    info = np.zeros((6, 6))
    if len(points) < 4:
        return info
    J = np.column_stack([normals_body[:, 0], normals_body[:, 1],
                         normals_body[:, 1] * points[:, 0] - normals_body[:, 0] * points[:, 1]])
    dof = max(float(weights.sum()) - 3.0, 1.0)
    var = max(float(np.sum(weights * residuals**2)) / dof, min_sigma**2)
    H = (J * weights[:, None]).T @ J / (var * REGISTRATION_INFLATION)
    idx = [3, 4, 2]
    info[np.ix_(idx, idx)] = H
    return info


def limited_by_the_map(information: np.ndarray, planar: bool) -> np.ndarray:
    """A match's ``information`` ``(6, 6)`` (GTSAM order) with the map's own error :data:`MAP_SIGMA`
    added to its covariance: ``(I^-1 + S)^-1``, computed as ``I (1 + S I)^-1`` so directions the match
    does not constrain (zero information) stay zero."""
    s_t, s_r = MAP_SIGMA
    var = np.array([s_r, s_r, s_r, s_t, s_t, s_t]) ** 2
    if planar:
        var[[0, 1, 5]] = 0.0
    out = information @ np.linalg.inv(np.eye(6) + np.diag(var) @ information)
    return 0.5 * (out + out.T)


def pose_filter_covariances(poses: np.ndarray, informations: list[np.ndarray | None], lost: np.ndarray,
                            planar: bool, noise: MotionNoise = MotionNoise()) -> np.ndarray:
    """``(N, 6, 6)`` covariance (GTSAM order, each pose's frame) of each pose a tracker output.

    Forward: the first pose starts at :func:`initial_covariance`, each next one is the previous
    carried through the step between the poses plus :func:`motion_covariance`, then combined with
    its scan's match ``informations[k]`` (:func:`take_the_match`; None: the match was not believed,
    e.g. lost). A fix after a
    lost span (the global search, independent of the dead reckoning) starts again from
    :func:`initial_covariance`. The lost span before a fix was re-anchored on it by dead
    reckoning, so its covariances are carried *backwards* from the fix (the scans before the first
    fix likewise); a lost span at the log's end keeps the forward ones.
    """
    from .geometry import inverse

    lost = np.asarray(lost, dtype=bool)
    n = len(poses)
    out = np.zeros((n, 6, 6))
    P = initial_covariance(planar)
    for k in range(n):
        if k and lost[k - 1] and not lost[k]:
            P = initial_covariance(planar)
        elif k:
            delta = inverse(poses[k - 1]) @ poses[k]
            P = propagate(P, delta, motion_covariance(delta, planar, noise))
        P = take_the_match(P, informations[k])
        out[k] = P = _pinned(P) if planar else P
    fixed_after = np.flip(np.logical_or.accumulate(np.flip(~lost)))  # some fix at or after k
    for k in range(n - 2, -1, -1):
        if lost[k] and fixed_after[k + 1]:
            delta = inverse(poses[k + 1]) @ poses[k]
            out[k] = propagate(out[k + 1], delta, motion_covariance(delta, planar, noise))
            out[k] = _pinned(out[k]) if planar else out[k]
    return out


def _pinned(P: np.ndarray) -> np.ndarray:
    """A planar pose's covariance with roll, pitch and z decoupled at :data:`PINNED_VARIANCE` (carried
    through the steps their pinned variance would otherwise grow with the lever arms)."""
    P = P.copy()
    P[[0, 1, 5], :] = 0.0
    P[:, [0, 1, 5]] = 0.0
    P[[0, 1, 5], [0, 1, 5]] = PINNED_VARIANCE
    return P
