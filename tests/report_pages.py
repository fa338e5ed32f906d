"""Reading and rendering the HTML report in tests: its embedded figures, and the page in headless
Chromium (skipped with a reason when Chromium is absent; ``.ci/run`` installs it as root)."""

from __future__ import annotations

import base64
import io
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="chromium not installed (apt-get install chromium)")

#: the plots a report against a reference carries: the map and evo's standard plots
REFERENCE_FIGURES = ("map", "evo-xyz", "evo-ape", "evo-hist")
#: the uncertainty a run with ``poses_cov.txt`` shows: σ along the path, and the map layer of 3σ ellipses
UNCERTAINTY_FIGURES = ("uncertainty-sigma", "layer-uncertainty")

# appended to a copy of the page: lists the images Chromium decoded with a size (ids, in order)
_PROBE = ("<script>document.body.setAttribute('data-rendered', Array.from(document.images)"
          ".filter(i => i.complete && i.naturalWidth > 0 && i.naturalHeight > 0).map(i => i.id).join(','));</script>")


def figure_png(html: str, ident: str) -> np.ndarray:
    """The ``(H, W, C)`` image of the page's embedded figure ``<img id="ident">``."""
    import matplotlib.image as mpimg

    m = re.search(rf'<img id="{ident}" src="data:image/png;base64,([^"]+)"', html)
    assert m, f"no figure {ident}"
    return mpimg.imread(io.BytesIO(base64.b64decode(m.group(1))), format="png")


def assert_not_blank(img: np.ndarray, what: str) -> None:
    """A plot, not an empty canvas: some ink and more than a handful of colours."""
    rgb = img[..., :3]
    assert float(np.std(rgb)) > 0.02 and np.mean(rgb.min(axis=2) < 0.9) > 0.01, f"{what} is blank"


def assert_layer_has_ink(img: np.ndarray, what: str, min_share: float = 0.002) -> None:
    """A transparent overlay layer that draws something: enough opaque pixels, spread over at least
    a fifth of the figure's width or height (its RGB under a transparent pixel says nothing, so
    :func:`assert_not_blank` cannot tell)."""
    assert img.shape[-1] == 4, f"{what} has no alpha channel: not an overlay"
    ink = img[..., 3] > 0.5
    assert float(np.mean(ink)) > min_share, f"{what} is blank ({np.mean(ink):.4%} opaque)"
    rows, cols = np.flatnonzero(ink.any(axis=1)), np.flatnonzero(ink.any(axis=0))
    assert max((rows[-1] - rows[0]) / ink.shape[0], (cols[-1] - cols[0]) / ink.shape[1]) > 0.2, \
        f"{what} draws in one spot only"


def chromium(args: list[str], tmp_path: Path) -> tuple[subprocess.CompletedProcess, list[str]]:
    """Run headless Chromium with ``args``; returns the process and its console lines."""
    proc = subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--enable-logging=stderr",
                           "--v=0", f"--user-data-dir={tmp_path / 'profile'}", *args],
                          capture_output=True, text=True, timeout=120)
    return proc, [ln for ln in proc.stderr.splitlines() if ":CONSOLE" in ln]


def rendered_figures(page: Path, tmp_path: Path) -> tuple[set[str], list[str]]:
    """``(ids of the images Chromium drew, console lines)`` for the report ``page`` (a probing copy
    of it in ``tmp_path`` is rendered; the page itself is not touched)."""
    probe = tmp_path / "probe.html"
    probe.write_text(page.read_text().replace("</body>", _PROBE + "</body>"))
    proc, console = chromium(["--dump-dom", probe.as_uri()], tmp_path)
    assert proc.returncode == 0, proc.stderr[-2000:]
    m = re.search(r'data-rendered="([^"]*)"', proc.stdout)
    assert m, "the probe did not run"
    return set(filter(None, m.group(1).split(","))), console
