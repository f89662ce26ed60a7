"""Malformed and oversized requests get a clear status and cost no healthy session anything.

The repros of issue #21 ("one request makes every session LOST"): huge batches of session ids,
duplicates, unknown ids whose list would overflow the error metadata, ids that are not ASCII, and
messages over the gateway's size limit. After each, the sessions of the shared stack are still
RUNNING on live workers and still step.
"""

from __future__ import annotations

import uuid

import numpy as np
import pytest

from tests.fault.test_faults import ZEROS, expect_error, states
from tests.conftest import LIFT
from zetta import Gateway, SessionGroup
from zetta_wire.v1 import gateway_pb2, types_pb2

#: The gateway's default ZETTA_MAX_SESSIONS_PER_CALL.
LIMIT = 1024


@pytest.fixture
async def live(gw: Gateway) -> SessionGroup:
    """Two reset sessions, one on each worker, that every test checks survive its bad requests."""
    group = await gw.create_sessions("robosuite", n=2, env_config=LIFT)
    await group.reset(seed=[5, 6])
    return group


async def assert_unharmed(gw: Gateway, group: SessionGroup) -> None:
    """Both workers alive, the sessions RUNNING, and they still step."""
    assert all(w.alive for w in await gw.list_workers())
    now = await states(gw)
    assert [now[s].state for s in group.ids] == [types_pb2.SESSION_STATE_RUNNING] * 2
    await group.action_step([ZEROS, ZEROS])


def unknown_ids(n: int) -> list[str]:
    """Well-formed ids that no session has."""
    return [uuid.uuid4().hex for _ in range(n)]


async def test_15001_ids_with_a_duplicate(gw: Gateway, live: SessionGroup) -> None:
    """The issue's repro (about 510 KB): refused at once for its size, no worker declared dead."""
    sids = [*unknown_ids(15_000), live.ids[0]]
    sids[7] = sids[8]
    err = await expect_error(gw.call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=sids)),
                             "INVALID_ARGUMENT")
    assert "15001 session ids" in err.details and f"at most {LIMIT}" in err.details
    assert "ZETTA_MAX_SESSIONS_PER_CALL" in err.details
    await assert_unharmed(gw, live)


async def test_200000_unknown_ids(gw: Gateway, live: SessionGroup) -> None:
    """200,000 ids (6.8 MB) are refused by count, not looked up one by one."""
    err = await expect_error(gw.call("Observe", gateway_pb2.ObserveRequest(session_ids=unknown_ids(200_000))),
                             "INVALID_ARGUMENT")
    assert "200000 session ids" in err.details
    await assert_unharmed(gw, live)


async def test_duplicates_within_the_limit_are_named_boundedly(gw: Gateway, live: SessionGroup) -> None:
    """A batch at the limit with many duplicates: INVALID_ARGUMENT, a bounded list of them."""
    base = unknown_ids(LIMIT // 2)
    err = await expect_error(gw.call("Observe", gateway_pb2.ObserveRequest(session_ids=base + base)),
                             "INVALID_ARGUMENT")
    assert "more than once" in err.details and f"and {LIMIT // 2 - 8} more" in err.details
    assert len(err.session_ids) + err.more_failed_sessions == LIMIT // 2
    await assert_unharmed(gw, live)


async def test_many_unknown_ids_fit_the_metadata(gw: Gateway, live: SessionGroup) -> None:
    """1,000 unknown ids (33 KB of ids, beyond the 8 KiB metadata limit) give the gateway's NOT_FOUND,
    not RESOURCE_EXHAUSTED "received metadata size exceeds hard limit"."""
    sids = unknown_ids(1000)
    err = await expect_error(gw.call("PolicyStep", gateway_pb2.PolicyStepRequest(session_ids=sids)), "NOT_FOUND")
    assert "unknown session(s)" in err.details and "and 992 more" in err.details
    assert 0 < len(err.session_ids) <= 100
    assert set(err.session_ids) <= set(sids)
    assert len(err.session_ids) + err.more_failed_sessions == 1000
    await assert_unharmed(gw, live)


@pytest.mark.parametrize(
    "bad",
    ["\u00e9" * 3000, "x" * 65, "a,b", "with space", "", "\x00"],
    ids=["3000-non-ascii", "too-long", "comma", "space", "empty", "nul"],
)
async def test_malformed_session_id(gw: Gateway, live: SessionGroup, bad: str) -> None:
    """An id that is not 1-64 characters of [A-Za-z0-9_.-] is INVALID_ARGUMENT naming its index
    (a 3,000-character non-ASCII id used to give INTERNAL "Invalid metadata")."""
    sids = [live.ids[0], bad]
    err = await expect_error(
        gw.call("ActionStep", gateway_pb2.ActionStepRequest(session_ids=sids, actions=[live_action()] * 2)),
        "INVALID_ARGUMENT",
    )
    assert "session_ids[1]" in err.details and "is not a session id" in err.details
    assert len(err.details) < 400
    await assert_unharmed(gw, live)


def live_action() -> types_pb2.Tensor:
    """A well-formed zero action."""
    from zetta_wire.codec import encode

    return encode(np.zeros(7, np.float32))


async def test_close_and_stream_are_bounded_too(gw: Gateway, live: SessionGroup) -> None:
    """CloseSessions and StepStream check their ids the same way."""
    err = await expect_error(
        gw.call("CloseSessions", gateway_pb2.CloseSessionsRequest(session_ids=unknown_ids(LIMIT + 1))),
        "INVALID_ARGUMENT")
    assert f"at most {LIMIT}" in err.details
    stream = gw._stub.StepStream()
    await stream.write(gateway_pb2.StepStreamRequest(session_id="\u00e9" * 100,
                                                     observe=gateway_pb2.ObserveOp()))
    with pytest.raises(Exception) as raised:
        await stream.read()
    assert raised.value.code().name == "INVALID_ARGUMENT"  # type: ignore[attr-defined]
    await assert_unharmed(gw, live)


async def test_oversized_message_is_refused_by_grpc(gw: Gateway, live: SessionGroup) -> None:
    """A request over ZETTA_MAX_REQUEST_BYTES (16 MiB) never reaches a handler."""
    big = types_pb2.Tensor(dtype=types_pb2.DTYPE_FLOAT32, shape=[7], data=b"\x00" * (17 * 1024 * 1024))
    req = gateway_pb2.ActionStepRequest(session_ids=live.ids[:1], actions=[big])
    await expect_error(gw.call("ActionStep", req), "RESOURCE_EXHAUSTED")
    await assert_unharmed(gw, live)
