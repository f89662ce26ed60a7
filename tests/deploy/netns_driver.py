"""Client side of the multi-host test, run inside a network namespace:

    ip netns exec NS python -m tests.deploy.netns_driver PHASE '{"gateway": "10.231.x.1:50051", ...}'

Prints one JSON object with what it observed; tests/deploy/test_multihost.py makes the assertions.
Phases: ``start`` (sessions on both workers, one step each), ``after_cut`` (the cut worker's
sessions LOST, everything else undisturbed, new sessions on the other worker) and ``after_heal``
(the worker is back, its old sessions stay LOST, new sessions can land on it again).
Every wait is bounded.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from typing import Any

import numpy as np

from zetta import Gateway, ZettaError
from zetta_wire.v1 import types_pb2

LIFT: dict[str, Any] = {"env_name": "Lift", "max_steps": 500}
ZEROS = np.zeros(7, np.float32)


def _state(info: types_pb2.SessionInfo) -> str:
    """LOST, RUNNING, ... of a session."""
    return types_pb2.SessionState.Name(info.state).removeprefix("SESSION_STATE_")


async def _states(gw: Gateway) -> dict[str, types_pb2.SessionInfo]:
    return {s.session_id: s for s in await gw.list_sessions()}


async def _steps(gw: Gateway, group) -> dict[str, int]:  # type: ignore[no-untyped-def]
    return {r.session_id: r.episode_step for r in await group.action_step([ZEROS] * len(group))}


async def start(args: dict[str, Any]) -> dict[str, Any]:
    """Create ``n`` sessions, reset them, one action step and one policy step (policy across hosts)."""
    async with Gateway(args["gateway"]) as gw:
        group = await gw.create_sessions("robosuite", n=args["n"], env_config=LIFT, keepalive=False,
                                         lease_seconds=600)
        await group.reset(seed=list(range(args["n"])))
        await group.action_step([ZEROS] * len(group))
        stepped = await group.policy_step(execute_steps=1)
        return {
            "sessions": {i.session_id: i.worker_id for i in group.infos},
            "workers": {w.worker_id: {"address": w.address, "alive": w.alive}
                        for w in await gw.list_workers()},
            "episode_step": {r.session_id: r.episode_step for r in stepped},
        }


async def after_cut(args: dict[str, Any]) -> dict[str, Any]:
    """Wait for the cut worker's sessions to turn LOST, then look at everything else."""
    from zetta.client import SessionGroup

    out: dict[str, Any] = {}
    async with Gateway(args["gateway"]) as gw:
        lost_ids, live_ids = args["lost"], args["live"]
        t0 = time.monotonic()
        while True:
            now = await _states(gw)
            if all(now[s].state == types_pb2.SESSION_STATE_LOST for s in lost_ids):
                break
            if time.monotonic() - t0 > args["timeout"]:
                break
            await asyncio.sleep(0.05)
        out["lost_after_s"] = time.monotonic() - t0
        now = await _states(gw)
        out["states"] = {s: _state(now[s]) for s in lost_ids + live_ids}
        out["reasons"] = {s: now[s].reason for s in lost_ids}
        out["workers"] = {w.worker_id: {"alive": w.alive, "free": w.free_slots} for w in await gw.list_workers()}
        infos = [now[s] for s in live_ids]
        live = SessionGroup(gw, infos)
        out["live_steps"] = await _steps(gw, live)
        out["live_policy"] = {r.session_id: r.episode_step for r in await live.policy_step(execute_steps=1)}
        lost = SessionGroup(gw, [now[s] for s in lost_ids])
        try:
            await lost.action_step([ZEROS] * len(lost))
            out["lost_step_error"] = None
        except ZettaError as err:
            out["lost_step_error"] = {"code": err.code.name, "details": err.details, "ids": sorted(err.session_ids)}
        fresh = await gw.create_sessions("robosuite", n=args["fresh"], env_config=LIFT, keepalive=False,
                                         lease_seconds=600)
        await fresh.reset()
        out["fresh"] = {i.session_id: i.worker_id for i in fresh.infos}
        out["fresh_steps"] = await _steps(gw, fresh)
    return out


async def after_heal(args: dict[str, Any]) -> dict[str, Any]:
    """Wait for the healed worker to be alive again; its old sessions stay LOST; it takes new ones."""
    out: dict[str, Any] = {}
    async with Gateway(args["gateway"]) as gw:
        t0 = time.monotonic()
        while time.monotonic() - t0 < args["timeout"]:
            workers = {w.worker_id: w for w in await gw.list_workers()}
            if workers[args["worker"]].alive and workers[args["worker"]].free_slots == args["slots"]:
                break
            await asyncio.sleep(0.1)
        out["back_after_s"] = time.monotonic() - t0
        workers = {w.worker_id: w for w in await gw.list_workers()}
        out["workers"] = {w.worker_id: {"alive": w.alive, "free": w.free_slots} for w in workers.values()}
        now = await _states(gw)
        out["old_states"] = {s: _state(now[s]) for s in args["lost"]}
        if workers[args["worker"]].alive:
            group = await gw.create_sessions("robosuite", n=args["n"], env_config=LIFT, keepalive=False,
                                             lease_seconds=600)
            await group.reset()
            out["new"] = {i.session_id: i.worker_id for i in group.infos}
            out["new_steps"] = await _steps(gw, group)
    return out


PHASES = {"start": start, "after_cut": after_cut, "after_heal": after_heal}


def main() -> None:
    phase, raw = sys.argv[1], sys.argv[2]
    result = asyncio.run(PHASES[phase](json.loads(raw)))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
