"""Fuzz under load: good sessions run episodes while a fuzzer sends malformed requests.

  python -m bench.bench_fuzz [--seconds 40] [--window 5] [--rate 20] [--sessions 4] [--json OUT]

Starts a private stack with auth on (Redis, gateway, critic service, a policy worker serving the
scripted policy, two env workers x 6 slots of robosuite Lift), then runs ``--sessions`` good
sessions (identity ``alice``) in a closed PolicyStep loop, resetting each episode as it ends. The
run is cut into windows of ``--window`` seconds that alternate quiet and fuzzed: in the fuzzed
ones a separate process (identity ``mallory``, its own session, and one of alice's ids) sends
every kind of bench/fuzz_kinds.py in turn, ``--rate`` requests per second over a few concurrent
callers. Quiet and fuzzed windows interleave, so the background load of the machine falls on
both alike, and the p99 of the good sessions' PolicyStep latency is compared side by side.

It prints, and returns (``--json``), the statuses per kind, every request that got a wrong
status, the good sessions' episodes, errors and final state, and the p99 ratio fuzzed / quiet.
The slow suite's tests/fault/test_fuzz.py holds it to: every bad request its expected status with
a message, zero good sessions lost or failed, p99 ratio <= 2.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]

#: Identities of the fuzz stack's tokens file: the good client, the fuzzer, the stack's own admin
#: calls, the env workers.
TOKENS = {"alice": ("user", "alice-fuzz-token-1"), "mallory": ("user", "mallory-fuzz-token-2"),
          "ops": ("admin", "ops-fuzz-token-3"), "pool": ("worker", "pool-fuzz-token-4")}


def write_tokens(directory: Path) -> Path:
    """The gateway's tokens file for TOKENS (digests only)."""
    from services.gateway.auth import digest

    path = directory / "tokens"
    path.write_text("".join(f"{name} {role} {digest(tok)}\n" for name, (role, tok) in TOKENS.items()))
    return path


def stack_settings(workdir: Path) -> dict[str, Any]:
    """LocalStack arguments of the fuzz stack: auth on, robosuite only, the scripted policy."""
    from bench.fuzz_kinds import MODEL

    return {
        "env_workers": 2, "slots": 6, "policy_workers": 1, "families": ("robosuite",), "models": (MODEL,),
        "workdir": workdir, "client_token": TOKENS["ops"][1],
        "extra_env": {"ZETTA_AUTH_TOKENS_FILE": str(write_tokens(workdir)), "ZETTA_WORKER_TOKEN": TOKENS["pool"][1],
                      "ZETTA_LOG_LEVEL": "WARNING"},
    }


# ---- the fuzzer (its own process) ----------------------------------------------------------------


@dataclass
class FuzzReport:
    """What the fuzzer sent and got."""

    sent: int = 0
    by_kind: dict[str, dict[str, int]] = field(default_factory=dict)
    #: Requests that got another status than their kind's, or no message (at most 50 kept).
    wrong: list[dict[str, Any]] = field(default_factory=list)
    wrong_count: int = 0
    slowest_s: float = 0.0

    def add(self, outcome: Any) -> None:
        """Count one outcome."""
        self.sent += 1
        self.by_kind.setdefault(outcome.kind, {}).setdefault(outcome.code, 0)
        self.by_kind[outcome.kind][outcome.code] += 1
        self.slowest_s = max(self.slowest_s, outcome.seconds)
        if not outcome.ok:
            self.wrong_count += 1
            if len(self.wrong) < 50:
                self.wrong.append({"kind": outcome.kind, "expected": outcome.expected, "code": outcome.code,
                                   "details": outcome.details[:300]})


async def fuzz(address: str, victim: str, start: float, window: float, windows: int, rate: float,
               callers: int = 4, kinds: Sequence[str] = ()) -> FuzzReport:
    """Send malformed requests during the odd windows of the schedule (window k covers
    ``start + k * window`` to ``start + (k + 1) * window`` on the wall clock), ``rate`` per second
    over ``callers`` concurrent callers, every kind in turn."""
    from bench.fuzz_kinds import KINDS, LIFT_CONFIG, Ctx, send
    from zetta import Gateway

    chosen = [k for k in KINDS if not kinds or k.name in kinds]
    async with Gateway(address, token=TOKENS["mallory"][1]) as gw:
        own = await gw.create_sessions("robosuite", n=2, env_config=LIFT_CONFIG)
        await own.reset(seed=[98, 99])
        ctx = Ctx(address, TOKENS["mallory"][1], TOKENS["pool"][1], own.ids[0], victim, scratch=own.ids[1])
        prepared = [(k, k.build(ctx)) for k in chosen]
        report = FuzzReport()
        end = start + window * windows
        turn = 0

        async def caller(offset: int) -> None:
            nonlocal turn
            interval = callers / rate
            while True:
                now = time.time()
                if now >= end:
                    return
                k = int((now - start) // window)
                if k < 0 or k % 2 == 0:  # quiet: sleep to the next fuzzed window
                    await asyncio.sleep(max(0.01, start + (max(k, 0) + 1) * window - now + offset * 0.01))
                    continue
                kind, fn = prepared[turn % len(prepared)]
                turn += 1
                t0 = time.perf_counter()
                report.add(await send(ctx, kind, fn))
                await asyncio.sleep(max(0.0, interval - (time.perf_counter() - t0)))

        try:
            await asyncio.gather(*(caller(i) for i in range(callers)))
        finally:
            await ctx.close()
            await own.close()
    return report


def fuzz_main(argv: Sequence[str]) -> int:
    """``python -m bench.bench_fuzz --fuzzer ADDRESS VICTIM START WINDOW WINDOWS RATE``: print the report as JSON."""
    address, victim, start, window, windows, rate = argv
    report = asyncio.run(fuzz(address, victim, float(start), float(window), int(windows), float(rate)))
    print(json.dumps(asdict(report)))
    return 0


# ---- the good sessions ---------------------------------------------------------------------------


@dataclass
class GoodReport:
    """What the good sessions did."""

    steps: int = 0
    episodes: int = 0
    errors: list[str] = field(default_factory=list)
    #: (wall-clock start, seconds) of every PolicyStep.
    samples: list[tuple[float, float]] = field(default_factory=list)
    lost: list[str] = field(default_factory=list)


async def run_good(gw: Any, n: int, end: float) -> GoodReport:
    """``n`` sessions, each in its own PolicyStep loop until ``end`` (wall clock); resets as episodes end."""
    from bench.fuzz_kinds import LIFT_CONFIG, MODEL
    from zetta import ZettaError
    from zetta_wire.v1 import types_pb2

    report = GoodReport()
    group = await gw.create_sessions("robosuite", n=n, env_config=LIFT_CONFIG)
    try:
        async def loop(i: int) -> None:
            session = group[i]
            seed = 1000 * i
            await session.reset(seed=seed)
            while time.time() < end:
                t_wall, t0 = time.time(), time.perf_counter()
                try:
                    result = await session.policy_step(model=MODEL, execute_steps=1)
                except ZettaError as exc:
                    report.errors.append(f"{session.session_id}: {exc}")
                    return
                report.samples.append((t_wall, time.perf_counter() - t0))
                report.steps += 1
                if result.done:
                    report.episodes += 1
                    seed += 1
                    await session.reset(seed=seed)

        await asyncio.gather(*(loop(i) for i in range(n)))
        states = {s.session_id: s for s in await gw.list_sessions()}
        report.lost = [sid for sid in group.ids
                       if sid not in states or states[sid].state != types_pb2.SESSION_STATE_RUNNING]
    finally:
        await group.close()
    return report


def p99(values: Sequence[float]) -> float:
    """The 99th percentile (0 when empty)."""
    return float(np.percentile(values, 99)) if values else 0.0


def split_windows(samples: Sequence[tuple[float, float]], start: float, window: float, windows: int
                  ) -> tuple[list[float], list[float]]:
    """Latencies of the quiet (even) and fuzzed (odd) windows, by each call's start."""
    quiet: list[float] = []
    fuzzed: list[float] = []
    for t, s in samples:
        k = int((t - start) // window)
        if 0 <= k < windows:
            (fuzzed if k % 2 else quiet).append(s)
    return quiet, fuzzed


async def run(address: str, seconds: float, window: float, rate: float, sessions: int, warmup: float = 3.0
              ) -> dict[str, Any]:
    """The whole measurement against a running fuzz stack; returns the result as a dict."""
    from zetta import Gateway

    windows = max(2, int(round(seconds / window)))
    windows += windows % 2  # as many fuzzed windows as quiet ones
    async with Gateway(address, token=TOKENS["alice"][1]) as gw:
        # The victim: a session of alice's that the fuzzer tries to use and close.
        victim = await gw.create_sessions("robosuite", n=1, env_config={"env_name": "Lift"})
        start = time.time() + warmup + 4.0  # the fuzzer's start-up (imports, its session) fits in
        fuzzer = subprocess.Popen(
            [sys.executable, "-m", "bench.bench_fuzz", "--fuzzer", address, victim.ids[0], repr(start),
             repr(window), str(windows), repr(rate)],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
            env={**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")])},
        )
        try:
            good = await run_good(gw, sessions, start + window * windows)
            out, err = await asyncio.get_running_loop().run_in_executor(None, fuzzer.communicate, None)
        finally:
            if fuzzer.poll() is None:
                fuzzer.kill()
                fuzzer.wait()
        from zetta_wire.v1 import types_pb2

        states = {s.session_id: s.state for s in await gw.list_sessions()}
        victim_alive = states.get(victim.ids[0]) == types_pb2.SESSION_STATE_RUNNING
        await victim.close()
    if fuzzer.returncode != 0:
        raise RuntimeError(f"the fuzzer failed ({fuzzer.returncode}):\n{err[-3000:]}")
    fuzz_report = json.loads(out.strip().splitlines()[-1])
    quiet, fuzzed = split_windows(good.samples, start, window, windows)
    q99, f99 = p99(quiet), p99(fuzzed)
    return {
        "seconds": window * windows, "window_s": window, "rate_per_s": rate, "good_sessions": sessions,
        "fuzz": fuzz_report,
        "kinds": len(fuzz_report["by_kind"]),
        "good": {"steps": good.steps, "episodes": good.episodes, "errors": good.errors[:20], "lost": good.lost,
                 "victim_alive": victim_alive},
        "latency_ms": {"quiet_calls": len(quiet), "fuzzed_calls": len(fuzzed),
                       "quiet_p50": 1e3 * float(np.median(quiet)) if quiet else 0.0,
                       "fuzzed_p50": 1e3 * float(np.median(fuzzed)) if fuzzed else 0.0,
                       "quiet_p99": 1e3 * q99, "fuzzed_p99": 1e3 * f99},
        "p99_ratio": f99 / q99 if q99 else float("inf"),
    }


def summary(result: dict[str, Any]) -> str:
    """The result as text."""
    fz, good, lat = result["fuzz"], result["good"], result["latency_ms"]
    lines = [
        f"fuzz: {fz['sent']} malformed requests of {result['kinds']} kinds over {result['seconds'] / 2:.0f} s "
        f"of fuzzed windows ({fz['sent'] / max(result['seconds'] / 2, 1e-9):.1f}/s of {result['rate_per_s']:g}/s "
        f"asked), {fz['wrong_count']} with a wrong status; "
        f"slowest answer {fz['slowest_s'] * 1e3:.0f} ms",
    ]
    for w in fz["wrong"][:10]:
        lines.append(f"  WRONG {w['kind']}: expected {w['expected']}, got {w['code']}: {w['details']}")
    codes: Counter[str] = Counter()
    for per in fz["by_kind"].values():
        codes.update(per)
    lines.append("  statuses: " + ", ".join(f"{c} {n}" for c, n in codes.most_common()))
    lines += [
        f"good sessions: {result['good_sessions']}, {good['steps']} PolicySteps, {good['episodes']} episodes, "
        f"{len(good['errors'])} errors, {len(good['lost'])} lost, victim alive: {good['victim_alive']}",
        f"PolicyStep latency quiet  p50 {lat['quiet_p50']:.1f} ms  p99 {lat['quiet_p99']:.1f} ms  "
        f"({lat['quiet_calls']} calls)",
        f"PolicyStep latency fuzzed p50 {lat['fuzzed_p50']:.1f} ms  p99 {lat['fuzzed_p99']:.1f} ms  "
        f"({lat['fuzzed_calls']} calls)",
        f"p99 ratio fuzzed/quiet: {result['p99_ratio']:.2f} (must be <= 2)",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point: start the fuzz stack, measure, print, stop."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "--fuzzer":
        return fuzz_main(argv[1:])
    parser = argparse.ArgumentParser(prog="bench_fuzz", description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=40, help="quiet + fuzzed time (default 40)")
    parser.add_argument("--window", type=float, default=5, help="length of each quiet or fuzzed window (default 5 s)")
    parser.add_argument("--rate", type=float, default=20, help="malformed requests per second while fuzzing")
    parser.add_argument("--sessions", type=int, default=4, help="good sessions (default 4)")
    parser.add_argument("--json", help="write the result here")
    args = parser.parse_args(argv)
    from services.ops.local_stack import LocalStack

    with tempfile.TemporaryDirectory(prefix="zetta-fuzz-") as tmp, LocalStack(**stack_settings(Path(tmp))) as stack:
        result = asyncio.run(run(stack.gateway_address, args.seconds, args.window, args.rate, args.sessions))
    print(summary(result))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    ok = (result["fuzz"]["wrong_count"] == 0 and not result["good"]["errors"] and not result["good"]["lost"]
          and result["p99_ratio"] <= 2.0)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
