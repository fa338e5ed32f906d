"""CLI command ``synth``: write a synthetic log (a named world, or a city along a KITTI path)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from ..errors import SubmapSlamError
from ._common import Overwrite, console, fail


def register(app: typer.Typer) -> None:
    """Add ``synth`` to ``app``."""

    @app.command("synth")
    def synth_cmd(
        world: Annotated[str, typer.Argument(help="rectangle, rooms, figure8, outdoor, aliased, kitti (a city "
                                                  "along a KITTI ground-truth path: --path, --rings), or landmarks "
                                                  "(a point-landmark log for `ekf`: --vanish, --appear).")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output log folder.")],
        seed: Annotated[int, typer.Option(help="Random seed (same seed, same files).")] = 0,
        laps: Annotated[int | None, typer.Option(help="Laps around the loop [default: 2].")] = None,
        sensor: Annotated[str | None, typer.Option(help="laser2d or lidar3d (default: the world's); kitti: livox "
                                                         "(a forward 70 deg non-repetitive pattern instead of "
                                                         "--rings).")] = None,
        max_scans: Annotated[int | None, typer.Option(min=1, help="Cut the log after N scans.")] = None,
        odometry_noise: Annotated[float, typer.Option(min=0.0, help="Scale of the wheel-odometry noise (0: exact).")] = 1.0,
        poles: Annotated[int, typer.Option(min=0, help="rectangle: free-standing poles (EKF point features).")] = 0,
        path: Annotated[Path | None, typer.Option("--path", help="kitti: KITTI pose file (NN.txt or NN.txt.xz).")] = None,
        rings: Annotated[int, typer.Option(help="kitti: 16 (VLP-16 like), 64 (HDL-64E like) or 128 (OS1-128 "
                                                "like).")] = 16,
        terrain: Annotated[bool, typer.Option("--terrain", help="kitti: the ground follows the path's real "
                                                                "height; the vehicle pitches and rolls with "
                                                                "the road.")] = False,
        keyframes: Annotated[bool, typer.Option("--keyframes", help="kitti: irregular keyframes (0.2-0.5 s "
                                                                    "apart, stops of 6-13 s standing "
                                                                    "still).")] = False,
        movers: Annotated[int, typer.Option(min=0, help="Things that move: kitti: cars both ways, pedestrians, parked "
                                                        "cars that leave; 2D worlds: people and boxes. Labelled in "
                                                        "labels/NNNNNN.label (SemanticKITTI).")] = 0,
        doors: Annotated[int, typer.Option(min=0, help="rooms: doors in the room doorways that open and close "
                                                      "(labelled 259 when they change state).")] = 0,
        vanish: Annotated[float, typer.Option(min=0.0, max=1.0, help="landmarks: fraction of the landmarks that "
                                                                    "vanish halfway.")] = 0.0,
        appear: Annotated[int, typer.Option(min=0, help="landmarks: new landmarks that appear halfway.")] = 0,
        landmarks: Annotated[int | None, typer.Option(min=1, help="landmarks: landmarks at the start "
                                                                 "[default: 30].")] = None,
        p_miss: Annotated[float, typer.Option(min=0.0, max=1.0, help="landmarks: chance a landmark in range is "
                                                                    "not detected.")] = 0.0,
        clutter: Annotated[float, typer.Option(min=0.0, help="landmarks: false detections per step (Poisson "
                                                            "mean).")] = 0.0,
        overwrite: Overwrite = False,
    ) -> None:
        """Generate a synthetic world and write it as a log folder (and CARMEN for 2D).

        ``synth landmarks --vanish 0.33 --appear 10 --out DIR`` writes ``DIR/landmarks.txt`` (the
        Victoria Park format that ``ekf`` reads) with ``landmarks_truth.csv`` (which landmark
        exists at which steps), ``poses_truth.txt`` and ``landmarks_meta.yaml`` beside it.

        ``synth kitti --path 00.txt.xz --rings 16 --out DIR`` drives the KITTI path through a
        generated city and ray-casts a Velodyne-like LiDAR at every pose (10 Hz). The log is
        written into a staging folder beside OUT and appears as OUT only when complete.
        """
        from ..io.output_folder import staged_folder

        try:
            if laps is not None and laps < 1:
                raise SubmapSlamError(f"--laps must be 1 or more, not {laps}")
            landmark_opts = (("--vanish", vanish or None), ("--appear", appear or None),
                             ("--p-miss", p_miss or None), ("--clutter", clutter or None), ("--landmarks", landmarks))
            if world != "landmarks":
                unused = [name for name, value in landmark_opts if value is not None]
                if unused:
                    raise SubmapSlamError(f"{', '.join(unused)} only for synth landmarks, not {world!r}")
            if doors and world != "rooms":
                raise SubmapSlamError(f"--doors is for the rooms world, not {world!r}")
            if world == "landmarks":
                _check_landmark_options(path=path, sensor=sensor, poles=poles, movers=movers, max_scans=max_scans,
                                        odometry_noise=odometry_noise != 1.0)
                with staged_folder(out, "synth", overwrite=overwrite) as staging:
                    meta = _landmarks(staging, seed, laps or 2, landmarks or 30, vanish, appear, p_miss, clutter)
                console.print(f"{meta} -> {out}/landmarks.txt")
                return
            if world == "kitti":
                _check_kitti_options(path, rings, laps=laps, sensor=sensor, poles=poles)
            elif terrain or keyframes:
                raise SubmapSlamError(f"--terrain and --keyframes are for the kitti world, not {world!r}")
            elif path is not None:
                raise SubmapSlamError(f"--path is for the kitti world, not {world!r}")
            else:
                _check_world(world)
            with staged_folder(out, "synth", overwrite=overwrite, inputs=[path]) as staging:
                if world == "kitti":
                    meta = _kitti(staging, path, "livox" if sensor == "livox" else rings, seed, max_scans,
                                  odometry_noise, movers, terrain=terrain, keyframes=keyframes)
                else:
                    meta = _world(world, staging, seed, laps or 2, sensor, max_scans, odometry_noise, poles, movers,
                                  doors)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        console.print(f"{meta} -> {out}")


def _check_world(world: str) -> None:
    """One line for a world name that does not exist (before any file is written)."""
    from datasets_synth import WORLDS

    if world not in WORLDS:
        raise SubmapSlamError(f"unknown world {world!r}; choose from {', '.join([*sorted(WORLDS), 'kitti', 'landmarks'])}")


def _check_kitti_options(path, rings, *, laps, sensor, poles) -> None:
    if path is None:
        raise SubmapSlamError("synth kitti needs --path: a KITTI pose file such as kitti_gt/00.txt.xz")
    unused = [name for name, value in (("--laps", laps), ("--sensor", None if sensor == "livox" else sensor),
                                       ("--poles", poles or None))
              if value is not None]
    if unused:
        raise SubmapSlamError(f"{', '.join(unused)} not used by synth kitti (the path is driven once, "
                              "the sensor is set by --rings, or --sensor livox)")
    if rings not in (16, 64, 128):
        raise SubmapSlamError(f"--rings must be 16, 64 or 128, not {rings}")
    if not Path(path).is_file():
        raise SubmapSlamError(f"--path {path}: no such KITTI pose file")


def _check_landmark_options(**given) -> None:
    unused = [f"--{name.replace('_', '-')}" for name, value in given.items() if value]
    if unused:
        raise SubmapSlamError(f"{', '.join(unused)} not used by synth landmarks (a landmark log, no scans)")


def _landmarks(out, seed, laps, n, vanish, appear, p_miss, clutter) -> str:
    import numpy as np

    from datasets_synth.landmarks import generate_landmark_log

    path = generate_landmark_log(Path(out) / "landmarks.txt", seed=seed, laps=laps, n_landmarks=n,
                                 vanish_fraction=vanish, appear=appear, p_miss=p_miss, clutter_rate=clutter)
    steps = len(np.loadtxt(path.parent / "poses_truth.txt", ndmin=2))
    gone = int(round(vanish * n))
    return (f"{steps} steps, {laps} laps, {n} landmarks"
            + (f", {gone} vanish and {appear} appear at step {steps // 2}" if gone or appear else ""))


def _world(world, out, seed, laps, sensor, max_scans, odometry_noise, poles, movers=0, doors=0) -> str:
    import yaml

    from datasets_synth import generate

    from ..api import progress_bar

    extra = {"poles": poles} if poles else {}
    with progress_bar(None) as bar:
        task = bar.add_task("scans", total=None)
        path = generate(world, out, seed=seed, laps=laps, sensor=sensor, max_scans=max_scans,
                        odometry_noise=odometry_noise, movers=movers, doors=doors,
                        progress=lambda done, total: bar.update(task, completed=done, total=total), **extra)
    meta = yaml.safe_load((path / "meta.yaml").read_text())
    return (f"{meta['n_scans']} scans of {world} ({meta['sensor']['type']}), loop {meta['loop_length_m']:.0f} m "
            f"x {meta['laps']} lap{'' if meta['laps'] == 1 else 's'}, wheel odometry end drift {meta['odometry_end_drift_m']:.2f} m{_movers_text(meta)}")


def _kitti(out, path, rings, seed, max_scans, odometry_noise, movers=0, *, terrain=False, keyframes=False) -> str:
    import yaml

    from datasets_synth import generate_kitti_drive

    from ..api import progress_bar

    with progress_bar(None) as bar:
        task = bar.add_task("scans", total=None)
        log = generate_kitti_drive(path, out, rings=rings, seed=seed, max_scans=max_scans,
                                   odometry_noise=odometry_noise, movers=movers, terrain=terrain,
                                   keyframes=keyframes, progress=lambda done, total: bar.update(task, completed=done, total=total))
    meta = yaml.safe_load((log / "meta.yaml").read_text())
    sensor = "Livox-like LiDAR" if rings == "livox" else f"{rings}-ring LiDAR"
    relief = f", terrain relief {meta['terrain']['relief_m']:.1f} m" if "terrain" in meta else ""
    return (f"{meta['n_scans']} scans along {path.name} ({sensor}{relief}), "
            f"{meta['path_length_m'] / 1000:.2f} km, {meta['city']['buildings']} buildings, "
            f"{meta['city']['cars']} parked cars{_movers_text(meta)}")


def _movers_text(meta: dict) -> str:
    counts = meta.get("movers") or {}
    return (", movers: " + ", ".join(f"{n} {kind}" for kind, n in counts.items())) if counts else ""
