"""The ground priors' flat-world bet, tested by the run: level ground keeps them; a road that
climbs and dips keeps them only where the loop closures fit better with them (issue 24)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from submapslam.config import BackendConfig, OdometryConfig
from submapslam.geometry import inverse, so3_exp
from submapslam.graph_builder import GraphBuilder
from submapslam.uncertainty import LevelGroundTest, odometry_information

UP = np.array([0.0, 0.0, 1.0])


def _tilted(deg_pitch: float, deg_roll: float = 0.0) -> np.ndarray:
    return so3_exp(np.deg2rad([deg_roll, deg_pitch, 0.0])) @ UP


def test_level_ground_test_tells_a_level_town_from_a_hilly_one():
    """Ground normals that wander by the odometry's own tilt error are level (ratio <= 1); ones that
    turn by a degree an anchor over a 0.05 deg odometry are not; too few windows, or no tilt
    estimate yet, give no answer."""
    rng = np.random.default_rng(0)
    level, hilly = LevelGroundTest(), LevelGroundTest()
    for k in range(30):
        level.add(k, _tilted(*rng.normal(0.0, 0.1, 2)), 12.0)
        hilly.add(k, _tilted(3.0 * np.sin(k / 3.0)), 12.0)
    sigma_16_rings = lambda d: np.deg2rad(0.2) * np.sqrt(d / 12.0)  # noqa: E731
    sigma_64_rings = lambda d: np.deg2rad(0.05) * np.sqrt(d / 12.0)  # noqa: E731
    assert level.ratio(sigma_16_rings) <= 1.0
    assert hilly.ratio(sigma_64_rings) > 3.0
    assert level.ratio(lambda d: None) is None
    few = LevelGroundTest(min_windows=8)
    for k in range(10):  # 7 windows of 3 anchors
        few.add(k, _tilted(3.0 * k), 12.0)
    assert few.ratio(sigma_64_rings) is None


def _road_submap(k: int, T_odom_anchor: np.ndarray, step: float):
    """A fake submap ``k`` at ``T_odom_anchor`` (4, 4): a 30 x 30 m ground patch 1.7 m below the
    anchor, level in the anchor's own frame (the vehicle pitches with the road)."""
    g = np.stack(np.meshgrid(np.linspace(-15, 15, 31), np.linspace(-15, 15, 31)), -1).reshape(-1, 2)
    return SimpleNamespace(id=k, T_odom_anchor=T_odom_anchor, points=np.c_[g, np.full(len(g), -1.7)], distance=step,
                           T_anchor_scans=np.eye(4)[None])


def _drive(grades_deg: list[float], step: float = 12.0, bias_deg: float = 0.0) -> tuple[list, list]:
    """True anchors along x, each pitched up by its road grade [deg], and the odometry's view of
    them (every step pitching ``bias_deg`` further up)."""
    truth, odometry = [np.eye(4)], [np.eye(4)]
    bias = np.eye(4)
    bias[:3, :3] = so3_exp(np.deg2rad([0.0, -bias_deg, 0.0]))
    for k in range(1, len(grades_deg)):
        T = np.eye(4)
        T[:3, :3] = so3_exp(np.deg2rad([0.0, -(grades_deg[k] - grades_deg[k - 1]), 0.0]))
        T[0, 3] = step
        truth.append(truth[-1] @ T)
        odometry.append(odometry[-1] @ T @ bias)
    return truth, odometry


def _run(truth, odometry, step=12.0, loops=(), tilt_deg=0.02, loop_sigma=(0.5, 0.05), edge_tilt_deg=None,
         **backend) -> tuple[GraphBuilder, float]:
    """A GraphBuilder fed the odometry (its edges' tilt corrections ``tilt_deg``: 0.02, a good 3D odometry;
    their roll and pitch sigma the drift model's, or ``edge_tilt_deg`` as TiltDrift would make it),
    the road's ground under every anchor and true loop constraints ``(i, j)`` (sigma ``loop_sigma``:
    deg, m; the graph builder floors them at 0.5 deg and 5 cm, as a run's); returns it after
    ``finish`` and the largest anchor position error [m]."""
    from submapslam.result import LoopRecord

    config = BackendConfig(odometry_registration_covariance=False, **backend)
    builder = GraphBuilder(config, OdometryConfig(), planar=False, match_voxel=0.5)
    submaps = [_road_submap(k, T, step) for k, T in enumerate(odometry)]
    for k, sm in enumerate(submaps):
        prev = submaps[k - 1] if k else None
        info = None
        if prev is not None:
            info = odometry_information(inverse(prev.T_odom_anchor) @ sm.T_odom_anchor, step, False, config,
                                        None if edge_tilt_deg is None else np.deg2rad(edge_tilt_deg))
        builder.add_submap(sm, prev, False, information=info, tilt=np.deg2rad([tilt_deg, -tilt_deg]) if k else None)
    info = np.diag([1 / np.deg2rad(loop_sigma[0]) ** 2] * 3 + [1 / loop_sigma[1] ** 2] * 3)
    builder.add_loops([LoopRecord(i=i, j=j, source="spatial", accepted=True, fitness=1.0, overlap=1.0, inlier_rmse=0.0,
                                  reason="", T_i_j=inverse(truth[i]) @ truth[j],
                                  information=info) for i, j in loops])
    builder.finish()
    error = max(np.linalg.norm(builder.graph.pose(k)[:3, 3] - truth[k][:3, 3]) for k in range(len(truth)))
    return builder, float(error)


def test_a_climbing_road_without_closures_keeps_its_good_odometry():
    """A good odometry over a road that climbs to 5 deg and dips back: the level prior pulls every
    climbing anchor flat (metres of height lost); the run finds the ground not level, has no
    closure to vouch for the priors, and drops them (the odometry's own heights, to centimetres)."""
    grades = [min(5.0, 0.5 * k) if k < 25 else max(0.0, 5.0 - 0.5 * (k - 25)) for k in range(40)]
    truth, odometry = _drive(grades)
    fixed, error = _run(truth, odometry)
    assert fixed.ground_prior_test["level"] is False and fixed.ground_prior_test["kept"] is False
    assert fixed.ground_prior_test["priors"] > 0 and fixed.ground_prior_test["loops"] == 0
    assert error < 0.05
    _, error_before = _run(truth, odometry, ground_priors_level_test=False)
    assert error_before > 1.0


def test_a_run_too_short_to_test_keeps_the_priors_only_where_closures_vouch_for_them():
    """Eight anchors over a 3 deg climb and dip: 5 windows of 3 anchors, too few to tell level
    ground from a hilly road (like the hand-held Livox main building, whose ground 2 of 8 anchors
    see). Without a closure the untested priors leave and the odometry's heights stand; with true
    closures that fit them they stay."""
    grades = [0.0, 1.0, 2.0, 3.0, 3.0, 2.0, 1.0, 0.0]
    truth, odometry = _drive(grades)
    alone, error = _run(truth, odometry)
    assert alone.ground_prior_test["level"] is None and alone.ground_prior_test["level_ratio"] is None
    assert alone.ground_prior_test["kept"] is False and alone.ground_prior_test["loops"] == 0
    assert error < 0.01
    _, error_kept = _run(truth, odometry, ground_priors_level_test=False)
    assert error_kept > 0.1  # the priors pulled the climb flat
    level_truth, level_odometry = _drive([0.0] * 8, bias_deg=0.1)
    vouched, _ = _run(level_truth, level_odometry, loops=[(0, 7), (1, 6)])
    assert vouched.ground_prior_test["level"] is None and vouched.ground_prior_test["kept"] is True


def test_priors_stay_on_level_ground_and_where_the_closures_agree_with_them():
    """Level ground under a 16-ring-like odometry that pitches 0.1 deg up every step and whose
    registrations correct its tilt by 0.1 deg: level, and the priors hold the climb the odometry
    invents. The same bias under registrations that see only 0.02 deg: the normals turn more than
    that allows (not level), but the closures fit as well with the priors as without, so they stay."""
    truth, odometry = _drive([0.0] * 40, bias_deg=0.1)
    loops = [(0, 39), (5, 30)]
    _, error_without = _run(truth, odometry, loops=loops, ground_attitude_sigma_deg=None,
                            ground_tilt_change_sigma_deg=None)
    for tilt_deg, level in ((0.1, True), (0.02, False)):
        builder, error = _run(truth, odometry, loops=loops, tilt_deg=tilt_deg)
        assert builder.ground_prior_test["level"] is level and builder.ground_prior_test["kept"] is True
        assert error < 0.5 * error_without, (tilt_deg, error, error_without)
    assert builder.ground_prior_test["loop_chi2_with"] <= builder.ground_prior_test["loop_chi2_without"] + 3.84


def test_closures_that_fit_either_way_do_not_keep_priors_on_a_climbing_road():
    """A good odometry over a road that climbs to 5 deg, falls to -5 deg and levels out (about 10 m
    of relief over 600 m), with true closures between its ends: they fit the priors' flattened
    chain almost as well as the true one (chi-square below 3.84 either way), the way a Livox-like
    drive's floored loop edges fitted KITTI 02's climbs. Not level and not favoured by the closures,
    the priors leave; before (kept unless contradicted by more than 3.84) they bent the chain by metres."""
    grades = [min(5.0, 0.5 * k) if k < 20 else max(-5.0, 5.0 - 0.5 * (k - 20)) if k < 40
              else min(0.0, -5.0 + 0.5 * (k - 40)) for k in range(52)]
    truth, odometry = _drive(grades)
    for loops in ([(0, 51)], [(0, 51), (2, 49)]):
        builder, error = _run(truth, odometry, loops=loops)
        test = builder.ground_prior_test
        assert test["level"] is False and test["kept"] is False and test["loops"] == len(loops)
        assert test["loop_chi2_without"] < test["loop_chi2_with"] < test["loop_chi2_without"] + 3.84
        assert error < 0.05
        _, error_kept = _run(truth, odometry, loops=loops, ground_priors_level_test=False)
        assert error_kept > 5.0


def test_with_every_prior_gone_the_odometry_edges_tilt_is_weighed_like_their_yaw_again():
    """Edges whose roll and pitch TiltDrift tightened to 0.02 deg (against the model's yaw of a few
    tenths): on the climbing road the priors leave, and with none left the edges' roll and pitch
    variance is raised to their yaw's (a tight tilt beside a loose yaw lets loops turn headings to
    mend heights); on level ground the priors stay and so does the tight tilt."""
    grades = [min(5.0, 0.5 * k) if k < 20 else max(-5.0, 5.0 - 0.5 * (k - 20)) if k < 40
              else min(0.0, -5.0 + 0.5 * (k - 40)) for k in range(52)]
    truth, odometry = _drive(grades)
    builder, error = _run(truth, odometry, loops=[(0, 51)], edge_tilt_deg=0.02)
    assert builder.ground_prior_test["kept"] is False and builder.ground_prior_test["odometry_tilt_restored"] == 51
    odometry_edges = [e for e in builder.graph.active_edges() if e.kind == "odometry"]
    assert len(odometry_edges) == 51
    for e in odometry_edges:
        sd = np.sqrt(np.diag(np.linalg.inv(e.information)))
        np.testing.assert_allclose(sd[:2], sd[2], rtol=1e-6)
        assert sd[2] > 10 * np.deg2rad(0.02)
    assert error < 0.05
    level_truth, level_odometry = _drive([0.0] * 40, bias_deg=0.1)
    kept, _ = _run(level_truth, level_odometry, tilt_deg=0.1, edge_tilt_deg=0.02)
    assert kept.ground_prior_test["kept"] is True and "odometry_tilt_restored" not in kept.ground_prior_test
    for e in (e for e in kept.graph.active_edges() if e.kind == "odometry"):
        assert np.sqrt(np.linalg.inv(e.information)[0, 0]) == pytest.approx(np.deg2rad(0.02))


def test_near_level_ground_lets_the_closures_go_against_the_priors_by_a_little():
    """The allowance the closures' chi-square may rise by with the priors (summary.json
    ground_priors.allowance): 3.84 on ground near level (the level drive whose odometry tilts 0.1
    deg a step while its registrations see 0.02 deg: ratio 1.12), none on the climbing road
    (ratio 4.8) nor on a run too short to test."""
    from submapslam.graph_builder import NEAR_LEVEL_RATIO, PRIOR_CONTRADICTION_CHI2

    truth, odometry = _drive([0.0] * 40, bias_deg=0.1)
    near = _run(truth, odometry, loops=[(0, 39)])[0].ground_prior_test
    assert near["level"] is False and near["level_ratio"] <= NEAR_LEVEL_RATIO
    assert near["allowance"] == PRIOR_CONTRADICTION_CHI2 and near["kept"] is True
    grades = [min(5.0, 0.5 * k) if k < 20 else max(-5.0, 5.0 - 0.5 * (k - 20)) if k < 40
              else min(0.0, -5.0 + 0.5 * (k - 40)) for k in range(52)]
    far = _run(*_drive(grades), loops=[(0, 51)])[0].ground_prior_test
    assert far["level_ratio"] > NEAR_LEVEL_RATIO and far["allowance"] == 0.0
    short = _run(*_drive([0.0] * 8, bias_deg=0.1), loops=[(0, 7), (1, 6)])[0].ground_prior_test
    assert short["level_ratio"] is None and short["allowance"] == 0.0


def test_closures_that_contradict_the_priors_win():
    """A straight level drive whose ground planes claim a 10 deg tilt under Gaussian priors: with
    two true closures the priors raise the closures' chi-square far beyond 3.84, so they leave
    and the closures stay (the odometry's own poses); with no closure they leave too."""
    from submapslam.backend.pose_graph import PoseGraph

    for loops in ([(0, 19), (5, 19)], []):
        config = BackendConfig(ground_prior_kernel=None)
        truth = [np.eye(4) for _ in range(20)]
        for k, T in enumerate(truth):
            T[0, 3] = 12.0 * k
        g = PoseGraph(config)
        g.add_node(0, truth[0], np.diag([1e8] * 6))
        for k in range(1, 20):
            m = inverse(truth[k - 1]) @ truth[k]
            g.add_node(k, g.pose(k - 1) @ m)
            g.add_between(k - 1, k, m, odometry_information(m, 12.0, False, config), "odometry")
            g.add_attitude(k, _tilted(10.0), UP, np.deg2rad(0.5))
        for i, j in loops:
            g.add_between(i, j, inverse(truth[i]) @ truth[j], np.diag([1 / np.deg2rad(0.5) ** 2] * 3 + [400.0] * 3),
                          "loop")
        g.update()
        bent = max(np.linalg.norm(g.pose(k)[:3, 3] - truth[k][:3, 3]) for k in range(20))
        if loops:  # an allowance beyond what the closures say against them keeps them
            assert g.drop_ground_priors_unless_loops_favour(allowance=1e6)["kept"] is True
        test = g.drop_ground_priors_unless_loops_favour()
        assert test["kept"] is False and test["priors"] == 19 and test["loops"] == len(loops)
        if loops:
            assert test["loop_chi2_with"] > test["loop_chi2_without"] + 3.84
        g.optimize_batch()
        assert bent > 1.0 and max(np.linalg.norm(g.pose(k)[:3, 3] - truth[k][:3, 3]) for k in range(20)) < 0.01
        assert sum(e.kind == "loop" for e in g.active_edges()) == len(loops)
        assert g.prior_chi2() == {}  # the priors left the graph


def _walled_submap(k: int, T_odom_anchor: np.ndarray, R_world_anchor: np.ndarray, step: float):
    """:func:`_road_submap` with three plumb walls (a facade on each side, 16 m off, and one across
    the street 20 m ahead, 6 m high, every 0.25 m), placed by the anchor's true attitude
    ``R_world_anchor`` (3, 3): in the anchor's frame they lean by the road's grade."""
    sm = _road_submap(k, T_odom_anchor, step)
    u, h = np.meshgrid(np.arange(-8.0, 8.0, 0.25), np.arange(-1.7, 4.3, 0.25))
    u, h = u.ravel(), h.ravel()
    walls = np.concatenate([np.c_[u, np.full_like(u, 16.0), h], np.c_[u, np.full_like(u, -16.0), h],
                            np.c_[np.full_like(u, 20.0), 0.5 * u, h]])  # beyond the 15 m the ground plane is fitted in
    sm.points = np.concatenate([sm.points, walls @ R_world_anchor])  # R^T w, row-wise
    return sm


def _feed(submaps: list, truth: list, tilt_deg: float = 0.1, edge_tilt_deg: float | None = None,
          **backend) -> tuple[GraphBuilder, float]:
    """A GraphBuilder fed ``submaps`` (12 m apart, their edges' tilt corrections ``tilt_deg``: 0.1, a
    16-ring odometry; their roll and pitch sigma the drift model's, or ``edge_tilt_deg`` as TiltDrift
    would make it), finished; returns it and the largest anchor position error [m] against ``truth``."""
    config = BackendConfig(odometry_registration_covariance=False, **backend)
    builder = GraphBuilder(config, OdometryConfig(), planar=False, match_voxel=0.5)
    for k, sm in enumerate(submaps):
        prev = submaps[k - 1] if k else None
        info = None if prev is None else odometry_information(
            inverse(prev.T_odom_anchor) @ sm.T_odom_anchor, 12.0, False, config,
            None if edge_tilt_deg is None else np.deg2rad(edge_tilt_deg))
        builder.add_submap(sm, prev, False, information=info, tilt=np.deg2rad([tilt_deg, -tilt_deg]) if k else None)
    builder.finish()
    return builder, max(np.linalg.norm(builder.graph.pose(k)[:3, 3] - truth[k][:3, 3]) for k in range(len(truth)))


def test_walls_hold_the_vertical_where_the_road_climbs():
    """A road that climbs to 5 deg and dips back, under an odometry that pitches 0.1 deg up every
    step. The ground planes cannot tell the grade from that drift: as priors they are dropped
    (not level, no closure) and the drift stays, or, kept, they flatten the climb. The walls beside
    the road stand plumb: their vertical holds the true attitude, so the heights come back (and the
    ground's tilt-change priors, which would fight the changes of grade, are not added)."""
    grades = [min(5.0, 0.5 * k) if k < 25 else max(0.0, 5.0 - 0.5 * (k - 25)) for k in range(40)]
    truth, odometry = _drive(grades, bias_deg=0.1)

    def run(walls: bool, **backend):
        make = (lambda k: _walled_submap(k, odometry[k], truth[k][:3, :3], 12.0)) if walls else (
            lambda k: _road_submap(k, odometry[k], 12.0))
        return _feed([make(k) for k in range(len(truth))], truth, **backend)

    walled, error = run(True)
    test = walled.ground_prior_test
    assert test["level_priors_from"] == "walls" and test["wall_verticals"] == len(truth)
    assert test["level_ratio"] is not None  # the ground was seen under every anchor ...
    assert len(walled.graph.prior_chi2()) == len(truth)  # ... but the priors are the walls' alone: no tilt change
    _, ground_only = run(True, wall_vertical_sigma_deg=None)
    _, no_walls = run(False)
    assert error < 0.25 * min(ground_only, no_walls), (error, ground_only, no_walls)
    assert error < 1.0


def test_a_stretch_without_walls_keeps_its_ground_planes_against_the_walls_up():
    """Walls for the first ten submaps, then a field with none, on level ground under an odometry
    that pitches 0.1 deg up every step. The walls set the world's up; the field's submaps get
    their ground planes' level priors against it, so its heights stay held (without any prior
    there the odometry climbs metres)."""
    truth, odometry = _drive([0.0] * 30, bias_deg=0.1)
    submaps = [_walled_submap(k, odometry[k], truth[k][:3, :3], 12.0) if k < 10 else _road_submap(k, odometry[k], 12.0)
               for k in range(len(truth))]
    builder, error = _feed(submaps, truth)
    assert builder.ground_prior_test["level_priors_from"] == "walls" and builder.ground_prior_test["wall_verticals"] == 10
    assert len(builder.graph.prior_chi2()) == len(truth)  # ten walls' priors, twenty ground planes'
    drift = max(np.linalg.norm(odometry[k][:3, 3] - truth[k][:3, 3]) for k in range(len(truth)))
    assert drift > 3.0 and error < 0.2 * drift, (error, drift)


def test_walls_alone_on_a_grade_weigh_the_odometry_tilt_like_its_yaw(monkeypatch):
    """A road that climbs to 5 deg and back with plumb walls beside it, under an odometry that pitches
    0.1 deg up every step while its registrations see 0.02 deg (TiltDrift tightens the edges' tilt
    to that). The walls are the only level priors, and they are no bet on level ground: the ground
    is not level, so the edges' tilt is weighed like their yaw and the walls take the heights back
    (a 64-ring drive along KITTI 02 with 50 m of relief: 0.27 -> 0.10 m, odometry 0.18). Held at
    0.02 deg, the edges outweigh the walls and the odometry's climb stays. On level ground the
    tight tilt stays."""
    grades = [min(5.0, 0.5 * k) if k < 25 else max(0.0, 5.0 - 0.5 * (k - 25)) for k in range(40)]
    truth, odometry = _drive(grades, bias_deg=0.1)
    walled = [_walled_submap(k, odometry[k], truth[k][:3, :3], 12.0) for k in range(len(truth))]
    drift = max(np.linalg.norm(odometry[k][:3, 3] - truth[k][:3, 3]) for k in range(len(truth)))
    builder, error = _feed(walled, truth, edge_tilt_deg=0.02, tilt_deg=0.02)
    test = builder.ground_prior_test
    assert test["level"] is False and test["priors"] == 0 and test["wall_verticals"] == len(truth)
    assert test["odometry_tilt_restored"] == len(truth) - 1
    assert drift > 10.0 and error < 0.1 * drift, (error, drift)
    monkeypatch.setattr("submapslam.backend.pose_graph.PoseGraph.reweigh_edges", lambda self, kind, f: 0)
    _, held = _feed(walled, truth, edge_tilt_deg=0.02, tilt_deg=0.02)
    assert held > 0.8 * drift, (held, drift)
    monkeypatch.undo()
    level_truth, level_odometry = _drive([0.0] * 30, bias_deg=0.1)
    level = [_walled_submap(k, level_odometry[k], level_truth[k][:3, :3], 12.0) for k in range(30)]
    kept, _ = _feed(level, level_truth, edge_tilt_deg=0.02, tilt_deg=0.1)
    assert kept.ground_prior_test["level"] is True and "odometry_tilt_restored" not in kept.ground_prior_test
