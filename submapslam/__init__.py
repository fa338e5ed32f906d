"""submapslam: autonomous map building with submaps, a topological submap graph, GTSAM and an
EKF stochastic-map reference.

Public API::

    from submapslam import SubmapSLAM, build_map_outputs, load_config, open_log, run, write_results
"""

from __future__ import annotations

__version__ = "0.1.0"

from .config import PipelineConfig, dump_config, load_config  # noqa: E402
from .errors import ConfigError, InputError, SubmapSlamError  # noqa: E402
from .io.registry import open_log  # noqa: E402
from .scan import Scan  # noqa: E402

__all__ = [
    "ConfigError", "InputError", "PipelineConfig", "Scan", "SubmapSLAM", "SubmapSlamError",
    "SlamResult", "dump_config", "load_config", "open_log", "run", "run_log", "write_results", "build_map_outputs",
    "SessionMap", "load_map", "save_map", "merge_sessions", "session_map_from_result", "run_sessions", "batch_logs",
    "drop_sessions",
]

_SESSIONS = {"SessionMap": "session_map", "load_map": "io.map_store", "save_map": "io.map_store",
             "merge_sessions": "fleet", "session_map_from_result": "fleet", "run_sessions": "fleet_api",
             "batch_logs": "fleet_api", "drop_sessions": "fleet"}


def __getattr__(name: str):
    """Lazy access to the heavy parts (gtsam/open3d/kiss-icp load on first use)."""
    if name in ("SubmapSLAM", "run"):
        from . import pipeline

        return getattr(pipeline, name)
    if name == "SlamResult":
        from .result import SlamResult

        return SlamResult
    if name == "write_results":
        from .io.results import write_results

        return write_results
    if name == "build_map_outputs":
        from .mapping.global_map import build_map_outputs

        return build_map_outputs
    if name == "run_log":
        from .api import run_log

        return run_log
    if name in _SESSIONS:  # maps from several sessions
        from importlib import import_module

        return getattr(import_module(f".{_SESSIONS[name]}", __name__), name)
    raise AttributeError(name)
