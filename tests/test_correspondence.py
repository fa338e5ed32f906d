import itertools

import numpy as np
import pytest

from submapslam.geometry import (
    inverse,
    matrix_to_se2,
    rotation_angle,
    se2_to_matrix,
    transform_points,
)
from submapslam.io.registry import open_log
from submapslam.registration import planar
from submapslam.registration.correspondence import check_correspondence
from submapslam.topology.descriptors import DescriptorIndex, compute_descriptor, descriptor_distance

from .conftest import shared_data


def corridor_submap(seed=0):
    """A planar 'submap': an L-shaped corridor with door recesses and pillars, points every 5 cm."""
    rng = np.random.default_rng(seed)
    segs = [((0, 0), (20, 0)), ((0, 3), (17, 3)), ((17, 3), (17, 12)), ((20, 0), (20, 12)),
            ((5, 0), (5, -1)), ((6.2, 0), (6.2, -1)), ((5, -1), (6.2, -1)), ((11, 3), (11, 4.3)),
            ((12.5, 3), (12.5, 4.3)), ((11, 4.3), (12.5, 4.3)), ((20, 6), (21, 6)), ((21, 6), (21, 7.5)),
            ((21, 7.5), (20, 7.5))]
    pts = []
    for a, b in segs:
        a, b = np.array(a, float), np.array(b, float)
        n = int(np.linalg.norm(b - a) / 0.05) + 1
        pts.append(a + (b - a) * np.linspace(0, 1, n)[:, None])
    for c in ((8, 2.6), (15, 0.4)):
        ang = np.linspace(0, 2 * np.pi, 40, endpoint=False)
        pts.append(np.array(c) + 0.2 * np.stack([np.cos(ang), np.sin(ang)], 1))
    xy = np.vstack(pts) + rng.normal(0, 0.01, (sum(len(p) for p in pts), 2))
    return np.c_[xy, np.zeros(len(xy))]


@pytest.mark.parametrize("guess", [None, "rough"])
def test_planar_transform_recovered_without_good_guess(guess):
    source = corridor_submap(0)
    T_true = se2_to_matrix(2.0, -1.5, np.deg2rad(40))
    target = transform_points(T_true, corridor_submap(1))
    init = se2_to_matrix(1.2, -0.8, np.deg2rad(30)) if guess else None
    res = check_correspondence(source, target, planar=True, initial_guess=init, search_radius=3.0,
                               yaw_window_deg=20.0)
    assert res.accepted, res.reason
    err = inverse(T_true) @ res.T_target_source
    assert np.linalg.norm(err[:3, 3]) < 0.05 and np.rad2deg(rotation_angle(err)) < 0.5
    assert res.T_target_source[2, 3] == 0.0  # planar result stays planar
    assert np.all(np.linalg.eigvalsh(res.information) > 0)


def test_different_places_are_rejected_with_a_reason():
    source = corridor_submap(0)
    rng = np.random.default_rng(3)
    other = np.c_[rng.uniform(0, 20, (800, 2)), np.zeros(800)]  # clutter, no walls
    res = check_correspondence(source, other, planar=True)
    assert not res.accepted
    assert res.reason.split()[0] in {"fitness", "inlier", "overlap", "ambiguous"}


def test_corridor_information_is_weak_along_the_corridor():
    a, b = np.linspace(0, 20, 400), np.zeros(400)
    walls = np.vstack([np.c_[a, b, b], np.c_[a, b + 3.0, b]])
    res = check_correspondence(walls, walls, planar=True, initial_guess=np.eye(4), refine_only=True)
    cov = np.linalg.inv(res.information)
    assert cov[3, 3] > 100 * cov[4, 4]  # x (along the corridor) far less certain than y


def box_room(seed=0):
    """A 3D room: floor, ceiling and four walls (8 x 5 x 2.5 m) with a pillar, points every ~10 cm."""
    rng = np.random.default_rng(seed)
    u = np.arange(0.0, 1.0, 0.0125)
    a, b = np.meshgrid(u, u)
    a, b = a.ravel(), b.ravel()
    faces = [np.c_[8 * a - 4, 5 * b - 2.5, 0 * a], np.c_[8 * a - 4, 5 * b - 2.5, 0 * a + 2.5],
             np.c_[8 * a - 4, 0 * a - 2.5, 2.5 * b], np.c_[8 * a - 4, 0 * a + 2.5, 2.5 * b],
             np.c_[0 * a - 4, 5 * b - 2.5, 2.5 * b], np.c_[0 * a + 4, 5 * b - 2.5, 2.5 * b],
             np.c_[0.4 * a + 1.0, 0 * a + 0.6, 2.5 * b], np.c_[0 * a + 1.0, 0.4 * a + 0.6, 2.5 * b]]
    pts = np.vstack(faces)
    return pts + rng.normal(0, 0.005, pts.shape)


@pytest.mark.parametrize("planar_case", [True, False], ids=["planar", "3d"])
def test_information_is_about_the_source_pose_wherever_the_target_frame_is(planar_case):
    """The information is about ``T_target_source · Exp(xi)`` (GTSAM's between-factor tangent):
    matching a cloud against itself gives the same information whether the target frame is the
    source's own or one 30 m away and turned 90 deg (about the target's origin, a yaw error
    would move the source by 30 m per radian)."""
    cloud = corridor_submap(0) if planar_case else box_room(0)
    far = se2_to_matrix(30.0, -10.0, np.pi / 2) if planar_case else \
        np.array([[0.0, -1.0, 0.0, 30.0], [1.0, 0.0, 0.0, -10.0], [0.0, 0.0, 1.0, 0.5], [0.0, 0.0, 0.0, 1.0]])
    infos = []
    for T in (np.eye(4), far):
        res = check_correspondence(cloud, transform_points(T, cloud), planar=planar_case, initial_guess=T,
                                   refine_only=True, voxel_size=0.1)
        infos.append(res.information_gtsam)
    axes = [2, 3, 4] if planar_case else list(range(6))
    here, there = (np.linalg.inv(i[np.ix_(axes, axes)]) for i in infos)
    sd = np.sqrt(np.diag(here))
    np.testing.assert_allclose(np.sqrt(np.diag(there)), sd, rtol=0.2)
    # yaw and the translation across it stay as uncorrelated as at home (about the target's origin
    # they would be almost fully correlated)
    corr = there / np.outer(np.sqrt(np.diag(there)), np.sqrt(np.diag(there)))
    home = here / np.outer(sd, sd)
    assert np.abs(corr - home).max() < 0.2


def test_corridor_information_is_weak_along_the_corridor_as_the_source_sees_it():
    a, b = np.linspace(0, 20, 400), np.zeros(400)
    walls = np.vstack([np.c_[a, b, b], np.c_[a, b + 3.0, b]])
    T = se2_to_matrix(3.0, 0.5, np.pi / 2)  # the corridor (target x) runs along the source's y
    res = check_correspondence(transform_points(inverse(T), walls), walls, planar=True, initial_guess=T,
                               refine_only=True)
    cov = np.linalg.inv(res.information)
    assert cov[4, 4] > 100 * cov[3, 3]


def test_real_laser_submap_recovered_from_far_offset():
    path = shared_data("carmen", "intel.clf.bz2")
    pts = []
    for s in itertools.islice(open_log(path), 0, 120, 4):
        pts.append(transform_points(s.odometry, s.points))
    submap = np.vstack(pts)
    T_true = se2_to_matrix(2.0, 1.0, np.deg2rad(-40))
    target = transform_points(T_true, submap)
    target[:, :2] += np.random.default_rng(0).normal(0, 0.02, (len(target), 2))
    res = check_correspondence(submap, target, planar=True)
    assert res.accepted, res.reason
    err = matrix_to_se2(inverse(T_true) @ res.T_target_source)
    assert np.hypot(*err[:2]) < 0.05 and abs(np.rad2deg(err[2])) < 0.5


def test_real_3d_pair_recovers_reference_transform():
    folder = shared_data("lidar3d", "small_gicp_pair")
    from submapslam.io.cloud_folder import read_cloud

    src, _ = read_cloud(folder / "source.ply")
    tgt, _ = read_cloud(folder / "target.ply")
    T_ref = np.loadtxt(folder / "T_target_source.txt")
    res = check_correspondence(src, tgt, planar=False, initial_guess=np.eye(4), voxel_size=0.1)
    err = inverse(T_ref) @ res.T_target_source
    assert np.linalg.norm(err[:3, 3]) < 0.1 and np.rad2deg(rotation_angle(err)) < 1.0
    assert res.fitness > 0.5
    assert np.all(np.linalg.eigvalsh(res.information) > 0)


def test_descriptor_finds_the_place_and_its_yaw():
    places = [corridor_submap(0)]
    rng = np.random.default_rng(7)
    for _ in range(4):  # other places: random boxes
        pts = []
        for _ in range(6):
            c, w = rng.uniform(-10, 10, 2), rng.uniform(1, 4, 2)
            t = np.linspace(0, 1, 60)[:, None]
            for a, b in (((0, 0), (1, 0)), ((1, 0), (1, 1)), ((1, 1), (0, 1)), ((0, 1), (0, 0))):
                pts.append(c + w * (np.array(a) + (np.array(b) - np.array(a)) * t))
        xy = np.vstack(pts)
        places.append(np.c_[xy, np.zeros(len(xy))])
    index = DescriptorIndex()
    for k, p in enumerate(places):
        index.add(k, compute_descriptor(p - [10, 3, 0], planar=True, max_range=20))
    yaw = np.deg2rad(60)
    query_pts = transform_points(se2_to_matrix(0, 0, -yaw), corridor_submap(2) - [10, 3, 0])
    q = compute_descriptor(query_pts, planar=True, max_range=20)
    best = index.query(q, top_k=2)
    assert best[0][0] == 0
    assert abs(np.rad2deg(best[0][2]) - 60) <= 6.0  # within one sector
    assert descriptor_distance(q, q)[0] == pytest.approx(0.0, abs=1e-9)



def test_correlative_search_does_not_wrap_the_source_onto_the_far_side():
    """The FFT search's grid is only a source radius wider than the target: a source whose other
    half lies beyond the target must not have that half wrapped onto the target's far side
    (circular correlation). Its score is the direct search's (one gather per point on a
    generously padded grid): about half of the points lie on the target."""
    from submapslam.registration.planar import coarse_search

    rng = np.random.default_rng(5)
    target = rng.uniform(0.0, 10.0, (600, 2))  # clutter: every wrapped point would find a neighbour
    source = np.vstack([target[:300], rng.uniform([10.0, 0.0], [20.0, 10.0], (300, 2))])
    yaws = np.zeros(1)
    wide, score_fft, _ = coarse_search(source, target, resolution=0.3, sigma=0.45, window=3.0, yaws=yaws,
                                       max_source_points=5000)
    near, score_direct, _ = coarse_search(source, target, resolution=0.3, sigma=0.45, window=0.6, yaws=yaws,
                                          max_source_points=5000)
    assert np.hypot(*wide[:2]) < 0.45 and np.hypot(*near[:2]) < 0.45  # 1.5 cells
    assert score_fft == pytest.approx(score_direct, abs=0.05)  # wrapped: 0.81


def test_global_search_finds_a_piece_at_the_far_end_of_a_larger_submap():
    """The correlative search's grid is only a source radius wider than the target (circular
    correlation must not wrap the source onto the far side): a small piece whose true place is
    at one end of the target is found there, and its score is the likelihood at that pose."""
    from submapslam.registration.planar import coarse_search

    target = corridor_submap(1)[:, :2]
    piece = corridor_submap(0)[:, :2]
    piece = piece[(piece[:, 1] > 4.0)]  # the far end of the L: the 9 m leg up to y = 12
    x, y, yaw = 3.0, -2.0, np.deg2rad(25.0)
    R = np.array([[np.cos(yaw), -np.sin(yaw)], [np.sin(yaw), np.cos(yaw)]])
    source = (piece - [x, y]) @ R  # so that R @ source + (x, y) = piece, in the target's frame
    extent = float(np.abs(target - target.mean(axis=0)).max()) + 2.0
    center = target.mean(axis=0) - source.mean(axis=0)
    xyt, score, _ = coarse_search(source, target, resolution=0.3, sigma=0.45, center=center, window=extent,
                                  yaws=np.deg2rad(np.arange(0.0, 50.0, 2.0)))
    assert np.hypot(xyt[0] - x, xyt[1] - y) < 0.35 and abs(np.rad2deg(xyt[2] - yaw)) <= 2.0
    assert score > 0.8


def _with_coarse_peaks(monkeypatch, second_xyt, ambiguity=0.95):
    """The coarse (window > 1 m) correlative search reports the true pose and, ``ambiguity`` of its
    score, a distinct second peak at ``second_xyt``; the fine searches run as they are."""
    real = planar.coarse_peaks

    def coarse_peaks(source, target, **kw):
        best = real(source, target, **kw)
        if kw.get("window", 15.0) <= 1.0:
            return best
        return best[0], best[1], ambiguity, np.asarray(second_xyt, dtype=float)

    monkeypatch.setattr(planar, "coarse_peaks", coarse_peaks)


def test_an_ambiguous_coarse_peak_that_refinement_tells_apart_is_resolved(monkeypatch):
    """Coarse scores are blurred: the second peak, refined, fits the L-shaped corridor far worse
    than the true pose (or ends on it), so the match is accepted; without the refinement the
    correlative ratio alone rejects it."""
    source = corridor_submap(0)
    target = corridor_submap(1)
    _with_coarse_peaks(monkeypatch, [2.5, 0.0, 0.0])
    res = check_correspondence(source, target, planar=True, initial_guess=se2_to_matrix(0.3, 0.0, 0.0),
                               search_radius=4.0)
    assert res.accepted and res.ambiguity < 0.9, res.reason
    assert np.linalg.norm(res.T_target_source[:2, 3]) < 0.05
    unresolved = planar.match_planar(source, target, initial_guess=se2_to_matrix(0.3, 0.0, 0.0), window=4.0,
                                     yaw_window=np.deg2rad(20.0))
    assert unresolved.ambiguity == pytest.approx(0.95)


def test_a_featureless_corridor_stays_ambiguous_after_refinement(monkeypatch):
    """Two parallel walls and nothing else: slid 2.5 m along them the source fits as well as in
    place, so the refined ratio stays near 1 and the match is rejected as ambiguous."""
    def walls(x0, x1):
        x = np.arange(x0, x1, 0.05)
        xy = np.r_[np.c_[x, np.zeros_like(x)], np.c_[x, np.full_like(x, 3.0)]]
        return np.c_[xy, np.zeros(len(xy))]

    _with_coarse_peaks(monkeypatch, [2.5, 0.0, 0.0])
    res = check_correspondence(walls(-4, 4), walls(-7, 7), planar=True, initial_guess=np.eye(4),
                               search_radius=4.0)
    assert not res.accepted and res.reason.startswith("ambiguous"), res.reason
    assert res.ambiguity > 0.9
