"""``batch --address``: a Ray cluster started apart (``ray start``, token authentication on, a
second node), joined by the command, with and without shipping the logs through Ray."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest

from datasets_synth import generate
from submapslam.errors import SubmapSlamError
from submapslam.io.bundle import pack, replace_with, unpack
from submapslam.ray_cluster import find_token, probe_gcs, split_address

CLI = [sys.executable, "-m", "submapslam"]
SCANS = 60


def _free_port() -> int:
    """A free TCP port outside the range Ray gives its workers (10002-19999)."""
    while True:
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            port = s.getsockname()[1]
        if not 10002 <= port <= 19999:
            return port


def test_token_is_found_where_ray_keeps_it(tmp_path):
    (tmp_path / ".ray").mkdir()
    (tmp_path / ".ray" / "auth_token").write_text("from-home\n")
    (tmp_path / "t").write_text("from-path")
    assert find_token({}, home=tmp_path).value == "from-home"
    assert find_token({"RAY_AUTH_TOKEN_PATH": str(tmp_path / "t")}, home=tmp_path).value == "from-path"
    found = find_token({"RAY_AUTH_TOKEN": "from-env", "RAY_AUTH_TOKEN_PATH": str(tmp_path / "t")}, home=tmp_path)
    assert (found.value, found.where) == ("from-env", "RAY_AUTH_TOKEN")
    assert find_token({}, home=tmp_path / "nobody") is None


def test_addresses_and_an_address_where_nothing_answers():
    assert split_address("10.0.0.2:6379") == ("10.0.0.2", 6379)
    assert split_address("ray://head:10001") == ("head", 10001)
    for bad in ("head", "head:port", ":6379"):
        with pytest.raises(SubmapSlamError, match="HOST:PORT"):
            split_address(bad)
    pytest.importorskip("grpc")
    assert probe_gcs(f"127.0.0.1:{_free_port()}", timeout_s=2) == "unreachable"


def test_bundles_carry_a_file_or_a_folder_and_replace_a_folder_whole(tmp_path):
    log = tmp_path / "drive.clf.bz2"
    log.write_bytes(os.urandom(3000))
    back = unpack(pack(log), tmp_path / "elsewhere")
    assert back.name == "drive.clf.bz2" and back.read_bytes() == log.read_bytes()
    results = tmp_path / "res"
    (results / "map").mkdir(parents=True)
    (results / "poses_tum.txt").write_text("1 0 0 0 0 0 0 1\n")
    (results / "map" / "manifest.json").write_text("{}")
    dest = tmp_path / "out" / "drive"
    dest.mkdir(parents=True)
    (dest / "stale.txt").write_text("from before")
    replace_with(pack(results), dest)
    assert sorted(p.relative_to(dest).as_posix() for p in dest.rglob("*")) == ["map", "map/manifest.json",
                                                                               "poses_tum.txt"]
    assert [p.name for p in dest.parent.iterdir()] == ["drive"]  # nothing left beside it


def _ray(home: Path, *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "HOME": str(home), "RAY_AUTH_MODE": "token", "RAY_USAGE_STATS_ENABLED": "0"}
    env.pop("RAY_AUTH_TOKEN", None)
    env.pop("RAY_AUTH_TOKEN_PATH", None)
    return subprocess.run([str(Path(sys.executable).with_name("ray")), *args], env=env, capture_output=True,
                          text=True, timeout=180)


def _stop_cluster(temp_dir: Path, port: int) -> None:
    """Kill this cluster's processes only (``ray stop`` would end every Ray instance of the
    machine, among them other tests' local ones): those whose command line names its folder or
    its head's address, and every process they started."""
    parent, named = {}, set()
    for pid_dir in Path("/proc").iterdir():
        if not pid_dir.name.isdigit():
            continue
        try:
            cmdline = (pid_dir / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            parent[int(pid_dir.name)] = int((pid_dir / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, ValueError, IndexError):
            continue
        if str(temp_dir) in cmdline or f"address=127.0.0.1:{port}" in cmdline or f":{port} " in cmdline:
            named.add(int(pid_dir.name))
    doomed = set(named)
    grown = True
    while grown:  # their descendants (Ray's agents rename themselves: "ray::DashboardAgent")
        more = {pid for pid, ppid in parent.items() if ppid in doomed} - doomed
        doomed |= more
        grown = bool(more)
    for pid in doomed - {os.getpid()}:
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    shutil.rmtree(temp_dir, ignore_errors=True)


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    """A head started with ``ray start`` (token authentication on; its token in a home of its
    own) and a second node of one CPU joined to it: ``(address, home holding the token)``."""
    pytest.importorskip("ray")
    pytest.importorskip("grpc")
    home = tmp_path_factory.mktemp("home")
    temp_dir = Path(f"/tmp/rt{uuid.uuid4().hex[:8]}")  # short: Ray's socket paths have a length limit
    port = _free_port()
    address = f"127.0.0.1:{port}"
    try:
        made = _ray(home, "get-auth-token", "--generate")  # the token, in this home's ~/.ray/auth_token
        assert made.returncode == 0, made.stderr
        head = _ray(home, "start", "--head", f"--port={port}", "--num-cpus=1", "--include-dashboard=false",
                    "--disable-usage-stats", f"--temp-dir={temp_dir}", f"--ray-client-server-port={_free_port()}")
        assert head.returncode == 0, head.stderr
        assert (home / ".ray" / "auth_token").is_file()
        node = _ray(home, "start", f"--address={address}", "--num-cpus=1", "--disable-usage-stats")
        assert node.returncode == 0, node.stderr
        deadline = time.monotonic() + 60
        while _alive_nodes(home, address) < 2:  # both nodes registered before any test
            assert time.monotonic() < deadline, "the second node did not join"
            time.sleep(1)
        yield address, home
    finally:
        _stop_cluster(temp_dir, port)


def _alive_nodes(home: Path, address: str) -> int:
    code = "import ray; ray.init(address=%r, log_to_driver=False); print(sum(n['Alive'] for n in ray.nodes()))"
    env = {**os.environ, "HOME": str(home), "RAY_AUTH_MODE": "token"}
    out = subprocess.run([sys.executable, "-c", code % address], env=env, capture_output=True, text=True, timeout=120)
    return int(out.stdout.strip().splitlines()[-1]) if out.returncode == 0 and out.stdout.strip() else 0


@pytest.fixture(scope="module")
def halls(tmp_path_factory):
    root = tmp_path_factory.mktemp("halls")
    a = generate("rectangle", root / "hall.a", seed=0, laps=1, size=(20.0, 12.0), max_scans=SCANS)
    b = generate("rectangle", root / "hall.b", seed=1, laps=1, size=(20.0, 12.0), max_scans=SCANS)
    return a, b


def _batch(home: Path, *args: str, token: bool = True, cwd: Path | None = None,
           **environ: str) -> subprocess.CompletedProcess:
    # without this process's RAY_AUTH_* (a local Ray started by an earlier test in this process
    # sets RAY_AUTH_MODE in its environment)
    env = {k: v for k, v in os.environ.items() if not k.startswith("RAY_AUTH")} | environ
    env["HOME"] = str(home) if token else str(home / "nobody")  # where the token is, or no token at all
    env["PYTHONPATH"] = os.pathsep.join([str(Path(__file__).resolve().parents[1]), env.get("PYTHONPATH", "")])
    return subprocess.run([*CLI, "batch", *args], env=env, capture_output=True, text=True, timeout=600, cwd=cwd)


def test_batch_joins_a_cluster_with_token_auth_with_and_without_shipping_the_logs(cluster, halls, tmp_path):
    address, home = cluster
    a, b = halls
    here = _batch(home, str(a), str(b), "--no-ray", "--out", str(tmp_path / "here"))
    assert here.returncode == 0, here.stderr
    outs = {}
    for ship in ("never", "always"):
        out = tmp_path / ship
        # the logs named relative to this folder: a cluster's workers run in folders of their own
        res = _batch(home, a.name, b.name, "--address", address, "--ship-logs", ship, "--out", str(out), cwd=a.parent)
        assert res.returncode == 0, res.stdout + res.stderr
        assert "gcs_client" not in res.stdout + res.stderr and "Traceback" not in res.stderr  # Ray kept quiet
        outs[ship] = out
    for out in outs.values():
        for name in ("hall.a", "hall.b"):
            assert (out / name / "poses_tum.txt").read_bytes() == (tmp_path / "here" / name / "poses_tum.txt").read_bytes()
        for name in ("poses_tum.txt", "map.pgm", "map.ply"):
            assert (out / "merged" / name).read_bytes() == (tmp_path / "here" / "merged" / name).read_bytes(), name
    # shipped: the results name the user's log, not the worker's copy of it
    shipped = json.loads((outs["always"] / "hall.a" / "input.json").read_text())
    assert shipped["path"] == str(a.resolve()) and shipped["sha256"] == json.loads(
        (outs["never"] / "hall.a" / "input.json").read_text())["sha256"]
    assert json.loads((outs["always"] / "hall.a" / "summary.json").read_text())["source"] == str(a.resolve())
    assert sorted(p.name for p in outs["always"].glob(".*")) == sorted(p.name for p in outs["never"].glob(".*"))


def test_a_missing_token_or_a_wrong_address_is_one_line(cluster, halls, tmp_path):
    address, home = cluster
    a, _ = halls
    res = _batch(home, str(a), "--address", address, "--out", str(tmp_path / "x"), token=False)
    assert res.returncode == 1
    lines = [ln for ln in res.stdout.splitlines() + res.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "token authentication" in lines[0] and "RAY_AUTH_TOKEN" in lines[0], lines
    wrong = home / "wrong_token"
    wrong.write_text("not-the-token")
    res = _batch(home, str(a), "--address", address, "--out", str(tmp_path / "y"), RAY_AUTH_TOKEN_PATH=str(wrong))
    assert res.returncode == 1 and "refused the token" in res.stderr, res.stdout + res.stderr
    nobody = f"127.0.0.1:{_free_port()}"
    res = _batch(home, str(a), "--address", nobody, "--out", str(tmp_path / "z"))
    assert res.returncode == 1 and "no Ray cluster answers" in res.stderr, res.stdout + res.stderr
    assert "Traceback" not in res.stderr
    assert not any((tmp_path / d).exists() and any((tmp_path / d).iterdir()) for d in ("x", "y", "z"))


def test_a_node_sees_the_logs_only_as_they_are_here(tmp_path):
    """What ``--ship-logs auto`` asks each node (a task pinned to it runs this): every log there
    with the same size (a folder as a folder), and the output folder writable."""
    from submapslam.fleet_ray import sees_files

    log = tmp_path / "a.clf"
    log.write_text("FLASER 0\n")
    folder_log = tmp_path / "scans"
    folder_log.mkdir()
    out = tmp_path / "out"
    out.mkdir()
    assert sees_files([(str(log), log.stat().st_size), (str(folder_log), None)], str(out))
    assert not sees_files([(str(log), log.stat().st_size + 1)], str(out))  # another file of that name
    assert not sees_files([(str(tmp_path / "elsewhere.clf"), 9)], str(out))
    assert not sees_files([(str(log), None)], str(out))  # a file where a folder was
    assert not sees_files([(str(log), log.stat().st_size)], str(tmp_path / "no_such_folder"))
