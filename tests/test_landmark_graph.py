"""GTSAM landmark graph: incremental iSAM2 and batch LM reach the same smoothing solution."""

import numpy as np

from datasets_synth.landmarks import generate_landmark_log
from submapslam.backend.landmark_graph import solve_landmark_graph
from submapslam.io.landmark_logs import read_victoria_park


def test_isam2_step_by_step_matches_batch_and_marginals_exist(tmp_path):
    log = read_victoria_park(generate_landmark_log(tmp_path / "syn.txt", seed=3, laps=1, sigma_range=0.03,
                                                   odo_sigma=(0.01, 0.01, 0.004)))
    batch = solve_landmark_graph(log)
    inc = solve_landmark_graph(log, incremental=True)
    assert set(batch.landmarks) == set(inc.landmarks) and len(batch.landmarks) > 5
    assert max(np.linalg.norm(batch.landmarks[k] - inc.landmarks[k]) for k in batch.landmarks) < 0.01
    assert np.linalg.norm(batch.poses[-1][:2] - inc.poses[-1][:2]) < 0.01
    assert batch.error < batch.initial_error and inc.error < 1.05 * batch.error + 1.0
    for C in list(batch.landmark_covs.values()) + list(inc.landmark_covs.values()):
        assert C.shape == (2, 2) and np.all(np.linalg.eigvalsh(C) > 0)
    assert np.all(np.linalg.eigvalsh(inc.final_pose_cov) > 0)


def test_warm_start_escapes_the_dead_reckoning_local_minimum_on_mrclam():
    from submapslam.ekf.runner import landmark_rmse
    from submapslam.io.landmark_logs import read_mrclam

    from .conftest import shared_data

    log = read_mrclam(shared_data("landmarks", "utias_mrclam7"), 1)
    cold = solve_landmark_graph(log)
    warm = solve_landmark_graph(log, warm_start=True)
    assert warm.error < 0.2 * cold.error
    assert landmark_rmse(warm.landmarks, log.truth_landmarks)[0] < landmark_rmse(cold.landmarks, log.truth_landmarks)[0]
