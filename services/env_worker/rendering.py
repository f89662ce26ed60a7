"""Offscreen rendering for env slots: the GL backend, on-demand camera frames, reflections.

GL backend
    MuJoCo and robosuite read ``MUJOCO_GL`` once, when they are imported, so the choice is made
    before any simulator import (:func:`select_gl_backend`, called by the family modules and at
    worker start, where the choice and its reason are logged). In order:

    1. ``MUJOCO_GL`` set by the operator: kept as is (``PYOPENGL_PLATFORM`` follows it).
    2. An NVIDIA GPU (``/dev/nvidia<N>``), ``libEGL`` and NVIDIA's EGL driver (``libEGL_nvidia``
       in the linker cache, or its glvnd vendor file ``/usr/share/glvnd/egl_vendor.d/*nvidia*.json``,
       which the NVIDIA container toolkit mounts with the ``graphics`` capability): ``egl``,
       rendering on the GPU (``MUJOCO_EGL_DEVICE_ID`` picks the device; the first one otherwise).
    3. ``libOSMesa`` installed (Debian ``libosmesa6``): ``osmesa``, Mesa's software renderer.
    4. ``libEGL`` installed (``libegl1`` + ``libegl-mesa0``): ``egl`` through Mesa's software
       rasterizer (llvmpipe). On the 2-core CPU machines it costs the same per frame as OSMesa
       (see docs/simulation.md, "Rendering").
    5. Neither: "" -- state-only configs work, a config with cameras fails at its first render.

On-demand frames
    robosuite's camera observables render every camera on every ``env.step`` (and on every settle
    step of a LIBERO reset) whether or not anyone looks at the image. Environments are built with
    ``use_camera_obs=False`` and no robosuite render context; a slot renders its cameras through
    :class:`SlotRenderer` only when an observation that carries images is produced: after a
    reset, and after the last action of an executed chunk (``Slot.step(action, render=False)``
    for the others), or when a video frame is due.

Contexts and threads
    Each environment carries one GL context and one ``MjrContext`` (textures uploaded once), made
    on first render and kept with the environment while it sits in its group's pool. A GL context
    is current on one thread at a time and environments move between slot threads (pool reuse,
    LIBERO task switches), so :class:`SceneRenderer` makes its context current for each batch of
    cameras and releases it afterwards (a few microseconds against milliseconds per frame).
    Making an ``MjrContext`` uploads the scene's textures; :func:`make_render_context` runs that
    with the GIL released (the bindings' constructor holds it: 2.6-3.8 s for a LIBERO scene on
    two loaded cores, during which the worker's heartbeats and other slots stopped), inside a
    busy lease (services/env_worker/busy.py) in case it has to fall back to the bindings.

Reflections
    ``env_config`` ``reflections: false`` zeroes ``model.mat_reflectance`` of the slot's model
    (a model is shared only within its config's group, so all its users asked for the same).
    MuJoCo draws a reflective plane by rendering the
    scene a second time, mirrored; without it a frame costs about a third (bench/bench_render.py).
    Off changes what the policy sees, so the default stays on.

Antialiasing
    ``env_config`` ``antialias: false`` renders into a single-sampled offscreen buffer instead of
    MuJoCo's 4x multisampled one. On Mesa's software rasterizer multisampling is most of a small
    frame's cost (a 64 px LIBERO frame: about 3x, bench/bench_render.py). The frames differ at
    edges (mean 3.8 of 255 at 64 px), enough to move a policy trained on the other kind, so the
    default stays on and a checkpoint's sessions render as its training frames were
    (services/common/policies.py, ``trained_antialiased``).

This module imports MuJoCo only inside the renderer classes: importing it (as
the families' API does) loads no simulator.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import glob
import logging
import os
import sys
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.env_worker import libmujoco
from services.env_worker.busy import busy
from services.env_worker.metrics import FRAMES

log = logging.getLogger(__name__)

#: Camera a video shows when the session's config renders no camera.
DEFAULT_VIDEO_CAMERA = "agentview"


# ---------------------------------------------------------------------------------------------
# GL backend


@dataclass(frozen=True)
class GLChoice:
    """The GL backend of this process and why it was chosen."""

    backend: str
    reason: str
    #: True when MUJOCO_GL was set before the choice (by the operator, or a prior import).
    preset: bool = False

    def describe(self) -> str:
        """One line for the start-up log."""
        return f"MUJOCO_GL={self.backend or '<none>'} ({self.reason})"


def nvidia_gpu_present() -> bool:
    """An NVIDIA GPU is visible to this process (device nodes or the driver's proc entries)."""
    return bool(glob.glob("/dev/nvidia[0-9]*") or glob.glob("/proc/driver/nvidia/gpus/*"))


#: Where glvnd looks for EGL vendor libraries; NVIDIA's entry names ``libEGL_nvidia.so.0``.
EGL_VENDOR_GLOB = "/usr/share/glvnd/egl_vendor.d/*nvidia*.json"


def nvidia_egl_vendor_files() -> list[str]:
    """glvnd's NVIDIA EGL vendor files: the driver is installed even when ldconfig's cache misses it."""
    return glob.glob(EGL_VENDOR_GLOB)


def choose_gl_backend(
    environ: Mapping[str, str],
    find_library: Callable[[str], str | None] = ctypes.util.find_library,
    nvidia: bool | None = None,
    egl_vendors: Callable[[], list[str]] = nvidia_egl_vendor_files,
) -> GLChoice:
    """The backend the rules in the module docstring give, without changing anything."""
    preset = environ.get("MUJOCO_GL", "").strip().lower()
    if preset:
        return GLChoice(preset, "MUJOCO_GL set in the environment", preset=True)
    gpu = nvidia_gpu_present() if nvidia is None else nvidia
    egl, osmesa = find_library("EGL"), find_library("OSMesa")
    note = ""
    if gpu:
        if egl and (find_library("EGL_nvidia") or egl_vendors()):
            return GLChoice("egl", "NVIDIA GPU: EGL on the device")
        note = "NVIDIA GPU without libEGL_nvidia (driver capability 'graphics' missing?); "
    if osmesa:
        return GLChoice("osmesa", note + f"no GPU EGL: OSMesa software renderer ({osmesa})")
    if egl:
        return GLChoice("egl", note + f"no GPU EGL and no OSMesa: EGL through Mesa's software rasterizer ({egl})")
    return GLChoice("", note + "no EGL or OSMesa library: state-only configs only")


_CHOICE: GLChoice | None = None
_CHOICE_LOCK = threading.Lock()


def select_gl_backend() -> str:
    """Choose the backend once per process and export it; returns it ("" when none exists).

    Must run before robosuite or PyOpenGL is imported: both bind MUJOCO_GL / PYOPENGL_PLATFORM
    at import time (this module's renderer picks its context class itself, so an earlier
    ``import mujoco`` does no harm). When they are already loaded nothing is changed.
    """
    global _CHOICE
    with _CHOICE_LOCK:
        if _CHOICE is None:
            choice = choose_gl_backend(os.environ)
            bound = [m for m in ("robosuite", "OpenGL") if m in sys.modules]
            if not choice.preset and bound:
                choice = GLChoice("", f"{' and '.join(bound)} imported before a backend was chosen; MuJoCo's default")
            elif choice.backend:
                os.environ["MUJOCO_GL"] = choice.backend
                if choice.backend in ("egl", "osmesa"):
                    os.environ.setdefault("PYOPENGL_PLATFORM", choice.backend)
            _CHOICE = choice
        return _CHOICE.backend


def gl_backend_choice() -> GLChoice:
    """The backend in effect and the reason, choosing it first if nobody has."""
    select_gl_backend()
    assert _CHOICE is not None
    return _CHOICE


# ---------------------------------------------------------------------------------------------
# Scene rendering


def _release_current_context() -> None:
    """Make no GL context current on this thread, so another thread may take ours."""
    backend = os.environ.get("MUJOCO_GL", "").lower()
    if backend == "egl":
        import mujoco.egl
        from mujoco.egl import egl_ext as EGL

        if mujoco.egl.EGL_DISPLAY is not None:
            EGL.eglMakeCurrent(mujoco.egl.EGL_DISPLAY, EGL.EGL_NO_SURFACE, EGL.EGL_NO_SURFACE, EGL.EGL_NO_CONTEXT)
    elif backend == "osmesa":
        from OpenGL import GL, osmesa

        osmesa.OSMesaMakeCurrent(None, None, GL.GL_FLOAT, 0, 0)
    elif backend in ("glfw", ""):
        import glfw

        glfw.make_context_current(None)


def _gl_context_class() -> Any:
    """MuJoCo's GL context class for the backend in effect.

    Chosen here rather than through ``mujoco.gl_context``, which binds MUJOCO_GL when MuJoCo is
    first imported: a process that imported MuJoCo before the backend was chosen still renders
    headless instead of falling back to GLFW (which needs a display).
    """
    backend = os.environ.get("MUJOCO_GL", "").lower()
    if backend == "egl":
        from mujoco.egl import GLContext
    elif backend == "osmesa":
        from mujoco.osmesa import GLContext
    else:
        from mujoco.gl_context import GLContext
    return GLContext


# ---------------------------------------------------------------------------------------------
# Render contexts made with the GIL released

#: ctypes types of the C scalars mjrContext is made of (mujoco.introspect names them).
_C_SCALARS: dict[str, Any] = {"float": ctypes.c_float, "int": ctypes.c_int, "unsigned int": ctypes.c_uint}
_MAKE_CONTEXT: Any = None
_MAKE_CONTEXT_LOCK = threading.Lock()


def _mjr_context_layout() -> Any:
    """A ctypes Structure with mjrContext's layout, built from the bindings' own introspection
    (so it is the layout of the MuJoCo that is loaded); None when a field type is unknown."""
    from mujoco.introspect import structs

    fields: list[tuple[str, Any]] = []
    for f in structs.STRUCTS["mjrContext"].fields:
        kind = type(f.type).__name__
        if kind == "ValueType" and f.type.name in _C_SCALARS:
            fields.append((f.name, _C_SCALARS[f.type.name]))
        elif kind == "ArrayType" and getattr(f.type.inner_type, "name", "") in _C_SCALARS:
            ctype = _C_SCALARS[f.type.inner_type.name]
            for extent in reversed(f.type.extents):
                ctype = ctype * extent
            fields.append((f.name, ctype))
        elif kind == "PointerType":
            fields.append((f.name, ctypes.c_void_p))
        else:
            return None
    return type("MjrContextLayout", (ctypes.Structure,), {"_fields_": fields})


def _gil_free_make_context() -> Any:
    """``(layout, mjr_makeContext)`` through ctypes, which releases the GIL; False where not possible."""
    global _MAKE_CONTEXT
    with _MAKE_CONTEXT_LOCK:
        if _MAKE_CONTEXT is None:
            _MAKE_CONTEXT = False
            try:
                import mujoco

                lib = libmujoco.library()
                layout = _mjr_context_layout()
                if lib is not None and layout is not None and hasattr(mujoco.MjModel, "_address"):
                    fn = lib.mjr_makeContext
                    fn.restype = None
                    fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int]
                    _MAKE_CONTEXT = (layout, fn)
            except Exception as exc:  # noqa: BLE001 - the bindings' own constructor still works
                log.info("rendering: render contexts are made holding the GIL (%s)", exc)
        return _MAKE_CONTEXT


def _context_address(con: Any, layout: Any) -> int | None:
    """Address of the mjrContext a bindings ``MjrContext`` wraps, or None when it cannot be proven.

    The bindings expose the struct's arrays as numpy views into it: every array field's address
    less its offset in ``layout`` must name the same struct start, else the layout is not the one
    the bindings were built with and nothing is written.
    """
    import numpy as np

    bases = set()
    for name, ctype in layout._fields_:
        if not issubclass(ctype, ctypes.Array):
            continue
        view = getattr(con, name, None)
        if not isinstance(view, np.ndarray) or view.nbytes != ctypes.sizeof(ctype):
            return None
        bases.add(view.ctypes.data - getattr(layout, name).offset)
    return bases.pop() if len(bases) == 1 else None


def make_render_context(model: Any, font_scale: int) -> Any:
    """``mujoco.MjrContext(model, font_scale)`` on the current GL context, made with the GIL released.

    The bindings' constructor runs ``mjr_makeContext`` holding the GIL, and that uploads every
    texture of the model (2.6-3.8 s for a LIBERO scene on two loaded cores): the worker's event
    loop, its heartbeats and its other slots stop meanwhile. Here an empty bindings context (no
    GL work) is made and ``mjr_makeContext`` is called on its struct through ctypes, which
    releases the GIL: the same function on the same inputs, so the same context and the same
    frames. Where the struct's address cannot be proven (``_context_address``) the bindings'
    constructor is used.

    A failure inside ``mjr_makeContext`` called through ctypes would end the process (MuJoCo's
    default error handler) instead of raising, so the checks that can fail (GL version and
    extensions, the offscreen buffer's size) are made first through the bindings, on an empty
    model with the same offscreen size (once per size and process, a few milliseconds): they
    raise a Python error there.
    """
    import mujoco

    made = _gil_free_make_context()
    if made:
        layout, fn = made
        _preflight(model, font_scale)
        con = mujoco.MjrContext()
        address = _context_address(con, layout)
        if address is not None:
            fn(model._address, address, int(font_scale))
            return con
    return mujoco.MjrContext(model, font_scale)


#: Offscreen sizes (and font scales) a render context was made for through the bindings.
_PREFLIGHTS: set[tuple[int, int, int]] = set()


def _preflight(model: Any, font_scale: int) -> None:
    """Make and free a context of an empty model with ``model``'s offscreen size, through the bindings."""
    import mujoco

    vis = model.vis.global_
    key = (int(vis.offwidth), int(vis.offheight), int(font_scale))
    if key in _PREFLIGHTS:
        return
    empty = mujoco.MjModel.from_xml_string(
        f"<mujoco><visual><global offwidth='{key[0]}' offheight='{key[1]}'/></visual></mujoco>")
    mujoco.MjrContext(empty, font_scale).free()
    _PREFLIGHTS.add(key)


_RENDERER_LOGGED = False

#: Busy lease (services/env_worker/busy.py) around making a render context: several times the
#: longest GIL hold measured (3.8 s, LIBERO on two loaded cores), within ZETTA_HEARTBEAT_MAX_BUSY_MS.
RENDER_CONTEXT_LEASE_MS = 15_000


class SceneRenderer:
    """One GL context and MuJoCo render context for one (model, data) pair.

    Not bound to a thread: every :meth:`render` takes the context and gives it back. Calls on one
    renderer must not overlap (a slot uses its environment from one thread at a time); a lock
    makes an overlap wait instead of corrupting the frame.
    """

    def __init__(self, model: Any, data: Any, width: int, height: int, samples: int | None = None) -> None:
        import mujoco

        GLContext = _gl_context_class()
        self.model, self.data = model, data
        vis = model.vis.global_
        # The offscreen buffer bounds every frame; grow it before the context is made.
        vis.offwidth, vis.offheight = max(vis.offwidth, width), max(vis.offheight, height)
        if samples is not None:  # multisampling of the offscreen buffer, fixed when the context is made
            model.vis.quality.offsamples = samples
        self._lock = threading.Lock()
        self._con: Any = None
        # MjrContext uploads the model's textures (2.6-3.8 s for a LIBERO scene on two loaded cores).
        # make_render_context releases the GIL for it; where it falls back to the bindings (which
        # hold it) the worker's heartbeats stop meanwhile, so the gateway is told first.
        with busy(RENDER_CONTEXT_LEASE_MS, "render context"):
            self._gl = GLContext(vis.offwidth, vis.offheight)
            with self._current():
                self._con = make_render_context(model, mujoco.mjtFontScale.mjFONTSCALE_150)
                mujoco.mjr_setBuffer(mujoco.mjtFramebuffer.mjFB_OFFSCREEN, self._con)
                _log_renderer_once()
        self._scene = mujoco.MjvScene(model, maxgeom=max(1000, 4 * model.ngeom))
        self._camera = mujoco.MjvCamera()
        self._camera.type = mujoco.mjtCamera.mjCAMERA_FIXED
        self._option = mujoco.MjvOption()
        # As robosuite's offscreen renderer: visual meshes (group 1) on, collision meshes (group 0) off.
        self._option.geomgroup[0], self._option.geomgroup[1] = 0, 1
        # No sites: they are visualization markers robosuite hides (alpha 0) at reset. ``site_rgba``
        # lives in the model slots share, and whether a model's sites are hidden depends on which
        # resets ran on it, so drawing them rendered one state differently on different models
        # (the "Replays" paragraph of docs/evolution.md).
        self._option.sitegroup[:] = 0
        self._perturb = mujoco.MjvPerturb()
        self.frames = 0

    @contextmanager
    def _current(self) -> Iterator[None]:
        self._gl.make_current()
        try:
            yield
        finally:
            _release_current_context()

    def camera_id(self, name: str) -> int:
        """Id of a named camera of the model; ValueError naming the model's cameras if unknown."""
        import mujoco

        cid = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, name)
        if cid < 0:
            names = [self.model.camera(i).name for i in range(self.model.ncam)]
            raise ValueError(f"camera {name!r} is not in the model; its cameras: {names}")
        return cid

    def render(self, camera_ids: Sequence[int], width: int, height: int) -> list[np.ndarray]:
        """Upright RGB frames (row 0 at the top) of the current state from each camera."""
        import mujoco

        if self._con is None:
            raise RuntimeError("the renderer is closed")
        rect = mujoco.MjrRect(0, 0, width, height)
        frames = []
        with self._lock, self._current():
            if width > self._con.offWidth or height > self._con.offHeight:
                raise ValueError(f"{width}x{height} exceeds the offscreen buffer {self._con.offWidth}x{self._con.offHeight}")
            for cid in camera_ids:
                self._camera.fixedcamid = cid
                mujoco.mjv_updateScene(
                    self.model, self.data, self._option, self._perturb, self._camera,
                    mujoco.mjtCatBit.mjCAT_ALL, self._scene,
                )
                mujoco.mjr_render(rect, self._scene, self._con)
                rgb = np.empty((height, width, 3), dtype=np.uint8)
                mujoco.mjr_readPixels(rgb, None, rect, self._con)
                frames.append(np.ascontiguousarray(rgb[::-1]))  # OpenGL's origin is bottom-left
                FRAMES.labels(self.model.camera(cid).name).inc()
        self.frames += len(frames)
        return frames

    def close(self) -> None:
        """Free the render context and the GL context (idempotent)."""
        if self._con is None:
            return
        try:
            with self._lock, self._current():
                self._con.free()
        finally:
            self._con = None
            self._gl.free()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001 - interpreter shutdown may have torn GL down already
            pass


def _log_renderer_once() -> None:
    """Warn once if an NVIDIA GPU is present but the first context renders in software."""
    global _RENDERER_LOGGED
    if _RENDERER_LOGGED:
        return
    _RENDERER_LOGGED = True
    try:
        from OpenGL import GL

        renderer = (GL.glGetString(GL.GL_RENDERER) or b"?").decode(errors="replace")
        version = (GL.glGetString(GL.GL_VERSION) or b"?").decode(errors="replace")
    except Exception as exc:  # noqa: BLE001 - informational only
        log.debug("rendering: %s; OpenGL renderer unknown (%s)", gl_backend_choice().describe(), exc)
        return
    log.debug("rendering: %s; OpenGL renderer %s, %s", gl_backend_choice().describe(), renderer, version)
    if nvidia_gpu_present() and "llvmpipe" in renderer.lower():
        log.warning("rendering: an NVIDIA GPU is present but frames are rendered in software (%s)", renderer)


def gl_renderer_string() -> str:
    """The OpenGL renderer of a throw-away context (e.g. 'llvmpipe (LLVM 15...)'), for benchmarks."""
    ctx = _gl_context_class()(16, 16)
    try:
        ctx.make_current()
        from OpenGL import GL

        return (GL.glGetString(GL.GL_RENDERER) or b"?").decode(errors="replace")
    finally:
        _release_current_context()
        ctx.free()


def _interchangeable(a: Any, b: Any) -> bool:
    """Models of one sharing template, differing at most in body poses (sharing.interchangeable)."""
    try:
        from services.env_worker.sharing import interchangeable
    except ImportError:  # pragma: no cover - sharing is part of the worker; be safe if it moves
        return False
    return bool(interchangeable(a, b))


def disable_reflections(model: Any) -> None:
    """Zero ``model.mat_reflectance``: reflective materials render as plain ones (physics unaffected)."""
    model.mat_reflectance[:] = 0


# ---------------------------------------------------------------------------------------------
# What a slot renders


def camera_image_name(camera: str) -> str:
    """Canonical image name of a camera (as in the observation schema)."""
    return f"{camera.removeprefix('robot0_')}_image"


class SlotRenderer:
    """The frames a slot needs, rendered from whichever environment the slot holds right now.

    ``env`` returns the slot's current robosuite environment (LIBERO slots swap environments on a
    task change); each environment keeps its own :class:`SceneRenderer` as an attribute, so the
    render context travels with it through the group's pool.
    """

    _ATTR = "_zetta_scene_renderer"

    def __init__(
        self,
        env: Callable[[], Any],
        cameras: Sequence[str],
        size: int,
        reflections: bool = True,
        video_camera: str = DEFAULT_VIDEO_CAMERA,
        antialias: bool = True,
    ) -> None:
        self._env = env
        self.cameras = tuple(cameras)
        self.size = size
        self.reflections = reflections
        self.antialias = antialias
        self.video_camera = video_camera
        self.image_names = tuple(camera_image_name(c) for c in self.cameras)
        #: Camera renders done by this slot (one per camera per frame).
        self.frames_rendered = 0

    @classmethod
    def for_config(cls, env: Callable[[], Any], config: Mapping[str, Any]) -> SlotRenderer:
        """The renderer a family config asks for (``cameras``, ``camera_size``, ``reflections``,
        ``antialias``)."""
        return cls(env, config.get("cameras", ()), config.get("camera_size", 128), config.get("reflections", True),
                   antialias=config.get("antialias", True))

    def scene(self) -> SceneRenderer:
        """The scene renderer of the slot's current environment, made on first use.

        Environments of a group share their model (services/env_worker/sharing.py); a LIBERO
        reset may move the environment to another model of the same template (other fixture
        poses). Such models have the same meshes, textures and materials, so the renderer keeps
        its context and only follows the model; any other change makes a new context.
        """
        env = self._env()
        model, data = env.sim.model._model, env.sim.data._data
        scene: SceneRenderer | None = getattr(env, self._ATTR, None)
        if scene is not None and (scene.model is not model or scene.data is not data):
            if scene.data is data and _interchangeable(scene.model, model):
                scene.model = model
            else:
                scene.close()
                scene = None
        if not self.reflections:
            # Idempotent; every model of a group (a shared template or a private variant) has the
            # same config, so zeroing a model other slots render is what they ask for too.
            disable_reflections(model)
        if scene is None:
            scene = SceneRenderer(model, data, self.size, self.size, None if self.antialias else 0)
            setattr(env, self._ATTR, scene)
        return scene

    def warm(self) -> None:
        """Make the render context now if the slot has cameras and an environment.

        Creating it uploads the model's textures (1-4 s for a LIBERO scene on the CPU renderer;
        the GIL is released meanwhile, :func:`make_render_context`), so the worker does it while
        opening slots, where environment builds already take their time, instead of inside the
        first reset.
        """
        if self.cameras and self._env() is not None:
            self.scene()

    def render(self, cameras: Sequence[str]) -> list[np.ndarray]:
        """Upright frames of the named cameras at the configured size, for the current state."""
        scene = self.scene()
        frames = scene.render([scene.camera_id(c) for c in cameras], self.size, self.size)
        self.frames_rendered += len(frames)
        return frames

    def images(self) -> dict[str, np.ndarray]:
        """Canonical image tensors of the configured cameras for the current simulator state."""
        if not self.cameras:
            return {}
        return dict(zip(self.image_names, self.render(self.cameras), strict=True))

    def video_frame(self, images: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """One video frame: the configured cameras side by side, or the video camera if none.

        ``images`` are this state's observation images when they were rendered already.
        """
        if self.cameras:
            if images is None or any(n not in images for n in self.image_names):
                images = self.images()
            return np.concatenate([images[n] for n in self.image_names], axis=1)
        return self.render([self.video_camera])[0]

    def video_size(self) -> tuple[int, int]:
        """Width and height of :meth:`video_frame`."""
        return self.size * max(1, len(self.cameras)), self.size

    def fps(self) -> float:
        """Control rate of the environment: one video frame per executed action."""
        return float(getattr(self._env(), "control_freq", 20))


def close_env_renderer(env: Any) -> None:
    """Free the render context an environment carries, if any (before ``env.close()``)."""
    scene = getattr(env, SlotRenderer._ATTR, None)
    if scene is not None:
        scene.close()
        setattr(env, SlotRenderer._ATTR, None)
