"""The uncertainty a run reports: the per-axis calibration and the per-scan covariances."""

from types import SimpleNamespace

import numpy as np
import pytest

from submapslam.config import BackendConfig, PipelineConfig
from submapslam.errors import ConfigError
from submapslam.uncertainty import (
    COVARIANCE_SCALE_3D,
    COVARIANCE_SCALE_PLANAR,
    calibrate,
    covariance_scale,
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
    result.submap_covariances = np.full((1, 6, 6), np.nan)  # a failed final optimisation: no covariances
    assert scan_covariances(result) is None
