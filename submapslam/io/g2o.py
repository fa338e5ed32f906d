"""g2o pose-graph files (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``), readable by g2o and GTSAM.

Edge information is written as the upper triangle of the 6x6 matrix in g2o's order
``(tx, ty, tz, rx, ry, rz)``; GTSAM's Pose3 order is ``(rx, ry, rz, tx, ty, tz)``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..geometry import matrix_to_quat

_GTSAM_TO_G2O = np.array([3, 4, 5, 0, 1, 2])


def _pose_fields(T: np.ndarray) -> str:
    q = matrix_to_quat(T[:3, :3])
    t = T[:3, 3]
    return " ".join(f"{v:.9g}" for v in (*t, *q))


def write_g2o(path: str | Path, poses: np.ndarray, edges: list[tuple], fixed: tuple[int, ...] = (0,)) -> None:
    """Write vertices ``poses (S, 4, 4)`` and edges ``(i, j, T_i_j, information_gtsam, kind)``."""
    lines = []
    for k, T in enumerate(poses):
        lines.append(f"VERTEX_SE3:QUAT {k} {_pose_fields(T)}")
    for k in fixed:
        if k < len(poses):
            lines.append(f"FIX {k}")
    iu = np.triu_indices(6)
    for i, j, T_i_j, info, _kind in edges:
        info_g2o = np.asarray(info)[np.ix_(_GTSAM_TO_G2O, _GTSAM_TO_G2O)]
        tri = " ".join(f"{v:.9g}" for v in info_g2o[iu])
        lines.append(f"EDGE_SE3:QUAT {i} {j} {_pose_fields(np.asarray(T_i_j))} {tri}")
    Path(path).write_text("\n".join(lines) + "\n")


def read_g2o_edges(path: str | Path) -> tuple[dict[int, np.ndarray], list[tuple[int, int, np.ndarray, np.ndarray]]]:
    """Read back vertices and edges of a file written by :func:`write_g2o` (GTSAM-order info)."""
    from ..errors import InputError
    from ..geometry import pose_from_xyz_quat

    vertices: dict[int, np.ndarray] = {}
    edges = []
    inv = np.argsort(_GTSAM_TO_G2O)
    iu = np.triu_indices(6)
    for lineno, line in enumerate(Path(path).read_text().splitlines(), start=1):
        tok = line.split()
        if not tok:
            continue
        try:
            if tok[0] == "VERTEX_SE3:QUAT":
                v = np.array(tok[2:9], dtype=float)
                vertices[int(tok[1])] = pose_from_xyz_quat(v[:3], v[3:])
            elif tok[0] == "EDGE_SE3:QUAT":
                v = np.array(tok[3:10], dtype=float)
                tri = np.array(tok[10:31], dtype=float)
                info = np.zeros((6, 6))
                info[iu] = tri
                info = info + np.triu(info, 1).T
                edges.append((int(tok[1]), int(tok[2]), pose_from_xyz_quat(v[:3], v[3:]), info[np.ix_(inv, inv)]))
        except (ValueError, IndexError):
            raise InputError(path, f"malformed {tok[0]} line", lineno) from None
    return vertices, edges
