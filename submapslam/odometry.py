"""Scan-to-map odometry: KISS-ICP's registration core, seeded by wheel odometry.

We drive KISS-ICP's building blocks (preprocessor, voxel hash map, adaptive threshold,
point-to-point registration) ourselves so that the ICP initial guess can come from the wheel
odometry increment when the log has one (else KISS-ICP's constant-velocity model).
Planar scans (z = 0) stay planar: point-to-point ICP is well-posed on them, the estimate is
projected back onto SE(2) after every step, and then refined point-to-line against the last
scans (:mod:`.registration.point_to_line`), which removes point-to-point ICP's lag on sparse 2D scans.
"""

from __future__ import annotations

import math
import statistics
from collections import deque
from collections.abc import Callable

import numpy as np

from .checkpoint import KnownScan
from .config import OdometryConfig
from .geometry import (
    blend_poses,
    inverse,
    matrix_to_se2,
    rotation_angle,
    se2_to_matrix,
    splice_height_and_tilt,
)
from .registration.previous_scan import PreviousScan
from .registration.voxel_gicp import VoxelGicpSettings, VoxelGicpTracker, azimuth_coverage_deg
from .registration.wall_noise import WallNoise
from .scan import Scan
from .scan_intervals import ScanIntervals, bent, gap_steps, most_promising, paced, restart_steps

#: [m] the starts tried for a 3D log's second scan, along the sensor's x and y axes, besides no
#: motion (:meth:`Odometry._first_step`); one wins when it puts a FIRST_STEP_MARGIN larger share
#: of the scan's points above the ground within half a voxel of the first scan
FIRST_STEP_GUESSES_M = (1.5, -1.5, 3.0, -3.0)
FIRST_STEP_MARGIN = 0.05

NARROW_FIELD_DEG = 180.0  # auto registration: a first scan seeing less than this around z is a narrow-field sensor
#: planar: a scan fitting the last scans below this share of their usual fit (median of the last 20)
#: fits poorly: its registration may give way to the wheels' pose, and it is checked against the
#: previous scan (:meth:`Odometry._check_against_previous_scan`)
POOR_FIT = 0.75
#: [local-map voxels] spacing of the guesses along the motion carried over a long interval
#: (:meth:`Odometry._over_the_gap`): within reach of registration from one of them
GAP_GUESS_SPACING = 2.0
#: [deg] turns about the vertical tried at each of those guesses, after the unturned ones (a drive
#: turned 18 deg in 2 s of dropped scans; a robot indoors turns a corner in as long)
GAP_GUESS_TURNS_DEG = (10.0, -10.0, 20.0, -20.0)
GAP_GUESS_TURNS_PLANAR_DEG = (15.0, -15.0, 30.0, -30.0, 45.0, -45.0, 60.0, -60.0, 90.0, -90.0)
#: [local-map voxels], [deg] a step shorter than this that turns less than that stood still: the
#: scan after it and a long interval is also guessed at the pace before the stop (:meth:`Odometry._over_the_gap`)
STOOD_VOXELS = 0.1
STOOD_DEG = 1.0
#: [share of the scan's points] the margin by which the best registration from those guesses and the
#: one-interval guess's must differ in fit for the other to win (:meth:`Odometry._gap_margin`)
GAP_FIT_MARGIN = 0.05
#: how many of those guesses are registered: those that fit best as they are
GAP_GUESSES_REGISTERED = 3
#: [m], [deg] a spinning LiDAR's registrations at the adaptive threshold and at a voxel this close
#: agree, and the first stands (:meth:`Odometry._tight_or_wide`)
TIGHT_AGREES_M = 0.05
TIGHT_AGREES_DEG = 0.2
#: 3D without wheels: a scan whose share on the delayed local map falls below this part of the
#: usual (the median of the last FRESH_MAP_HISTORY scans') has the waiting scans put into the map
#: and registers again (:meth:`Odometry._fresh_map_if_off`)
FRESH_MAP_RATIO = 0.5
FRESH_MAP_HISTORY = 10
#: [deg] turns about the vertical the guess of such a scan is bent by when the map's refresh does
#: not bring its share back: a drive that stopped turning between keyframes (the prediction
#: carried 10 deg on where the truth turned 5, and registration kept the 10)
FRESH_MAP_TURNS_DEG = (-5.0, 5.0, -10.0, 10.0)


def resolve_registration(config: OdometryConfig, scan: Scan) -> OdometryConfig:
    """``config`` with ``registration: auto`` made concrete from the log's first ``scan``:
    voxel_gicp for a 3D sensor seeing less than 180 deg around the vertical axis (solid-state,
    Livox-like), kiss_icp otherwise (spinning LiDARs, 2D lasers)."""
    if config.registration != "auto":
        return config
    method = "kiss_icp"
    if not scan.planar and len(scan.points):
        if azimuth_coverage_deg(scan.points, min_range=max(config.min_range, 0.5)) < NARROW_FIELD_DEG:
            method = "voxel_gicp"
    return config.model_copy(update={"registration": method})


def odometry_voxels(config: OdometryConfig, planar: bool) -> tuple[float, float]:
    """``(map voxel, frame voxel)`` [m]: the local map's voxel as resolved for the log's kind
    and registration (``config.registration`` resolved, see :func:`resolve_registration`), and
    the voxel each scan is thinned to first (half of it)."""
    if config.voxel_size:
        voxel = config.voxel_size
    elif planar:
        voxel = 0.2
    elif config.registration == "voxel_gicp":
        voxel = VoxelGicpSettings().fine_voxel
    else:
        voxel = config.max_range / 100.0
    return voxel, 0.5 * voxel


#: a scan keeps all its points when fewer than this many lie above its ground band
MIN_POINTS_ABOVE_GROUND = 200


def above_ground_band(points: np.ndarray, band_m: float) -> np.ndarray:
    """The rows of ``points`` ``(N, 3)`` (sensor frame, z up) higher than ``band_m`` [m] above the
    scan's 5th percentile of height: what is left when the ground is taken out. All of ``points``
    when fewer than :data:`MIN_POINTS_ABOVE_GROUND` would be left (an open field: the ground is
    all there is to register)."""
    if len(points) == 0:
        return points
    z = points[:, 2]
    above = points[z > np.percentile(z, 5.0) + band_m]
    return above if len(above) >= MIN_POINTS_ABOVE_GROUND else points


def young_scans(config: OdometryConfig) -> int:
    """3D: how many scans after the first register against a local map of fewer than
    ``young_map_scans`` scans, at most: those, and the ``movers_delay`` scans each waits before it
    enters the map (fewer where ``movers_delay_s`` lets them in sooner: a keyframed log); KISS-ICP
    registration only, voxelised GICP has no young map."""
    if config.registration == "voxel_gicp":
        return 0
    delayed = config.movers_delay if (config.drop_movers or config.movers_delay > 0) else 0
    return delayed + config.young_map_scans


class Odometry:
    """Incremental odometry: ``register(scan) -> T_odomframe_base`` of that scan.

    The world frame of this estimator is the pose of the first scan.
    """

    def __init__(self, config: OdometryConfig, planar: bool) -> None:
        from kiss_icp.config import KISSConfig
        from kiss_icp.mapping import get_voxel_hash_map
        from kiss_icp.preprocess import get_preprocessor
        from kiss_icp.registration import get_registration
        from kiss_icp.threshold import get_threshold_estimator
        from kiss_icp.voxelization import voxel_down_sample

        self.config = config
        self.planar = planar
        kiss = KISSConfig()
        kiss.data.max_range = config.max_range
        kiss.data.min_range = config.min_range
        kiss.data.deskew = False  # this preprocessor only crops; _deskewing corrects the motion when asked
        kiss.mapping.voxel_size, self.frame_voxel = odometry_voxels(config, planar)
        kiss.mapping.max_points_per_voxel = config.max_points_per_voxel or (20 if planar else 3)
        kiss.registration.max_num_iterations = config.max_iterations
        kiss.registration.convergence_criterion = config.convergence_criterion or (1e-4 if planar else 3e-3)
        kiss.registration.max_num_threads = 1
        kiss.adaptive_threshold.initial_threshold = config.initial_threshold
        kiss.adaptive_threshold.min_motion_th = config.min_motion_threshold
        self.voxel_size: float = kiss.mapping.voxel_size
        self.last_frame_down = np.zeros((0, 3))
        self.last_xyt: np.ndarray | None = None  # planar: (3,) x, y, yaw of the last scan as refined
        self._preprocessor = get_preprocessor(kiss)
        kiss.data.deskew = True
        self._deskewing = get_preprocessor(kiss) if config.deskew is not False else None
        self._intervals = ScanIntervals()  # between the scans so far [s]
        self._registration = get_registration(kiss)
        self._local_map = get_voxel_hash_map(kiss)
        self._threshold = get_threshold_estimator(kiss)
        self._down = voxel_down_sample
        self.last_pose = np.eye(4)
        self.last_delta = np.eye(4)
        self._last_move: tuple[np.ndarray, float] | None = None  # the last step (4, 4) that did not stand still, its interval [s]
        self._last_wheel: np.ndarray | None = None
        self.n_registered = 0
        self.first_step_moved = False  # 3D: the second scan's registration started from a guessed step
        self._scans_in_map = 0  # scans added to KISS-ICP's local map so far
        self._map_tree: tuple[int, object] | None = None  # (scans in map, small_gicp k-d tree of the local map then)
        self._wheel_predicted = False  # the last prediction came from the wheels
        self.wheel_overruled = 0  # planar scans whose constant-velocity guess fitted better than the wheels'
        self.gap_guesses_tried = 0  # scans after a long interval also registered from the motion carried over it
        self.gap_guess_won = 0  # ... and of them, those where that guess's registration fitted better
        self.gap_stood_won = 0  # 3D, a steady log: scans after a long interval registered as standing still
        self.tight_tried = 0  # 3D: scans registered at a voxel too, the two results apart (:meth:`_tight_or_wide`)
        self.tight_won = 0  # ... and of them, those where the tight result was kept
        self.fresh_map_tried = 0  # 3D without wheels: scans registered again once the waiting scans entered the map
        self.fresh_map_won = 0  # ... and of them, those where that registration was kept
        self.fresh_map_turned = 0  # ... and those where a registration from a turned guess was kept instead
        self.last_map_refreshed = False  # the waiting scans entered the local map early for the last scan
        self.last_guess: np.ndarray | None = None  # (4, 4) the guess the last scan's kept registration started from, if not the prediction
        self._recent_shares: deque[float] = deque(maxlen=FRESH_MAP_HISTORY)  # 3D: the last scans' map shares
        self.registration_overruled = 0  # planar scans whose wheel pose fitted better than where registration went
        self.previous_scan_checked = 0  # planar scans that fitted poorly, so that their match to the previous scan was tried
        self.previous_scan_preferred = 0  # ... and of them, those where that match's pose was kept
        self._recent_fits: deque[float] = deque(maxlen=20)  # planar: fit of the last scans to the ones before
        self._refiner = None
        self._wall_noise = WallNoise()  # planar: the laser's scatter across walls, for the line test
        self.movers = None  # 3D: keeps what moved out of registration and the local map
        self._gicp = None  # 3D narrow-field sensors: voxelised GICP instead of KISS-ICP's registration
        if not planar and config.registration == "voxel_gicp":
            voxel = self.voxel_size
            self._gicp = VoxelGicpTracker(VoxelGicpSettings(fine_voxel=voxel, coarse_voxel=4.0 * voxel,
                                                            frame_voxel=self.frame_voxel, coarse_frame_voxel=voxel,
                                                            coarse_distance=8.0 * voxel, fine_distance=2.0 * voxel,
                                                            coarse_translation_epsilon=0.04 * voxel,
                                                            fine_translation_epsilon=0.004 * voxel,
                                                            far_m=2.0 * voxel))
        elif not planar and (config.drop_movers or config.movers_delay > 0):
            from .mapping.moving_points import MoverFilter

            self.movers = MoverFilter(history=config.movers_history, delay=config.movers_delay,
                                      max_views=config.movers_views, test=config.drop_movers,
                                      delay_s=config.movers_delay_s)
        if planar and config.planar_point_to_line:
            from .registration.point_to_line import RecentScanMap

            self._refiner = RecentScanMap()

    def register(self, scan: Scan, known: KnownScan | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Register one scan; return ``(T_odom_base, points_deskewed)``.

        ``points_deskewed`` is ``(N, 3)`` in the scan's sensor frame after range filtering and
        motion compensation; :attr:`last_frame_down` is the same thinned to :attr:`frame_voxel`
        (what registration used). ``known``: how this scan was registered before (a resumed run's
        :class:`~submapslam.checkpoint.KnownScan`): no ICP, the local map, the motion model and the
        adaptive threshold are updated exactly as they were.
        :attr:`last_xyt` is the planar pose as refined; :attr:`last_guess` the guess the kept
        registration started from where not the prediction, :attr:`last_map_refreshed` whether the
        waiting scans entered the local map early for it.
        """
        self.last_map_refreshed = False
        self.last_guess = None
        frame = self._crop_and_deskew(scan)
        prediction = self._predicted_delta(scan)
        if self._refiner is not None:
            self._wall_noise.add(scan.points[:, :2])  # the reader's points, beams in order
            self._refiner.noise_m = self._wall_noise.sigma_m
        if len(frame) < 10:
            # nothing to register: dead-reckon on the prediction
            new_pose = self.last_pose @ prediction if known is None else known.pose
            self.last_xyt = matrix_to_se2(new_pose) if self.planar else None
            self._advance(new_pose)
            self.last_frame_down = frame
            return new_pose, frame
        frame_down = self._down(frame, self.frame_voxel)
        initial_guess = predicted = self.last_pose @ prediction
        gap_guesses = []
        if known is None and self._gicp is None:
            turns = GAP_GUESS_TURNS_PLANAR_DEG if self.planar else GAP_GUESS_TURNS_DEG
            gap_guesses = self._over_the_gap(scan, GAP_GUESS_SPACING * self.voxel_size, turns, may_stand=True)
        elif known is None:  # GICP's coarse stage reaches further, turns its guesses itself when they
            # fit poorly, and always tries no motion
            gap_guesses = self._over_the_gap(scan, self._gicp.settings.coarse_distance, (), may_stand=False)
        if self._gicp is not None:
            return self._register_gicp(frame, frame_down, initial_guess, known, gap_guesses), frame
        # planar: when the wheels and the constant-velocity model disagree, or a long interval passed
        # since the last scan, both guesses are tried (below)
        alternative = None
        if self.planar and known is None and self._wheel_disagrees(prediction):
            alternative = self.last_pose @ self.last_delta
        elif self.planar and gap_guesses:
            alternative = self._best_planar_guess(frame_down, gap_guesses)
        registered = frame_down
        if self.movers is not None and not self._local_map.empty():
            # what the last scans saw through is a mover entering: not registered (a replay tests
            # it too: its votes decide the scan's later map entry, as they did live)
            registered = frame_down[~self.movers.entering(frame_down, initial_guess)]
        source = self._down(registered, self.voxel_size * 1.5)
        if known is not None:
            new_pose = known.pose
            if not self.planar and not self._local_map.empty():
                self._fresh_map_if_off(source, initial_guess, new_pose, replayed=known.map_refreshed)
            if known.guess is not None:
                initial_guess = known.guess
            if self.planar:
                xyt = known.xyt if known.xyt is not None else matrix_to_se2(new_pose)
                if self._refiner is not None:  # the fits the live run kept, for the scans after the replay
                    self._recent_fits.append(self._fit(frame_down, xyt))
                    self._refiner.add(frame_down[:, :2], xyt)
                self.last_xyt = xyt
        elif self._local_map.empty():
            new_pose = initial_guess
        elif not self.planar:
            new_pose = self._align_3d(source, initial_guess)
            if self.n_registered == 1 and np.allclose(prediction, np.eye(4)):
                new_pose = self._first_step(source, new_pose)
            elif gap_guesses:
                new_pose, initial_guess = self._better_over_the_gap(source, new_pose, initial_guess, gap_guesses)
            new_pose, initial_guess = self._fresh_map_if_off(source, initial_guess, new_pose)
        else:
            new_pose = self._align(source, initial_guess)
        if self.planar and known is None:
            xyt = self._refine(frame_down, new_pose, initial_guess)
            if alternative is not None and not self._local_map.empty():
                # stale or jumping wheel odometry (MIT CSAIL's FLASER poses stand still for a few
                # scans, then jump by up to 85 deg) leads ICP into a wrong minimum: the guess
                # whose result fits the recent scans better wins (after a long interval, by a margin:
                # :meth:`_gap_margin`); when neither
                # fits as the last scans did, guesses turned by up to +-30 deg from both are tried too
                fit = self._fit(frame_down, xyt)
                alt_xyt = self._refine(frame_down, self._align(source, alternative), alternative)
                alt_fit = self._fit(frame_down, alt_xyt)
                if alt_fit > fit + (self._gap_margin() if gap_guesses else 0.0):
                    xyt, initial_guess, fit = alt_xyt, alternative, alt_fit
                    if gap_guesses:
                        self.gap_guess_won += 1
                        prediction = inverse(self.last_pose) @ alternative  # the step the previous-scan check centres on
                    else:
                        self.wheel_overruled += 1
                usual = 0.5 * statistics.median(self._recent_fits) if self._recent_fits else 0.0
                if fit < usual:
                    # a turned guess wins only if it fits as the last scans did: where the scan sees
                    # mostly new ground (a doorway), every guess fits poorly and the best of them is
                    # noise (MIT CSAIL's scan 1807 once took a 76 deg turn the wheels put at 10)
                    best, best_guess, best_fit = xyt, initial_guess, fit
                    for base in (self.last_pose @ prediction, alternative):
                        for turn in (-30.0, -20.0, -10.0, 10.0, 20.0, 30.0):
                            guess = base @ se2_to_matrix(0.0, 0.0, np.deg2rad(turn))
                            cand = self._refine(frame_down, self._align(source, guess), guess)
                            cand_fit = self._fit(frame_down, cand)
                            if cand_fit > best_fit:
                                best, best_guess, best_fit = cand, guess, cand_fit
                    if best_fit >= usual:
                        xyt, initial_guess, fit = best, best_guess, best_fit
            elif self._refiner is not None:
                fit = self._fit(frame_down, xyt)
                poor = bool(self._recent_fits) and fit < POOR_FIT * statistics.median(self._recent_fits)
                if poor and self._wheel_predicted and self._departs(initial_guess, xyt):
                    # the wheels and the motion model agreed, yet registration ended far from both
                    # and fits the last scans worse than usual (Intel's scan 11455 once turned 20 deg
                    # where the wheels turned 0.4): the wheels' pose, refined, is tried too, and the
                    # better fit wins. Wheels slip in turns, so a registration that fits as usual stays.
                    kept = self._refine(frame_down, initial_guess, initial_guess)
                    kept_fit = self._fit(frame_down, kept)
                    if kept_fit > fit:
                        xyt, fit = kept, kept_fit
                        self.registration_overruled += 1
            if self._refiner is not None:  # one of the branches above set ``fit`` (stale wheels imply the refiner)
                xyt, fit = self._check_against_previous_scan(frame_down, xyt, fit, prediction)
                self._recent_fits.append(fit)
                self._refiner.add(frame_down[:, :2], xyt)
            new_pose = se2_to_matrix(*xyt)
            self.last_xyt = xyt
        # row-major, as a resumed run's poses from its checkpoint are (registrations come row-major
        # from _align): numpy's 4x4 products differ in the last bit by memory layout, and a resumed
        # run carried the difference into every later registration (0.1-4 mm by the end)
        new_pose = np.ascontiguousarray(new_pose)
        self._threshold.update_model_deviation(inverse(initial_guess) @ new_pose)
        self.last_guess = None if initial_guess is predicted else initial_guess
        if self.movers is None:
            self._local_map.update(frame_down, new_pose)
            self._scans_in_map += 1
        else:  # each scan enters the local map a few scans late, without what the scans around it saw through
            for points, pose in self.movers.add(frame, frame_down, new_pose, immediate=self._local_map.empty(),
                                                timestamp=scan.timestamp if scan.timed else None):
                self._local_map.update(points, pose)
                self._scans_in_map += 1
        self._advance(new_pose)
        self.last_frame_down = frame_down
        return new_pose, frame

    def _crop_and_deskew(self, scan: Scan) -> np.ndarray:
        """The scan's points within the range limits, ``(N, 3)`` in its frame; motion-corrected
        to the end of the sweep (KISS-ICP's convention) when it has per-point times
        (``config.deskew`` not False).

        The motion during the sweep is the last scan-to-scan motion (KISS-ICP's model), scaled
        down when those scans lay further apart in time than usual (the median of the last 50
        gaps): after a pause, or in a keyframed log, a sweep is a small share of that motion.
        """
        times, intervals = scan.point_times, self._intervals
        intervals.add(scan.timestamp)
        no_times = np.zeros(len(scan.points))
        if self._deskewing is None or times is None or len(times) != len(scan.points) or len(times) == 0:
            return self._preprocessor.preprocess(scan.points, no_times, self.last_delta)
        times = np.asarray(times, dtype=np.float64)
        span = float(times.max() - times.min())
        if not np.isfinite(span) or span <= 0.0:
            return self._preprocessor.preprocess(scan.points, no_times, self.last_delta)
        motion = self.last_delta
        sweep = intervals.usual()  # a sweep lasts no longer than the usual time between scans
        if intervals.before is not None and sweep is not None and intervals.before > sweep:
            # after a pause or in a keyframed log: the last motion took longer than a sweep
            motion = blend_poses(np.eye(4), self.last_delta, sweep / intervals.before)
        return self._deskewing.preprocess(scan.points, (times - times.min()) / span, motion)

    def _register_gicp(self, frame: np.ndarray, frame_down: np.ndarray, initial_guess: np.ndarray,
                       known: KnownScan | None,
                       gap_guesses: list[np.ndarray] | None = None) -> np.ndarray:
        """Narrow-field 3D: voxelised GICP from the prediction (without wheels: the last motion as
        it was, then at its pace) and from no motion (a hand-held sensor turns in ways a
        constant-velocity model does not foresee), after a long interval also from ``gap_guesses``
        (:meth:`_over_the_gap`, tried after the prediction); ``T_odom_base``."""
        cloud = self._gicp.prepare(frame)
        if known is not None:
            new_pose = known.pose
        elif self._gicp.empty():
            new_pose = initial_guess
        else:
            guesses = [initial_guess]
            one_interval = self.last_pose @ self.last_delta
            apart = float(np.linalg.norm(one_interval[:3, 3] - initial_guess[:3, 3]))
            if not self._wheel_predicted and 0.0 < apart < 0.5 * self._gicp.settings.coarse_distance:
                # the motion at its pace only second where the one-interval guess lies within the
                # coarse stage's reach anyway: a hand-held sensor keeps its pace less than a vehicle
                # (the Livox main building at every second keyframe: 0.28 -> 0.43 m with it first)
                guesses.insert(0, one_interval)
            elif not self._wheel_predicted and apart > 0.0:
                guesses.append(one_interval)
            guesses.extend(gap_guesses or [])
            if not np.allclose(initial_guess, self.last_pose):
                guesses.append(self.last_pose)
            new_pose, _ = self._gicp.align(cloud, guesses, search_all=bool(gap_guesses))
            u, _, vt = np.linalg.svd(new_pose[:3, :3])  # exactly a rotation (KISS-ICP's deskew checks it)
            new_pose[:3, :3] = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
        new_pose = np.ascontiguousarray(new_pose)  # row-major, as a resumed run's (see register)
        self._gicp.insert(cloud, new_pose)
        self._advance(new_pose)
        self.last_frame_down = frame_down
        return new_pose

    def _align_3d(self, source: np.ndarray, initial_guess: np.ndarray) -> np.ndarray:
        """A spinning LiDAR's ``source (N, 3)`` registered to the local map from ``initial_guess``.
        While the map is young, x, y and yaw come from the scan without its ground (whose rings
        would hold it where the map's rings are), then height, roll and pitch from the whole scan."""
        if self._scans_in_map < self.config.young_map_scans:
            level = self._align(above_ground_band(source, self.config.ground_band_m), initial_guess)
            return splice_height_and_tilt(level, self._align(source, level))
        return self._tight_or_wide(source, initial_guess)

    def _tight_or_wide(self, source: np.ndarray, initial_guess: np.ndarray) -> np.ndarray:
        """KISS-ICP's registration of ``source (N, 3)`` from ``initial_guess`` at its adaptive
        threshold, and, when that threshold is wider than a map voxel, again at a voxel: the tight
        result unless the wide one puts more of the scan on the local map (:meth:`_map_share`).

        The adaptive threshold grows with how far the predictions were off, a rotation error
        weighed at the maximum range: without wheels between keyframes 0.2-0.5 s apart it stays
        near 2.3 m (correspondences 7 m long) against 0.75 m with wheels. Registration needs that
        reach to converge from such guesses, but where half the scan is new ground (a corner into a
        street the map has not seen) the long pairs pull it off: a 64-ring drive ended 0.63 m off
        (odometry 0.64 m), its steps 0.4 m short and then backwards from a guess 0.13 m off; at a
        voxel it registered within 0.04 m of the truth. The two rarely differ (5 cm, 0.2 deg);
        when they do, the share decides."""
        sigma = self._threshold.get_threshold()
        wide = self._align(source, initial_guess, sigma)
        if sigma <= self.voxel_size:
            return wide
        tight = self._align(source, initial_guess, self.voxel_size)
        apart = inverse(wide) @ tight
        if np.linalg.norm(apart[:3, 3]) < TIGHT_AGREES_M and rotation_angle(apart) < np.deg2rad(TIGHT_AGREES_DEG):
            return wide
        share = self._map_share(source)
        if share is None:
            return wide
        self.tight_tried += 1
        if share(tight) < share(wide):
            return wide
        self.tight_won += 1
        return tight

    def _fresh_map_if_off(self, source: np.ndarray, initial_guess: np.ndarray, pose: np.ndarray,
                          replayed: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
        """A spinning LiDAR without wheels: ``(pose, guess)``, ``pose`` ``(4, 4)`` the registration of
        ``source`` ``(N, 3)`` from ``initial_guess`` as given, or, when the scan lands on the delayed
        local map much less than the last scans did (its share, :meth:`_map_share`, below
        ``FRESH_MAP_RATIO`` of their median), the scans still waiting for the map enter it now and
        the scan registers again from the same guess; of the two, the one with the larger share on
        that map. If that share is still below the usual, the guess bent by each of
        ``FRESH_MAP_TURNS_DEG`` is registered too, and the best of those replaces it (with its
        guess) when it lands on the map as the last scans did, by ``GAP_FIT_MARGIN`` more.
        ``replayed``: a resumed run's decision for this scan (its ``pose`` is the one kept).

        Each scan enters the map 0.8 s late (``movers_delay_s``: the odometry drifts less, and
        movers can be seen through). Where the last keyframes turned into a street the map has
        not seen, the scan's share fell from 0.89 to 0.14 and registration carried the turn on
        at 4-10 deg a keyframe (a 64-ring drive without wheels ended 89 m off; the waiting
        scans had seen that street). With the wheels' guess the delayed map holds."""
        if self.movers is None or self._wheel_predicted or not self.movers.waiting:
            return pose, initial_guess
        share = self._map_share(source)
        if share is None:
            return pose, initial_guess
        fit = share(pose)
        usual = FRESH_MAP_RATIO * statistics.median(self._recent_shares) if len(self._recent_shares) >= 3 else 0.0
        refresh = fit < usual if replayed is None else replayed
        if refresh:
            for points, entered in self.movers.flush():
                self._local_map.update(points, entered)
                self._scans_in_map += 1
            self.last_map_refreshed = True
            share = self._map_share(source)
            fit = share(pose)
            if replayed is None:
                self.fresh_map_tried += 1
                again = self._tight_or_wide(source, initial_guess)
                again_fit = share(again)
                if again_fit > fit:
                    pose, fit = again, again_fit
                    self.fresh_map_won += 1
                if fit < usual:
                    pose, initial_guess, fit = self._turned_if_better(source, initial_guess, pose, fit, share, usual)
        self._recent_shares.append(fit)  # the kept pose's share on the map it was kept on
        return pose, initial_guess

    def _turned_if_better(self, source: np.ndarray, initial_guess: np.ndarray, pose: np.ndarray, fit: float,
                          share: Callable[..., float], usual: float) -> tuple[np.ndarray, np.ndarray, float]:
        """``(pose, guess, share)``: ``pose`` (from ``initial_guess``, with ``fit``), or the
        registration of ``source`` ``(N, 3)`` from ``initial_guess`` bent by one of
        ``FRESH_MAP_TURNS_DEG`` whose ``share`` is the largest, if that reaches ``usual`` and beats
        ``fit`` by ``GAP_FIT_MARGIN`` (a scan on new ground fits poorly from every guess)."""
        step = inverse(self.last_pose) @ initial_guess
        best, best_guess, best_fit = pose, initial_guess, fit
        for turn in FRESH_MAP_TURNS_DEG:
            guess = self.last_pose @ bent(step, np.radians(turn))
            candidate = self._tight_or_wide(source, guess)
            candidate_fit = share(candidate)
            if candidate_fit > best_fit:
                best, best_guess, best_fit = candidate, guess, candidate_fit
        if best_fit < usual or best_fit <= fit + GAP_FIT_MARGIN:
            return pose, initial_guess, fit
        self.fresh_map_turned += 1
        return best, best_guess, best_fit

    def _first_step(self, source: np.ndarray, from_rest: np.ndarray) -> np.ndarray:
        """The second scan of a 3D log with no motion known yet: ``from_rest`` ``(4, 4)`` (its
        registration from no motion) or, if one fits the first scan clearly better, a
        registration from ``FIRST_STEP_GUESSES_M`` along the sensor's x or y axis. A log that
        starts at speed (2.6 m a scan) otherwise registered its second scan 0.1 m on (a street
        constrains little along itself), and the motion model kept that pace."""
        share = self._map_share(source)
        if share is None:
            return from_rest
        best, best_share = from_rest, share(from_rest)
        for axis in (0, 1):
            for distance in FIRST_STEP_GUESSES_M:
                step = np.eye(4)
                step[axis, 3] = distance
                pose = self._align_3d(source, self.last_pose @ step)
                fit = share(pose)
                if fit > (1.0 + FIRST_STEP_MARGIN) * best_share:
                    best, best_share = pose, fit
        self.first_step_moved = best is not from_rest
        return best

    def _map_share(self, source: np.ndarray) -> Callable[..., float] | None:
        """3D: a function ``share(pose, threshold=None)`` of a pose ``(4, 4)`` giving the share of
        ``source``'s points ``(N, 3)`` above the ground band (flat ground fits any step along it)
        that land within ``threshold`` [m] (default half a voxel) of the local map there (one k-d
        tree of the map as it is, kept until the map changes); None when no point lies above the band."""
        import small_gicp

        above = above_ground_band(source, self.config.ground_band_m)
        if not len(above):
            return None
        if self._map_tree is None or self._map_tree[0] != self._scans_in_map:  # every map update counts a scan
            self._map_tree = (self._scans_in_map,
                              small_gicp.KdTree(np.asarray(self._local_map.point_cloud(), dtype=np.float64)))
        tree = self._map_tree[1]

        def share(pose: np.ndarray, threshold: float | None = None) -> float:
            limit = 0.5 * self.voxel_size if threshold is None else threshold
            _, d2 = tree.batch_knn_search(above @ pose[:3, :3].T + pose[:3, 3], 1)
            return float(np.mean(np.asarray(d2).reshape(-1) < limit * limit))

        return share

    def _over_the_gap(self, scan: Scan, spacing_m: float, turns_deg: tuple[float, ...],
                      may_stand: bool) -> list[np.ndarray]:
        """Guesses ``(4, 4)`` ``T_odom_base`` of the last motion carried on at its pace over the
        interval since the last scan, when that interval is ``config.gap_ratio`` times (or a
        ``gap_ratio``-th of) the one the last motion spans and nothing else predicts the scan (no
        wheels); else none. After frames were dropped the motion spans the gap, and the scan after
        it comes at the usual interval again. Over a gap the pace and the heading may have changed (a
        drive that turned 18 deg in 2 s of dropped scans), so the guesses lie along the carried-on
        motion from the whole gap's step down towards one interval's, ``spacing_m`` [m] apart, then
        the same bent into arcs that turn by each of ``turns_deg`` about the vertical
        (:func:`~submapslam.scan_intervals.bent`), and with ``may_stand`` in a keyframed log last
        the last pose itself (the interval was a stop, and the last motion came before it). Needs
        the scans' times."""
        ratio, over = self.config.gap_ratio, self._intervals.pace()
        if ratio is None or not scan.timed or self._wheel_predicted or self.n_registered < 2 or over is None:
            return []
        if 1.0 / ratio < over < ratio:
            return []
        standing = may_stand and not self._intervals.steady()
        self.gap_guesses_tried += 1
        steps = gap_steps(self.last_delta, over, spacing_m, turns_deg, standing)
        if over < 1.0 and self._last_move is not None and self._stood(self.last_delta):
            # the first scan after a stop: the motion before it, at its pace and slower (a keyframed
            # 128-ring drive went on at 12 m/s after 10 s standing, and registration from no motion
            # found 1.2 of its 6 m)
            move, interval = self._last_move
            steps += restart_steps(move, self._intervals.last / interval, spacing_m, turns_deg)
        return [self.last_pose @ step for step in steps]

    def _stood(self, step: np.ndarray) -> bool:
        """Whether ``step`` ``(4, 4)`` stood still (:data:`STOOD_VOXELS`, :data:`STOOD_DEG`)."""
        return bool(np.linalg.norm(step[:3, 3]) < STOOD_VOXELS * self.voxel_size
                    and np.degrees(rotation_angle(step)) < STOOD_DEG)

    def _better_over_the_gap(self, source: np.ndarray, new_pose: np.ndarray, initial_guess: np.ndarray,
                             gap_guesses: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
        """3D spinning LiDAR: ``(pose, guess)``: ``new_pose`` (registered from ``initial_guess``),
        unless the registration of ``source`` ``(N, 3)`` from one of ``gap_guesses`` puts a larger
        share of the scan on the local map (:meth:`_map_share`), by :meth:`_gap_margin`; of those,
        the :data:`GAP_GUESSES_REGISTERED` that put the most of the scan near the map as they are
        (within the guesses' spacing) are registered."""
        share = self._map_share(source)
        if share is None:
            return new_pose, initial_guess
        reach = GAP_GUESS_SPACING * self.voxel_size  # within reach of registration
        best, best_guess, best_share = None, None, -1.0
        for guess in most_promising(gap_guesses, lambda g: share(g, reach), GAP_GUESSES_REGISTERED):
            pose = self._align_3d(source, guess)
            fit = share(pose)
            if fit > best_share:
                best, best_guess, best_share = pose, guess, fit
        kept_share = share(new_pose)
        if best_share <= kept_share + self._gap_margin():
            return self._stood_if_better(source, new_pose, initial_guess, kept_share, share)
        self.gap_guess_won += 1
        return self._stood_if_better(source, best, best_guess, best_share, share)

    def _stood_if_better(self, source: np.ndarray, pose: np.ndarray, guess: np.ndarray, fit: float,
                         share: Callable[..., float]) -> tuple[np.ndarray, np.ndarray]:
        """``(pose, guess)`` as given (``pose`` with the share ``fit``), or, after a long interval
        in a log at a steady rate, the registration of ``source`` ``(N, 3)`` from the last pose when
        its ``share`` beats ``fit`` by ``GAP_FIT_MARGIN``. A steady log's long interval is taken
        for scans lost while moving, and its guesses leave standing still out; yet a logger may
        pause where the sensor stands (keyframes every 0.4-0.5 s, three of them 3.4 s apart at one
        pose: fourteen of twenty such stops along a street were registered as 3-9 m of driving, with
        37-40 % of the scan on the map where standing still put 58-70 % there)."""
        pace = self._intervals.pace()
        if pace is None or pace < 1.0 or not self._intervals.steady():
            return pose, guess
        stand = self._align_3d(source, self.last_pose)
        if share(stand) <= fit + GAP_FIT_MARGIN:
            return pose, guess
        self.gap_stood_won += 1
        return stand, self.last_pose.copy()

    def _gap_margin(self) -> float:
        """[share of the scan] how much better the best registration over a long interval must fit
        than the one-interval guess's to replace it. Along a corridor or a street every step fits
        about alike, so it is the log's own rate that decides: a log at a steady rate
        (:meth:`ScanIntervals.steady`) lost scans and the motion went on (``-GAP_FIT_MARGIN``: kept unless
        the one-interval guess fits clearly better); a keyframed log pauses where the sensor stood
        (``+GAP_FIT_MARGIN``)."""
        return -GAP_FIT_MARGIN if self._intervals.steady() else GAP_FIT_MARGIN

    def _best_planar_guess(self, frame_down: np.ndarray, guesses: list[np.ndarray]) -> np.ndarray:
        """Planar: of the :data:`GAP_GUESSES_REGISTERED` of ``guesses`` ``(4, 4)`` that put the most
        of the scan near the last scans as they are (within the guesses' spacing), the one whose
        registration of the scan ``frame_down`` ``(N, 3)`` (refined) fits them best (:meth:`_fit`);
        the earliest on a tie (the first without the point-to-line refiner). It then replaces the
        constant-velocity guess if it fits better by :meth:`_gap_margin`."""
        if len(guesses) == 1 or self._refiner is None:
            return guesses[0]
        source = self._down(frame_down, self.voxel_size * 1.5)
        reach = GAP_GUESS_SPACING * self.voxel_size  # within reach of registration
        candidates = most_promising(guesses, lambda g: self._refiner.fit(frame_down[:, :2], matrix_to_se2(g), reach),
                                    GAP_GUESSES_REGISTERED)
        fits = [self._fit(frame_down, self._refine(frame_down, self._align(source, g), g)) for g in candidates]
        return candidates[int(np.argmax(fits))]

    def _align(self, source: np.ndarray, initial_guess: np.ndarray, sigma: float | None = None) -> np.ndarray:
        """KISS-ICP point-to-point registration of ``source (N, 3)`` to the local map from ``initial_guess``,
        at ``sigma`` [m] (correspondences up to three times it; default: the adaptive threshold). Row-major:
        KISS-ICP's result comes column-major (Eigen), and every pose here is kept row-major (:meth:`register`)."""
        if sigma is None:
            sigma = self._threshold.get_threshold()
        return np.ascontiguousarray(self._registration.align_points_to_map(
            points=source, voxel_map=self._local_map, initial_guess=initial_guess,
            max_correspondance_distance=3.0 * sigma, kernel=sigma))

    def _refine(self, frame_down: np.ndarray, pose: np.ndarray, initial_guess: np.ndarray) -> np.ndarray:
        """Planar ``(x, y, yaw)`` of ``pose``, refined point-to-line when on; degenerate directions
        take the ``initial_guess`` (the prediction: wheel odometry when the log has it)."""
        xyt = matrix_to_se2(pose)
        if self._refiner is not None:
            xyt, _ = self._refiner.refine(frame_down[:, :2], xyt, matrix_to_se2(initial_guess))
        return xyt

    def _check_against_previous_scan(self, frame_down: np.ndarray, xyt: np.ndarray, fit: float,
                                     prediction: np.ndarray) -> tuple[np.ndarray, float]:
        """Planar: ``(xyt, fit)`` of the scan, or of the pose its match to the previous scan gives
        (:class:`~submapslam.registration.previous_scan.PreviousScan`, refined against the last scans)
        when ``fit`` is below :data:`POOR_FIT` of the usual and that pose puts clearly more of the scan
        on the previous scan's points. ``prediction``: the predicted step ``(4, 4)`` from the last pose."""
        if (not self.config.planar_previous_scan_check or not self._recent_fits or self.last_xyt is None
                or fit >= POOR_FIT * statistics.median(self._recent_fits)):
            return xyt, fit
        self.previous_scan_checked += 1
        previous = PreviousScan(self.last_frame_down, self.last_xyt)
        candidate = previous.candidate(frame_down, prediction)
        if candidate is None:
            return xyt, fit
        pose = se2_to_matrix(*candidate)
        candidate = self._refine(frame_down, pose, pose)
        if not previous.prefers(frame_down, candidate, xyt):
            return xyt, fit
        self.previous_scan_preferred += 1
        return candidate, self._fit(frame_down, candidate)

    def _fit(self, frame_down: np.ndarray, xyt: np.ndarray) -> float:
        """Share of the scan's points ``(N, 3)`` placed at ``xyt`` within half an odometry-map voxel
        of the last scans (the point-to-line target; 0 when there is none)."""
        if self._refiner is None:
            return 0.0
        return self._refiner.fit(frame_down[:, :2], xyt, 0.5 * self.voxel_size)

    def checks(self) -> dict:
        """How often a check tried more than the first guess (``summary.json`` ``odometry_checks``).
        Planar runs: ``wheel_overruled`` scans whose constant-velocity guess fitted better than the
        wheels', ``registration_overruled`` scans whose wheel pose fitted better than where
        registration went. Narrow-field 3D runs (voxel_gicp): ``turned_guesses_tried`` scans whose
        usual guesses fitted poorly, ``turned_guess_won`` of those where a turned one replaced the usual
        alignment, ``far_from_prediction`` scans whose best alignment ended far
        from the prediction, ``near_alignment_kept`` of those where a near one won
        (:class:`~submapslam.registration.voxel_gicp.VoxelGicpTracker`). Other 3D runs:
        ``first_step_from_a_guessed_move``, whether the second scan started from a step along the
        sensor's axes (:meth:`_first_step`); ``tight_tried`` scans whose registration at a voxel
        ended apart from the one at the adaptive threshold, ``tight_won`` of those where it was
        kept (:meth:`_tight_or_wide`); without wheels ``fresh_map_tried`` scans registered again once
        the waiting scans entered the local map, ``fresh_map_won`` of those where that was kept,
        ``fresh_map_turned`` those where a registration from a turned guess was
        (:meth:`_fresh_map_if_off`); ``gap_stood_won`` scans after a long interval in a steady log
        registered as standing still (:meth:`_stood_if_better`). Every kind: ``gap_guesses_tried``
        scans that came after a long interval (``odometry.gap_ratio``) and were also registered
        from the motion carried over it; but with voxel_gicp (whose search takes the best of all its guesses) ``gap_guess_won``, those
        where that registration was kept."""
        gap = {"gap_guesses_tried": self.gap_guesses_tried}
        if self._gicp is not None:
            t = self._gicp
            return {"turned_guesses_tried": t.turned_tries, "turned_guess_won": t.turned_won,
                    "far_from_prediction": t.far_results,
                    "near_alignment_kept": t.near_kept, **gap}
        gap["gap_guess_won"] = self.gap_guess_won
        if not self.planar:
            return {"first_step_from_a_guessed_move": self.first_step_moved, "tight_tried": self.tight_tried,
                    "tight_won": self.tight_won, "fresh_map_tried": self.fresh_map_tried,
                    "fresh_map_won": self.fresh_map_won, "fresh_map_turned": self.fresh_map_turned,
                    "gap_stood_won": self.gap_stood_won, **gap}
        return {"wheel_overruled": self.wheel_overruled, "registration_overruled": self.registration_overruled,
                "previous_scan_checked": self.previous_scan_checked,
                "previous_scan_preferred": self.previous_scan_preferred, **gap,
                "wall_noise_m": round(float(self._wall_noise.sigma_m), 4)}

    def _beyond_wheel_check(self, distance_m: float, turn_deg: float) -> bool:
        """Two planar poses ``distance_m`` [m] and ``turn_deg`` [deg] apart differ by more than
        ``wheel_check_m`` or ``wheel_check_deg``."""
        return bool(distance_m > self.config.wheel_check_m or abs(turn_deg) > self.config.wheel_check_deg)

    def _departs(self, guess: np.ndarray, xyt: np.ndarray) -> bool:
        """The planar pose ``xyt`` (3,) lies beyond the wheel check from the ``guess`` (4, 4) it was
        registered from."""
        g = matrix_to_se2(guess)
        return self._beyond_wheel_check(math.hypot(xyt[0] - g[0], xyt[1] - g[1]),
                                        math.degrees(math.remainder(xyt[2] - g[2], 2 * math.pi)))

    def _wheel_disagrees(self, prediction: np.ndarray) -> bool:
        """The wheel-odometry ``prediction`` (4, 4) is not the constant-velocity one and lies beyond
        the wheel check from it."""
        c = self.config
        if self._refiner is None or not c.use_wheel_odometry or not self._wheel_predicted:
            return False
        diff = inverse(self.last_delta) @ prediction
        return self._beyond_wheel_check(np.linalg.norm(diff[:2, 3]), np.degrees(np.arctan2(diff[1, 0], diff[0, 0])))

    def _predicted_delta(self, scan: Scan) -> np.ndarray:
        """The predicted step ``(4, 4)`` from the last pose to ``scan``'s: the wheels' when the log
        has them (:attr:`_wheel_predicted`), else the last motion at its pace (:meth:`_paced_motion`)."""
        wheel = scan.odometry if self.config.use_wheel_odometry else None
        self._wheel_predicted = wheel is not None and self._last_wheel is not None
        delta = inverse(self._last_wheel) @ wheel if self._wheel_predicted else self._paced_motion(scan)
        self._last_wheel = wheel
        return delta

    def _paced_motion(self, scan: Scan) -> np.ndarray:
        """The last motion ``(4, 4)`` carried on at its pace over the interval since the last scan,
        when that interval differs from the one it spans by more than
        :data:`~submapslam.scan_intervals.PACE_TOLERANCE` and by
        less than ``config.gap_ratio`` (a longer gap is searched: :meth:`_over_the_gap`); else the
        last motion itself (KISS-ICP's constant-velocity model, one motion a scan). Keyframes
        0.2-0.5 s apart at 10 m/s otherwise start registration up to 3 m off."""
        if self.config.gap_ratio is None or not scan.timed:
            return self.last_delta
        return paced(self.last_delta, self._intervals.pace(), self.config.gap_ratio)

    def _advance(self, new_pose: np.ndarray) -> None:
        self.last_delta = inverse(self.last_pose) @ new_pose
        if self._intervals.last is not None and not self._stood(self.last_delta):
            self._last_move = (self.last_delta, self._intervals.last)
        self.last_pose = new_pose
        self.n_registered += 1
