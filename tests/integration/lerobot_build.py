"""Build a real LeRobot policy offline and save it as a checkpoint directory (no hub download).

``python -m tests.integration.lerobot_build OUT`` makes a TD-MPC policy (LeRobot's
``TDMPCPolicy``, built from its ``TDMPCConfig`` with random weights, small so it runs in
milliseconds) reading one 64 x 64 camera and LIBERO's 8-wide ``observation.state``, writes it with
``save_pretrained`` and its pre/post-processor pipelines with action statistics (min ``LOW``, max
``HIGH``), and prints one JSON line describing it (with the inputs ``LeRobotAdapter`` declares for
it by default: its image reads ``agentview_image``). It also builds a camera-less TD-MPC whose
``observation.state`` has the 16 columns of Zetta's LeRobot export and serves one batch of it through
``LeRobotAdapter`` in this process (reported under ``state_only``). It runs in its own process so the
test process never imports lerobot (and its torchvision stand-in). Exit code 3: lerobot is not
importable here.
"""

from __future__ import annotations

import json
import sys
from typing import Any

#: Action statistics the postprocessor unnormalizes with: TD-MPC plans in [-1, 1], so every
#: served action must land in [LOW, HIGH] (per dimension) if the postprocessor was applied.
LOW = [-0.2, -0.1, -0.3, -0.05, -0.05, -0.05, -1.0]
HIGH = [0.6, 0.1, 0.3, 0.05, 0.05, 0.05, 1.0]
IMAGE = 64
CHUNK = 5
#: TD-MPC, shrunk: the planner still runs CEM over sampled and policy trajectories.
SMALL = dict(n_action_repeats=1, n_action_steps=CHUNK, horizon=CHUNK, latent_dim=16, mlp_dim=32,
             image_encoder_hidden_dim=8, state_encoder_hidden_dim=32, q_ensemble_size=2, n_gaussian_samples=16,
             n_pi_samples=4, n_elites=4, cem_iterations=2)


def _save(out: str, inputs: dict[str, Any]) -> Any:
    from services.policy_worker.vla.lerobot_import import import_lerobot

    factory = import_lerobot()
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature

    torch.manual_seed(0)
    cfg = factory.make_policy_config(
        "tdmpc", device="cpu", **SMALL, output_features={"action": PolicyFeature(FeatureType.ACTION, (7,))},
        input_features={k: PolicyFeature(getattr(FeatureType, kind), shape) for k, (kind, shape) in inputs.items()})
    policy = factory.get_policy_class(cfg.type)(cfg)
    policy.save_pretrained(out)
    stats = {"action": {"min": torch.tensor(LOW), "max": torch.tensor(HIGH)}}
    pre, post = factory.make_pre_post_processors(cfg, dataset_stats=stats)
    pre.save_pretrained(out)
    post.save_pretrained(out)
    return policy


def _serve_state_only(out: str) -> dict[str, object]:
    """The export-layout policy through LeRobotAdapter, as the worker builds it, on one batch of 3."""
    import numpy as np

    from services.common.policies import PROPRIO_INPUTS
    from services.policy_worker.vla.adapter import make_lerobot_adapter

    _save(out, {"observation.state": ("STATE", (sum(w for _, w in PROPRIO_INPUTS),))})
    adapter = make_lerobot_adapter({"ZETTA_LEROBOT_CHECKPOINT": out, "ZETTA_LEROBOT_CHUNK": "3"})
    rng = np.random.default_rng(0)
    batch = {s.name: rng.normal(size=(3, *s.shape)).astype(np.float32) for s in adapter.input_specs()}
    actions = adapter.infer(batch, ["lift the cube"] * 3)
    return {"inputs": [s.name for s in adapter.input_specs()], "state_parts": list(adapter.state_parts),
            "actions_shape": list(actions.shape), "in_range": bool(((actions >= np.array(LOW) - 1e-5)
                                                                    & (actions <= np.array(HIGH) + 1e-5)).all())}


def build(out: str) -> dict[str, object]:
    from services.policy_worker.vla.adapter import make_lerobot_adapter

    policy = _save(out, {"observation.image": ("VISUAL", (3, IMAGE, IMAGE)), "observation.state": ("STATE", (8,))})
    default_inputs = [s.name for s in make_lerobot_adapter({"ZETTA_LEROBOT_CHECKPOINT": out}).input_specs()]
    return {"type": policy.config.type, "class": f"{type(policy).__module__}.{type(policy).__name__}",
            "parameters": sum(p.numel() for p in policy.parameters()), "default_inputs": default_inputs,
            "state_only": _serve_state_only(out + "-state")}


def main() -> int:
    from services.policy_worker.vla.lerobot_import import LeRobotUnavailable

    try:
        info = build(sys.argv[1])
    except LeRobotUnavailable as exc:
        print(json.dumps({"unavailable": str(exc)}))
        return 3
    print(json.dumps(info))
    return 0


if __name__ == "__main__":
    sys.exit(main())
