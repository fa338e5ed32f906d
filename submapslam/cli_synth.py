"""CLI command ``synth``: write a synthetic log."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.console import Console

from .cli_common import fail
from .errors import SubmapSlamError


def register(app: typer.Typer) -> None:
    """Add ``synth`` to ``app``."""

    @app.command("synth")
    def synth_cmd(
        world: Annotated[str, typer.Argument(help="rectangle, rooms, figure8 or outdoor.")],
        out: Annotated[Path, typer.Option("--out", "-o", help="Output log folder.")],
        seed: Annotated[int, typer.Option(help="Random seed (same seed, same files).")] = 0,
        laps: Annotated[int, typer.Option(help="Laps around the loop.")] = 2,
        sensor: Annotated[str | None, typer.Option(help="laser2d or lidar3d (default: the world's).")] = None,
        max_scans: Annotated[int | None, typer.Option(help="Cut the log after N scans.")] = None,
        odometry_noise: Annotated[float, typer.Option(help="Scale of the wheel-odometry noise.")] = 1.0,
        poles: Annotated[int, typer.Option(min=0, help="rectangle: free-standing poles (EKF point features).")] = 0,
    ) -> None:
        """Generate a synthetic loop world and write it as a log folder (and CARMEN for 2D)."""
        import yaml

        from datasets_synth import generate

        try:
            extra = {"poles": poles} if poles else {}
            path = generate(world, out, seed=seed, laps=laps, sensor=sensor, max_scans=max_scans,
                            odometry_noise=odometry_noise, **extra)
        except SubmapSlamError as exc:
            raise fail(exc) from None
        meta = yaml.safe_load((path / "meta.yaml").read_text())
        Console().print(f"{meta['n_scans']} scans of {world} ({meta['sensor']['type']}), loop {meta['loop_length_m']:.0f} m "
                        f"x {laps} laps, wheel odometry end drift {meta['odometry_end_drift_m']:.2f} m -> {path}")
