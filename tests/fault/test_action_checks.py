"""Bad action values and policy specs are refused before anything steps (issue #21, item 5).

NaN, inf and 1e30 actions used to run silently although the action spec says [-1, 1], and
``execute_steps=-3`` was accepted.
"""

from __future__ import annotations

import numpy as np
import pytest

from tests.fault.test_bounded_requests import live  # noqa: F401 - fixture
from tests.fault.test_faults import episode_steps, expect_error
from zetta import Gateway, SessionGroup
from zetta_wire.codec import encode
from zetta_wire.v1 import gateway_pb2, types_pb2


@pytest.mark.parametrize(
    "value,index,shape,needle",
    [
        (np.nan, (3,), (7,), "element [3] is nan"),
        (np.inf, (0,), (7,), "element [0] is inf"),
        (-np.inf, (6,), (7,), "element [6] is -inf"),
        (1e30, (2,), (7,), "element [2] is 1e+30, outside the action spec's range [-1, 1]"),
        (-1.5, (4, 1), (5, 7), "element [4, 1] is -1.5, outside"),
    ],
    ids=["nan", "inf", "-inf", "1e30", "chunk-out-of-range"],
)
async def test_bad_action_values(gw: Gateway, live: SessionGroup, value: float,  # noqa: F811
                                 index: tuple[int, ...], shape: tuple[int, ...], needle: str) -> None:
    """INVALID_ARGUMENT naming the session and the element; neither session of the batch steps."""
    bad = np.zeros(shape, np.float32)
    bad[index] = value
    good = np.zeros(shape, np.float32)
    req = gateway_pb2.ActionStepRequest(session_ids=live.ids, actions=[encode(good), encode(bad)])
    err = await expect_error(gw.call("ActionStep", req), "INVALID_ARGUMENT")
    assert needle in err.details and live.ids[1] in err.details
    assert err.session_ids == [live.ids[1]]
    assert await episode_steps(gw, live.ids) == [0, 0]
    # The same on a stream.
    err = await expect_error(live[1].stream().action_step(bad), "INVALID_ARGUMENT")
    assert needle in err.details
    assert await episode_steps(gw, live.ids) == [0, 0]


async def test_boundary_values_run(gw: Gateway, live: SessionGroup) -> None:  # noqa: F811
    """Exactly -1 and 1 are inside the spec and step."""
    edge = np.array([-1, 1, -1, 1, 0, 0, 1], np.float32)
    assert [r.episode_step for r in await live.action_step([edge, edge])] == [1, 1]


@pytest.mark.parametrize("spec,needle", [
    (types_pb2.PolicySpec(execute_steps=-3), "execute_steps"),
    (types_pb2.PolicySpec(execute_steps=100_000), "execute_steps"),
    (types_pb2.PolicySpec(timeout_ms=-1), "timeout_ms"),
], ids=["execute-steps-negative", "execute-steps-huge", "timeout-negative"])
async def test_bad_policy_spec(gw: Gateway, live: SessionGroup, spec: types_pb2.PolicySpec,  # noqa: F811
                               needle: str) -> None:
    """A PolicySpec that cannot mean anything is INVALID_ARGUMENT on every call that takes one."""
    for method, req in (
        ("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=live.ids, policy=spec)),
        ("PolicyInfer", gateway_pb2.PolicyInferRequest(session_ids=live.ids, policy=spec)),
        ("RunEpisode", gateway_pb2.RunEpisodeRequest(session_ids=live.ids, policy=spec, max_steps=3)),
    ):
        err = await expect_error(gw.call(method, req), "INVALID_ARGUMENT")
        assert needle in err.details, method
    assert await episode_steps(gw, live.ids) == [0, 0]
