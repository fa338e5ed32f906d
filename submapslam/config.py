"""Configuration: one pydantic model per component, ``extra="forbid"`` everywhere.

A misspelled key is an error naming the key, never silently ignored. ``load_config`` reads
YAML; ``dump_config`` writes the effective configuration back.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any, Literal, TypeVar

import yaml
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from .errors import ConfigError


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True, allow_inf_nan=False)


_M = TypeVar("_M", bound=_Strict)


def _require_order(low_name: str, low: float | None, high_name: str, high: float | None) -> None:
    """Raise a ValueError naming both keys unless ``low < high`` (skipped when either is None)."""
    if low is not None and high is not None and not low < high:
        raise ValueError(f"{low_name} ({low}) must be less than {high_name} ({high})")


def narrow_field(registration: str) -> bool:
    """Whether a run's resolved ``odometry.registration`` is the narrow-field sensors' (voxel_gicp):
    how the stages after the odometry tell a forward-looking solid-state sensor's run (Livox-like)
    from a spinning LiDAR's."""
    return registration == "voxel_gicp"


class OdometryConfig(_Strict):
    """KISS-ICP scan-to-map registration, seeded by wheel odometry when the log has it."""

    registration: Literal["auto", "kiss_icp", "voxel_gicp"] = Field(
        "auto", description="3D scan-to-map registration: kiss_icp (KISS-ICP's point-to-point ICP, for spinning "
        "LiDARs), voxel_gicp (small_gicp's voxelised GICP, coarse to fine from several initial guesses, for "
        "narrow-field solid-state sensors whose non-repetitive pattern never samples the same points twice); "
        "auto: voxel_gicp when the first scan sees less than 180 deg around the vertical axis, else kiss_icp")
    voxel_size: float | None = Field(
        None, gt=0, description="[m]; None: 0.2 for planar (2D laser) logs, 0.5 with voxel_gicp, "
        "max_range / 100 for other 3D"
    )
    max_range: float = Field(80.0, gt=0, description="drop points farther than this [m]")
    min_range: float = Field(0.3, ge=0, description="drop points closer than this [m]")
    max_points_per_voxel: int | None = Field(
        None, ge=1, description="points kept per map voxel; None: 20 for planar logs, 3 for 3D (with the local "
        "map's scans entering movers_delay scans late, 3 points drift less than 1 on the terrain drives: ATE "
        "along KITTI 08 0.144 -> 0.100 m, with 64 rings 0.134 -> 0.079 m, for about 15 % more odometry time; "
        "BENCHMARKS.md)"
    )
    deskew: bool | None = Field(
        None, description="correct each scan's motion during the sweep from its per-point times (a PLY/PCD "
        "time/t/timestamp/offset_time field, a PointCloud2's t/time/timestamp/offset_time); None: on when the "
        "scans carry such times, off otherwise")
    use_wheel_odometry: bool = Field(True, description="wheel odometry as the ICP initial guess")
    planar_point_to_line: bool = Field(
        True, description="2D lasers: refine each pose point-to-line against the last scans (removes the "
        "lag of point-to-point ICP on sparse scans)"
    )
    wheel_check_deg: float = Field(
        5.0, gt=0, description="2D lasers: when the wheel-odometry increment and the constant-velocity one differ "
        "by more than this [deg] (or wheel_check_m), the scan is registered from both and the better fit to the "
        "last scans is kept (stale or jumping wheel poses, as in MIT CSAIL's log, otherwise lead ICP astray)")
    wheel_check_m: float = Field(0.25, gt=0, description="2D lasers: the same in translation [m]")
    gap_ratio: float | None = Field(
        3.0, gt=1, description="without wheel odometry, how the last motion predicts a scan whose interval "
        "since the last differs from the one that motion spans (the scans need their times: a cloud folder "
        "with times.txt, a bag, a CARMEN log): by less than this factor (keyframes 0.2-0.5 s apart), the motion "
        "is carried on at its pace over the interval (voxel_gicp tries the one-interval motion first where it "
        "lies within 2 m of that: a hand-held sensor keeps its pace less than a vehicle); by this factor or more (dropped frames, a recorder's "
        "hiccup, a stop, and the scan after it), the scan is also registered from guesses along the motion "
        "carried over the interval, bent into turns (and no motion, in a keyframed log), and the best replaces "
        "the one-interval guess's registration unless that fits the map clearly better (a log at a steady "
        "rate) or when it fits clearly better (a keyframed log, which pauses where the sensor stood). Without "
        "it, a 16-ring drive without wheels that lost 1, 3 and 2 s of its scans ended 9.7 m off (now 0.10 m), "
        "keyframed drives without wheels 15 m, 81 m and 9.1 m (16 and 64 rings, Livox-like; now 0.10, 0.63 "
        "and 0.02 m; BENCHMARKS.md, stop 69). None: the one-interval motion alone (KISS-ICP's constant-velocity "
        "model)")
    planar_previous_scan_check: bool = Field(
        True, description="2D lasers: a scan that fits the last scans below three quarters of the usual is also "
        "matched to the scan before it (exhaustive correlative search, +-1 m and +-45 deg around the predicted "
        "step), and that pose, refined, is kept when it puts clearly more of the scan on the previous scan's "
        "points. Wheels miss part of a fast turn, registration from them stays near them, and once a scan is off "
        "the map of the last scans holds its error (FR079 at a third of its scan rate: ATE 1.48 -> 0.10 m)")
    startup_refit_scans: int | None = Field(
        None, ge=0, description="once this many scans follow the first, the first is registered again against "
        "them and the run's frame re-based on it; None: 20 for 2D lasers, 30 for 3D LiDARs; 0: never. Registered "
        "against a map of one scan, the first scans carry a shared error that every pose of the run inherits: "
        "2D, a heading error of 0.05-0.08 deg on the rooms world (point-to-line against all of them); 3D, tilts "
        "of up to 1.4 deg a scan on a 16-ring LiDAR at the steep start of a terrain drive (GICP against the scans "
        "registered after the young local map: young_map_scans + movers_delay)")
    young_map_scans: int = Field(
        3, ge=0, description="3D spinning LiDARs (KISS-ICP registration): while the local map holds fewer than this "
        "many scans, a scan registers without its ground band (its lowest ground_band_m): a map of one scan has its "
        "ground rings where the new scan's are, which pulls point-to-point ICP towards no motion (the second scan "
        "of a 9 m/s drive came out 0.36 m short); 0: never")
    ground_band_m: float = Field(0.3, gt=0, description="[m] height of that ground band above the scan's 5th "
                                 "percentile of height (sensor frame)")
    initial_threshold: float = Field(2.0, gt=0)
    min_motion_threshold: float = Field(0.1, ge=0)
    max_iterations: int = Field(500, ge=1)
    convergence_criterion: float | None = Field(
        None, gt=0, description="ICP stops below this pose change; None: 1e-4 for planar logs, 3e-3 for 3D"
    )
    drop_movers: bool = Field(
        False, description="3D LiDAR: leave out of registration what the evidence says moved: the points of a scan "
        "that the last movers_history scans saw through (movers entering), and, in KISS-ICP's local map (each "
        "scan enters it movers_delay scans late), the points the scans before and after saw through (movers "
        "leaving); 2D lasers: not used. Off by default: it doubles the odometry's time per scan and, beside the "
        "delayed local map (movers_delay, on by default), lowered the ATE on one of three 600-scan drives with "
        "80 movers (KITTI 05: 0.215 -> 0.189 m) and not on the others (00: 0.104 -> 0.109, 08: 0.239 -> 0.246)")
    movers_history: int = Field(10, ge=1, description="3D: recent scans (range images) that test each scan for movers")
    movers_delay: int = Field(8, ge=0, description="3D: scans a scan waits before it enters KISS-ICP's local map, so "
                              "that later scans can see through what moved; also with drop_movers off (the odometry "
                              "drifts less when the newest scans are not yet in the map it registers to: 600 scans "
                              "of KITTI 00, ATE 0.148 -> 0.082 m); 0: at once (the behaviour before)")
    movers_delay_s: float | None = Field(
        0.8, ge=0, description="3D: a waiting scan also enters KISS-ICP's local map once the newest scan is this "
        "many seconds later [s]. At 10 Hz movers_delay scans come first; a keyframed log (scans 0.2-0.5 s and "
        "1-6 m apart) waits 2-4 scans: 8 keyframes back the map lay 20-40 m behind, and registering to it shrank "
        "the path by 0.15-0.2 % (keyframed worlds along KITTI 05, 06, 07 and 10: ATE 0.135, 0.244, 0.110 and "
        "0.589 -> 0.078, 0.073, 0.061 and 0.311 m; MulRan KAIST03 0.036 -> 0.029 m; BENCHMARKS.md, stop 68). "
        "A log without times (a cloud folder without times.txt, its scans numbered), or whose scans never come "
        "within twice this of each other (times not in seconds), waits by the count; None: movers_delay scans alone. "
        "Without wheels, a scan that lands on the delayed map far less than the last scans did lets the waiting "
        "scans in at once and registers again (a 64-ring keyframed drive turning into a street the map had not "
        "seen: 89 -> 0.09 m; BENCHMARKS.md, stop 72)")
    movers_views: int = Field(4, ge=1, description="3D: at most this many of those scans test one scan (spread "
                              "over them): the cost per scan")
    separate_process: bool | None = Field(
        None, description="register scans in a child process, a few scans ahead of the graph work (KISS-ICP "
        "holds Python's GIL while it registers, so in one process the two wait for each other); the same "
        "poses either way; None: on for 3D logs, and for 2D lasers when the process may use more than one core"
    )

    @model_validator(mode="after")
    def _range_order(self) -> OdometryConfig:
        _require_order("min_range", self.min_range, "max_range", self.max_range)
        if self.voxel_size is not None and self.voxel_size >= self.max_range:
            raise ValueError(f"voxel_size ({self.voxel_size}) must be less than max_range ({self.max_range})")
        return self


class SubmapConfig(_Strict):
    """How consecutive scans are fused into submaps (virtual sensors)."""

    max_distance: float | None = Field(
        None, gt=0, description="cut after this much travel [m]; None: 5 for planar logs, 12 for 3D"
    )
    min_scans: int | None = Field(
        None, ge=1, description="a submap cut at max_distance holds at least this many scans; None: 10 for 3D "
        "(at highway speed 12 m is 5 scans, and the graph work of a submap, its mover split, registration and "
        "loop tests, outgrew the odometry's: terrain along KITTI 01, 37.8 -> 25.8 s at the same ATE), 1 for "
        "planar logs")
    max_scans: int = Field(400, ge=1)
    voxel_size: float | None = Field(None, gt=0, description="[m]; None: odometry voxel / 2")
    max_points: int = Field(200_000, ge=100)


class LoopConfig(_Strict):
    """Cycle hypotheses: proposal, correspondence test, consistency check."""

    enabled: bool = True
    spatial_sigma: float = Field(3.0, gt=0, description="Mahalanobis gate on anchor distance")
    spatial_min_radius: float | None = Field(
        None, gt=0, description="[m] search radius floor; None: 5 for planar logs, 20 for 3D (3D submaps "
        "see 80 m around: anchors 20 m apart still share most of their view)")
    spatial_max_radius: float = Field(60.0, gt=0, description="[m] search radius ceiling")
    use_descriptor: bool = True
    descriptor_max_distance: float = Field(0.45, gt=0, le=1.0)
    descriptor_radius: float = Field(20.0, gt=0, description="[m] outer ring of the place descriptor")
    descriptor_top_k: int = Field(3, ge=0)
    yaw_window_deg: float = Field(20.0, gt=0, le=180, description="yaw search half-width around a guess")
    min_submap_gap: int = Field(2, ge=1, description="skip neighbours closer than this in the chain")
    min_loop_path_m: float | None = Field(
        None, ge=0, description="[m] a cycle needs at least this much odometry path between the two submaps; "
        "closer pairs are odometry, not cycles. None: 0 for planar logs, 4 submap lengths for 3D")
    max_loop_distance_m: float | None = Field(
        None, gt=0, description="[m] a closure's anchors may be at most this far apart (as registered); "
        "None: no limit for planar logs, 2 submap lengths for 3D (farther pairs share only the edges of "
        "their view and are counted as false closures by the city-scale benchmark)")
    min_structure_overlap: float = Field(
        0.35, ge=0, le=1, description="3D: overlap of the non-ground points (walls, poles, cars) both ways; the "
        "ground of any street matches any other, so overlap over all points does not tell wrong from right")
    max_plane_rmse: float = Field(
        0.25, gt=0, description="[m] 3D: point-to-plane RMSE of the structure inliers after fine registration")
    min_fitness: float = Field(0.45, ge=0, le=1)
    max_inlier_rmse: float = Field(0.15, gt=0)
    min_overlap: float = Field(0.35, ge=0, le=1)
    min_search_window: float = Field(2.0, gt=0, description="[m] translation search half-width floor")
    max_search_window: float = Field(10.0, gt=0, description="[m] translation search half-width cap")
    neighbour_min_overlap: float = Field(0.15, ge=0, le=1, description="adjacent submap overlap that counts as evidence")
    unconfirmed_min_fitness: float = Field(0.85, ge=0, le=1, description="accept without adjacent evidence above this fitness")
    consistency_tolerance_m: float = Field(0.6, gt=0)
    consistency_tolerance_deg: float = Field(4.0, gt=0)
    hints_file: Path | None = None

    @model_validator(mode="after")
    def _window_order(self) -> LoopConfig:
        if self.min_search_window > self.max_search_window:
            raise ValueError(f"min_search_window ({self.min_search_window}) must not exceed max_search_window "
                             f"({self.max_search_window})")
        if self.spatial_min_radius is not None and self.spatial_min_radius > self.spatial_max_radius:
            raise ValueError(f"spatial_min_radius ({self.spatial_min_radius}) must not exceed spatial_max_radius "
                             f"({self.spatial_max_radius})")
        return self


class BackendConfig(_Strict):
    """GTSAM pose graph."""

    robust_kernel: Literal["gnc", "huber", "cauchy", "gm", "none"] = Field(
        "gnc",
        description="loop-edge outlier handling: 'gnc' = Gaussian in iSAM2 (loops are verified "
        "first) + graduated non-convexity (TLS) in the final batch; else an M-estimator everywhere",
    )
    robust_scale: float = Field(3.0, gt=0, description="M-estimator scale [whitened units]")
    gnc_inlier_probability: float = Field(0.99, gt=0, lt=1)
    incremental: bool = Field(True, description="iSAM2 update at every submap")
    final_batch: bool = Field(True, description="Levenberg-Marquardt pass at the end")
    odometry_registration_covariance: bool = Field(
        True, description="shape odometry-edge covariances with a registration between consecutive submaps"
    )
    wheel_drift: float = Field(
        0.02, gt=0, description="[m/m] wheel-odometry translation sigma per metre: where the planar "
        "odometry follows the wheels (degenerate directions), the registration-shaped covariance stops here"
    )
    odometry_drift: float = Field(0.005, gt=0, description="odometry translation sigma per metre")
    odometry_drift_deg_per_m: float | None = Field(
        None, gt=0, description="odometry rotation sigma per metre [deg]; None: 0.1 for planar logs, 0.01 for 3D "
        "(KISS-ICP's published KITTI rotation error is 0.0017 deg/m; a loose model lets a wrong loop bend the "
        "odometry chain at little cost, so the optimiser cannot tell it from a right one)")
    odometry_turn_fraction: float | None = Field(
        None, ge=0, description="odometry rotation sigma as a fraction of the turned angle; None: 0.03 for "
        "planar logs, 0.01 for 3D")
    odometry_tilt_factor: float | None = Field(
        3.0, gt=0, description="3D logs: each odometry edge's roll and pitch sigma is this many times the tilt "
        "by which the registration between consecutive submaps corrects the odometry (a robust RMS over the run "
        "so far, per metre; uncertainty.TiltDrift), where that is below the drift model's: a sensor that holds "
        "its tilt is not outweighed by the ground priors; where the ground is not level and no ground prior is left "
        "at the end (the level test dropped them, or the walls' verticals were the only level priors), the edges' "
        "roll and pitch are weighed like their yaw again. null: the drift model alone")
    odometry_sigma_floor_m: float = Field(0.02, gt=0)
    odometry_sigma_floor_deg: float = Field(0.2, gt=0)
    ground_attitude_sigma_deg: float | None = Field(
        2.0, gt=0, description="3D logs: each submap's ground plane is level in the world within this sigma "
        "[deg] (a soft roll/pitch prior; the world's up is the first submap's ground normal). Without an IMU "
        "the vertical drifts: on a 3.7 km drive scan matching alone climbed 45 m on flat ground. null: off "
        "(e.g. a robot climbing ramps of more than a few degrees)")
    wall_vertical_sigma_deg: float | None = Field(
        0.5, gt=0, description="3D logs from spinning LiDARs: where a submap sees walls facing at least two ways, "
        "its level prior holds the vertical those walls give (mapping.vertical: plumb whatever the road's grade) "
        "within this sigma [deg], instead of its ground plane within ground_attitude_sigma_deg; once a run has "
        "had such a prior (within its first 5 submaps), a submap without walls gets its ground plane's prior against "
        "the walls' up (ground_attitude_sigma_deg). The walls' priors "
        "are not a bet on level ground, so the level test does not take them out (summary.json ground_priors: "
        "level_priors_from, wall_verticals). Narrow-field sensors (voxel_gicp odometry) keep their ground planes. "
        "null: ground planes only (the behaviour before)")
    ground_tilt_change_sigma_deg: float | None = Field(
        0.2, gt=0, description="3D logs: consecutive submaps' ground planes, each seen under its own anchor, "
        "tilt alike within this sigma [deg]: the road's grade and cross-slope change by less than this from one "
        "anchor to the next (~12 m). A soft prior on the relative roll and pitch (a constant slope satisfies it; "
        "the yaw and the positions stay free) that keeps the odometry's small pitch bias from adding up: on three "
        "600-scan drives ATE 0.10-0.24 -> 0.07-0.13 m, the height error most of it. null: off (terrain whose "
        "slope changes sharply, ramps). Not added where the level priors come from the walls "
        "(wall_vertical_sigma_deg), which hold each anchor's tilt themselves")
    ground_tilt_change_from_data: bool = Field(
        True, description="3D logs: the tilt-change prior's sigma is the larger of ground_tilt_change_sigma_deg and "
        "the spread of the tilt changes the run itself sees between consecutive anchors (their ground normals "
        "carried through the odometry; a robust sigma over the pairs so far, less the odometry's own tilt sigma "
        "per edge; uncertainty.TiltChangeSpread): a hilly road or a rough ground plane loosens it, a flat town "
        "keeps it. The priors wait for the first 5 pairs. false: the configured sigma alone")
    ground_priors_level_test: bool = Field(
        True, description="3D logs: at the end of the run, test whether the ground was level (the anchors' "
        "ground normals, carried through the odometry, turn over 3 anchors by more than the odometry's own "
        "tilt sigma can: uncertainty.LevelGroundTest); if it was not, or if too few anchors saw the ground to "
        "tell (fewer than 8 windows, e.g. a hand-held sensor indoors), the ground priors stay only if the loop "
        "closures do not speak against them: near level (ratio <= 3) they may raise the closures' summed "
        "chi-square by 3.84, further from level or untested they must lower it; with no closure they leave "
        "(summary.json: ground_priors). false: the priors always stay")
    ground_prior_kernel: float | None = Field(
        1.0, gt=0, description="3D logs: Cauchy kernel width [whitened units, sigmas] on the ground priors "
        "(attitude and tilt change): a prior the data contradict by many sigmas (a change of grade, a crest, "
        "a road climbing at more than a few degrees) pulls with at most half a sigma instead of bending the "
        "graph, while the odometry's small pitch drift (a fraction of a sigma per submap) is held as before. "
        "null: Gaussian priors (the behaviour before)")
    loop_sigma_floor_m: float = Field(0.05, gt=0)
    loop_sigma_floor_deg: float = Field(0.5, gt=0)
    final_check: bool = Field(
        True, description="after the batch pass, drop loop closures the solution cannot reconcile with the "
        "odometry (whitened residual above the chi-square 99.9 % bound), one at a time, and re-solve. When "
        "the closures agree with each other and one odometry edge or ground prior is what they contradict, "
        "that edge or prior gives way instead (summary.json: final_check); never more than half the closures "
        "are dropped")
    final_check_consensus: int = Field(
        3, ge=1, description="the final check lets an odometry edge or ground prior give way only when at "
        "least this many loop closures remain and all of them fit once it has")

    covariance_scale: tuple[float, float, float, float, float, float] | None = Field(
        None, description="variance scale per axis, GTSAM order (roll, pitch, yaw, x, y, z), applied in each "
        "anchor's frame to the marginal covariances a run reports (submaps.csv, poses_cov.txt, the saved map); "
        "the graph, its estimate and the gates that read its covariances (spatial loop search, plausibility) "
        "are not touched. null: a run that measured its odometry noise reports its estimate's covariance under "
        "that noise (uncertainty.OdometryNoise), other runs the marginals scaled by COVARIANCE_SCALE_PLANAR / "
        "COVARIANCE_SCALE_3D in submapslam/uncertainty.py (fitted with tools/bench_calibration.py, bounded by real "
        "logs); set: every run the marginals scaled by it ([1, 1, 1, 1, 1, 1]: the graph's raw marginals)")

    @field_validator("covariance_scale")
    @classmethod
    def _positive_scale(cls, v):
        if v is not None and not all(0 < x < float("inf") for x in v):
            raise ValueError(f"covariance_scale must be six finite numbers > 0, not {list(v)}")
        return v

    def rotation_drift(self, planar: bool) -> tuple[float, float]:
        """``(deg per metre, fraction of the turned angle)`` of the odometry rotation sigma."""
        per_m = self.odometry_drift_deg_per_m or (0.1 if planar else 0.01)
        turn = self.odometry_turn_fraction if self.odometry_turn_fraction is not None else (0.03 if planar else 0.01)
        return per_m, turn


class MappingConfig(_Strict):
    """Fused output map and evidence grids."""

    map_voxel_size: float | None = Field(
        None, gt=0, description="[m] voxel size of map.ply; None: 0.1 for planar logs, the submap voxel (at "
        "least 0.1) for 3D: the submaps hold nothing finer, and a finer map keeps every submap's copy of a wall")
    grid_resolution: float = Field(0.05, gt=0, description="[m] cell size of occupancy grids from 2D lasers")
    grid_resolution_3d: float = Field(0.2, gt=0, description="[m] cell size of occupancy grids from 3D LiDAR")
    grid_min_height: float = Field(0.3, description="[m] 3D LiDAR: lowest obstacle height above the ground")
    grid_max_height: float = Field(2.0, description="[m] 3D LiDAR: highest obstacle height above the ground")
    grid_ground_z: float | None = Field(
        None, description="[m] 3D LiDAR: ground height in the sensor frame (e.g. -1.7); null estimates it per scan")
    grid_max_free_range_3d: float = Field(
        30.0, gt=0, description="[m] 3D LiDAR: free space is carved along at most this much of a ray")
    grid: GridParams = Field(
        default_factory=lambda: GridParams(), description="evidence model of the occupancy grids (log-odds "
        "per hit and per ray, clearing of what moved); the cell size is grid_resolution / grid_resolution_3d "
        "and, for 3D LiDAR, the free range grid_max_free_range_3d")
    write_grid: bool = True
    grid_process: bool | None = Field(
        None, description="make two of every three submaps' local grids of the final occupancy grid in a "
        "child process while this one makes the rest and fuses them (the same grid to the bit, sooner: the "
        "end's ray tracing on two cores; the child's memory is in summary.json's peak); None: for 2D lasers "
        "when the process may use more than one core (a 3D run's fusion is mostly its cloud: no gain "
        "measured); either way only from 8 submaps on")
    write_pcd: bool = Field(False, description="also write map.pcd (and map_dynamic.pcd): the fused cloud as "
                            "binary PCD, for PCL-based tools (ROS pcl_ros, Autoware, NDT localisers)")
    split_movers: bool = Field(
        True, description="3D LiDAR: each closed submap's voxels that other scans of its window saw through "
        "(clusters, :mod:`submapslam.mapping.moving_points`) leave its cloud (map.ply, place descriptors, "
        "loop registration) for its dynamic cloud (map_dynamic.ply); 2D lasers: not used (their grid "
        "clears what moved)")
    split_floor_cell: float | None = Field(
        None, gt=0, description="[m] 3D mover split on static, hilly ground (off: null): a voxel seen through "
        "within 0.4 m of the submap's own floor (the lowest of its points in this column and those beside "
        "it) casts no free vote; on 600 scans of a terrain town the dynamic share fell 6.0 -> 0.74 %, but "
        "on the labelled mover drive DA fell 0.955 -> 0.931 (BENCHMARKS, 'The submap's own floor')")
    moved_verdict_range: float = Field(
        20.0, ge=0, description="[m] 3D mover split: a map voxel leaves map.ply (for map_dynamic.ply) when at "
        "least as many submaps took it out as moved, each within this distance of its own path, as kept a point "
        "in it: a submap keeps what it has no evidence against, a split's verdict is evidence (a car one submap "
        "saw standing and the next saw drive off). Nearer than the split's 50 m so that far, grazing evidence "
        "does not overrule what nearer submaps saw; 0: a voxel any submap kept stays")

    @model_validator(mode="after")
    def _band_order(self) -> MappingConfig:
        if self.grid_max_height <= self.grid_min_height:
            raise ValueError(f"grid_max_height ({self.grid_max_height}) must exceed grid_min_height "
                             f"({self.grid_min_height})")
        return self


def check_credibility_rates(a: float, b: float) -> None:
    """The credibility learning rate ``a`` and forgetting rate ``b`` divide the counts: both > 0."""
    if not a > 0:
        raise ConfigError(f"credibility learning rate a must be > 0, got {a!r}")
    if not b > 0:
        raise ConfigError(f"credibility forgetting rate b must be > 0, got {b!r}")


class CredibilityParams(_Strict):
    """Credibility of EKF features, ``c = 1 - exp(-(n_s/a - n_u/b))`` (seed eq. 5.70); checked on
    construction (:class:`ConfigError`)."""

    a: float = Field(1.0, description="learning rate (> 0): larger = slower to believe")
    b: float = Field(2.0, description="forgetting rate (> 0): larger = slower to forget")
    remove_below: float = Field(0.05, description="remove a feature whose credibility falls below this, in [0, 1]")
    min_observations: int = Field(1, description="a feature must be seen this often before removal is considered")
    min_chances: int = Field(1, ge=1, description="removal is considered only once the feature had this many chances to "
                             "be seen (sightings + misses): a newborn feature missed once is not removed at once, "
                             "clutter seen once still goes")
    memory: float = Field(1.0, gt=0.0, le=1.0, description="n_s and n_u are multiplied by this each time the feature "
                          "is matched or missed (1: the seed's counts, never forgotten; 0.95: about the last 20 chances "
                          "count, so removal takes a bounded number of misses)")

    @model_validator(mode="before")
    @classmethod
    def _rates(cls, data: Any) -> Any:
        if isinstance(data, dict):  # raw values, so the message shows what was given
            a, b, rb = data.get("a", 1.0), data.get("b", 1.0), data.get("remove_below", 0.0)  # only given ones
            if isinstance(a, int | float) and isinstance(b, int | float):
                check_credibility_rates(a, b)
            if isinstance(rb, int | float) and not 0.0 <= rb <= 1.0:
                raise ConfigError(f"credibility remove_below must be in [0, 1], got {rb!r}")
            memory = data.get("memory", 1.0)
            if isinstance(memory, int | float) and not 0.0 < memory <= 1.0:
                raise ConfigError(f"credibility memory must be in (0, 1], got {memory!r}")
        return data


class EkfCredibility(CredibilityParams):
    """:class:`CredibilityParams` with the defaults of ``submapslam ekf``: features are never
    forgotten nor removed unless told otherwise."""

    b: float = Field(1e9, description="forgetting rate (> 0): larger = slower to forget")
    remove_below: float = Field(0.0, description="remove a feature whose credibility falls below this, in [0, 1]")


class EkfConfig(_Strict):
    """The stochastic-map (EKF) reference of ``submapslam ekf``."""

    credibility: EkfCredibility = Field(default_factory=EkfCredibility)


class GridParams(_Strict):
    """Evidence (log-odds occupancy) grids: one per submap, fused into the global grid."""

    resolution: float = Field(0.05, gt=0, description="[m] cell size")
    l_occ: float = Field(0.85, description="log-odds added at a hit")
    l_free: float = Field(-0.4, description="log-odds added along a ray")
    l_min: float = -4.0
    l_max: float = 4.0
    free_confidence: float = Field(-1.5, description="local log-odds below this count as confidently free")
    occupied_threshold: float = Field(0.6, description="global log-odds above this are 'occupied'")
    clear_margin_cells: int = Field(2, ge=0, description="a clearing cell needs this many free cells around it")
    max_free_range: float = Field(12.0, gt=0, description="[m] free space is carved along at most this much of a ray")
    free_scan_stride: int = Field(2, ge=1, description="carve free space with every n-th scan of a submap")
    recent_free_observations: int = Field(
        3, ge=0, description="a cell that a submap saw free this many times since its last hit there, as did "
        "the 8 cells around it, is free in the global grid whatever came before (a door that opened, a box taken "
        "away while the submap was being built: the summed evidence may still say occupied); 0: off")

    @model_validator(mode="after")
    def _evidence_signs(self) -> GridParams:
        if self.l_occ <= 0:
            raise ValueError(f"l_occ ({self.l_occ}) must be positive: a hit is evidence of an obstacle")
        if self.l_free >= 0:
            raise ValueError(f"l_free ({self.l_free}) must be negative: a ray is evidence of free space")
        _require_order("l_min", self.l_min, "l_max", self.l_max)
        return self


MappingConfig.model_rebuild()  # its ``grid`` field refers to GridParams, defined above


class LocalizationConfig(_Strict):
    """Localization in a fixed map (``submapslam localize``).

    ``voxel_size`` / ``inlier_distance`` default (None) to 0.05 / 0.2 m for planar maps and
    0.4 / 0.8 m for 3D maps.
    """

    min_range: float = Field(0.1, ge=0, description="[m] drop closer scan points")
    max_range: float = Field(80.0, gt=0, description="[m] drop farther scan points")
    voxel_size: float | None = Field(None, gt=0, description="[m] scan (and 3D map) downsampling")
    inlier_distance: float | None = Field(
        None, gt=0, description="[m] a scan point is an inlier if a map point is this close")
    mapped_distance: float | None = Field(
        None, gt=0, description="[m] 3D: scan points farther than this from any map point are unmapped space, "
        "left out of fitness_mapped (default 5 x inlier)")
    see_through: float = Field(
        0.5, ge=0, description="[m] planar: a beam reaching this far past a mapped wall contradicts the map")
    beam_width: float = Field(
        0.0087, gt=0, description="[rad] planar: bearing bins of the map rendered from the pose (0.5 deg)")
    min_fitness: float = Field(0.75, ge=0, le=1, description="consistency gate on fitness_mapped (inliers among "
                               "the mapped points)")
    min_mapped_fraction: float = Field(
        0.25, ge=0, le=1, description="below this fraction of scan points in the mapped area the gate cannot "
        "judge: the local fit is kept (looking at unmapped space)")
    max_correction: float = Field(0.5, gt=0, description="[m] a local fit moving the prediction farther is "
                                  "inconsistent")
    max_correction_yaw: float = Field(0.35, gt=0, description="[rad] same for the heading")
    lost_after: int = Field(5, ge=1, description="consecutive inconsistent scans before 'lost'")
    local_window: int = Field(
        20, ge=1, description="recent tracked scans kept as a local target for unmapped space")
    local_rebuild_every: int = Field(5, ge=1, description="rebuild that local target every this many tracked scans")
    relocalize_min_fitness: float = Field(0.7, ge=0, le=1, description="a global-search fix must reach this fitness")
    max_ambiguity: float = Field(
        0.9, gt=0, le=1, description="planar global search: second place / best place at most this")
    global_scans: int = Field(10, ge=1, description="scans fused (dead reckoning) into the global-search cloud")
    relocalize_every: int = Field(
        5, ge=1, description="before the first fix (after the first global_scans scans) and while lost, retry the "
        "global search at most every this many scans")
    global_time_budget: float = Field(
        0.25, ge=0, le=1, description="... and only while global searches took at most this fraction of the "
        "wall time so far (they never run while tracking)")
    use_wheel_odometry: bool = Field(True, description="predict from Scan.odometry when the log has it")
    min_consistent_fraction: float = Field(
        0.5, ge=0, le=1, description="the log counts as localised in the map when at least this share of its "
        "scans is tracked with the mapped area explained (fitness_mapped >= min_fitness); else 'not localised'")

    @model_validator(mode="after")
    def _range_order(self) -> LocalizationConfig:
        _require_order("min_range", self.min_range, "max_range", self.max_range)
        return self


class SessionConfig(_Strict):
    """Several sessions in one map: placing a new session (unknown start) against the map."""

    descriptor_top_k: int = Field(5, ge=1, description="map submaps tested per session submap by place recognition")
    descriptor_max_distance: float = Field(
        0.8, gt=0, le=1.0, description="place-recognition candidates up to this descriptor distance (looser than "
        "loops': there is no pose to propose by, and every candidate is verified and must agree with others)")
    max_recognition_tests: int = Field(
        300, ge=1, description="cap on place-recognition tests per session (each a correspondence test)")
    min_links: int = Field(
        3, ge=1, description="session submaps with verified, mutually consistent links to the map needed to "
        "place a session (links of one session submap count once)")
    min_candidate_links: int = Field(
        2, ge=1, description="a group of consistent place-recognition links from this many session submaps is a "
        "candidate placement, tried by the guided search (which must then confirm it from min_links session "
        "submaps); capped by min_links. Only when place recognition tested every hypothesis it had (not stopped "
        "by max_recognition_tests), and only when no other candidate is confirmed too")
    max_candidates: int = Field(
        4, ge=1, description="groups of consistent place-recognition links tried by the guided search, best first, "
        "per session and try (weaker groups than min_candidate_links only tell whether a candidate is ambiguous)")
    enough_links: int = Field(
        6, ge=1, description="stop place recognition once consistent links come from this many session submaps")
    min_agreement: float = Field(
        0.3, ge=0, le=1, description="share of the session submaps a placement puts on the map that must be "
        "verified there (a false placement by look-alike places is contradicted by the rest of the session)")
    guided_per_submap: int = Field(
        3, ge=0, description="nearest map submaps tested per session submap by the guided search (2 confirmed the "
        "right placement of the third Intel piece by 28-31 % of its session submaps, at the edge of min_agreement; "
        "3: 42 %, in about the same time, since fewer candidates are tried)")
    guided_passes: int = Field(
        3, ge=1, description="rounds of the guided search per candidate placement; each later round searches "
        "through the links the one before found (the session's own drift bends its frame along the way); "
        "stops early when a round links no new session submap")
    densify_passes: int = Field(
        3, ge=0, description="rounds of (search near the optimised estimate, optimise) after a placement; "
        "stops early when a round adds no link")
    densify_per_submap: int = Field(
        3, ge=0, description="after a placement and optimisation, nearest map submaps tested per session submap")
    consistency_tolerance_m: float = Field(1.0, gt=0, description="[m] two links agree when they place the session "
                                           "submaps within this (plus consistency_per_m of the path between them)")
    consistency_per_m: float = Field(0.02, ge=0, description="[m/m] tolerance growth with the session path")
    consistency_tolerance_deg: float = Field(5.0, gt=0, description="[deg] rotation tolerance between links")
    start_prior_sigma_m: float = Field(
        100.0, gt=0, description="[m] weak prior on each later session's first anchor (keeps an unplaced session "
        "in its own frame; negligible for a placed one)")


class ScanRefineConfig(_Strict):
    """2D lasers: scan-level refinement after the submap solve (:mod:`submapslam.scan_refine`)."""

    enabled: bool = Field(True, description="2D lasers: after the submap solve, keyframe scans become nodes of "
                          "a planar pose graph with odometry between them and scan-to-submap matches against the "
                          "other submaps near them, so every scan (not only each submap's anchor) takes the final "
                          "map's accuracy; 3D logs: not used")
    keyframe_step_m: float = Field(0.3, gt=0, description="[m] a keyframe every this much odometry travel")
    keyframe_step_deg: float = Field(10.0, gt=0, description="[deg] or this much turn")
    rounds: int = Field(1, ge=1, description="match, solve; repeated from the new estimate")
    match_radius_m: float = Field(5.0, gt=0, description="[m] a keyframe is matched against the submaps whose "
                                  "scans passed within this distance of it")
    max_submaps_per_scan: int = Field(3, ge=1, description="at most this many (the nearest)")
    max_scan_points: int = Field(80, ge=20, description="each keyframe matched with at most this many of its "
                                 "points (evenly spread over the scan)")
    grid_cell_m: float = Field(0.1, gt=0, description="[m] cell of each submap's nearest-point lookup grid")
    max_correspondence_m: float = Field(0.3, gt=0, description="[m] first point-to-line correspondence distance")
    min_fitness: float = Field(0.5, ge=0, le=1, description="share of scan points within 0.1 m of the submap")
    max_inlier_rmse_m: float = Field(0.05, gt=0, description="[m] point-to-line RMSE of the matched points")
    max_correction_m: float = Field(0.3, gt=0, description="[m] a match farther than this from the estimate is dropped")
    max_correction_deg: float = Field(3.0, gt=0, description="[deg] the same in rotation")
    match_sigma_floor_m: float = Field(0.01, gt=0, description="[m] a match's translation is trusted no further")
    match_sigma_floor_deg: float = Field(
        1.0, gt=0, description="[deg] a match's rotation is trusted no further: the odometry between keyframes holds "
        "the rotation better (a floor of 0.2 deg made the derived relations of Intel worse, 0.425 -> 0.429 deg)")
    odometry_sigma_m: float = Field(0.005, gt=0, description="[m] odometry between keyframes: sigma floor")
    odometry_drift: float = Field(0.02, gt=0, description="[m/m] plus this per metre travelled")
    odometry_sigma_deg: float = Field(0.1, gt=0, description="[deg] rotation sigma floor")
    odometry_turn_fraction: float = Field(0.02, ge=0, description="plus this fraction of the turned angle")
    anchor_sigma_m: float | None = Field(0.01, gt=0, description="[m] each submap anchor held at its pose from the "
                                         "submap solve within this sigma; None: free")
    anchor_sigma_deg: float = Field(0.1, gt=0, description="[deg] the same in rotation")
    anchor_bend_factor: float = Field(
        1.0, ge=0, description="an anchor's prior sigmas are at least this times how far the submap solve bent the "
        "odometry between it and its neighbouring anchors [m, rad]: where the loops bent the chain the anchor "
        "gives way to the scans' matches (MIT CSAIL 0.132 -> 0.125 m, FR079 0.0665 -> 0.0651 m, Intel 0.0609 -> "
        "0.0608 m); 0: every anchor held alike")
    anchor_kernel: float | None = Field(
        1.0, gt=0, description="Cauchy width [whitened units] of those anchor priors: an anchor the scans' matches "
        "contradict by many sigmas (an odometry edge of the submap graph that went wrong) gives way; None: Gaussian")
    kernel: float = Field(2.0, gt=0, description="Cauchy width of the match factors [whitened units]")


class PipelineConfig(_Strict):
    """The whole run."""

    odometry: OdometryConfig = Field(default_factory=OdometryConfig)
    submaps: SubmapConfig = Field(default_factory=SubmapConfig)
    loops: LoopConfig = Field(default_factory=LoopConfig)
    backend: BackendConfig = Field(default_factory=BackendConfig)
    mapping: MappingConfig = Field(default_factory=MappingConfig)
    scan_refinement: ScanRefineConfig = Field(default_factory=ScanRefineConfig)
    max_scans: int | None = Field(None, ge=1, description="stop after this many scans")
    checkpoint_every_submaps: int | None = Field(
        20, ge=1, description="keep a checkpoint beside OUT every this many submaps (and when interrupted) for "
        "`run --resume OUT`; removed when the run ends; None: never")
    localization: LocalizationConfig = Field(
        default_factory=LocalizationConfig, description="`localize` in a fixed map (not used by `run`)")
    ekf: EkfConfig = Field(default_factory=EkfConfig, description="the `ekf` command (not used by `run`)")
    sessions: SessionConfig = Field(
        default_factory=SessionConfig, description="several logs in one map (`run LOG1 LOG2`, `run --map`, `batch`)")


def _format_validation_error(exc: ValidationError, source: str) -> str:
    first = exc.errors()[0]
    loc = ".".join(str(p) for p in first["loc"]) or "<root>"
    if first["type"] == "extra_forbidden":
        return f"{source}: unknown config key {loc!r}"
    return f"{source}: config key {loc!r}: {first['msg']}"


def config_from_dict(data: dict[str, Any] | None, source: str = "<config>") -> PipelineConfig:
    """Validate a plain dict into a :class:`PipelineConfig`; raise :class:`ConfigError`."""
    try:
        return PipelineConfig.model_validate(data or {})
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def validated(model: type[_M], source: str = "<options>", **values: Any) -> _M:
    """``model(**values)``, with a validation error as one :class:`ConfigError` line naming the key."""
    try:
        return model.model_validate(values)
    except ValidationError as exc:
        raise ConfigError(_format_validation_error(exc, source)) from None


def with_overrides(section: _M, source: str = "<options>", **values: Any) -> _M:
    """A copy of the config ``section`` with the ``values`` that are not None (e.g. command-line
    options given) replacing its own, validated (:class:`ConfigError`)."""
    given = {k: v for k, v in values.items() if v is not None}
    return validated(type(section), source, **{**section.model_dump(), **given})


def _deep_merge(base: dict[str, Any], updates: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in updates.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = _deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def with_updates(config: _M, updates: dict[str, Any], source: str = "<options>") -> _M:
    """A copy of ``config`` with the nested ``updates`` (``{"loops": {"enabled": False}}``)
    merged in and the whole validated again, relations between values included
    (:class:`ConfigError`). ``model_copy(update=...)`` would skip the validation."""
    return validated(type(config), source, **_deep_merge(config.model_dump(), updates))


def load_config(path: str | Path | None) -> PipelineConfig:
    """Read a YAML config file (``None``: defaults)."""
    if path is None:
        return PipelineConfig()
    path = Path(path)
    try:
        text = path.read_text()
        data = yaml.safe_load(text)
    except FileNotFoundError:
        raise ConfigError(f"{path}: no such config file") from None
    except IsADirectoryError:
        raise ConfigError(f"{path}: cannot read the config file (it is a folder)") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read the config file ({exc.__class__.__name__})") from None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
        where = f"{path}:{mark.line + 1}" if mark is not None else f"{path}"
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ConfigError(f"{where}: not valid YAML ({problem})") from None
    if data is not None and not isinstance(data, dict):
        raise ConfigError(f"{path}: a config file must be a YAML mapping")
    try:
        return PipelineConfig.model_validate(data or {})
    except ValidationError as exc:
        line = _yaml_line(text, exc.errors()[0]["loc"])
        raise ConfigError(_format_validation_error(exc, f"{path}:{line}" if line else str(path))) from None


def _yaml_line(text: str, loc: tuple) -> int | None:
    """1-based line of the deepest key along ``loc`` (a validation error's path) in YAML ``text``."""
    try:
        node = yaml.compose(text, Loader=yaml.SafeLoader)
    except yaml.YAMLError:
        return None
    line = None
    for part in loc:
        if not isinstance(node, yaml.MappingNode):
            break
        for key, value in node.value:
            if isinstance(key, yaml.ScalarNode) and key.value == str(part):
                line, node = key.start_mark.line + 1, value
                break
        else:
            break
    return line


def dump_config(config: PipelineConfig, comments: bool = False) -> str:
    """The config as YAML text (every key, defaults included); ``comments``: each section and key
    preceded by what it means (the models' docstrings and field descriptions) as ``#`` lines."""
    if not comments:
        return yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False)
    return "\n".join(_commented(config, 0)) + "\n"


def _commented(model: BaseModel, depth: int) -> list[str]:
    """YAML lines of ``model`` with a comment above every field (recursing into sub-models)."""
    import textwrap

    pad = "  " * depth
    lines: list[str] = []
    for name, info in type(model).model_fields.items():
        value = getattr(model, name)
        text = info.description or (type(value).__doc__ if isinstance(value, BaseModel) else None) or ""
        text = " ".join(text.split())
        if isinstance(value, BaseModel) and depth == 0 and lines:
            lines.append("")
        lines += [f"{pad}# {ln}" for ln in textwrap.wrap(text, max(40, 98 - len(pad)), break_on_hyphens=False)]
        if isinstance(value, BaseModel):
            lines.append(f"{pad}{name}:")
            lines += _commented(value, depth + 1)
        else:
            dumped = yaml.safe_dump({name: model.model_dump(mode="json")[name]}, sort_keys=False).rstrip("\n")
            lines += [pad + ln for ln in dumped.splitlines()]
    return lines
