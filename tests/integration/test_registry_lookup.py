"""Registry.lookup reads a batch of sessions with one Lua command (found by the fuzz,
bench/bench_fuzz.py): 1,000 pipelined HMGETs held the gateway's event loop for about 130 ms on two
busy cores, so one well-formed request of unknown ids delayed every other call; one command whose
flat reply hiredis parses takes about 10 ms. The records must be what the pipeline gave."""

from __future__ import annotations

import uuid
from collections.abc import AsyncIterator

import pytest

from services.gateway.registry import Registry, SessionRecord
from services.ops.local_stack import find_redis_server
from tests.conftest import private_registry


@pytest.fixture
async def registry() -> AsyncIterator[Registry]:
    async with private_registry(find_redis_server()) as reg:
        yield reg


async def test_lookup_matches_the_stored_records(registry: Registry) -> None:
    r = registry.r
    full = uuid.uuid4().hex
    await r.hset(f"zt:session:{full}", mapping={
        "state": "RUNNING", "worker": "env-1", "family": "robosuite", "reason": "", "action_dtype": "float32",
        "action_shape": "7", "expires_ms": "123", "action_bounds": "-1.0,1.0", "owner": "alice", "schema": b"\x00\x01"})
    # A session still being created: no action fields yet.
    partial = uuid.uuid4().hex
    await r.hset(f"zt:session:{partial}", mapping={"state": "CREATE", "worker": "env-0", "family": "libero",
                                                   "owner": "bob"})
    unknown = [uuid.uuid4().hex for _ in range(3)]
    records = await registry.lookup([unknown[0], full, unknown[1], partial, unknown[2]])
    assert records[0] is None and records[2] is None and records[4] is None
    assert records[1] == SessionRecord(session_id=full, state="RUNNING", worker_id="env-1", family="robosuite",
                                       reason="", action_dtype="float32", action_shape=(7,), expires_ms=123,
                                       action_low=-1.0, action_high=1.0, owner="alice")
    assert records[3] == SessionRecord(session_id=partial, state="CREATE", worker_id="env-0", family="libero",
                                       reason="", action_dtype="", action_shape=(), expires_ms=0, action_low=None,
                                       action_high=None, owner="bob")
    assert await registry.lookup([]) == []


async def test_a_full_batch_is_one_round_trip(registry: Registry) -> None:
    """1,024 ids (the default per-call limit), all unknown: every one None, the order kept."""
    known = uuid.uuid4().hex
    await registry.r.hset(f"zt:session:{known}", mapping={"state": "RUNNING", "owner": "a"})
    sids = [uuid.uuid4().hex for _ in range(1023)]
    sids.insert(500, known)
    records = await registry.lookup(sids)
    assert [i for i, rec in enumerate(records) if rec is not None] == [500]
    assert records[500] is not None and records[500].session_id == known
