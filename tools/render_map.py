"""Render a run's occupancy grid (map.pgm) and trajectory (poses_tum.txt) to a PNG.

Usage: python tools/render_map.py OUT_DIR [--png FILE]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out_dir", type=Path)
    ap.add_argument("--png", type=Path)
    args = ap.parse_args(argv)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import yaml

    from submapslam.io.grid import read_pgm
    from submapslam.io.trajectory import read_tum

    img = read_pgm(args.out_dir / "map.pgm")
    meta = yaml.safe_load((args.out_dir / "map.yaml").read_text())
    res, (x0, y0, _) = meta["resolution"], meta["origin"]
    h, w = img.shape
    fig, ax = plt.subplots(figsize=(10, 10 * h / max(w, 1)))
    ax.imshow(img, cmap="gray", vmin=0, vmax=255, extent=(x0, x0 + w * res, y0, y0 + h * res))
    traj = read_tum(args.out_dir / "poses_tum.txt")
    ax.plot(traj.positions[:, 0], traj.positions[:, 1], "r-", lw=0.4)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")
    png = args.png or args.out_dir / "map.png"
    fig.savefig(png, dpi=110, bbox_inches="tight")
    print(png)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
