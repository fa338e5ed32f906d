"""Readable, unique names for trajectory files, taken from their run folders.

``runA/poses_tum.txt`` and ``runB/poses_tum.txt`` are ``runA/poses`` and ``runB/poses``: the
folder says which run, the file name (without its format suffix) which trajectory of it.
"""

from __future__ import annotations

from pathlib import Path

_FORMAT_SUFFIXES = ("_tum", "_kitti", "_carmen")
_EXTENSIONS = (".gz", ".bz2", ".xz", ".txt", ".log", ".csv", ".tum", ".kitti", ".clf")


def trajectory_stem(path: Path) -> str:
    """File name without compression, extension and format suffix: ``poses_tum.txt`` -> ``poses``."""
    name = path.name
    changed = True
    while changed:
        changed = False
        for ext in _EXTENSIONS:
            if name.lower().endswith(ext) and len(name) > len(ext):
                name, changed = name[: -len(ext)], True
    for suffix in _FORMAT_SUFFIXES:
        if name.endswith(suffix) and len(name) > len(suffix):
            return name[: -len(suffix)]
    return name


def trajectory_labels(paths: list[Path]) -> list[str]:
    """One unique label per path, in order: ``folder/stem``, with more parent folders where two
    paths still share one, and ``#2``, ``#3`` for the same file given twice."""
    paths = [Path(p) for p in paths]
    stems = [trajectory_stem(p) for p in paths]
    parents = [list(p.resolve().parent.parts[1:]) for p in paths]  # without the root
    resolved = [p.resolve() for p in paths]
    depth = [1] * len(paths)

    def label(k: int) -> str:
        folders = parents[k][-depth[k]:] if depth[k] and parents[k] else []
        return "/".join([*folders, stems[k]])

    while True:
        labels = [label(k) for k in range(len(paths))]
        clashes = [k for k, lab in enumerate(labels) if depth[k] < len(parents[k])
                   and any(labels[m] == lab and resolved[m] != resolved[k] for m in range(len(paths)))]
        if not clashes:
            break
        for k in clashes:
            depth[k] += 1
    seen: dict[str, int] = {}
    out = []
    for lab in labels:
        seen[lab] = seen.get(lab, 0) + 1
        out.append(lab if seen[lab] == 1 else f"{lab}#{seen[lab]}")
    return out
