"""Data flows one way: the core modules reworked for issue 11 import neither io/, the CLI nor
datasets_synth, and draw no plots (matplotlib only in evaluation/)."""

import ast
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "submapslam"
CORE = ["trajectory.py", "landmark_log.py", "evaluation/metrics.py", "backend/landmark_graph.py",
        *(f"ekf/{p.name}" for p in sorted((PKG / "ekf").glob("*.py")))]


def imported_modules(path: Path) -> list[str]:
    """Absolute names of every module ``path`` imports (at any depth, lazy imports included)."""
    package = ["submapslam", *path.relative_to(PKG).parent.parts]
    names = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            names.append(".".join([*base, *([node.module] if node.module else [])]))
    return names


@pytest.mark.parametrize("module", CORE)
def test_core_module_imports_no_io_cli_synth_or_matplotlib(module):
    bad = [m for m in imported_modules(PKG / module)
           if m.startswith(("submapslam.io", "submapslam.cli", "datasets_synth", "matplotlib"))]
    assert not bad, f"{module} imports {bad}"


def test_the_check_sees_relative_and_lazy_imports():
    assert "submapslam.io.trajectory" in imported_modules(PKG / "io" / "ekf_results.py")
    assert "matplotlib" in imported_modules(PKG / "evaluation" / "landmark_compare.py")  # inside a function
