"""Rendering: GL backend choice, frames only when needed, reflections switch, episode videos.

The robosuite Lift scene at 32x32 keeps these cheap (a frame costs a few ms on the CPU
renderer); one LIBERO test checks that a reset renders once, not on every settle step.
"""

from __future__ import annotations

import ctypes.util
import os
import subprocess
import sys
import threading
from pathlib import Path

import cv2
import grpc
import numpy as np
import pytest
from prometheus_client import REGISTRY

from services.common.config import ConfigError
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.families import ConfigError as FamilyConfigError
from services.env_worker.families import ResetSpec, get_family, select_gl_backend
from services.env_worker.rendering import choose_gl_backend, gl_backend_choice, nvidia_gpu_present
from services.env_worker.video import VideoError, VideoRecorder, check_video_dir

ROOT = Path(__file__).resolve().parents[2]
CAMERAS = ["agentview", "robot0_eye_in_hand"]
IMAGES = ["agentview_image", "eye_in_hand_image"]
SIZE = 32
NO_GL = pytest.mark.skipif(not select_gl_backend(), reason="no EGL or OSMesa library for offscreen rendering")
UP = np.array([0, 0, 0.5, 0, 0, 0, -1], np.float32)


@pytest.fixture(scope="module")
def lift():
    family = get_family("robosuite")({"env_name": "Lift", "cameras": CAMERAS, "camera_size": SIZE})
    yield family
    family.close()


@pytest.fixture
def slot(lift):
    s = lift.init()
    yield s
    s.close()


# ---- GL backend ---------------------------------------------------------------------------------


def _libs(*present: str):
    return lambda name: f"lib{name}.so" if name in present else None


_VENDOR = "/usr/share/glvnd/egl_vendor.d/10_nvidia.json"


@pytest.mark.parametrize(
    ("environ", "libs", "vendors", "gpu", "backend"),
    [
        ({"MUJOCO_GL": "glfw"}, ("EGL", "OSMesa"), [], False, "glfw"),  # the operator's choice wins
        ({}, ("EGL", "EGL_nvidia", "OSMesa"), [], True, "egl"),  # GPU: EGL on the device
        ({}, ("EGL", "OSMesa"), [_VENDOR], True, "egl"),  # GPU, driver known to glvnd only
        ({}, ("OSMesa",), [_VENDOR], True, "osmesa"),  # GPU driver but no libEGL to load it
        ({}, ("EGL", "OSMesa"), [], True, "osmesa"),  # GPU but no NVIDIA EGL: software
        ({}, ("EGL", "EGL_nvidia", "OSMesa"), [_VENDOR], False, "osmesa"),  # no GPU: the driver alone is not enough
        ({}, ("EGL", "OSMesa"), [], False, "osmesa"),  # CPU: OSMesa when installed
        ({}, ("EGL",), [], False, "egl"),  # CPU without OSMesa: EGL through Mesa
        ({}, (), [], False, ""),  # nothing: state-only
    ],
)
def test_gl_backend_rules(environ: dict, libs: tuple, vendors: list, gpu: bool, backend: str) -> None:
    choice = choose_gl_backend(environ, _libs(*libs), nvidia=gpu, egl_vendors=lambda: vendors)
    assert choice.backend == backend
    assert choice.reason and (backend or "state-only") in choice.describe() + choice.reason


def test_backend_in_effect_is_exported() -> None:
    choice = gl_backend_choice()
    assert os.environ.get("MUJOCO_GL", "") == choice.backend
    assert f"MUJOCO_GL={choice.backend}" in choice.describe()


_RENDER_ONE = (
    "import numpy as np; from services.env_worker.families import get_family, ResetSpec; "
    "f = get_family('robosuite')({'env_name': 'Lift', 'cameras': ['agentview'], 'camera_size': 16}); "
    "s = f.init(); o, _ = s.reset(ResetSpec('')); img = o['agentview_image']; "
    "from services.env_worker.rendering import gl_renderer_string; "
    "print(img.shape, int(img.std() > 0), gl_renderer_string())"
)


@pytest.mark.parametrize(("backend", "library"), [("egl", "EGL"), ("osmesa", "OSMesa")])
def test_cpu_backend_renders(backend: str, library: str) -> None:
    """Each backend whose library is installed renders a non-blank frame in a fresh process."""
    if not ctypes.util.find_library(library):
        pytest.skip(f"lib{library} is not installed")
    if gl_backend_choice().backend == backend:
        pytest.skip(f"{backend} renders the other tests of this process")
    env = {**os.environ, "MUJOCO_GL": backend, "PYOPENGL_PLATFORM": backend}
    out = subprocess.run([sys.executable, "-c", _RENDER_ONE], cwd=ROOT, env=env, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.splitlines()[-1].startswith("(16, 16, 3) 1 ")


@pytest.mark.gpu
@pytest.mark.skipif(not nvidia_gpu_present(), reason="no NVIDIA GPU")
def test_gpu_renders_on_the_device() -> None:
    """With a GPU the automatic choice is EGL and the frames come from the GPU, not llvmpipe."""
    env = {k: v for k, v in os.environ.items() if k not in ("MUJOCO_GL", "PYOPENGL_PLATFORM")}
    code = "from services.env_worker.rendering import gl_backend_choice as c; print(c().backend)\n" + _RENDER_ONE
    out = subprocess.run([sys.executable, "-c", code.replace("\n", "; ")], cwd=ROOT, env=env, capture_output=True,
                         text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert lines[0] == "egl"
    assert "llvmpipe" not in lines[-1].lower() and lines[-1].startswith("(16, 16, 3) 1 ")


# ---- frames only when needed --------------------------------------------------------------------


@NO_GL
def test_schema_declares_the_chosen_cameras(lift) -> None:
    schema = lift.obs_schema()
    for name in IMAGES:
        assert schema[name].dtype == "uint8" and tuple(schema[name].shape) == (SIZE, SIZE, 3)
    state_only = get_family("robosuite")({"env_name": "Lift"}).obs_schema()
    assert not [n for n in state_only if n.endswith("_image")]


@NO_GL
def test_images_rendered_only_when_an_observation_needs_them(slot) -> None:
    renderer = slot.renderer
    obs, _ = slot.reset(ResetSpec(""))
    assert renderer.frames_rendered == 2 and all(obs[n].std() > 0 for n in IMAGES)
    assert not slot._env.use_camera_obs  # robosuite itself never renders
    for _ in range(4):  # a chunk's intermediate actions
        outcome = slot.step(UP, render=False)
        assert not set(IMAGES) & set(outcome.observation)
    assert renderer.frames_rendered == 2
    last = slot.step(UP)  # the chunk's last action
    assert renderer.frames_rendered == 4 and set(IMAGES) <= set(last.observation)
    slot.step(UP, render=False)
    observed = slot.observe()  # asked later: rendered once, then cached
    assert renderer.frames_rendered == 6 and set(IMAGES) <= set(observed)
    assert np.array_equal(slot.observe()["agentview_image"], observed["agentview_image"])
    assert renderer.frames_rendered == 6


def _frames_metric(camera: str) -> float:
    return REGISTRY.get_sample_value("zetta_env_frames_rendered_total", {"camera": camera}) or 0.0


@NO_GL
def test_frames_rendered_metric_counts_each_camera_render(slot) -> None:
    """The Prometheus counter moves exactly when a frame is rendered, per camera, and not on
    steps whose observations carry no images."""
    before = {c: _frames_metric(c) for c in CAMERAS}
    slot.reset(ResetSpec(""))
    slot.step(UP, render=False)
    slot.step(UP, render=False)
    assert {c: _frames_metric(c) - before[c] for c in CAMERAS} == {c: 1.0 for c in CAMERAS}
    slot.step(UP)
    slot.observe()  # cached: no new frame
    assert {c: _frames_metric(c) - before[c] for c in CAMERAS} == {c: 2.0 for c in CAMERAS}
    assert slot.renderer.frames_rendered == 4


@NO_GL
def test_libero_reset_renders_once_and_keeps_its_context() -> None:
    """A reset renders once (not per settle step); moving to another model of the template keeps
    the GL context and renders what a slot that has always been on that model renders."""
    family = get_family("libero")(
        {"suite": "libero_goal", "task": "put_the_cream_cheese_in_the_bowl", "cameras": ["agentview"],
         "camera_size": SIZE, "settle_steps": 5}
    )
    a, b = family.init(), family.init()
    try:
        obs, _ = b.reset(ResetSpec("", seed=1))
        assert b.renderer.frames_rendered == 1 and obs["agentview_image"].std() > 0
        scene = b.renderer.scene()
        first_model = scene.model
        theirs, _ = a.reset(ResetSpec("", seed=2))
        mine, _ = b.reset(ResetSpec("", seed=2))  # b now shares a's model (same fixture poses)
        assert b._env.sim.model._model is not first_model and b.renderer.scene() is scene
        assert scene.model is b._env.sim.model._model
        assert np.array_equal(mine["agentview_image"], theirs["agentview_image"])
    finally:
        a.close()
        b.close()
        family.close()


@NO_GL
def test_frames_do_not_depend_on_site_colours() -> None:
    """Site colours live in the model slots share and depend on which model a slot got; a frame of
    one state is the same whatever they are (they are markers robosuite hides, never scene)."""
    family = get_family("libero")(
        {"suite": "libero_goal", "task": "put_the_wine_bottle_on_the_rack", "cameras": ["agentview"],
         "camera_size": 64, "settle_steps": 2}
    )
    slot = family.init()
    try:
        slot.reset(ResetSpec("", seed=49, init_state_index=49))
        model = slot._env.sim.model._model
        frames = []
        for alpha in (0.0, 1.0):
            model.site_rgba[:, 3] = alpha
            frames.append(slot.renderer.images()["agentview_image"])
        assert np.array_equal(frames[0], frames[1])
    finally:
        slot.close()
        family.close()


@NO_GL
def test_frames_follow_the_env_across_threads(slot) -> None:
    """Pooled envs move between slot threads; a frame rendered on another thread is the same frame."""
    obs, _ = slot.reset(ResetSpec("", seed=3))
    seen: dict[str, np.ndarray] = {}

    def other() -> None:
        slot._images = None  # force a fresh render of the same state on this thread
        seen.update(slot.observe())

    t = threading.Thread(target=other)
    t.start()
    t.join()
    assert np.array_equal(seen["agentview_image"], obs["agentview_image"])


# ---- reflections --------------------------------------------------------------------------------


def _lift_frames(option: str, probe) -> dict[bool, np.ndarray]:
    """Lift's agentview frame after reset with ``option`` on and off; ``probe(model, on)`` checks
    the slot's model while it is open."""
    with pytest.raises(FamilyConfigError, match="true or false"):
        get_family("robosuite")({"env_name": "Lift", option: "maybe"})
    frames = {}
    for on in (True, False):
        family = get_family("robosuite")({"env_name": "Lift", "cameras": ["agentview"], "camera_size": 64, option: on})
        slot = family.init()
        try:
            frames[on] = slot.reset(ResetSpec(""))[0]["agentview_image"].astype(int)
            probe(slot._env.sim.model._model, on)
        finally:
            slot.close()
            family.close()
    return frames


@NO_GL
def test_reflections_switch() -> None:
    def probe(model, on: bool) -> None:
        assert bool(model.mat_reflectance.any()) is on

    frames = _lift_frames("reflections", probe)
    assert not np.array_equal(frames[True], frames[False])


@NO_GL
def test_antialias_switch() -> None:
    """Off renders single-sampled frames of the same scene: edges differ, the picture does not."""
    def probe(model, on: bool) -> None:
        assert model.vis.quality.offsamples == (4 if on else 0)

    frames = _lift_frames("antialias", probe)
    gap = np.abs(frames[True] - frames[False])
    assert gap.any() and gap.mean() < 8


# ---- videos -------------------------------------------------------------------------------------


def _video_stats(path: str) -> tuple[int, int, int]:
    cap = cv2.VideoCapture(path)
    assert cap.isOpened(), path
    frames = 0
    size = (0, 0)
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        frames += 1
        size = (frame.shape[1], frame.shape[0])
    cap.release()
    return frames, *size


def test_video_recorder_writes_a_readable_mp4(tmp_path: Path) -> None:
    rec = VideoRecorder(str(tmp_path / "x.mp4"), 20, 48, 32)
    for i in range(7):
        rec.add(np.full((32, 48, 3), i * 30, np.uint8))
    with pytest.raises(VideoError, match="does not fit"):
        rec.add(np.zeros((48, 32, 3), np.uint8))
    assert rec.close() == str(tmp_path / "x.mp4")
    assert _video_stats(rec.path) == (7, 48, 32)


def test_video_dir_is_checked_at_start_up(tmp_path: Path) -> None:
    assert check_video_dir(str(tmp_path / "new" / "dir")) == str((tmp_path / "new" / "dir").resolve())
    blocker = tmp_path / "file"
    blocker.write_text("x")
    base = {"ZETTA_GATEWAY_ADDRESS": "127.0.0.1:1"}
    with pytest.raises(ConfigError, match="ZETTA_VIDEO_DIR"):
        EnvWorkerConfig.from_env({**base, "ZETTA_VIDEO_DIR": str(blocker / "sub")})
    assert EnvWorkerConfig.from_env({**base, "ZETTA_VIDEO_DIR": str(tmp_path)}).video_dir == str(tmp_path.resolve())
    assert EnvWorkerConfig.from_env(base).video_dir == ""


@NO_GL
def test_slot_records_one_frame_per_action(slot, tmp_path: Path) -> None:
    path = str(tmp_path / "ep.mp4")
    slot.reset(ResetSpec("", video_path=path))
    outcomes = [slot.step(UP, render=False) for _ in range(5)]
    assert all(o.video_path == "" for o in outcomes)
    assert slot.finish_video() == path
    assert _video_stats(path) == (6, 2 * SIZE, SIZE)  # reset + 5 actions, two cameras side by side
    slot.reset(ResetSpec(""))  # the next episode records nothing
    slot.step(UP)
    assert slot.finish_video() == ""


# ---- through the env worker's gRPC service --------------------------------------------------------


@NO_GL
async def test_worker_renders_at_chunk_end_and_writes_video(tmp_path: Path) -> None:
    from google.protobuf import struct_pb2

    from services.env_worker.policy_client import PolicyClient
    from services.env_worker.servicer import EnvWorkerServicer
    from services.env_worker.slots import SlotTable
    from zetta_wire.codec import decode_observation, encode
    from zetta_wire.v1 import env_worker_pb2 as pb
    from zetta_wire.v1 import env_worker_pb2_grpc, types_pb2

    table = SlotTable(2, ["robosuite"])
    servicer = EnvWorkerServicer(table, PolicyClient([], 1000), video_dir=str(tmp_path))
    server = grpc.aio.server()
    env_worker_pb2_grpc.add_EnvWorkerServiceServicer_to_server(servicer, server)
    port = server.add_insecure_port("127.0.0.1:0")
    await server.start()
    try:
        async with grpc.aio.insecure_channel(f"127.0.0.1:{port}") as channel:
            stub = env_worker_pb2_grpc.EnvWorkerServiceStub(channel)
            config = struct_pb2.Struct()
            config.update({"env_name": "Lift", "cameras": CAMERAS, "camera_size": SIZE, "max_steps": 7})
            opened = await stub.OpenSlots(pb.OpenSlotsRequest(session_ids=["a", "b"], env_family="robosuite",
                                                              env_config=config))
            declared = {s.name: list(s.shape) for s in opened.observation_schema}
            assert all(declared[n] == [SIZE, SIZE, 3] for n in IMAGES)
            reset = await stub.ResetSlots(pb.ResetSlotsRequest(
                session_ids=["a", "b"], specs=[types_pb2.ResetSpec(record_video=True), types_pb2.ResetSpec()]))
            path = reset.results[0].video_path
            assert path == str(tmp_path / f"{reset.results[0].episode_id}.mp4") and not reset.results[1].video_path
            renderer = table.get(["b"])[0].env.renderer
            assert renderer.frames_rendered == 2
            chunk = np.tile(UP, (4, 1))
            step = await stub.StepSlots(pb.StepSlotsRequest(session_ids=["a", "b"], actions=[encode(chunk)] * 2))
            assert renderer.frames_rendered == 4  # one render per camera for a chunk of 4
            assert set(IMAGES) <= set(decode_observation(step.results[1].observation))
            assert not step.results[0].video_path  # the episode goes on
            # 3 of these 4 actions fit in the budget of 7: the episode ends inside the chunk.
            step = await stub.StepSlots(pb.StepSlotsRequest(session_ids=["a", "b"], actions=[encode(chunk)] * 2))
            assert step.results[1].truncated and renderer.frames_rendered == 6
            assert set(IMAGES) <= set(decode_observation(step.results[1].observation))
            assert step.results[0].video_path == path
            assert _video_stats(path) == (8, 2 * SIZE, SIZE)  # reset + 7 actions
            with pytest.raises(grpc.aio.AioRpcError) as err:
                servicer.video_dir = ""
                await stub.ResetSlots(pb.ResetSlotsRequest(session_ids=["a"], specs=[types_pb2.ResetSpec(record_video=True)]))
            assert err.value.code() == grpc.StatusCode.FAILED_PRECONDITION
            await stub.CloseSlots(pb.CloseSlotsRequest(session_ids=["a", "b"]))
    finally:
        await server.stop(None)
        table.shutdown()
