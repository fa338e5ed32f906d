"""A run's checkpoint on disk: ``.OUT.checkpoint/`` beside the output folder OUT.

Files (open formats, no pickles):

* ``checkpoint.npz`` — ``timestamps (K,)``, ``odometry_poses (K, 4, 4)``, ``planar_poses (K, 3)``
  (empty for 3D), ``information_ids (M,)`` and ``information (M, 6, 6)`` of the odometry edges,
  ``run_frame (4, 4)`` the start's re-base of a planar run (empty: none), ``map_refreshed (K,)``
  the scans for which the 3D odometry put its waiting scans into its local map early (empty: none),
  ``guess_ids (G,)`` and ``guesses (G, 4, 4)`` the guesses kept registrations started from where
  not the prediction;
* ``loops.json`` — per submap id, the tested hypotheses (every :class:`LoopRecord` field);
* ``run.json`` — format version, and how the run was started (log, format, hints, options),
  which ``run --resume OUT`` repeats;
* ``config.yaml`` — the run's effective config.

The folder is replaced atomically (written beside it, then renamed), so a crash while writing
leaves the previous checkpoint.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from dataclasses import fields
from pathlib import Path

import numpy as np

from ..checkpoint import Checkpoint
from ..config import PipelineConfig, config_from_dict, dump_config
from ..errors import InputError
from ..result import LoopRecord

VERSION = 2


def checkpoint_folder(out_dir: str | Path) -> Path:
    """Where the checkpoint of a run writing into ``out_dir`` lives (a hidden sibling)."""
    out = Path(out_dir).expanduser()
    return out.with_name(f".{out.name}.checkpoint")


def _record_to_json(rec: LoopRecord) -> dict:
    doc = {}
    for f in fields(LoopRecord):
        value = getattr(rec, f.name)
        if isinstance(value, np.ndarray):
            value = value.tolist()
        elif isinstance(value, float) and math.isnan(value):
            value = None
        doc[f.name] = value
    return doc


def _record_from_json(doc: dict) -> LoopRecord:
    values = dict(doc)
    for name in ("T_i_j", "information"):
        if values.get(name) is not None:
            values[name] = np.asarray(values[name], dtype=np.float64)
    for name in ("structure_overlap", "plane_rmse"):
        if values.get(name) is None:
            values[name] = float("nan")
    return LoopRecord(**values)


def write_checkpoint(out_dir: str | Path, checkpoint: Checkpoint, config: PipelineConfig, run: dict) -> Path:
    """Write ``checkpoint`` for the run writing into ``out_dir``; ``run``: JSON-ready options
    that start the run again. Returns the checkpoint folder."""
    folder = checkpoint_folder(out_dir)
    tmp = folder.with_name(folder.name + f".partial-{os.getpid()}")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    ids = sorted(checkpoint.odometry_information)
    np.savez(tmp / "checkpoint.npz", timestamps=checkpoint.timestamps, odometry_poses=checkpoint.odometry_poses,
             planar_poses=(checkpoint.planar_poses if checkpoint.planar_poses is not None else np.zeros((0, 3))),
             information_ids=np.asarray(ids, dtype=np.int64),
             information=np.asarray([checkpoint.odometry_information[k] for k in ids]).reshape(-1, 6, 6),
             tilt_ids=np.asarray(sorted(checkpoint.odometry_tilt), dtype=np.int64),
             tilt=np.asarray([checkpoint.odometry_tilt[k] for k in sorted(checkpoint.odometry_tilt)]).reshape(-1, 2),
             correction_ids=np.asarray(sorted(checkpoint.odometry_correction), dtype=np.int64),
             correction=np.asarray([checkpoint.odometry_correction[k]
                                    for k in sorted(checkpoint.odometry_correction)]).reshape(-1, 6),
             run_frame=(checkpoint.run_frame if checkpoint.run_frame is not None else np.zeros((0, 4, 4))),
             map_refreshed=(checkpoint.map_refreshed if checkpoint.map_refreshed is not None
                            else np.zeros(0, dtype=bool)),
             guess_ids=np.asarray(sorted(checkpoint.guesses), dtype=np.int64),
             guesses=np.asarray([checkpoint.guesses[k] for k in sorted(checkpoint.guesses)]).reshape(-1, 4, 4))
    loops = {str(k): [_record_to_json(r) for r in recs] for k, recs in sorted(checkpoint.loop_records.items())}
    (tmp / "loops.json").write_text(json.dumps(loops) + "\n")
    (tmp / "config.yaml").write_text(dump_config(config))
    (tmp / "run.json").write_text(json.dumps({"version": VERSION, "source": checkpoint.source,
                                             "scans": checkpoint.n_scans, "submaps": checkpoint.n_submaps,
                                             **run}, indent=2) + "\n")
    old = folder.with_name(folder.name + f".old-{os.getpid()}")
    if folder.exists():
        os.rename(folder, old)
    os.rename(tmp, folder)
    shutil.rmtree(old, ignore_errors=True)
    return folder


def read_checkpoint(out_dir: str | Path) -> tuple[Checkpoint, PipelineConfig, dict]:
    """The checkpoint of the run that writes into ``out_dir``: ``(checkpoint, config, run
    options)``; :class:`InputError` (one line) when there is none or it cannot be read."""
    folder = checkpoint_folder(out_dir)
    if not folder.is_dir():
        raise InputError(out_dir, "no checkpoint to resume from (a run leaves one when it is interrupted "
                         f"or stops early; expected {folder})")
    try:
        run = json.loads((folder / "run.json").read_text())
        if run.get("version") != VERSION:
            raise InputError(folder, f"checkpoint format version {run.get('version')}, this submapslam reads {VERSION}")
        import yaml

        config = config_from_dict(yaml.safe_load((folder / "config.yaml").read_text()), str(folder / "config.yaml"))
        with np.load(folder / "checkpoint.npz") as npz:
            arrays = {name: npz[name] for name in npz.files}
        loops = json.loads((folder / "loops.json").read_text())
    except InputError:
        raise
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise InputError(folder, f"damaged checkpoint ({exc.__class__.__name__}: {exc})") from None
    planar = arrays["planar_poses"] if len(arrays["planar_poses"]) else None
    checkpoint = Checkpoint(
        timestamps=arrays["timestamps"], odometry_poses=arrays["odometry_poses"], planar_poses=planar,
        odometry_information={int(k): info for k, info in zip(arrays["information_ids"], arrays["information"])},
        odometry_tilt={int(k): t for k, t in zip(arrays["tilt_ids"], arrays["tilt"])},
        odometry_correction={int(k): c for k, c in zip(arrays.get("correction_ids", ()), arrays.get("correction", ()))},
        loop_records={int(k): [_record_from_json(d) for d in recs] for k, recs in loops.items()},
        source=run.get("source", ""),
        run_frame=arrays["run_frame"] if len(arrays.get("run_frame", ())) else None,
        map_refreshed=arrays["map_refreshed"] if len(arrays.get("map_refreshed", ())) else None,
        guesses={int(k): g for k, g in zip(arrays.get("guess_ids", ()), arrays.get("guesses", ()))})
    return checkpoint, config, run


def remove_checkpoint(out_dir: str | Path) -> None:
    """Delete the checkpoint of ``out_dir`` (after the run it belongs to has finished)."""
    shutil.rmtree(checkpoint_folder(out_dir), ignore_errors=True)
