"""The robocasa family: refused with an actionable reason where RoboCasa cannot run, real where it can.

This project's venv pins robosuite 1.4.0 (LIBERO), and RoboCasa needs robosuite >= 1.5 plus about
10 GB of kitchen assets, so here the family is always unavailable: the first tests check that the
real detection says so (and how to fix it), including through the env worker's slot table; the
detection tests build each case in tmp_path, replacing only the package-location and version
lookups; the episode test runs a real RoboCasa episode and is skipped, with the reason, elsewhere.
"""

from __future__ import annotations

import grpc
import numpy as np
import pytest

from services.common.grpc_errors import ServiceError
from services.env_worker.families import robocasa as rc
from services.env_worker.families import ConfigError, ResetSpec, canonical_config_key, get_family
from services.env_worker.slots import SlotTable

REASON = rc.unavailable_reason()
needs_robocasa = pytest.mark.skipif(bool(REASON), reason=REASON or "RoboCasa is available")


# ---- here: unavailable, with the reason -------------------------------------------------------


@pytest.mark.skipif(not REASON, reason="RoboCasa is installed here; the unavailable path is not reachable")
def test_requesting_the_family_here_names_what_is_missing_and_how_to_install() -> None:
    with pytest.raises(ConfigError) as err:
        get_family("robocasa")({"env_name": "PnPCounterToCab"})
    message = str(err.value)
    assert message == REASON
    # What is missing: in this venv the package itself, or (had it been installed) robosuite 1.4.
    assert "'robocasa' is not installed" in message or "robosuite 1.4" in message
    assert "robosuite >= 1.5" in message and "1.4.0" in message  # why it needs its own environment
    for step in ("pip install -e robosuite", "pip install -e robocasa", "download_kitchen_assets"):
        assert step in message
    with pytest.raises(ConfigError, match="download_kitchen_assets"):
        canonical_config_key("robocasa", {})


@pytest.mark.skipif(not REASON, reason="RoboCasa is installed here; the unavailable path is not reachable")
def test_env_worker_answers_invalid_argument_with_the_reason() -> None:
    table = SlotTable(1, ["robocasa"])
    with pytest.raises(ServiceError) as err:
        table.group("robocasa", {})
    assert err.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert "env_config for 'robocasa'" in str(err.value) and "download_kitchen_assets" in str(err.value)


# ---- the detection, case by case --------------------------------------------------------------


def _package(tmp_path, assets: dict[str, bool]) -> str:
    """A fake robocasa package dir whose asset folders exist filled (True) or empty (False)."""
    package = tmp_path / "robocasa"
    (package / "models" / "assets").mkdir(parents=True)
    for folder, filled in assets.items():
        path = package / "models" / "assets" / folder
        path.mkdir(parents=True)
        if filled:
            (path / "something.xml").write_text("<mujoco/>")
    return str(package)


def _lookups(monkeypatch, package: str | None, version: str | None) -> None:
    monkeypatch.setattr(rc, "_robocasa_dir", lambda: package)
    monkeypatch.setattr(rc, "_robosuite_version", lambda: version)


def test_reason_package_missing(monkeypatch) -> None:
    _lookups(monkeypatch, None, "1.5.1")
    reason = rc.unavailable_reason()
    assert "'robocasa' is not installed" in reason and "git clone https://github.com/robocasa/robocasa" in reason


def test_reason_robosuite_missing(monkeypatch, tmp_path) -> None:
    _lookups(monkeypatch, _package(tmp_path, {"textures": True, "objects/objaverse": True}), None)
    assert "robosuite is not" in rc.unavailable_reason()


@pytest.mark.parametrize("version", ["1.4.0", "1.4.1", "0.3"])
def test_reason_robosuite_too_old(monkeypatch, tmp_path, version: str) -> None:
    _lookups(monkeypatch, _package(tmp_path, {"textures": True, "objects/objaverse": True}), version)
    reason = rc.unavailable_reason()
    assert f"robosuite {version} is installed" in reason and ">= 1.5" in reason and "own" in reason


def test_reason_assets_absent(monkeypatch, tmp_path) -> None:
    package = _package(tmp_path, {})
    _lookups(monkeypatch, package, "1.5.1")
    reason = rc.unavailable_reason()
    assert "kitchen assets are missing or empty" in reason and "download_kitchen_assets" in reason
    assert f"{package}/models/assets/textures" in reason and "objaverse" in reason


def test_reason_assets_empty_vs_filled(monkeypatch, tmp_path) -> None:
    package = _package(tmp_path, {"textures": True, "objects/objaverse": False})
    _lookups(monkeypatch, package, "1.5.1")
    reason = rc.unavailable_reason()
    assert "assets/objects/objaverse" in reason and "assets/textures" not in reason
    (tmp_path / "robocasa" / "models" / "assets" / "objects" / "objaverse" / "apple").mkdir()
    assert rc.unavailable_reason() == ""  # every check passes: the family would import RoboCasa


@pytest.mark.parametrize(("version", "ok"), [("1.5.0", True), ("1.5.1.dev0", True), ("1.10", True), ("2.0", True),
                                             ("1.4.0", False)])
def test_version_threshold(monkeypatch, tmp_path, version: str, ok: bool) -> None:
    _lookups(monkeypatch, _package(tmp_path, {"textures": True, "objects/objaverse": True}), version)
    assert (rc.unavailable_reason() == "") is ok


def test_real_lookups_import_nothing() -> None:
    """The checks read package metadata only: no simulator is imported by asking."""
    import subprocess
    import sys

    code = (
        "import sys; from services.env_worker.families import robocasa as rc; rc.unavailable_reason(); "
        "print(sorted(m for m in sys.modules if m.split('.')[0] in ('robocasa', 'robosuite', 'mujoco')))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"


# ---- where RoboCasa is installed: a real episode ----------------------------------------------


@needs_robocasa
def test_robocasa_episode_resets_steps_and_reports() -> None:
    family = get_family("robocasa")(
        {"env_name": "PnPCounterToCab", "layout_ids": [1], "style_ids": [1], "max_steps": 5}
    )
    try:
        action = family.action_spec()
        assert len(action.shape) == 1 and action.shape[0] >= 7
        slot = family.init()
        spec = ResetSpec(task="", seed=3)
        obs, instruction = slot.reset(spec)
        assert isinstance(instruction, str) and instruction
        schema = family.obs_schema()
        assert set(obs) == set(schema)
        for name, tensor in obs.items():
            assert tensor.shape == schema[name].shape, name
        first_object = obs["task_object_pos"].copy()
        rng = np.random.default_rng(0)
        outcome = None
        for _ in range(5):
            outcome = slot.step(rng.uniform(-0.2, 0.2, size=action.shape).astype(np.float32))
            assert isinstance(outcome.success, bool)
        assert outcome is not None and outcome.truncated
        assert outcome.info["layout_id"] == 1.0 and outcome.info["style_id"] == 1.0
        # The same key draws the same kitchen and objects.
        again, instruction_again = slot.reset(spec)
        assert instruction_again == instruction
        assert np.allclose(again["task_object_pos"], first_object)
        slot.close()
    finally:
        family.close()


# ---- the family's glue, on a stand-in for robosuite 1.5 (only the simulator is replaced) -------


class _StandInKitchen:
    """What the family reads from a RoboCasa env: action_spec, observations, ep meta, success."""

    control_freq = 20
    action_spec = (np.full(12, -1.0), np.full(12, 1.0))

    def __init__(self, **kwargs) -> None:
        self.kwargs = kwargs
        self.rng = np.random.default_rng(kwargs.get("seed"))
        self.objects: dict = {}
        self.layout, self.t, self.meta_unset = -1, 0, 0

    def _get_observations(self, force_update: bool = False) -> dict[str, np.ndarray]:
        q = np.linspace(-1, 1, 7) + 0.01 * self.layout
        return {
            "robot0_eef_pos": np.full(3, float(self.t)), "robot0_eef_quat": np.array([0.0, 0, 0, 1]),
            "robot0_gripper_qpos": np.zeros(2), "robot0_joint_pos_cos": np.cos(q), "robot0_joint_pos_sin": np.sin(q),
            "robot0_proprio-state": np.arange(50, dtype=np.float64), "robot0_base_pos": np.zeros(3),
            "robot0_base_quat": np.array([0.0, 0, 0, 1]), "robot0_base_to_eef_pos": np.ones(3),
            "robot0_base_to_eef_quat": np.array([0.0, 0, 0, 1]), "object-state": np.ones(14),
        }

    def unset_ep_meta(self) -> None:
        self.meta_unset += 1

    def reset(self) -> dict[str, np.ndarray]:
        self.layout, self.t = int(self.rng.integers(0, 60)), 0
        return self._get_observations()

    def get_ep_meta(self) -> dict:
        return {"lang": f"pick the apple in kitchen {self.layout}", "layout_id": self.layout, "style_id": 7}

    def step(self, action):
        assert action.shape == (12,)
        self.t += 1
        return self._get_observations(), 0.0, False, {}

    def _check_success(self) -> bool:
        return self.t >= 2

    def close(self) -> None:
        pass


@pytest.fixture
def stand_in(monkeypatch):
    built: list[_StandInKitchen] = []

    def make(env_name, **kwargs):
        built.append(_StandInKitchen(**kwargs))
        return built[-1]

    monkeypatch.setattr(rc, "unavailable_reason", lambda: "")
    monkeypatch.setattr(rc, "_simulator", lambda: {
        "robosuite": type("robosuite", (), {"make": staticmethod(make)}),
        "controller_config": lambda controller, robot: {"type": "BASIC", "robot": robot},
        "envs": {"PnPCounterToCab": _StandInKitchen}, "robots": {"PandaOmron": object},
    })
    return built


def test_family_glue_on_a_stand_in(stand_in) -> None:
    with pytest.raises(ConfigError, match="unknown env_name"):
        rc.RobocasaFamily({"env_name": "NoSuchKitchen"})
    with pytest.raises(ConfigError, match="layout_ids"):
        rc.RobocasaFamily({"layout_ids": ["one"]})
    family = rc.RobocasaFamily({"task": "PnPCounterToCab", "robots": "PandaMobile", "layout_ids": 1.0,
                                "max_steps": 4})
    assert family.config["robots"] == "PandaOmron" and family.config["layout_ids"] == [1]
    action = family.action_spec()  # read from a built env, parked for the first slot
    assert action.shape == (12,) and (action.low, action.high) == (-1.0, 1.0)
    schema = family.obs_schema()
    assert schema["robot0_proprio"].shape == (50,) and schema["robot0_base_to_eef_quat"].shape == (4,)
    assert len(stand_in) == 1 and stand_in[0].kwargs["hard_reset"] and stand_in[0].kwargs["layout_ids"] == [1]

    slot = family.init()
    assert len(stand_in) == 1 and family.sharing_stats()["envs_reused"] == 1
    obs, instruction = slot.reset(ResetSpec(task="", seed=11))
    assert instruction.startswith("pick the apple") and stand_in[0].meta_unset == 1
    assert set(obs) == set(schema) and obs["task_object_pos"].tolist() == [0.0, 0.0, 0.0]
    assert np.allclose(obs["robot0_joint_pos"], np.linspace(-1, 1, 7) + 0.01 * stand_in[0].layout)
    first = slot.step(np.zeros(12, np.float32))
    assert not first.success and first.info["style_id"] == 7.0
    second = slot.step(np.zeros(12, np.float32))
    assert second.success and second.terminated  # the env's own _check_success
    again, same = slot.reset(ResetSpec(task="PnPCounterToCab", seed=11))
    assert same == instruction  # the same key draws the same kitchen
    other = {slot.reset(ResetSpec(task="0", seed=s))[1] for s in range(6)}
    assert len(other) > 1
    slot.close()
    family.close()
