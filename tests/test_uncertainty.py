"""The uncertainty a run reports: the per-axis calibration and the per-scan covariances."""

from types import SimpleNamespace

import numpy as np
import pytest

from submapslam.config import BackendConfig, PipelineConfig
from submapslam.errors import ConfigError
from submapslam.geometry import adjoint, inverse
from submapslam.uncertainty import (
    COVARIANCE_SCALE_3D,
    COVARIANCE_SCALE_PLANAR,
    TiltDrift,
    calibrate,
    covariance_scale,
    odometry_information,
    scan_covariances,
)


def test_calibration_scales_variances_per_axis_and_keeps_correlations():
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    cov[3, 4] = cov[4, 3] = 2.0
    out = calibrate(cov, np.array([1.0, 1.0, 4.0, 0.25, 9.0, 1.0]))
    np.testing.assert_allclose(np.diag(out), [1.0, 2.0, 12.0, 1.0, 45.0, 6.0])
    rho = lambda c: c[3, 4] / np.sqrt(c[3, 3] * c[4, 4])  # noqa: E731
    assert rho(out) == pytest.approx(rho(cov))
    assert np.all(np.linalg.eigvalsh(out) > 0)


def test_scale_defaults_per_kind_of_log_and_config_override():
    np.testing.assert_allclose(covariance_scale(BackendConfig(), True), COVARIANCE_SCALE_PLANAR)
    np.testing.assert_allclose(covariance_scale(BackendConfig(), False), COVARIANCE_SCALE_3D)
    raw = BackendConfig(covariance_scale=[1, 1, 1, 1, 1, 1])
    np.testing.assert_allclose(covariance_scale(raw, True), np.ones(6))
    with pytest.raises((ConfigError, ValueError), match="covariance_scale"):
        BackendConfig(covariance_scale=[1, 1, 1, -1, 1, 1])


def test_scan_covariance_carries_the_anchor_and_grows_along_the_submap():
    """A submap driving 10 m along x: the anchor's scan has the anchor's marginal; 10 m ahead
    the anchor's yaw sigma becomes lateral (y) sigma 10 m x sigma_yaw, plus the drift model."""
    config = PipelineConfig(backend=BackendConfig(covariance_scale=[1, 1, 1, 1, 1, 1]))
    anchor_cov = np.diag([1e-8, 1e-8, np.deg2rad(1.0) ** 2, 0.01, 0.01, 1e-8])
    T_scans = np.tile(np.eye(4), (11, 1, 1))
    T_scans[:, 0, 3] = np.arange(11.0)
    result = SimpleNamespace(submap_covariances=anchor_cov[None], config=config, planar=True,
                             poses=T_scans.copy(), submap_scan_indices=[list(range(11))], submap_scan_poses=[T_scans])
    covs = scan_covariances(result)
    assert covs.shape == (11, 6, 6)
    np.testing.assert_allclose(covs[0], anchor_cov, atol=1e-15)
    var_y = covs[:, 4, 4]
    assert np.all(np.diff(var_y) > 0)
    lever = 100.0 * np.deg2rad(1.0) ** 2  # (10 m)^2 sigma_yaw^2
    assert lever + 0.01 < var_y[-1] < 1.5 * (lever + 0.01)
    assert covs[-1, 3, 3] > 0.01  # x: the anchor's plus the drift over 10 m
    scaled = scan_covariances(SimpleNamespace(**{**vars(result), "config": PipelineConfig(
        backend=BackendConfig(covariance_scale=[1, 1, 1, 4, 4, 1]))}))
    # the anchors' marginals come calibrated (the pipeline scales them): only the drift share is scaled here
    np.testing.assert_allclose(scaled[0], anchor_cov, atol=1e-15)
    np.testing.assert_allclose(scaled[-1, 3, 3] - 0.01, 4 * (covs[-1, 3, 3] - 0.01))
    per_m = np.array([1e-6, 2e-6, 3e-8, 1e-4, 5e-5, 2e-5])
    measured = scan_covariances(SimpleNamespace(**{**vars(result), "covariance_model": {"variance_per_m": per_m}}))
    # a run that measured its odometry noise: that noise over the distance from the anchor, whatever the scale
    A = adjoint(inverse(T_scans[-1]))  # the anchor's covariance carried 10 m ahead
    np.testing.assert_allclose(measured[-1], A @ anchor_cov @ A.T + np.diag(per_m * 10.0), rtol=1e-9, atol=1e-15)
    result.submap_covariances = np.full((1, 6, 6), np.nan)  # a failed final optimisation: no covariances
    assert scan_covariances(result) is None


def _tilt(roll_deg: float, pitch_deg: float) -> np.ndarray:
    from submapslam.geometry import so3_exp

    T = np.eye(4)
    T[:3, :3] = so3_exp(np.deg2rad([roll_deg, pitch_deg, 0.0]))
    T[0, 3] = 12.0
    return T


def test_tilt_drift_is_measured_from_the_registration_and_ignores_a_few_bad_ones():
    """Registrations that tilt the odometry by N(0, s sqrt(d)) per axis: the estimate is
    ``factor`` s within 15 %, also with every tenth registration 10x off; nothing before
    ``min_edges`` edges; never below the floor."""
    rng = np.random.default_rng(3)
    per_sqrt_m = np.deg2rad(0.03)  # 0.1 deg over 12 m
    for outliers in (False, True):
        drift = TiltDrift(factor=2.0)
        for k in range(200):
            dist = rng.uniform(8.0, 14.0)
            roll, pitch = rng.normal(0.0, np.rad2deg(per_sqrt_m) * np.sqrt(dist), 2) * (10 if outliers and k % 10 == 0
                                                                                       else 1)
            correction = TiltDrift.correction(_tilt(0.0, 0.0), _tilt(roll, pitch))
            np.testing.assert_allclose(correction, np.deg2rad([roll, pitch]), atol=1e-9)
            drift.add(correction, dist)
            if k < drift.min_edges - 1:
                assert drift.sigma(12.0) is None and drift.summary()["sigma_deg_over_12_m"] is None
        assert drift.per_sqrt_metre() == pytest.approx(2.0 * per_sqrt_m, rel=0.15)
        assert drift.sigma(12.0) == pytest.approx(2.0 * per_sqrt_m * np.sqrt(12.0), rel=0.15)
    still = TiltDrift(factor=2.0)
    for _ in range(10):
        still.add(np.zeros(2), 12.0)
    assert still.sigma(12.0) == still.floor_rad


def test_odometry_tilt_sigma_only_tightens_roll_and_pitch():
    config = BackendConfig()
    T = _tilt(0.0, 0.0)
    model = odometry_information(T, 12.0, False, config)
    tight = odometry_information(T, 12.0, False, config, tilt_sigma=np.deg2rad(0.03))
    np.testing.assert_allclose(np.diag(tight)[:2], [1 / np.deg2rad(0.03) ** 2] * 2)
    np.testing.assert_allclose(np.diag(tight)[2:], np.diag(model)[2:])  # yaw and translation: the model's
    loose = odometry_information(T, 12.0, False, config, tilt_sigma=np.deg2rad(5.0))
    np.testing.assert_allclose(loose, model)  # never looser than the model
    planar = odometry_information(T, 12.0, True, config, tilt_sigma=np.deg2rad(0.03))
    np.testing.assert_allclose(planar, odometry_information(T, 12.0, True, config))  # pinned anyway


def test_a_measured_tilt_drift_keeps_real_grades_the_priors_would_flatten():
    """A drive over hills (the grade swings +-1.5 deg over 288 m, changing by up to 0.4 deg from
    one anchor to the next) with an odometry that tilts 0.02 deg wrong per edge, as a 64-ring sensor's does,
    and the ground priors at their defaults. Weighed against the drift model (0.3 deg) the priors
    bend the chain towards a flat world; with the odometry's measured tilt sigma the heights are
    the odometry's own."""
    from submapslam.backend.pose_graph import PoseGraph
    from submapslam.geometry import inverse, so3_exp

    n, step = 60, 12.0
    grade = np.deg2rad(1.5) * np.sin(np.arange(n) * 2 * np.pi / 24)
    truth = [np.eye(4)]
    for k in range(1, n):
        T = np.eye(4)
        T[:3, :3] = so3_exp([0.0, -(grade[k] - grade[k - 1]), 0.0])
        T[0, 3] = step
        truth.append(truth[-1] @ T)
    noise = np.random.default_rng(1)
    measured = []
    for k in range(1, n):
        err = np.eye(4)
        err[:3, :3] = so3_exp(np.deg2rad(noise.normal(0.0, 0.02, 3)))
        measured.append(inverse(truth[k - 1]) @ truth[k] @ err)
    dead_reckoned = [np.eye(4)]
    for meas in measured:
        dead_reckoned.append(dead_reckoned[-1] @ meas)
    odometry_error = max(abs(a[2, 3] - b[2, 3]) for a, b in zip(dead_reckoned, truth))
    config = BackendConfig(robust_kernel="none")
    up = np.array([0.0, 0.0, 1.0])  # the ground straight below each anchor
    height_error = {}
    for name, tilt_sigma in (("model", None), ("measured", np.deg2rad(2.0 * 0.02))):
        g = PoseGraph(config)
        g.add_node(0, truth[0], np.diag([1e8] * 6))
        for k, meas in enumerate(measured, start=1):
            g.add_node(k, g.pose(k - 1) @ meas)
            g.add_between(k - 1, k, meas, odometry_information(meas, step, False, config, tilt_sigma), "odometry")
            g.add_attitude(k, up, up, np.deg2rad(config.ground_attitude_sigma_deg))
            g.add_relative_attitude(k - 1, k, up, up, meas, np.deg2rad(config.ground_tilt_change_sigma_deg))
        g.update()
        g.optimize_batch()
        height_error[name] = max(abs(g.pose(k)[2, 3] - truth[k][2, 3]) for k in range(n))
    assert np.ptp([T[2, 3] for T in truth]) > 2.0  # hills
    assert height_error["measured"] < 1.5 * odometry_error + 0.1, (height_error, odometry_error)
    assert height_error["model"] > 2.0 * height_error["measured"], height_error


def test_tilt_change_spread_recovers_the_ground_normals_spread_above_its_floor():
    """Ground normals whose tilt from one anchor to the next is off by sigma per axis give back
    sigma; a spread below the floor keeps the floor; nothing before 5 pairs; the odometry's own
    tilt sigma is taken out."""
    from submapslam.geometry import so3_exp
    from submapslam.uncertainty import TiltChangeSpread

    rng = np.random.default_rng(5)
    for sigma_deg, want_deg in ((0.8, 0.8), (0.05, 0.2)):
        spread = TiltChangeSpread(np.deg2rad(0.2))
        for k in range(400):
            if k == 4:
                assert spread.sigma() is None
            T = np.eye(4)
            T[:3, :3] = so3_exp(np.deg2rad([0.0, 0.0, rng.uniform(-20, 20)]))  # any turn between the anchors
            up = so3_exp(np.deg2rad(np.r_[rng.normal(0.0, sigma_deg, 2), 0.0])) @ np.array([0.0, 0.0, 1.0])
            spread.add(TiltChangeSpread.observed(np.array([0.0, 0.0, 1.0]), T[:3, :3].T @ up, T))
        assert np.rad2deg(spread.sigma()) == pytest.approx(want_deg, rel=0.15)
        assert spread.summary(None)["pairs"] == 400
    # the odometry's own tilt error is taken out of the spread (the prior is there to correct it)
    rough = np.deg2rad(0.8)
    spread.angles = [rough * np.sqrt(2.0 * np.log(2.0))] * 10
    assert spread.sigma(np.deg2rad(0.6)) == pytest.approx(np.sqrt(rough**2 - np.deg2rad(0.6) ** 2))
    assert spread.sigma(np.deg2rad(1.0)) == spread.floor_rad


def _ground_submap(k: int, step: float, up: np.ndarray):
    """A fake submap ``k`` of a straight drive along x (``step`` m apart): a 30 x 30 m ground patch
    around its anchor whose normal is ``up`` ``(3,)`` in the anchor's frame, 1.7 m below it."""
    g = np.stack(np.meshgrid(np.linspace(-15, 15, 31), np.linspace(-15, 15, 31)), -1).reshape(-1, 2)
    z = -1.7 - (up[0] * g[:, 0] + up[1] * g[:, 1]) / up[2]
    T = np.eye(4)
    T[0, 3] = k * step
    return SimpleNamespace(id=k, T_odom_anchor=T, points=np.c_[g, z], distance=step, T_anchor_scans=np.eye(4)[None])


def test_tilt_change_priors_take_the_runs_own_spread_and_stop_bending_a_good_odometry():
    """A level straight drive with a perfect odometry, whose ground planes are rough (each
    normal 1 deg off): the tilt-change priors at the configured 0.2 deg bend the early odometry
    edges (still on the drift model) by tenths of a degree; measured from the run (held back
    until 5 pairs, then at the pairs' spread) they leave it within hundredths. A run with fewer
    pairs still gets its priors, at the configured sigma."""
    from submapslam.config import OdometryConfig
    from submapslam.geometry import inverse, so3_exp, so3_log
    from submapslam.graph_builder import GraphBuilder

    rng = np.random.default_rng(2)
    n, step = 14, 12.0
    ups = [so3_exp(np.deg2rad(np.r_[rng.normal(0.0, 1.0, 2), 0.0])) @ np.array([0.0, 0.0, 1.0]) for _ in range(n)]
    submaps = [_ground_submap(k, step, ups[k]) for k in range(n)]
    bend = {}
    for from_data in (False, True):
        # no closures and no registration: the level test could not tell, and would take the priors
        # out (test_ground_priors.py); here they stay, to see what their sigma does
        config = BackendConfig(odometry_registration_covariance=False, ground_tilt_change_from_data=from_data,
                               ground_attitude_sigma_deg=None, robust_kernel="none", ground_priors_level_test=False)
        builder = GraphBuilder(config, OdometryConfig(), planar=False, match_voxel=0.5)
        counts = []
        for k, sm in enumerate(submaps):
            builder.add_submap(sm, submaps[k - 1] if k else None, False)
            counts.append(sum(kind == "ground tilt-change prior" for kind, *_ in builder.graph._priors.values()))
        builder.finish()
        if from_data:
            assert counts[:5] == [0] * 5 and counts[5] == 5 and counts[-1] == n - 1  # held, then all added
            assert builder.tilt_change_summary()["sigma_deg"] > 0.5
        else:
            assert counts == list(range(n))
        bend[from_data] = max(np.rad2deg(np.linalg.norm(so3_log(
            (inverse(builder.graph.pose(k - 1)) @ builder.graph.pose(k))[:3, :3]))) for k in range(1, n))
    assert bend[False] > 0.1 and bend[True] < 0.5 * bend[False], bend

    short = GraphBuilder(BackendConfig(odometry_registration_covariance=False), OdometryConfig(), planar=False,
                         match_voxel=0.5)
    for k, sm in enumerate(submaps[:3]):
        short.add_submap(sm, submaps[k - 1] if k else None, False)
    short.finish()
    assert sum(kind == "ground tilt-change prior" for kind, *_ in short.graph._priors.values()) == 2


def test_refined_planar_scans_between_two_anchors_grow_as_a_bridge():
    """Scans refined between their submap's anchor and the next: the measured noise over
    ``d1 d2 / (d1 + d2)`` (zero at both anchors, a quarter of the walk midway), not ``d1``; the
    last submap, open at its end, and an unrefined run keep the walk from the anchor."""
    anchor_cov = np.diag([1e-8, 1e-8, 1e-6, 1e-4, 1e-4, 1e-8])
    T_scans = np.tile(np.eye(4), (11, 1, 1))
    T_scans[:, 0, 3] = np.arange(11.0)  # 10 m along x, the last scan the next submap's anchor
    per_m = np.array([1e-6, 2e-6, 3e-8, 1e-4, 5e-5, 2e-5])
    result = SimpleNamespace(submap_covariances=np.stack([anchor_cov, anchor_cov]), config=PipelineConfig(),
                             planar=True, poses=np.tile(np.eye(4), (21, 1, 1)),
                             submap_scan_indices=[list(range(11)), list(range(10, 21))],
                             submap_scan_poses=[T_scans, T_scans], covariance_model={"variance_per_m": per_m},
                             scan_refinement={"keyframes": 7})
    covs = scan_covariances(result)
    A = adjoint(inverse(T_scans[5]))
    carried = A @ anchor_cov @ A.T
    np.testing.assert_allclose(covs[5], carried + np.diag(per_m * 2.5), rtol=1e-9, atol=1e-15)  # 5 * 5 / 10
    np.testing.assert_allclose(covs[15], carried + np.diag(per_m * 5.0), rtol=1e-9, atol=1e-15)  # open end
    unrefined = scan_covariances(SimpleNamespace(**{**vars(result), "scan_refinement": {}}))
    np.testing.assert_allclose(unrefined[5], carried + np.diag(per_m * 5.0), rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(covs[10], unrefined[10])  # the shared scan: the next submap's anchor
