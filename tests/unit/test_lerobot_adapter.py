"""The ``lerobot`` model's settings and the torchvision stand-in, without lerobot itself
(tests/integration/test_lerobot_policy.py serves a real LeRobot policy end to end)."""

from __future__ import annotations

import pytest

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
