"""Render contexts made with the GIL released (services/env_worker/rendering.make_render_context).

The bindings' ``MjrContext(model, ...)`` uploads the model's textures holding the GIL (2.6-3.8 s
for a LIBERO scene on two loaded cores: heartbeats and other slots stop). The worker calls the
same ``mjr_makeContext`` through ctypes instead: the frames must be the same bit for bit, other
threads must run meanwhile, and where the struct's address cannot be proven the bindings'
constructor is used.
"""

from __future__ import annotations

import ctypes
import threading
import time
from typing import Any

import numpy as np
import pytest

from services.env_worker import rendering
from services.env_worker.families import select_gl_backend

pytestmark = pytest.mark.skipif(not select_gl_backend(), reason="no EGL or OSMesa library for offscreen rendering")

#: A textured scene: a big procedural texture makes the upload take long enough to watch.
SCENE = """
<mujoco>
  <asset>
    <texture name="grid" type="2d" builtin="checker" width="4096" height="4096" rgb1=".2 .3 .4" rgb2=".8 .7 .1"/>
    <material name="grid" texture="grid" texrepeat="4 4"/>
    <texture name="sky" type="skybox" builtin="gradient" width="256" height="256" rgb1=".4 .6 .8" rgb2="0 0 0"/>
  </asset>
  <worldbody>
    <light pos="0 0 3"/>
    <geom type="plane" size="2 2 .1" material="grid"/>
    <geom type="box" size=".2 .2 .2" pos="0 0 .2" rgba=".9 .1 .1 1"/>
    <camera name="cam" pos="0 -2 1.5" xyaxes="1 0 0 0 .6 .8"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture(scope="module")
def scene() -> tuple[Any, Any]:
    import mujoco

    model = mujoco.MjModel.from_xml_string(SCENE)
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    return model, data


def _frame(model: Any, data: Any) -> tuple[np.ndarray, int]:
    renderer = rendering.SceneRenderer(model, data, 64, 64)
    try:
        frame = renderer.render([renderer.camera_id("cam")], 64, 64)[0]
        return frame, renderer._con.ntexture
    finally:
        renderer.close()


def test_the_ctypes_context_renders_the_same_frames(scene: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    model, data = scene
    assert rendering._gil_free_make_context(), "mjr_makeContext through ctypes is not available here"
    ours, ntex = _frame(model, data)
    monkeypatch.setattr(rendering, "_gil_free_make_context", lambda: False)
    theirs, ntex_bindings = _frame(model, data)
    assert ntex == ntex_bindings == 2
    assert ours.std() > 0 and np.array_equal(ours, theirs)


def test_other_threads_run_while_the_textures_upload(scene: tuple[Any, Any], monkeypatch: pytest.MonkeyPatch) -> None:
    model, _ = scene
    layout, make = rendering._gil_free_make_context()
    ticks = [0]
    stop = threading.Event()

    def ticker() -> None:
        while not stop.is_set():
            ticks[0] += 1
            time.sleep(0.001)

    seen: list[tuple[int, int, float]] = []

    def watched(*args: Any) -> None:
        before, start = ticks[0], time.perf_counter()
        make(*args)
        seen.append((before, ticks[0], time.perf_counter() - start))

    monkeypatch.setattr(rendering, "_MAKE_CONTEXT", (layout, watched))
    thread = threading.Thread(target=ticker, daemon=True)
    thread.start()
    try:
        renderer = rendering.SceneRenderer(model, scene[1], 64, 64)
        renderer.close()
    finally:
        stop.set()
        thread.join()
    [(before, after, took)] = seen
    assert after > before, f"no other thread ran during a {took:.3f} s context creation: the GIL was held"


def test_an_unproven_address_falls_back_to_the_bindings(scene: tuple[Any, Any],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    import mujoco

    layout, make = rendering._gil_free_make_context()
    con = mujoco.MjrContext()
    address = rendering._context_address(con, layout)
    assert address is not None and address == con.fogRGBA.ctypes.data - layout.fogRGBA.offset
    # A layout that does not match the bindings' struct (one field fewer at the front) proves nothing.
    shifted = type("Shifted", (ctypes.Structure,), {"_fields_": layout._fields_[1:]})
    assert rendering._context_address(con, shifted) is None

    calls = []
    monkeypatch.setattr(rendering, "_MAKE_CONTEXT", (shifted, lambda *a: calls.append(a)))
    model, data = scene
    frame, ntex = _frame(model, data)
    assert calls == [] and ntex == 2 and frame.std() > 0
