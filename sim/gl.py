"""Pick MuJoCo's offscreen GL backend before ``mujoco`` is imported.

MuJoCo reads MUJOCO_GL once, at import. EGL (Mesa's software EGL works
without a GPU) is the default; if no libEGL is installed, fall back to OSMesa
with one clear line on stderr.
"""

from __future__ import annotations

import ctypes.util
import os
import sys


def choose_gl_backend() -> str:
    if "MUJOCO_GL" in os.environ:
        return os.environ["MUJOCO_GL"]
    backend = "egl"
    if ctypes.util.find_library("EGL") is None:
        if ctypes.util.find_library("OSMesa") is not None:
            backend = "osmesa"
            print("tether: libEGL not found; rendering with OSMesa (slower). "
                  "Install libegl1 and libegl-mesa0 for EGL.", file=sys.stderr)
        else:
            print("tether: neither libEGL nor libOSMesa found; videos cannot be rendered. "
                  "Install libegl1 libegl-mesa0 (or libosmesa6).", file=sys.stderr)
    os.environ["MUJOCO_GL"] = backend
    os.environ.setdefault("PYOPENGL_PLATFORM", backend)
    return backend
