"""The lazy open3d import: plotly and dash only when open3d's plotly drawing is first used."""

import subprocess
import sys

_SCRIPT = """
import sys
import numpy as np
from submapslam._deps import open3d
o3d = open3d()
assert "dash" not in sys.modules and "plotly" not in sys.modules, "plotly/dash imported with open3d"
cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.random.default_rng(0).random((20, 3))))
figure = o3d.visualization.get_plotly_fig([cloud])
assert type(figure).__name__ == "Figure"
assert "dash" in sys.modules
assert callable(o3d.visualization.draw_plotly), "open3d.visualization.draw_plotly is the function, as open3d binds it"
print("ok")
"""


def test_open3d_defers_plotly_and_dash_until_used():
    out = subprocess.run([sys.executable, "-c", _SCRIPT], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"


_OTHER_NAME = """
import sys
from submapslam._deps import open3d
open3d()  # open3d imported with the stand-in for its plotly module
assert "plotly" not in sys.modules
from open3d.visualization.draw_plotly import get_plotly_fig  # a name open3d takes today: still deferred
assert "plotly" not in sys.modules
from open3d.visualization.draw_plotly import go  # a name it does not take: the real module, loaded now
assert "plotly" in sys.modules and go.__name__.startswith("plotly")
print("ok")
"""


def test_a_name_open3d_may_take_later_loads_the_real_module():
    """A later open3d that imports another name from its plotly module still imports: the stand-in
    hands over to the real module for any name it does not defer."""
    out = subprocess.run([sys.executable, "-c", _OTHER_NAME], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "ok"
