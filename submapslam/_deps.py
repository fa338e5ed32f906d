"""Lazy loaders for heavy dependencies (open3d, gtsam).

open3d's wheel links against ``libusb-1.0.so.0``. Machines without it (and without root) can
still import open3d: we preload the copy shipped by the ``libusb-package`` wheel with
``RTLD_GLOBAL`` before the first ``import open3d``.

``import open3d`` also imports ``open3d.visualization.draw_plotly``, and with it plotly and dash
(about half of open3d's import time, 0.6 s of CPU), which submapslam never uses: that module is
imported on the first call of one of its functions instead (:func:`_defer_draw_plotly`).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import importlib
import logging
import sys
from types import ModuleType

from .errors import DependencyError

log = logging.getLogger(__name__)


def _preload_libusb() -> None:
    if ctypes.util.find_library("usb-1.0"):
        return
    try:
        import libusb_package
    except ImportError:  # pragma: no cover - declared dependency
        return
    path = libusb_package.get_library_path()
    if path is not None:
        ctypes.CDLL(str(path), mode=ctypes.RTLD_GLOBAL)
        log.debug("preloaded libusb from %s", path)


_DRAW_PLOTLY = "open3d.visualization.draw_plotly"
_DRAW_PLOTLY_NAMES = ("get_plotly_fig", "draw_plotly", "draw_plotly_server")  # what open3d.visualization takes


def _defer_draw_plotly() -> None:
    """Before open3d's first import: a stand-in for ``open3d.visualization.draw_plotly`` whose
    functions import the real module (plotly, dash) on their first call and run its own."""
    if "open3d" in sys.modules or _DRAW_PLOTLY in sys.modules:
        return
    stand_in = ModuleType(_DRAW_PLOTLY, "open3d's plotly drawing, imported on first use")

    def real() -> ModuleType:
        if sys.modules.get(_DRAW_PLOTLY) is not stand_in:
            return sys.modules[_DRAW_PLOTLY]
        del sys.modules[_DRAW_PLOTLY]
        module = importlib.import_module(_DRAW_PLOTLY)
        package = sys.modules["open3d.visualization"]
        for name in _DRAW_PLOTLY_NAMES:  # as open3d binds them (the import set draw_plotly to the module)
            setattr(package, name, getattr(module, name))
        return module

    def deferred(name: str):
        def call(*args, **kwargs):
            return getattr(real(), name)(*args, **kwargs)

        call.__name__ = call.__qualname__ = name
        return call

    def any_other(name: str):  # a name a later open3d takes from the module: the real one, now
        if name.startswith("__"):  # the import machinery's probes (__path__, __spec__ ...)
            raise AttributeError(name)
        return getattr(real(), name)

    for name in _DRAW_PLOTLY_NAMES:
        setattr(stand_in, name, deferred(name))
    stand_in.__getattr__ = any_other
    sys.modules[_DRAW_PLOTLY] = stand_in


@functools.cache
def open3d() -> ModuleType:
    """Import and return open3d, preloading libusb when the system lacks it (plotly and dash,
    which only its plotly drawing needs, on that drawing's first use)."""
    _preload_libusb()
    _defer_draw_plotly()
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - environment problem
        sys.modules.pop(_DRAW_PLOTLY, None)
        raise DependencyError(f"cannot import open3d: {exc}") from exc
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d
