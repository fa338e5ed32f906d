"""Spatial loop proposals of a planar run: submaps whose paths pass near each other are tested,
however far apart their anchors (the first scans) are; near the chain, the anchors decide."""

from __future__ import annotations

import numpy as np

from submapslam.config import LoopConfig
from submapslam.geometry import se2_to_matrix
from submapslam.submaps import Submap
from submapslam.topology.loop_closure import LoopCloser


class _Estimate:
    """A graph estimate with the anchors where given and a tight covariance."""

    def __init__(self, anchors: list[np.ndarray]) -> None:
        self.anchors = anchors

    def pose(self, key: int) -> np.ndarray:
        return self.anchors[key]

    def marginal_covariance(self, key: int) -> np.ndarray:
        return np.eye(6) * 0.01**2

    def odometry_chain(self, i: int, j: int) -> tuple[np.ndarray, np.ndarray]:
        return np.linalg.inv(self.anchors[i]) @ self.anchors[j], np.eye(6) * 0.01**2


def _straight(id_: int, start: tuple[float, float], heading: float, length: float) -> tuple[Submap, np.ndarray]:
    """A submap whose scans go ``length`` m straight from ``start`` along ``heading`` [rad], 0.25 m
    apart; its anchor (first scan) pose in the world."""
    steps = np.arange(0.0, length + 1e-9, 0.25)
    scans = np.array([se2_to_matrix(s, 0.0, 0.0) for s in steps])
    submap = Submap(id=id_, scan_indices=list(range(len(steps))), T_odom_anchor=np.eye(4), T_anchor_scans=scans,
                    points=np.zeros((10, 3)), distance=length, planar=True)
    return submap, se2_to_matrix(start[0], start[1], heading)


def _drive() -> tuple[list[Submap], _Estimate]:
    """Submap 0 runs east from (0, 0) to (12, 0), submap 1 south from there; submaps 2-5 go round
    a block and come back west along y = 1; submap 6 goes on west from (30, 1) to (11, 1). Its
    anchor is 30 m from submap 0's and 18 m from submap 1's; its path passes 1 m from both paths
    (where they meet), 12 m or more from those of submaps 2-4, and begins where submap 5's ends."""
    legs = [((0.0, 0.0), 0.0, 12.0), ((12.0, 0.0), -np.pi / 2, 20.0), ((12.0, -20.0), 0.0, 30.0),
            ((42.0, -20.0), np.pi / 2, 10.0), ((42.0, -10.0), np.pi / 2, 11.0), ((42.0, 1.0), np.pi, 12.0),
            ((30.0, 1.0), np.pi, 19.0)]
    built = [_straight(k, *leg) for k, leg in enumerate(legs)]
    return [s for s, _ in built], _Estimate([a for _, a in built])


def test_a_planar_submap_is_tested_against_the_submaps_its_path_passes():
    submaps, estimate = _drive()
    closer = LoopCloser(LoopConfig(use_descriptor=False), planar=True, voxel_size=0.1, max_range=30.0,
                        submap_length=5.0)
    hyps = closer.propose(submaps[6], None, submaps, estimate, [])
    # by their anchors (18 and 30 m away, beyond the 5 m search radius) neither would be
    assert [(h.i, h.j, h.source) for h in hyps] == [(0, 6, "spatial"), (1, 6, "spatial")]
    # the guess is the anchors' relative pose, as for any spatial hypothesis
    np.testing.assert_allclose(hyps[0].initial_guess, np.linalg.inv(estimate.pose(0)) @ estimate.pose(6))


def test_3d_runs_keep_the_anchors():
    """A 3D submap sees 80 m around its anchor: there the anchors decide (submap 0's, 30 m
    away, is beyond a 25 m radius; submap 1's, 18 m away, is within)."""
    submaps, estimate = _drive()
    closer = LoopCloser(LoopConfig(use_descriptor=False, spatial_min_radius=25.0), planar=False, voxel_size=0.4,
                        max_range=80.0, submap_length=12.0)
    assert [h.i for h in closer.propose(submaps[6], None, submaps, estimate, [])] == [1]


def test_near_the_chain_the_anchors_decide():
    """Submap 5's path ends where submap 6's begins (0 m), its anchor is 12 m away: the paths of
    submaps fewer than four apart on the chain meet through the ones between them, so such a
    submap is proposed only when its anchor is near."""
    submaps, estimate = _drive()
    closer = LoopCloser(LoopConfig(use_descriptor=False, min_submap_gap=1), planar=True, voxel_size=0.1,
                        max_range=30.0, submap_length=5.0)
    assert [h.i for h in closer.propose(submaps[6], None, submaps, estimate, [])] == [0, 1]


def test_without_wheels_a_farther_path_is_proposed():
    """The same drive with submap 6 on y = 4: its path passes 4 m from submaps 0 and 1. A log
    whose odometry followed wheels proposes paths within 2 m (plus three sigma) only; one without
    wheels, whose odometry drifts more, proposes paths within the radius's 5 m floor."""
    submaps, estimate = _drive()
    estimate.anchors[6] = se2_to_matrix(30.0, 4.0, np.pi)
    closer = LoopCloser(LoopConfig(use_descriptor=False), planar=True, voxel_size=0.1, max_range=30.0,
                        submap_length=5.0)
    assert closer.propose(submaps[6], None, submaps, estimate, [], wheel_odometry=True) == []
    hyps = closer.propose(submaps[6], None, submaps, estimate, [], wheel_odometry=False)
    assert [(h.i, h.source) for h in hyps] == [(0, "spatial"), (1, "spatial")]


def test_a_run_tells_the_closer_whether_its_odometry_followed_wheels(tmp_path, monkeypatch):
    """A planar log with wheel odometry: its run's loop tests know it, unless the config turns the
    wheels off (``odometry.use_wheel_odometry``), as for a log without them."""
    from datasets_synth import generate
    from submapslam.api import run_log
    from submapslam.config import PipelineConfig

    log = generate("rectangle", tmp_path / "log", seed=1, laps=1, max_scans=200, size=(16.0, 10.0))
    seen: list[bool] = []
    original = LoopCloser.process

    def recording(self, new, submaps, graph, hint_pairs, wheel_odometry=True):
        seen.append(wheel_odometry)
        return original(self, new, submaps, graph, hint_pairs, wheel_odometry)

    monkeypatch.setattr(LoopCloser, "process", recording)
    run_log(log, None)
    assert seen and all(seen)
    seen.clear()
    run_log(log, None, config=PipelineConfig.model_validate({"odometry": {"use_wheel_odometry": False}}))
    assert seen and not any(seen)
