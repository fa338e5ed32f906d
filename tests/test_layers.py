"""Import layers: data flows one way (log -> scans -> odometry -> submaps -> graph -> results ->
writers/reports -> CLI). A module may import its own layer and the layers below, never one
above; gtsam lives in backend/, matplotlib in evaluation/, datasets_synth only reaches the CLI,
and topology/ never writes (imports) the graph backend. A small AST check, lazy imports inside
functions included; see docs/architecture.md for what each layer owns.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "submapslam"

# low to high; a module belongs to the first entry that is its name or a package above it
LAYERS: list[tuple[str, ...]] = [
    ("geometry", "config", "errors", "trajectory", "landmark_log", "result", "process_stats", "child_process", "_deps", "scan",
     "scan_intervals",
     "checkpoint", "observer", "session_map", "progress", "uncertainty"),
    ("registration",),
    ("odometry", "odometry_stage", "start_frame", "submaps", "mapping", "topology", "backend", "ekf"),
    ("graph_builder", "scan_refine"),
    ("pipeline", "localization", "fleet"),
    ("evaluation",),
    ("io",),
    ("viz",),  # live views (observers), above the engine and evaluation, below the CLI
    ("api", "fleet_api", "fleet_ray", "ray_cluster", ""),  # "": the package's __init__, the public facade over api/io/pipeline
    ("cli", "__main__"),
]

# Real violations left in place, each with its reason. The test fails when one disappears,
# so this list only shrinks.
KNOWN_EXCEPTIONS: dict[tuple[str, str], str] = {}


def _module_name(path: Path) -> str:
    parts = path.relative_to(PKG).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_module(name: str) -> bool:
    rel = Path(*name.split(".")) if name else Path()
    return (PKG / rel).with_suffix(".py").is_file() or (PKG / rel / "__init__.py").is_file()


def imports(path: Path) -> set[str]:
    """Every name ``path`` imports: submapslam modules relative to the package ("" for the
    package itself, e.g. ``io.scan``), others absolute with a leading ``/`` (``/gtsam``)."""
    own = _module_name(path)
    package = own.split(".") if path.name == "__init__.py" else own.split(".")[:-1]
    package = [p for p in package if p]
    found: set[str] = set()

    def add(absolute: str) -> None:
        if absolute == "submapslam" or absolute.startswith("submapslam."):
            found.add(absolute.removeprefix("submapslam").removeprefix("."))
        else:
            found.add("/" + absolute)

    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            for alias in node.names:
                add(alias.name)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                rel = ".".join([*base, *([node.module] if node.module else [])])
                for alias in node.names:  # "from . import demo": the module demo, not the package
                    sub = f"{rel}.{alias.name}".lstrip(".")
                    found.add(sub if _is_module(sub) else rel)
            else:
                add(node.module or "")
    return found


def layer_of(module: str) -> int:
    """Index in :data:`LAYERS` of a submapslam module name (relative, "" for the package)."""
    for k, names in enumerate(LAYERS):
        for name in names:
            if module == name or (name and module.startswith(name + ".")):
                return k
    raise AssertionError(f"submapslam.{module} is in no layer: add it to LAYERS in {Path(__file__).name}")


MODULES = sorted(PKG.rglob("*.py"))


def _violations() -> list[tuple[str, str]]:
    bad = []
    for path in MODULES:
        own = _module_name(path)
        for target in imports(path):
            if not target.startswith("/") and layer_of(target) > layer_of(own):
                bad.append((own, target))
    return bad


def test_every_module_has_a_layer():
    for path in MODULES:
        layer_of(_module_name(path))


def test_no_module_imports_a_higher_layer():
    bad = [f"submapslam.{a or '__init__'} imports submapslam.{b}" for a, b in _violations()
           if (a, b) not in KNOWN_EXCEPTIONS]
    assert not bad, "\n".join(bad)


def test_known_exceptions_are_still_real():
    """A fixed exception must leave the list, so the list cannot hide a new violation."""
    real = set(_violations())
    stale = [pair for pair in KNOWN_EXCEPTIONS if pair not in real]
    assert not stale, f"no longer violations, remove from KNOWN_EXCEPTIONS: {stale}"


@pytest.mark.parametrize(("third_party", "allowed_under"), [
    ("gtsam", ("backend",)),
    ("matplotlib", ("evaluation",)),
    ("datasets_synth", ("cli",)),
])
def test_third_party_only_in_its_package(third_party, allowed_under):
    bad = [_module_name(p) for p in MODULES
           if any(t == "/" + third_party or t.startswith(f"/{third_party}.") for t in imports(p))
           and not any(_module_name(p) == a or _module_name(p).startswith(a + ".") for a in allowed_under)]
    assert not bad, f"{third_party} imported outside {allowed_under}: {bad}"


def test_topology_never_imports_backend():
    bad = [(_module_name(p), t) for p in sorted((PKG / "topology").rglob("*.py"))
           for t in imports(p) if t == "backend" or t.startswith("backend.")]
    assert not bad, bad


def test_the_check_sees_what_it_must():
    """The AST walk resolves relative and lazy imports, and the layers order what they should."""
    assert "scan" in imports(PKG / "pipeline.py")                     # module level, relative
    assert "io.scan" in imports(PKG / "io" / "cloud_folder.py")
    assert "/gtsam" in imports(PKG / "backend" / "pose_graph.py")
    assert "/matplotlib" in imports(PKG / "evaluation" / "report.py")  # inside a function
    assert "demo" not in imports(PKG / "cli" / "__init__.py") and "cli.demo" in imports(PKG / "cli" / "__init__.py")
    assert layer_of("geometry") < layer_of("registration.planar") < layer_of("topology.loop_closure")
    assert layer_of("pipeline") < layer_of("evaluation.metrics") < layer_of("io.trajectory") < layer_of("cli.run")
    with pytest.raises(AssertionError, match="in no layer"):
        layer_of("brand_new_module")
