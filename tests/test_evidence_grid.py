import numpy as np

from submapslam.geometry import se2_to_matrix
from submapslam.io.grid import FREE, OCCUPIED, read_pgm, write_pgm_yaml
from submapslam.mapping.evidence_grid import EvidenceGrid, GridParams, fuse_submap_grids

HALF = 5.0  # square room [-5, 5]^2


def room_scan(sensor_xy, person=None, n=360):
    """Analytic 360-degree scan in the square room; optional round person (x, y, radius)."""
    a = np.linspace(-np.pi, np.pi, n, endpoint=False)
    d = np.stack([np.cos(a), np.sin(a)], 1)
    o = np.asarray(sensor_xy, float)
    with np.errstate(divide="ignore"):
        tx = np.where(d[:, 0] > 0, (HALF - o[0]) / d[:, 0], (-HALF - o[0]) / d[:, 0])
        ty = np.where(d[:, 1] > 0, (HALF - o[1]) / d[:, 1], (-HALF - o[1]) / d[:, 1])
    t = np.minimum(np.abs(tx), np.abs(ty))
    if person is not None:
        c, r = np.asarray(person[:2]) - o, person[2]
        b = d @ c
        disc = b**2 - (c @ c - r**2)
        hit = (disc > 0) & (b > 0)
        t = np.where(hit, np.minimum(t, b - np.sqrt(np.where(hit, disc, 0))), t)
    pts = np.zeros((n, 3))
    pts[:, :2] = d * t[:, None]
    return pts


def occupied(grid, xy):
    r, c, inside = grid.cells(np.atleast_2d(xy))
    return bool(inside[0]) and grid.logodds[r[0], c[0]] > grid.params.occupied_threshold


def local(scans_xy, person, params):
    grid = EvidenceGrid(np.array([-6.0, -6.0]), (240, 240), params)
    for xy in scans_xy:
        grid.integrate_scan(se2_to_matrix(*xy, 0.0), room_scan(xy, person))
    return grid


def test_walls_occupied_and_interior_free():
    params = GridParams(resolution=0.05, free_scan_stride=1)
    grid = local([(0.0, 0.0), (1.0, 0.5)], None, params)
    assert occupied(grid, (HALF + 0.01, 0.3))
    assert occupied(grid, (-1.0, -HALF + 0.01))
    r, c, _ = grid.cells(np.array([[2.0, 2.0]]))
    assert grid.logodds[r[0], c[0]] < 0


def test_global_grid_forgets_a_person_who_left_but_keeps_walls():
    params = GridParams(resolution=0.05, free_scan_stride=1)
    person = (2.0, 0.0, 0.25)
    before = local([(-2.0, 0.0), (-2.0, 0.3), (-2.0, -0.3)] * 3, person, params)  # person present
    after = local([(-2.0, 0.0), (-2.0, 0.3), (-2.0, -0.3)] * 3, None, params)     # person gone
    g = EvidenceGrid(np.array([-6.0, -6.0]), (240, 240), params)
    fuse_submap_grids(g, before, np.eye(4))
    front = (person[0] - person[2] + 0.01, 0.0)
    assert occupied(g, front)
    cleared = fuse_submap_grids(g, after, np.eye(4))
    assert cleared > 0
    assert not occupied(g, front)
    assert occupied(g, (HALF + 0.01, 2.0)) and occupied(g, (-HALF + 0.01, -1.0))


def test_a_box_taken_away_within_one_submap_is_freed_in_the_global_grid():
    """A box stands in front of the sensor for the first 24 scans of a submap and is gone for
    the last 6: the summed evidence of that submap still says occupied (+0.85 a hit, -0.4 a
    ray), but the cell has been seen free since its last hit, so the global grid frees it
    (and not with the rule off); the walls stay."""
    box = (2.0, 0.0, 0.25)
    front = (box[0] - box[2] + 0.01, 0.0)
    held = {}
    for recent in (0, 3):
        params = GridParams(resolution=0.05, free_scan_stride=1, recent_free_observations=recent)
        poses = [(-2.0, 0.0), (-2.0, 0.3), (-2.0, -0.3)]
        first = local(poses * 3, box, params)  # an earlier submap: the box is there
        grid = local(poses * 8, box, params)  # this submap: there for 24 scans ...
        for xy in poses * 2:  # ... then gone for 6
            grid.integrate_scan(se2_to_matrix(*xy, 0.0), room_scan(xy, None))
        assert occupied(grid, front)  # the submap's own evidence: still occupied
        g = EvidenceGrid(np.array([-6.0, -6.0]), (240, 240), params)
        fuse_submap_grids(g, first, np.eye(4))
        fuse_submap_grids(g, grid, np.eye(4))
        held[recent] = occupied(g, front)
        assert occupied(g, (HALF + 0.01, 2.0)) and occupied(g, (-HALF + 0.01, -1.0))
    assert held == {0: True, 3: False}


def test_pgm_yaml_round_trip(tmp_path):
    prob = np.full((4, 6), 0.5)
    prob[0, 0] = 0.99  # row 0 = lowest y -> bottom row of the image
    prob[3, 5] = 0.01
    pgm, yml = write_pgm_yaml(tmp_path / "m", prob, np.array([1.0, 2.0]), 0.05)
    img = read_pgm(pgm)
    assert img.shape == (4, 6)
    assert img[3, 0] == OCCUPIED and img[0, 5] == FREE
    text = yml.read_text()
    assert "image: m.pgm" in text and "resolution: 0.05" in text and "origin: [1.000000, 2.000000, 0.0]" in text


def test_the_grid_evidence_model_is_set_from_the_config():
    from types import SimpleNamespace

    from submapslam.config import config_from_dict
    from submapslam.mapping.global_map import grid_params

    cfg = config_from_dict({"mapping": {"grid": {"l_occ": 1.2, "free_scan_stride": 3}, "grid_resolution": 0.1,
                                        "grid_max_free_range_3d": 25.0}})
    planar = grid_params(SimpleNamespace(config=cfg, planar=True))
    assert (planar.l_occ, planar.free_scan_stride, planar.resolution, planar.max_free_range) == (1.2, 3, 0.1, 12.0)
    spatial = grid_params(SimpleNamespace(config=cfg, planar=False))
    assert (spatial.l_occ, spatial.resolution, spatial.max_free_range) == (1.2, 0.2, 25.0)
    default = grid_params(SimpleNamespace(config=config_from_dict({}), planar=False))
    assert (default.l_occ, default.resolution, default.max_free_range) == (0.85, 0.2, 30.0)


def test_probabilities_consumed_in_place_equal_the_copy():
    params = GridParams(resolution=0.05, free_scan_stride=1)
    grid = local([(0.0, 0.0), (1.0, 0.5)], None, params)
    logodds = grid.logodds.copy()
    copy = grid.probabilities()
    assert np.array_equal(grid.logodds, logodds)  # the default leaves the grid as it was
    consumed = grid.probabilities(consume=True)
    assert consumed is grid.logodds  # no second grid-sized array: the log-odds' own
    assert np.array_equal(consumed, copy)
    assert np.allclose(copy, 1.0 / (1.0 + np.exp(-logodds)))
    assert (copy[logodds > 0] > 0.5).all() and (copy[logodds < 0] < 0.5).all()


def test_a_scans_rays_traced_in_parts_give_the_grid_traced_at_once(monkeypatch):
    """A 3D scan's rays go in parts above RAY_POINTS_AT_ONCE (a 64-ring scan's reach 1.1 M ray
    points, 44 MB of temporaries at once): every cell still counts once per scan, with the sensor
    inside the grid and with part of the scan beyond its edge."""
    import submapslam.mapping.evidence_grid as evidence_grid

    params = GridParams(resolution=0.05, free_scan_stride=1)
    people = [(2.0, 0.0, 0.25), None, (-1.0, 1.5, 0.3)]
    poses = [(0.0, 0.0), (1.0, 0.5), (-3.0, 2.0)]

    def traced(origin, shape):
        grid = EvidenceGrid(np.array(origin), shape, params)
        for xy, person in zip(poses, people):
            grid.integrate_scan(se2_to_matrix(*xy, 0.3), room_scan(xy, person), no_returns=None)
        return grid

    for origin, shape in (((-6.0, -6.0), (240, 240)), ((-6.0, -2.0), (240, 160))):  # the room inside, part outside
        at_once = traced(origin, shape)
        monkeypatch.setattr(evidence_grid, "RAY_POINTS_AT_ONCE", 700)  # a few dozen rays a part
        in_parts = traced(origin, shape)
        monkeypatch.undo()
        assert (at_once.logodds < 0).sum() > 1000  # free space was carved
        np.testing.assert_array_equal(in_parts.logodds, at_once.logodds)
        np.testing.assert_array_equal(in_parts.free_run, at_once.free_run)


def test_fused_evidence_stays_within_its_bounds_where_submaps_add_up():
    """Fusing clips the cells a submap touched (not the whole grid): walls seen by many submaps
    saturate at l_max, space seen free by many at l_min, and untouched cells stay 0."""
    params = GridParams(resolution=0.05, free_scan_stride=1, recent_free_observations=0)
    g = EvidenceGrid(np.array([-8.0, -8.0]), (320, 320), params)
    for _ in range(12):
        fuse_submap_grids(g, local([(0.0, 0.0), (1.0, 0.5), (-1.0, -0.5)] * 4, None, params), np.eye(4))
    assert g.logodds.max() == params.l_max
    assert g.logodds.min() == params.l_min
    assert g.logodds[0, 0] == 0.0  # beyond the room: never touched
