"""The shipped default policy sees what a real robot's policy sees: camera images, its own
proprioception and the instruction. Nothing the env family marks privileged."""

from __future__ import annotations

import json

from services.common.policies import DEFAULT_POLICY, PRIVILEGED_BASELINE, default_checkpoint, policy_env_config
from services.policy_worker.input_check import supplied_schema
from services.policy_worker.models.base import load_model


def privileged_inputs(model_name: str) -> list[str]:
    """Inputs of a served model that the libero family marks privileged."""
    specs = list(load_model(model_name).input_specs())
    schema = supplied_schema("libero", specs)
    return [s.name for s in specs if schema[s.name].privileged]


def test_the_default_policy_reads_no_privileged_tensor() -> None:
    assert privileged_inputs(DEFAULT_POLICY) == []
    names = {s.name for s in load_model(DEFAULT_POLICY).input_specs()}
    assert "agentview_image" in names, "the default policy is a vision policy"


def test_the_check_catches_a_privileged_model() -> None:
    """The same check flags the state baseline (object poses), so it can fail."""
    assert privileged_inputs(PRIVILEGED_BASELINE) == ["object_state"]


def test_every_default_names_the_image_vla() -> None:
    from services.evolver.rollout import RunConfig
    from services.policy_worker.config import PolicyWorkerConfig
    from bench.bench_sweep import DEFAULT_MODEL
    from services.ops.local_stack import LocalStack

    assert PolicyWorkerConfig.from_env({}).models == (DEFAULT_POLICY,)
    assert LocalStack().models == (DEFAULT_POLICY,)
    assert RunConfig(gateway="127.0.0.1:1").model == DEFAULT_POLICY
    assert DEFAULT_MODEL == DEFAULT_POLICY


def test_sessions_for_the_default_render_its_cameras_only() -> None:
    from services.common.specs import camera_of_image

    cfg = policy_env_config(DEFAULT_POLICY)
    images = [s for s in load_model(DEFAULT_POLICY).input_specs() if s.name.endswith("_image")]
    # Its frames were rendered single-sampled, as a recipe run renders them now.
    assert cfg == {"cameras": [camera_of_image(s.name) for s in images], "camera_size": images[0].shape[0],
                   "reflections": False, "antialias": False}
    assert cfg["cameras"][0] == "agentview"
    assert policy_env_config("scripted-pick-place") == {}


def test_the_shipped_checkpoint_is_small_and_documented() -> None:

    ck = default_checkpoint()
    assert sum(f.stat().st_size for f in ck.iterdir()) <= 25e6
    doc = json.loads((ck / "config.json").read_text())
    assert doc["data"]["recipes"] and doc["training"]["steps_done"] > 0 and doc["inputs"]
    suites = {r["recipe"]["suite"] for r in doc["data"]["recipes"]}
    assert suites == {"libero_goal"}, "trained on original LIBERO tasks only, never a LIBERO-PRO variant"
