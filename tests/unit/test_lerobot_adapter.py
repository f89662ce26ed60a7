"""The ``lerobot`` model's settings and the torchvision stand-in, without lerobot itself
(tests/integration/test_lerobot_policy.py serves a real LeRobot policy end to end)."""

from __future__ import annotations

import json

import pytest

from services.common.policies import lerobot_cameras, policy_env_config
from services.common.specs import TensorSpec, render_config
from services.env_worker.families.schema import camera_obs_name
from services.policy_worker.config import PolicyWorkerConfig
from services.policy_worker.vla.adapter import _parse_pairs, make_lerobot_adapter
from services.policy_worker.vla.lerobot_import import TorchvisionUnavailable, _refusing_module


def test_lerobot_is_a_served_model_that_needs_its_checkpoint() -> None:
    assert PolicyWorkerConfig.from_env({"ZETTA_MODELS": "lerobot"}).models == ("lerobot",)
    with pytest.raises(ValueError, match="ZETTA_LEROBOT_CHECKPOINT"):
        make_lerobot_adapter({})


def test_camera_mapping_is_parsed_and_bad_items_named() -> None:
    assert _parse_pairs(" observation.images.top=agentview, observation.images.wrist=robot0_eye_in_hand ", "X") == {
        "observation.images.top": "agentview", "observation.images.wrist": "robot0_eye_in_hand"}
    with pytest.raises(ValueError, match="X: .*'agentview'"):
        _parse_pairs("agentview", "X")


def test_torchvision_stand_in_imports_but_refuses_every_use() -> None:
    tv = _refusing_module("torchvision.transforms.v2")

    class Mine(tv.Transform):  # lerobot subclasses torchvision's Transform at import
        pass

    with pytest.raises(TorchvisionUnavailable, match="torchvision.transforms.v2.Transform"):
        Mine()
    with pytest.raises(TorchvisionUnavailable, match="resize"):
        tv.resize(None)
    assert not hasattr(tv, "__wrapped__")


def test_lerobot_image_inputs_map_to_env_cameras(tmp_path, monkeypatch) -> None:
    pi05 = [("observation.images.image", (3, 224, 224)), ("observation.images.wrist_image", (3, 224, 224))]
    assert lerobot_cameras(pi05) == [("observation.images.image", "agentview_image", 224),
                                     ("observation.images.wrist_image", "eye_in_hand_image", 224)]
    aloha = [("observation.images.top", (3, 96, 96)), ("observation.images.front", (3, 96, 96))]
    with pytest.raises(ValueError, match="two of them would read the agentview camera"):
        lerobot_cameras(aloha)
    assert [t for _, t, _ in lerobot_cameras(aloha, {"observation.images.front": "frontview"})] == [
        "agentview_image", "frontview_image"]
    with pytest.raises(ValueError, match="square"):
        lerobot_cameras([("observation.image", (3, 96, 128))])
    with pytest.raises(ValueError, match="does not read"):
        lerobot_cameras(pi05, {"observation.images.side": "sideview"})
    # The CLI's sessions render what the checkpoint's config.json declares.
    (tmp_path / "config.json").write_text(json.dumps({"type": "pi05", "input_features": {
        "observation.images.image": {"type": "VISUAL", "shape": [3, 224, 224]},
        "observation.images.wrist_image": {"type": "VISUAL", "shape": [3, 224, 224]},
        "observation.state": {"type": "STATE", "shape": [8]}}}))
    monkeypatch.setenv("ZETTA_LEROBOT_CHECKPOINT", str(tmp_path))
    assert policy_env_config("lerobot") == {"cameras": ["agentview", "robot0_eye_in_hand"], "camera_size": 224,
                                            "reflections": False, "antialias": True}


def test_render_config_names_robot_cameras_as_the_env_does() -> None:
    """A wrist-camera input (``eye_in_hand_image``: the tensor drops ``robot0_``) renders ``robot0_eye_in_hand``."""
    specs = [TensorSpec("agentview_image", "uint8", (64, 64, 3)), TensorSpec("eye_in_hand_image", "uint8", (64, 64, 3))]
    assert render_config(specs)["cameras"] == ["agentview", "robot0_eye_in_hand"]
    assert camera_obs_name(render_config(specs)["cameras"][1]) == "eye_in_hand_image"
