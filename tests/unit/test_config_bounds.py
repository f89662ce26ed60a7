"""Size-like env_config options are bounded (found by the control-plane fuzz, bench/bench_fuzz.py).

``camera_size``, ``object_state_dim``, ``max_steps`` and ``settle_steps`` used to have only a lower
bound: ``{"cameras": ["agentview"], "camera_size": 1e6}`` or ``{"object_state_dim": 1e10}`` had the
env worker allocate whatever a client asked for (terabytes, or 40 GB per observation), and a
``max_steps`` of 1e30 does not fit the int32 of a ResetResult. They are INVALID_ARGUMENT now,
refused by the family's config check before any environment is built.
"""

from __future__ import annotations

import pytest

from services.env_worker.families import ConfigError, canonical_config_key
from services.env_worker.families.options import (
    MAX_CAMERA_SIZE,
    MAX_EPISODE_STEPS,
    MAX_OBJECT_STATE_DIM,
    MAX_SETTLE_STEPS,
    int_option,
)


@pytest.mark.parametrize(("config", "needle"), [
    ({"cameras": ["agentview"], "camera_size": 1e6}, f"camera_size must be <= {MAX_CAMERA_SIZE}"),
    ({"object_state_dim": 1e10}, f"object_state_dim must be <= {MAX_OBJECT_STATE_DIM}"),
    ({"max_steps": 1e30}, f"max_steps must be <= {MAX_EPISODE_STEPS}"),
], ids=["camera-size", "object-state-dim", "max-steps"])
def test_oversized_robosuite_options_are_refused(config: dict, needle: str) -> None:
    with pytest.raises(ConfigError) as err:
        canonical_config_key("robosuite", {"env_name": "Lift", **config})
    assert needle in str(err.value)


def test_bounds_are_inclusive() -> None:
    """The largest allowed values pass; one more does not."""
    canonical_config_key("robosuite", {"env_name": "Lift", "camera_size": MAX_CAMERA_SIZE,
                                       "object_state_dim": MAX_OBJECT_STATE_DIM, "max_steps": MAX_EPISODE_STEPS})
    assert int_option("libero", {"settle_steps": MAX_SETTLE_STEPS}, "settle_steps", 10,
                      maximum=MAX_SETTLE_STEPS) == MAX_SETTLE_STEPS
    with pytest.raises(ConfigError, match="settle_steps must be <= 1000"):
        int_option("libero", {"settle_steps": MAX_SETTLE_STEPS + 1}, "settle_steps", 10, maximum=MAX_SETTLE_STEPS)
