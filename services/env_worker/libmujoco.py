"""The MuJoCo C library that the ``mujoco`` wheel ships beside its bindings.

Some calls hold the GIL for seconds through the bindings (copying a model, uploading a scene's
textures); calling the same C functions through ctypes releases it. The fast step's numba kernels
resolve their MuJoCo symbols from the same library.
"""

from __future__ import annotations

import ctypes
import functools
import glob
import os


@functools.cache
def path() -> str | None:
    """Where libmujoco lies next to the ``mujoco`` package, or None."""
    import mujoco

    here = os.path.dirname(mujoco.__file__)
    found = sorted(glob.glob(os.path.join(here, "libmujoco.so*"))) + sorted(glob.glob(os.path.join(here, "libmujoco*.dylib")))
    return found[0] if found else None


@functools.cache
def library() -> ctypes.CDLL | None:
    """libmujoco through ctypes (its calls release the GIL), or None where it is not found."""
    where = path()
    return ctypes.CDLL(where) if where else None
