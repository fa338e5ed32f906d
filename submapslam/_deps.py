"""Lazy loaders for heavy dependencies (open3d, gtsam).

open3d's wheel links against ``libusb-1.0.so.0``. Machines without it (and without root) can
still import open3d: we preload the copy shipped by the ``libusb-package`` wheel with
``RTLD_GLOBAL`` before the first ``import open3d``.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools
import logging
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


@functools.cache
def open3d() -> ModuleType:
    """Import and return open3d, preloading libusb when the system lacks it."""
    _preload_libusb()
    try:
        import open3d as o3d
    except ImportError as exc:  # pragma: no cover - environment problem
        raise DependencyError(f"cannot import open3d: {exc}") from exc
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    return o3d
