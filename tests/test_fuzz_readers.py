"""Property-based tests (Hypothesis) over every reader and the YAML config: whatever the bytes,
the answer is a result or one line (a :class:`SubmapSlamError`), never another exception, and
never a NaN in what is returned. Example counts are bounded: all of them take well under 30 s."""

import bz2
import gzip
import math
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from submapslam.config import PipelineConfig, dump_config, load_config
from submapslam.errors import SubmapSlamError
from submapslam.io.carmen import laser_choices
from submapslam.io.hints import hint_problems, read_hint_file
from submapslam.io.registry import open_log

from .test_carmen_records import flaser_line, odom_line, rawlaser_line, robotlaser_line

FUZZ = settings(deadline=None, derandomize=True, suppress_health_check=list(HealthCheck), database=None)


def fuzz(examples: int) -> settings:
    """The shared settings (no deadline, same examples every run, no database) with a bounded count."""
    return settings(FUZZ, max_examples=examples)


def workdir():
    return tempfile.TemporaryDirectory(prefix="fuzz-")


def one_line(exc: SubmapSlamError) -> None:
    text = str(exc)
    assert text and "\n" not in text, repr(text)


def assert_clean_scans(scans) -> None:
    for k, s in enumerate(scans):
        assert s.index == k
        assert s.points.ndim == 2 and s.points.shape[1] == 3
        assert np.isfinite(s.points).all(), s.source
        assert math.isfinite(s.timestamp), s.source
        if s.odometry is not None:
            assert s.odometry.shape == (4, 4) and np.isfinite(s.odometry).all()
        if s.point_times is not None:
            assert len(s.point_times) == len(s.points) and np.isfinite(s.point_times).all()


def read_log(path: Path, **options):
    """All scans of the log, or None after a one-line error; any other exception fails the test."""
    try:
        reader = open_log(path, **options)
        scans = list(reader)
    except SubmapSlamError as exc:
        one_line(exc)
        return None
    assert_clean_scans(scans)
    info = getattr(reader, "log_info", {})
    assert info.get("skipped_records", 0) >= 0
    return scans


# ------------------------------------------------------------------------------------- CARMEN
TOKENS = st.one_of(
    st.sampled_from(["0", "1", "-1", "3", "5", "12", "181", "1e308", "-1e308", "1e400", "nan", "inf", "-inf",
                     "x", "", "0.5", "99999999999", "²", "٣", "0x10", "1_0", "--", "#", "\x00"]),
    st.integers(-3, 30).map(str),
    st.floats(allow_nan=True, allow_infinity=True, width=32).map(repr),
    st.text(alphabet="abcXYZ.-+e0123456789", max_size=6),
)
TAGS = st.sampled_from(["FLASER", "RLASER", "ROBOTLASER1", "ROBOTLASER2", "RAWLASER1", "RAWLASER3", "ODOM",
                        "PARAM", "TRUEPOS", "NEFF", "FOO", "flaser", "#", "garbled~", "ODOM ODOM"])
RANDOM_LINE = st.builds(lambda tag, toks: " ".join([tag, *toks]), TAGS, st.lists(TOKENS, max_size=40))
GOOD_LINES = [flaser_line([2.0] * 5, ts=100.0), robotlaser_line([2.0] * 5, ts=100.05),
              robotlaser_line([2.0] * 5, ts=100.07, remissions=False), rawlaser_line([2.0] * 5, 100.1),
              odom_line(0.1, 0.2, 0.3, 100.02), odom_line(0.2, 0.2, 0.3, 100.2)]


@st.composite
def mutated_line(draw):
    """A valid record with one damage: cut short, a token replaced, dropped or doubled."""
    tokens = draw(st.sampled_from(GOOD_LINES)).split()
    i = draw(st.integers(0, len(tokens) - 1))
    kind = draw(st.sampled_from(["cut", "replace", "drop", "double"]))
    if kind == "cut":
        tokens = tokens[:i]
    elif kind == "replace":
        tokens[i] = draw(TOKENS)
    elif kind == "drop":
        del tokens[i]
    else:
        tokens.insert(i, tokens[i])
    return " ".join(tokens)


CARMEN_LINES = st.lists(st.one_of(st.sampled_from([ln.strip() for ln in GOOD_LINES]), mutated_line(), RANDOM_LINE),
                        min_size=0, max_size=12)


def _replaced(line: str, index: int, token: str) -> str:
    tokens = line.split()
    tokens[index] = token
    return " ".join(tokens)


@fuzz(250)
@given(lines=CARMEN_LINES, laser=st.sampled_from([None, *laser_choices()]), skip_bad=st.booleans())
@example(lines=[_replaced(GOOD_LINES[1], 14, "²")], laser=None, skip_bad=False)  # a digit int() refuses
@example(lines=["FLASER 1 2.00 1.0 2.0 0.5 1.0 2.0 0.5 100.000000 host 1.000000"], laser=None, skip_bad=False)
def test_carmen_reader_gives_scans_or_one_line(lines, laser, skip_bad):
    with workdir() as d:
        path = Path(d) / "log.clf"
        path.write_text("\n".join(lines) + "\n")
        scans = read_log(path, format="carmen", laser=laser, skip_bad=skip_bad)
        if scans is not None and skip_bad:
            assert len(scans) > 0


@fuzz(40)
@given(data=st.binary(max_size=300), suffix=st.sampled_from([".clf", ".clf.gz", ".clf.bz2", ".log.xz"]),
       keep=st.floats(0.0, 1.0))
def test_damaged_compressed_carmen_logs_give_one_line(data, suffix, keep):
    """Random bytes, and a valid compressed log cut short."""
    with workdir() as d:
        path = Path(d) / f"log{suffix}"
        path.write_bytes(data)
        read_log(path, format="carmen")
        text = "".join(GOOD_LINES * 3).encode()
        packed = {".gz": gzip.compress, ".bz2": bz2.compress}.get(path.suffix, lambda b: b)(text)
        path.write_bytes(packed[: int(len(packed) * keep)])
        read_log(path, format="carmen")


# ---------------------------------------------------------------------------------- hints
HINT_TOKENS = st.one_of(st.integers(-5, 100).map(str), st.floats(allow_nan=True, allow_infinity=True).map(repr),
                        st.sampled_from(["12", "1.5", "nan", "1e999", "²", "", "#", "0x1", "007", "1.0e2"]))


@fuzz(150)
@given(lines=st.lists(st.lists(HINT_TOKENS, max_size=4).map(" ".join), max_size=8))
def test_hint_files_give_hints_or_one_line_and_problems_never_raise(lines):
    with workdir() as d:
        path = Path(d) / "hints.txt"
        path.write_text("\n".join(lines) + "\n")
        try:
            hints = read_hint_file(path)
        except SubmapSlamError as exc:
            one_line(exc)
            return
    for h in hints:
        assert math.isfinite(h.a) and math.isfinite(h.b)
    stamps = 100.0 + 0.1 * np.arange(30)
    problems = hint_problems(hints, stamps, [list(range(0, 10)), list(range(10, 30))])
    assert all(isinstance(p, str) and "\n" not in p for p in problems)
    assert len(problems) <= len(hints)


# ---------------------------------------------------------------------------------- config
CONFIG_KEYS = sorted({k for section in PipelineConfig().model_dump().values() if isinstance(section, dict)
                      for k in section})
SECTIONS = sorted(PipelineConfig().model_dump())
VALUES = st.one_of(st.none(), st.booleans(), st.integers(-10, 10**6), st.floats(allow_nan=True, allow_infinity=True),
                   st.text(max_size=8), st.lists(st.integers(), max_size=3))
SECTION_BODY = st.dictionaries(st.one_of(st.sampled_from(CONFIG_KEYS), st.text(max_size=6)), VALUES, max_size=4)


SPECIAL = st.sampled_from([float("nan"), float("inf"), float("-inf"), 0.0, -1.0, 1e300, 0, -7])
SECTION_KEYS = sorted((sec, key) for sec, body in PipelineConfig().model_dump().items() if isinstance(body, dict)
                      for key in body)


@fuzz(150)
@given(doc=st.dictionaries(st.one_of(st.sampled_from(SECTIONS), st.text(max_size=6)),
                           st.one_of(SECTION_BODY, VALUES), max_size=3),
       real=st.lists(st.tuples(st.sampled_from(SECTION_KEYS), st.one_of(SPECIAL, VALUES)), max_size=3),
       raw=st.text(max_size=80), mode=st.sampled_from(["random", "real keys", "text"]))
def test_yaml_config_gives_a_config_or_one_line(doc, real, raw, mode):
    """Random documents, real keys with random values, and random text."""
    if mode == "real keys":
        doc = {}
        for (section, key), value in real:
            doc.setdefault(section, {})[key] = value
    with workdir() as d:
        path = Path(d) / "c.yaml"
        path.write_text(raw if mode == "text" else yaml.safe_dump(doc))
        try:
            cfg = load_config(path)
        except SubmapSlamError as exc:
            one_line(exc)
            return
    text = dump_config(cfg)  # an accepted config holds no NaN/inf a run would trip over
    assert ".nan" not in text and ".inf" not in text, text


# ------------------------------------------------------------------ cloud folders, PLY and PCD
PLY_HEAD = ("ply\nformat {fmt} 1.0\nelement vertex {n}\nproperty {t} x\nproperty {t} y\nproperty {t} z\n"
            "{extra}end_header\n")
PCD_HEAD = ("# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {n}\nHEIGHT 1\n"
            "POINTS {n}\nDATA {fmt}\n")


@st.composite
def cloud_file(draw):
    n = draw(st.sampled_from([0, 1, 3, 20, -1, 10**9]))
    if draw(st.booleans()):
        head = PLY_HEAD.format(fmt=draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian"])),
                               n=n, t=draw(st.sampled_from(["float", "double"])),
                               extra=draw(st.sampled_from(["", "property float time\n", "property list uchar int i\n"])))
        suffix = ".ply"
    else:
        head = PCD_HEAD.format(fmt=draw(st.sampled_from(["ascii", "binary", "binary_compressed"])), n=n)
        suffix = ".pcd"
    body = draw(st.one_of(
        st.binary(max_size=400),
        st.lists(st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=32)] * 3), max_size=25)
        .map(lambda rows: "".join(f"{x} {y} {z}\n" for x, y, z in rows).encode()),
    ))
    return suffix, head.encode() + body


@fuzz(30)
@given(files=st.lists(cloud_file(), min_size=1, max_size=3), skip_bad=st.booleans())
def test_ply_and_pcd_folders_give_scans_or_one_line(files, skip_bad):
    with workdir() as d:
        for k, (suffix, data) in enumerate(files):
            (Path(d) / f"{k:06d}{suffix}").write_bytes(data)
        read_log(Path(d), format="cloud_folder", skip_bad=skip_bad)


TEXT_FILE = st.one_of(st.none(), st.lists(st.one_of(HINT_TOKENS, st.just("1.0 2.0")), max_size=5).map("\n".join))
META = st.one_of(st.none(), st.text(max_size=30),
                 st.fixed_dictionaries({}, optional={"planar": VALUES, "T_base_sensor": st.one_of(
                     VALUES, st.lists(st.lists(st.floats(allow_nan=True), min_size=4, max_size=4), max_size=4))})
                 .map(yaml.safe_dump))


@fuzz(80)
@given(bins=st.lists(st.one_of(st.binary(max_size=200),
                               st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), max_size=40)
                               .map(lambda v: np.asarray(v[: len(v) // 4 * 4], dtype=np.float32).tobytes())),
                     min_size=1, max_size=3),
       times=TEXT_FILE, odometry=TEXT_FILE, meta=META, skip_bad=st.booleans())
def test_kitti_bin_folders_give_scans_or_one_line(bins, times, odometry, meta, skip_bad):
    with workdir() as d:
        root = Path(d)
        (root / "velodyne").mkdir()
        for k, data in enumerate(bins):
            (root / "velodyne" / f"{k:06d}.bin").write_bytes(data)
        for name, text in (("times.txt", times), ("odometry_tum.txt", odometry), ("meta.yaml", meta)):
            if text is not None:
                (root / name).write_text(text)
        read_log(root, skip_bad=skip_bad)


# ------------------------------------------------------------------------------------ bags
@pytest.fixture(scope="module")
def small_bags(tmp_path_factory):
    """A valid ROS 1 bag and MCAP file: 4 clouds of 30 points and wheel odometry."""
    from .test_rosbag import BagWriter, random_clouds

    root = tmp_path_factory.mktemp("bags")
    out = {}
    for name in ("a.bag", "a.mcap"):
        w = BagWriter(root / name)
        for k, cloud in enumerate(random_clouds(4, 30)):
            w.odom("/odom", 1_700_000_000 + 0.1 * k, 0.1 * k, 0.0, 0.0)
            w.cloud("/points", 1_700_000_000 + 0.1 * k + 0.01, cloud)
        out[name] = w.write().read_bytes()
    return out


@fuzz(60)
@given(name=st.sampled_from(["a.bag", "a.mcap"]), keep=st.floats(0.0, 1.0),
       flips=st.lists(st.tuples(st.floats(0.0, 1.0), st.integers(0, 255)), max_size=4))
@example(name="a.mcap", keep=0.5, flips=[(0.00390625, 1)])  # a header length of petabytes: MemoryError
def test_damaged_bags_give_scans_or_one_line(small_bags, name, keep, flips):
    data = bytearray(small_bags[name])
    for where, value in flips:
        data[int(where * (len(data) - 1))] = value
    with workdir() as d:
        path = Path(d) / name
        path.write_bytes(bytes(data[: max(1, int(len(data) * keep))]))
        read_log(path)
        shutil.rmtree(d, ignore_errors=True)


def test_no_config_number_takes_nan_or_infinity(tmp_path):
    """Exhaustive over the config's number keys: .nan, .inf and -.inf are refused in one line."""
    path = tmp_path / "c.yaml"
    accepted = []
    for section, key in SECTION_KEYS:
        default = PipelineConfig().model_dump()[section][key]
        if isinstance(default, bool) or not isinstance(default, (int, float)):
            continue
        for value in (".nan", ".inf", "-.inf"):
            path.write_text(f"{section}:\n  {key}: {value}\n")
            try:
                load_config(path)
            except SubmapSlamError as exc:
                one_line(exc)
                continue
            accepted.append(f"{section}.{key}: {value}")
    assert accepted == []


# ----------------------------------------------------- format sniffing and trajectory files
@fuzz(40)
@given(data=st.one_of(st.binary(max_size=200), st.lists(RANDOM_LINE, max_size=4).map(lambda ls: "\n".join(ls).encode())),
       name=st.sampled_from(["x.clf", "x.log.gz", "x.bag", "x.mcap", "x.txt", "x.ply", "x.pcd", "x", "x.clf.bz2"]))
def test_any_file_opened_without_a_format_gives_scans_or_one_line(data, name):
    with workdir() as d:
        path = Path(d) / name
        path.write_bytes(data)
        read_log(path)


TRAJECTORY_ROW = st.lists(st.one_of(st.floats(allow_nan=True, allow_infinity=True).map(repr), TOKENS),
                          min_size=7, max_size=13).map(" ".join)


@fuzz(40)
@given(rows=st.lists(st.one_of(TRAJECTORY_ROW, st.sampled_from(["1 0 0 0 0 0 0 1", "# c", "", "1,2,3"])), max_size=6),
       name=st.sampled_from(["t.txt", "t.tum", "t.log"]))
@example(rows=["1 0 0 0 0 0 0 0"], name="t.txt")  # a zero quaternion
def test_trajectory_files_give_poses_or_one_line(rows, name):
    from submapslam.io.trajectory import read_trajectory

    with workdir() as d:
        path = Path(d) / name
        path.write_text("\n".join(rows) + "\n")
        try:
            traj = read_trajectory(path)
        except SubmapSlamError as exc:
            one_line(exc)
            return
    assert np.isfinite(traj.timestamps).all() and np.isfinite(traj.poses).all()


# ------------------------------------------------------------------ landmark logs (ekf)
VP_LINE = st.one_of(
    st.builds(lambda i, vals: f"ODOMETRY {i} {i + 1} " + " ".join(vals), st.integers(-2, 5),
              st.lists(st.one_of(st.sampled_from(["0.1", "0", "-1", "nan", "inf", "1e-3"]), TOKENS),
                       min_size=0, max_size=11)),
    st.builds(lambda i, lid, vals: f"LANDMARK {i} {lid} " + " ".join(vals), st.integers(-2, 5), st.integers(0, 3),
              st.lists(st.one_of(st.sampled_from(["1.0", "0", "-1", "nan", "inf", "0.01"]), TOKENS),
                       min_size=0, max_size=8)),
    RANDOM_LINE,
)
GOOD_VP = ["ODOMETRY 0 1 0.1 0.0 0.01 0.01 0 0 0.01 0 0.001", "LANDMARK 1 0 5.0 1.0 0.01 0 0.01"]


@fuzz(60)
@given(lines=st.lists(st.one_of(st.sampled_from(GOOD_VP), VP_LINE), max_size=8))
@example(lines=["ODOMETRY 0 1 nan 0.0 0.01 0.01 0 0 0.01 0 0.001"])
def test_victoria_park_format_gives_a_landmark_log_or_one_line(lines):
    from submapslam.io.landmark_logs import read_landmark_log

    with workdir() as d:
        path = Path(d) / "vp.txt"
        path.write_text("\n".join(lines) + "\n")
        try:
            log = read_landmark_log(path)
        except SubmapSlamError as exc:
            one_line(exc)
            return
    assert np.isfinite(log.measurement_cov).all() and np.all(np.diag(log.measurement_cov) >= 0)
    for step in log.steps:
        assert np.isfinite(step.motion).all() and np.isfinite(step.motion_cov).all()
        assert np.isfinite(step.ranges_bearings).all()
        assert np.linalg.eigvalsh(step.motion_cov).min() >= -1e-12
