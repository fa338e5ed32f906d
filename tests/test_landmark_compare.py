"""EKF vs factor-graph comparison figures on a small synthetic map."""

import numpy as np

from datasets_synth.landmarks import generate_landmark_log
from submapslam.backend.landmark_graph import solve_landmark_graph
from submapslam.ekf import CredibilityParams
from submapslam.ekf.runner import run_ekf
from submapslam.evaluation.landmark_compare import compare_landmark_solutions
from submapslam.io.landmark_logs import read_victoria_park


def test_compare_reports_agreement_and_covariances(tmp_path):
    log = read_victoria_park(generate_landmark_log(tmp_path / "syn.txt", seed=0, laps=1, sigma_range=0.02,
                                                   odo_sigma=(0.005, 0.005, 0.002)))
    run = run_ekf(log, CredibilityParams(b=1e9, remove_below=0.0))
    sol = solve_landmark_graph(log)
    c = compare_landmark_solutions(log, run, sol)
    assert c["landmarks_shared"] == run.filter.n > 5
    assert c["ekf_vs_graph_landmark_max_m"] < 0.02 and c["ekf_vs_graph_final_position_m"] < 0.02
    assert c["ekf_vs_graph_final_heading_deg"] < 0.2
    # on a small map with low noise the filter's covariances match the smoother's marginals
    assert 0.8 < c["cov_area_ratio_median"] < 1.25 and c["cov_sym_kl_median"] < 0.1
    # a shifted EKF map shows up in the figures
    run.filter.x[3::2] += 0.5
    assert compare_landmark_solutions(log, run, sol)["ekf_vs_graph_landmark_rms_m"] > 0.45
    assert np.isfinite(c["graph_error"])


def test_graph_marginals_agree_with_the_ekf_and_both_are_consistent(tmp_path):
    """The EKF as the reference, over 10 Monte Carlo landmark worlds (1 lap, 20 landmarks; the noise
    of the NEES study): every landmark's EKF covariance agrees with the graph's marginal (symmetric
    KL at most 0.05, ellipse areas within 10 %), so does the last pose's (KL at most 0.05), and
    both estimators are inside the 95 % band of the NEES mean: the joint landmark NEES per DOF (all
    landmarks of a run as one sample) and the last pose's NEES (3 DOF)."""
    from submapslam.cli.ekf import synthetic_nees_trials
    from submapslam.evaluation.landmark_compare import landmark_consistency_study

    st = landmark_consistency_study(synthetic_nees_trials(tmp_path, runs=10, seed=100, laps=1))
    assert st["runs"] == 10 and st["landmark_dof"] >= 200
    assert st["landmark_sym_kl_max"] < 0.05 and st["final_pose_sym_kl_max"] < 0.05
    lo, hi = st["landmark_area_ratio_range"]
    assert 0.9 < lo <= hi < 1.1
    for who in ("ekf", "graph"):
        a, b = st["landmark_nees_per_dof_band_95"]
        assert a <= st[f"{who}_landmark_nees_per_dof"] <= b, (who, st[f"{who}_landmark_nees_per_dof"], a, b)
        a, b = st["final_nees_band_95"]
        assert a <= st[f"{who}_final_nees_mean"] <= b, (who, st[f"{who}_final_nees_mean"], a, b)
