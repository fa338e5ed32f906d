"""The submap graph, built from what the front end and the loop closer return.

:class:`GraphBuilder` owns the :class:`~submapslam.backend.pose_graph.PoseGraph`. It turns each
closed submap into a node with its odometry edge (a drift model, shaped by a registration
between consecutive submaps; for 3D logs its roll and pitch sigma follow the tilt those
registrations corrected so far in the run, :class:`~submapslam.uncertainty.TiltDrift`) and, for
3D logs, soft ground priors: level, and tilted like the anchor before within the spread of
tilt changes the run itself sees (:class:`~submapslam.uncertainty.TiltChangeSpread`); it adds the
loop constraints the closer returns (information floored: no registration is trusted beyond a few
centimetres); and at the end it runs the batch pass, the final check and the marginals. Nothing
else writes the graph; the loop closer reads it through :meth:`estimate`.
"""

from __future__ import annotations

import logging
from contextlib import nullcontext

import numpy as np

from .backend.pose_graph import GROUND_ATTITUDE_PRIOR, PoseGraph, cap_covariance, floor_information
from .config import BackendConfig, OdometryConfig, narrow_field
from .geometry import inverse, pose_difference
from .result import LoopRecord
from .submaps import Submap
from .uncertainty import (
    LevelGroundTest,
    OdometryNoise,
    TiltChangeSpread,
    TiltDrift,
    first_cloud_covariance,
    measured_vote_variance,
    odometry_information,
    tilt_no_tighter_than_yaw,
    world_up_covariance,
)

log = logging.getLogger(__name__)

#: 3D: how much the ground priors may raise the loop closures' chi-square (1 DOF, 95 %) on ground
#: the run found near level (:data:`NEAR_LEVEL_RATIO`) before the closures count as against them;
#: further from level, or untested, they must lower it
PRIOR_CONTRADICTION_CHI2 = 3.84
#: 3D: the level ratio (:class:`~submapslam.uncertainty.LevelGroundTest`) up to which the ground is
#: near level: its normals turn at most this many times what the odometry's tilt allows (which holds
#: 3x its registrations' corrections already). 16-ring towns on terrain: 1.6-2.1, where the priors hold
#: the odometry's tilt bias; Livox-like drives: 36-72, where they squeeze the hills
NEAR_LEVEL_RATIO = 3.0

PRIOR_INFORMATION = np.diag([1e8] * 6)  # the first anchor is the world frame
WALL_VERTICAL_PRIOR = "wall vertical prior"  # the kind of a level prior whose up comes from the walls
#: level priors that are no bet on level ground: the ground test neither tests nor drops them
NO_BET_PRIORS = frozenset({WALL_VERTICAL_PRIOR})
LEVEL_SOURCE_WAIT = 5  # submaps without walls after which the level priors come from the ground
WORLD_UP_VOTES = 3  # submaps with walls whose verticals agree the world's up


#: GTSAM-order indices of what a planar log cannot observe: roll, pitch, z
PLANAR_PINNED = (0, 1, 5)


def pin_planar(information: np.ndarray, sigma: float = 1e-4) -> np.ndarray:
    """``information (6, 6)`` (GTSAM order) with roll, pitch and z decoupled from the planar
    directions and held at ``sigma`` (rad / m): a 2D log observes x, y and yaw only, and a
    registration's or a cap's looseness there must not let anchors drift out of the plane."""
    out = np.array(information, dtype=np.float64)
    idx = list(PLANAR_PINNED)
    out[idx, :] = 0.0
    out[:, idx] = 0.0
    out[idx, idx] = 1.0 / sigma**2
    return out


def consensus_up(votes: list[np.ndarray], agree_deg: float = 1.0) -> np.ndarray:
    """The world's up ``(3,)`` from a few submaps' wall verticals ``votes`` (each ``(3,)``, unit,
    in the odometry frame): the mean of those within ``agree_deg`` of the medoid (the vote nearest
    to all others). One submap's walls can be off by degrees (a street canyon fixes the tilt about
    its own axis with a few cross walls; the first submap carries the odometry's start), and every
    level prior of the run is measured against this up."""
    keep = np.asarray(votes, dtype=np.float64).reshape(-1, 3)[consensus_members(votes, agree_deg)]
    up = keep.mean(axis=0)
    return up / np.linalg.norm(up)


def consensus_members(votes: list[np.ndarray], agree_deg: float = 1.0) -> np.ndarray:
    """``(n,)`` bool: the ``votes`` :func:`consensus_up` averages (within ``agree_deg`` of the medoid)."""
    v = np.asarray(votes, dtype=np.float64).reshape(-1, 3)
    angles = np.arccos(np.clip(v @ v.T, -1.0, 1.0))
    medoid = v[int(np.argmin(angles.sum(axis=1)))]
    return np.arccos(np.clip(v @ medoid, -1.0, 1.0)) <= np.deg2rad(agree_deg)


class GraphBuilder:
    """Adds submaps, odometry edges, ground priors and loop constraints to one pose graph.

    ``clouds``: the prepared 3D clouds (:class:`~submapslam.registration.spatial.SubmapClouds`)
    shared with the loop closer; ``match_voxel``: the voxel [m] submaps are registered at;
    ``timer``: a stage timer (``timer("stage")`` is a context manager) or None.
    """

    def __init__(self, config: BackendConfig, odometry: OdometryConfig, *, planar: bool, match_voxel: float,
                 clouds=None, timer=None) -> None:
        self.config = config
        self.odometry = odometry
        self.planar = planar
        self.match_voxel = match_voxel
        self.clouds = clouds
        self.graph = PoseGraph(config)
        self.odometry_information: dict[int, np.ndarray] = {}  # submap id -> its odometry edge's (6, 6)
        self.odometry_tilt: dict[int, np.ndarray] = {}  # 3D: submap id -> (2,) its edge's TiltDrift.correction
        self.odometry_correction: dict[int, np.ndarray] = {}  # submap id -> (6,) its edge's registration correction
        self.edge_distance: dict[int, float] = {}  # submap id -> [m] length of its odometry edge
        self.covariance_model: OdometryNoise | None = None  # set by finish() when the reported covariances use it
        self._timer = timer
        self._world_up: np.ndarray | None = None  # 3D: the world's up direction (first ground seen)
        self._ground_up: dict[int, np.ndarray] = {}  # 3D: submap id -> (3,) ground normal in its anchor frame
        factor = config.odometry_tilt_factor
        self.tilt_drift = TiltDrift(factor) if factor is not None and not planar else None
        change = config.ground_tilt_change_sigma_deg
        self.tilt_change = (TiltChangeSpread(float(np.deg2rad(change)))
                            if change is not None and config.ground_tilt_change_from_data and not planar else None)
        self._pending_tilt_changes: list[tuple] = []  # tilt-change priors waiting for tilt_change's sigma
        self._tilt_change_sigma: float | None = None  # [rad] the sigma the last of them took
        priors = config.ground_attitude_sigma_deg is not None or change is not None
        self.level_test = (LevelGroundTest() if priors and config.ground_priors_level_test and not planar
                           and self.tilt_drift is not None else None)
        self.ground_prior_test: dict = {}  # summary.json's ground_priors: the level test and what it decided
        self._level_from: str | None = None  # 3D: where the level priors' up comes from: "walls" or "ground"
        self._pending_level: list[tuple[int, np.ndarray, np.ndarray]] = []  # (id, ground up, R_odom_anchor) waiting
        self._up_votes: list[np.ndarray] = []  # the first submaps' wall verticals in the odometry frame
        self._up_vote_ids: list[int] = []  # the submaps those votes came from
        self._up_from_ground: int | None = None  # the submap whose ground normal is the world's up (ground source)
        self._world_up_sigma: float | None = None  # [rad] per tilt axis, once finish() gave it to the covariances
        self._first_cloud: tuple[int, np.ndarray] | None = None  # (first submap id, (K,) its scans' path [m])
        self._first_cloud_sigma: np.ndarray | None = None  # (6,) once finish() gave it to the covariances
        self._waiting_for_up: list[tuple[int, np.ndarray, float, str]] = []  # (id, up in anchor, sigma, kind) waiting
        self._submaps_without_walls = 0  # 3D: submaps seen before the level priors' source was chosen
        # the walls' vertical: spinning LiDARs only. A narrow-field sensor's odometry holds its tilt to
        # 0.01 deg a submap, and on two of four Livox-like drives the wall priors cost lateral accuracy
        # (BENCHMARKS.md, "Level priors from the walls")
        self._walls_apply = (not planar and config.ground_attitude_sigma_deg is not None
                             and config.wall_vertical_sigma_deg is not None and not narrow_field(odometry.registration))
        self.wall_verticals = 0  # 3D: level priors from walls (summary.json ground_priors)

    def _time(self, stage: str):
        return self._timer(stage) if self._timer is not None else nullcontext()

    def estimate(self) -> PoseGraph:
        """The graph, for reading (poses, marginals, odometry chains)."""
        return self.graph

    # ------------------------------------------------------------------ nodes and odometry
    def add_submap(self, submap: Submap, previous: Submap | None, wheel_odometry: bool,
                   information: np.ndarray | None = None, tilt: np.ndarray | None = None,
                   correction: np.ndarray | None = None) -> None:
        """Add ``submap``'s anchor, its odometry edge from ``previous`` and its ground prior; update.

        ``wheel_odometry``: the log has wheel odometry (planar refinement then follows it where
        scan matching is blind, which caps the odometry edge's registration covariance).
        ``information``: the edge's ``(6, 6)`` information as computed before (a resumed run),
        instead of computing it, ``tilt`` its registration's tilt correction and ``correction`` its
        whole ``(6,)`` correction (None: none was measured). :attr:`odometry_information`,
        :attr:`odometry_tilt` and :attr:`odometry_correction` keep each edge's, by submap id.
        """
        info = T_prev_k = None
        if previous is not None:
            T_prev_k = inverse(previous.T_odom_anchor) @ submap.T_odom_anchor
            self.edge_distance[submap.id] = float(previous.distance)
            if information is not None:
                info = information
                if tilt is not None:
                    self._add_tilt(submap.id, tilt, previous.distance)
                if correction is not None:
                    self.odometry_correction[submap.id] = np.asarray(correction, dtype=np.float64)
            else:
                tilt_sigma = self.tilt_drift.sigma(previous.distance) if self.tilt_drift is not None else None
                info = odometry_information(T_prev_k, previous.distance, self.planar, self.config, tilt_sigma)
                if self.config.odometry_registration_covariance:
                    info = self._registration_shaped(info, previous, submap, T_prev_k, wheel_odometry)
                if self.planar:
                    info = pin_planar(info)
            self.odometry_information[submap.id] = info
        up = vertical = None
        if not self.planar and (self.config.ground_attitude_sigma_deg is not None
                                or self.config.ground_tilt_change_sigma_deg is not None):
            from .mapping.height_band import ground_normal

            with self._time("vertical"):
                up = ground_normal(submap.points)
                vertical = self._wall_vertical(submap, up)
        with self._time("optimisation"):
            if previous is None:
                steps = np.linalg.norm(np.diff(np.asarray(submap.T_anchor_scans)[:, :3, 3], axis=0), axis=1)
                self._first_cloud = (submap.id, np.concatenate([[0.0], np.cumsum(steps)]))
                self.graph.add_node(submap.id, submap.T_odom_anchor, PRIOR_INFORMATION)
            else:
                self.graph.add_node(submap.id, self.graph.pose(previous.id) @ T_prev_k)
                self.graph.add_between(previous.id, submap.id, T_prev_k, info, "odometry")
            if up is not None or vertical is not None:
                self._add_ground_attitude(submap, previous, T_prev_k, up, vertical)
            self.graph.update()

    def _wall_vertical(self, submap: Submap, up: np.ndarray | None) -> np.ndarray | None:
        """3D: the vertical ``(3,)`` the submap's walls give in its anchor frame
        (:func:`~submapslam.mapping.vertical.submap_vertical`), or None: none found, level priors
        off, a narrow-field sensor, or the run's level priors come from the ground."""
        if not self._walls_apply or self._level_from == "ground":
            return None
        from .mapping.vertical import submap_vertical

        return submap_vertical(submap.points, up, self.match_voxel / 2.0)  # 3D submaps: half the match voxel

    def _add_level_prior(self, submap: Submap, up: np.ndarray | None, vertical: np.ndarray | None) -> None:
        """3D: the soft prior that each anchor is level in the world. The world's up comes from one
        source for the whole run, so that all the priors agree on it: the walls (``vertical``,
        ``wall_vertical_sigma_deg``) when the run's first submaps show them, else the ground planes
        (``up``, ``ground_attitude_sigma_deg``: the world's up is the first anchor's ground normal).
        Until the source is chosen (walls seen, or :data:`LEVEL_SOURCE_WAIT` submaps without),
        ground priors wait. Once it is the walls, a submap without walls gets its ground plane's
        prior against the walls' up (the bet on level ground, where nothing better is seen). The
        walls' up is the consensus of the first :data:`WORLD_UP_VOTES` submaps with walls
        (:func:`consensus_up`); the priors wait for it."""
        R = submap.T_odom_anchor[:3, :3]  # the odometry frame is the world frame
        if vertical is not None:
            if self._level_from is None:
                self._level_from = "walls"
                self._pending_level.clear()
                self._pending_tilt_changes.clear()
            self.wall_verticals += 1
            if self._world_up is None and len(self._up_votes) < WORLD_UP_VOTES:
                self._up_votes.append(R @ vertical)
                self._up_vote_ids.append(submap.id)
            self._waiting_for_up.append((submap.id, vertical, np.deg2rad(self.config.wall_vertical_sigma_deg),
                                        WALL_VERTICAL_PRIOR))
            if self._world_up is not None or len(self._up_votes) == WORLD_UP_VOTES:
                self._add_priors_waiting_for_up()
            return
        if up is None:
            return
        if self._level_from == "walls":  # no walls here (a field, a highway): the ground plane, against the walls' up
            self._waiting_for_up.append((submap.id, up, np.deg2rad(self.config.ground_attitude_sigma_deg),
                                        GROUND_ATTITUDE_PRIOR))
            if self._world_up is not None:
                self._add_priors_waiting_for_up()
            return
        self._pending_level.append((submap.id, up, R))
        if self._level_from is None:
            self._submaps_without_walls += 1
            if self._walls_apply and self._submaps_without_walls < LEVEL_SOURCE_WAIT:
                return
            self._level_from = "ground"
        self._add_pending_ground_levels()

    def _add_priors_waiting_for_up(self) -> None:
        """The level priors held back until the walls' up was agreed (:attr:`_up_votes`)."""
        if self._world_up is None:
            self._world_up = consensus_up(self._up_votes)
        for key, direction, sigma, kind in self._waiting_for_up:
            self.graph.add_attitude(key, direction, self._world_up, sigma, kind=kind)
        self._waiting_for_up.clear()

    def _add_pending_ground_levels(self) -> None:
        """The ground-plane level priors held back while the walls might still have been the source."""
        sigma = np.deg2rad(self.config.ground_attitude_sigma_deg)
        for key, up, R in self._pending_level:
            if self._world_up is None:
                self._world_up = R @ up
                self._up_from_ground = key
            self.graph.add_attitude(key, up, self._world_up, sigma)
        self._pending_level.clear()

    def _add_ground_attitude(self, submap: Submap, previous: Submap | None, T_prev_k: np.ndarray | None,
                             up: np.ndarray | None, vertical: np.ndarray | None) -> None:
        """3D: the soft prior that each anchor is level in the world (:meth:`_add_level_prior`:
        from its walls' ``vertical`` or its ground normal ``up``, each ``(3,)`` in the anchor frame),
        and, unless the walls are that source, that its ground tilts like the ground under the
        previous anchor (``T_prev_k``: the odometry between them)."""
        sigma = self.config.ground_attitude_sigma_deg
        change = self.config.ground_tilt_change_sigma_deg
        if sigma is not None:
            self._add_level_prior(submap, up, vertical)
        if up is None:
            return
        self._ground_up[submap.id] = up
        if self.level_test is not None:
            self.level_test.add(submap.id, submap.T_odom_anchor[:3, :3] @ up,
                                previous.distance if previous is not None else 0.0)
        up_before = self._ground_up.get(previous.id) if previous is not None else None
        if change is None or up_before is None or self._level_from == "walls":
            return  # the walls hold each anchor's tilt: the ground's changes of grade are no prior then
        if self.tilt_change is None:
            self.graph.add_relative_attitude(previous.id, submap.id, up_before, up, T_prev_k, np.deg2rad(change))
            return
        self.tilt_change.add(TiltChangeSpread.observed(up_before, up, T_prev_k))
        self._pending_tilt_changes.append((previous.id, submap.id, up_before, up, T_prev_k))
        odometry = self.tilt_drift.sigma(previous.distance) if self.tilt_drift is not None else None
        sigma = self.tilt_change.sigma(odometry)
        if sigma is not None:
            self._add_pending_tilt_changes(sigma)

    def _add_pending_tilt_changes(self, sigma_rad: float) -> None:
        """The tilt-change priors held back until the run's spread was known, at ``sigma_rad``
        (none once the walls are the level priors' source)."""
        self._tilt_change_sigma = sigma_rad
        if self._level_from == "walls":
            self._pending_tilt_changes.clear()
        for i, j, up_i, up_j, T_i_j in self._pending_tilt_changes:
            self.graph.add_relative_attitude(i, j, up_i, up_j, T_i_j, sigma_rad)
        self._pending_tilt_changes.clear()

    def _test_ground_priors(self) -> None:
        """3D: unless the run showed its ground level (:class:`~submapslam.uncertainty.LevelGroundTest`:
        not level, or too few anchors saw the ground to tell), the ground priors stay only if the loop
        closures do not speak against them
        (:meth:`~submapslam.backend.pose_graph.PoseGraph.drop_ground_priors_unless_loops_favour`):
        near level (:data:`NEAR_LEVEL_RATIO`) the priors may raise the closures' chi-square by
        :data:`PRIOR_CONTRADICTION_CHI2`; further from level, or untested, they must lower it. Near
        level (a 16-ring town without walls along KITTI 00, ratio 2.1) the priors hold the
        odometry's tilt bias and closures that barely see them leave them in (0.36 m, 0.58 without);
        far from level (Livox-like drives, ratio 40-72) they squeeze the hills, and closures that
        fit either way had kept them (KITTI 02: 2.52 m, odometry 0.19). :attr:`ground_prior_test` says what was measured and
        decided. An untested bet is not kept on faith: the hand-held Livox main building, whose
        ground 2 of 8 anchors see, ended at 0.0625 m with its two level priors against its
        odometry's 0.0483 m (BENCHMARKS.md). On ground not level (or untested) where no ground prior
        is left, the walls' alone or none, the odometry edges' tilt is weighed like their yaw again
        (``odometry_tilt_restored``: how many edges)."""
        if self.level_test is None:
            return
        ratio = self.level_test.ratio(self.tilt_drift.sigma)
        self.ground_prior_test = {"level_ratio": None if ratio is None else round(ratio, 3), "level": None, "kept": True,
                                  "level_priors_from": self._level_from, "wall_verticals": self.wall_verticals}
        if ratio is not None:
            self.ground_prior_test["level"] = ratio <= 1.0
        if ratio is not None and ratio <= 1.0:
            return  # level: the priors' bet holds, and so does the tight tilt that holds them off
        allowance = PRIOR_CONTRADICTION_CHI2 if ratio is not None and ratio <= NEAR_LEVEL_RATIO else 0.0
        self.ground_prior_test.update(self.graph.drop_ground_priors_unless_loops_favour(
            allowance, keep_kinds=NO_BET_PRIORS))
        if not self.graph.has_active_priors(ignore_kinds=NO_BET_PRIORS):
            # TiltDrift tightened the edges' roll and pitch to hold off the ground priors' bet on level
            # ground. With none of them left on ground that is not level, a tight tilt beside the model's
            # loose yaw only does harm: on a grade a turn about the anchor's own (tilted) z axis tilts the
            # world's up, so whatever corrects the anchors' attitude, loops mending heights or the walls'
            # plumb verticals, is bought by turning headings (a Livox-like drive along KITTI 02: 0.29 m
            # against its odometry's 0.19 m; a 64-ring one with walls, 50 m of relief: 0.27 m against 0.18)
            self.ground_prior_test["odometry_tilt_restored"] = self.graph.reweigh_edges("odometry",
                                                                                        tilt_no_tighter_than_yaw)

    def _world_up_covariance(self, noise: OdometryNoise) -> np.ndarray | None:
        """``(3, 3)`` [rad^2]: the error of the world up every level prior is measured against
        (:func:`~submapslam.uncertainty.world_up_covariance`): the consensus of the first walled
        submaps' verticals, or the first ground normal, each as far off as the run's priors of
        that kind are from the estimate (:func:`~submapslam.uncertainty.measured_vote_variance`),
        and seen through the odometry's tilt (``noise``) at its anchor."""
        rate, residuals = noise.variance_per_metre(), self.graph.attitude_residuals()
        if self._world_up is None or rate is None or not residuals:  # no level prior (left): nothing shares it
            return None
        if self._up_from_ground is not None:
            ids, kind, sigma_deg = [self._up_from_ground], GROUND_ATTITUDE_PRIOR, self.config.ground_attitude_sigma_deg
        else:
            members = consensus_members(self._up_votes)
            ids, kind, sigma_deg = ([k for k, m in zip(self._up_vote_ids, members) if m], WALL_VERTICAL_PRIOR,
                                    self.config.wall_vertical_sigma_deg)
        vote = measured_vote_variance(residuals.get(kind, np.zeros((0, 2))), float(np.deg2rad(sigma_deg)) ** 2)
        path = {k: sum(d for m, d in self.edge_distance.items() if m <= k) for k in ids}
        cov = world_up_covariance(self._world_up, [path[k] for k in ids], vote, float(np.mean(rate[:2])))
        self._world_up_sigma = float(np.sqrt(np.trace(cov) / 2.0))
        return cov

    def _first_cloud_error(self, noise: OdometryNoise, jitter: np.ndarray | None, refit_scans: range | None,
                           start_path: np.ndarray | None) -> tuple[int, np.ndarray] | None:
        """``(first node, (6, 6))``: where the first submap's cloud sits relative to the first scan
        under the run's measured ``noise`` (:func:`~submapslam.uncertainty.first_cloud_covariance`;
        ``start_path``: the path [m] of the run's first scans, when it reaches past the cloud's)."""
        if self._first_cloud is None:
            return None
        node, travelled = self._first_cloud
        path = start_path if start_path is not None and len(start_path) > len(travelled) else travelled
        cov = first_cloud_covariance(path, noise.covariance_per_metre(), np.zeros(6) if jitter is None else jitter,
                                     refit_scans, cloud_scans=len(travelled))
        self._first_cloud_sigma = np.sqrt(np.diag(cov))
        return node, cov

    def world_up_summary(self) -> dict:
        """What ``summary.json``'s ``covariance_model`` says of the world up the level priors share:
        its sigma per tilt axis [deg] in the reported covariances, and where it came from."""
        if self._world_up_sigma is None:
            return {}
        source = "ground" if self._up_from_ground is not None else "walls"
        return {"world_up": {"from": source, "sigma_deg": round(float(np.rad2deg(self._world_up_sigma)), 4)}}

    def first_cloud_summary(self) -> dict:
        """What ``summary.json``'s ``covariance_model`` says of where the first submap's cloud sits
        relative to the first scan (:meth:`_first_cloud_error`): sigma per axis [deg, m]."""
        if self._first_cloud_sigma is None:
            return {}
        names = ("roll_deg", "pitch_deg", "yaw_deg", "x_m", "y_m", "z_m")
        sigma = [np.rad2deg(v) if n.endswith("_deg") else v for n, v in zip(names, self._first_cloud_sigma)]
        return {"first_cloud_sigma": {n: round(float(v), 5) for n, v in zip(names, sigma)}}

    def tilt_change_summary(self) -> dict:
        """``summary.json``'s ``ground_tilt_change``: pairs, their spread and the sigma in use
        (:class:`~submapslam.uncertainty.TiltChangeSpread`); empty when the sigma is not measured."""
        return self.tilt_change.summary(self._tilt_change_sigma) if self.tilt_change is not None else {}

    def _registration_shaped(self, info: np.ndarray, prev: Submap, new: Submap, T_prev_new: np.ndarray,
                             wheel_odometry: bool) -> np.ndarray:
        """Add the registration's own uncertainty to the drift model of an odometry edge.

        The new submap is aligned to the previous one (fine registration from the odometry
        estimate); the inverse of that registration's information grows where the geometry is
        degenerate (along a corridor), which is where scan matching alone cannot see. Edges
        between submaps that do not overlap keep the drift model alone.
        """
        from .registration.correspondence import check_correspondence

        with self._time("odometry_covariance"):
            src, tgt = new.points, prev.points
            if not self.planar:  # the clouds (and normals) the loop tests use too
                src, tgt = self.clouds(new), self.clouds(prev)
            res = check_correspondence(src, tgt, planar=self.planar, initial_guess=T_prev_new,
                                       refine_only=True, voxel_size=self.match_voxel)
        if res.overlap < 0.1:
            return info
        if self.tilt_drift is not None:
            self._add_tilt(new.id, TiltDrift.correction(T_prev_new, res.T_target_source), prev.distance)
        self.odometry_correction[new.id] = pose_difference(inverse(T_prev_new) @ res.T_target_source)
        cov_reg = np.linalg.inv(0.5 * (res.information + res.information.T))
        # Never more than a cap in any direction: 2 m / 20 deg, or, where the wheel odometry
        # holds the directions scan matching cannot see (planar refinement), the wheel's drift
        # over the edge.
        cap_m, cap_rad = 2.0, np.deg2rad(20.0)
        odo = self.odometry
        if self.planar and odo.planar_point_to_line and odo.use_wheel_odometry and wheel_odometry:
            cap_m = max(0.05, self.config.wheel_drift * prev.distance)
        cov_reg = cap_covariance(cov_reg, cap_m, cap_rad)
        cov = np.linalg.inv(info) + cov_reg
        return np.linalg.inv(0.5 * (cov + cov.T))

    def _add_tilt(self, submap_id: int, correction: np.ndarray, distance: float) -> None:
        """One edge's tilt correction ``(2,)`` [rad] into the run's tilt-drift estimate (kept by submap id)."""
        if self.tilt_drift is not None:
            self.tilt_drift.add(correction, distance)
            self.odometry_tilt[submap_id] = np.asarray(correction, dtype=np.float64)

    # ------------------------------------------------------------------ loops
    def add_loops(self, records: list[LoopRecord]) -> None:
        """Add the accepted loop constraints among ``records`` (their registration information,
        floored) as robust loop edges; update when any was added."""
        floor_m = self.config.loop_sigma_floor_m
        floor_rad = float(np.deg2rad(self.config.loop_sigma_floor_deg))
        accepted = [r for r in records if r.accepted]
        for rec in accepted:
            info = floor_information(rec.information, floor_m, floor_rad)
            if self.planar:
                info = pin_planar(info)
            self.graph.add_between(rec.i, rec.j, rec.T_i_j, info, "loop")
        if accepted:
            with self._time("optimisation"):
                self.graph.update(extra_iterations=2)

    # ------------------------------------------------------------------ finishing
    def finish(self, jitter: np.ndarray | None = None, refit_scans: range | None = None,
               start_path: np.ndarray | None = None) -> tuple[dict[tuple[int, int], str], dict[int, np.ndarray]]:
        """Batch pass, final check and covariances.

        ``jitter`` ``(6,)``: the scans' own odometry noise
        (:func:`~submapslam.uncertainty.scan_jitter_variance`), ``refit_scans``: the scans the
        first was registered again against (None: none; ``start_path`` ``(M,)`` [m]: the path of the
        run's first scans from the first, covering them); with them the reported covariances count
        where the first submap's cloud sits relative to the first scan
        (:func:`~submapslam.uncertainty.first_cloud_covariance`).

        Returns ``({(i, j): why} of loop edges the solution rejected, {node: (6, 6) covariance}``);
        the graph keeps only the loops it did not reject. The covariances are the graph's marginals,
        or, for a run that measured its odometry noise (:class:`OdometryNoise`, unless
        ``backend.covariance_scale`` is set), its estimate's covariances under that noise
        (:attr:`covariance_model` then holds it).
        """
        with self._time("optimisation"):
            if self._pending_tilt_changes:  # a run too short to measure the spread: the configured sigma
                self._add_pending_tilt_changes(self.tilt_change.floor_rad)
                self.graph.update()
            if self._waiting_for_up:  # a short run with fewer walled submaps than votes: those it has
                self._add_priors_waiting_for_up()
                self.graph.update()
            if self._pending_level:  # a short run without walls: its ground planes
                self._level_from = "ground"
                self._add_pending_ground_levels()
                self.graph.update()
            self._test_ground_priors()
            weights, dropped = {}, []
            if self.config.final_batch and self.graph.edges:
                weights = self.graph.optimize_batch()
                if self.config.final_check:
                    dropped = self.graph.final_check()
            covs = self.graph.all_marginal_covariances()
            noise = OdometryNoise(self.odometry_correction, self.edge_distance)
            if self.config.covariance_scale is None and noise.variance_per_metre() is not None:
                try:
                    first_cloud = self._first_cloud_error(noise, jitter, refit_scans, start_path)
                    covs = self.graph.estimator_covariances(noise.factor_covariance,
                                                            up_covariance=self._world_up_covariance(noise),
                                                            first_cloud=first_cloud)
                    self.covariance_model = noise
                except (RuntimeError, ValueError, np.linalg.LinAlgError) as exc:  # a singular system: the marginals
                    log.warning("the estimate's covariances could not be computed (%s); reporting the graph's "
                                "scaled marginals", str(exc).strip().splitlines()[0] if str(exc).strip() else exc)
        reasons = {key: f"rejected by the optimiser (GNC weight {w:.2f})" for key, w in weights.items() if w < 0.5}
        reasons.update({(i, j): why for i, j, why in dropped})
        return reasons, covs
