"""``import_pybullet()``: PyBullet without its build-time banner.

The extension prints ``pybullet build time: ...`` from C when it is first imported (to stderr
in the wheels we install, to stdout in some builds), so every command started with that line.
The import here runs with file descriptors 1 and 2 pointed at ``/dev/null``, C's buffers
flushed before they are put back, so the line never reaches the user. Every module of the
project that needs PyBullet imports it through this function.
"""

from __future__ import annotations

import ctypes
import importlib
import os
import sys
import threading

_lock = threading.Lock()


def _flush_c_streams() -> None:
    try:
        ctypes.CDLL(None).fflush(None)
    except (OSError, AttributeError):  # no C library handle on this platform: nothing to flush
        pass


def import_pybullet():
    """The ``pybullet`` module, imported with its banner sent to ``/dev/null``."""
    module = sys.modules.get("pybullet")
    if module is not None:
        return module
    with _lock:
        for stream in (sys.stdout, sys.stderr):
            if stream is not None:
                stream.flush()
        _flush_c_streams()
        try:
            saved = [os.dup(1), os.dup(2)]
        except OSError:  # a standard descriptor is closed: nothing to protect
            return importlib.import_module("pybullet")
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
            os.dup2(devnull, 2)
            module = importlib.import_module("pybullet")
            _flush_c_streams()
        finally:
            for fd, copy in zip((1, 2), saved):
                os.dup2(copy, fd)
                os.close(copy)
            os.close(devnull)
    return module
