"""Time budgets for package code: a critic that overruns or raises is switched off, not fatal.

Critics are code an evolver or an LLM wrote, run on the env worker's slot thread (library
critics at every env step, code critics at the cadence of :class:`PlatformLimits`). A critic whose
calls use more CPU time than its soft budget is switched off for the rest of the episode (CPU time
of the calling thread, not wall time: on a loaded machine a call preempted by the scheduler or
waiting for the GIL is not the critic's fault; see :class:`CallBudget`). A call that is still
running at the hard limit (an endless loop) is interrupted: a process-wide watchdog thread raises
:class:`CriticTimeout` inside the slot thread (``PyThreadState_SetAsyncExc``), so the episode goes
on. A call costs three wall-clock reads, a dict store and an uncontended lock; the watchdog wakes
every 10 ms. Code blocked inside a C call (a huge numpy operation) is interrupted when that call
returns.
"""

from __future__ import annotations

import ctypes
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


class CriticTimeout(Exception):
    """Raised inside a guarded call that ran past its hard limit."""


class _Watch:
    """One guarded call in flight: its thread, hard deadline and whether it was interrupted."""

    __slots__ = ("thread_id", "deadline", "fired", "done")

    def __init__(self, thread_id: int, deadline: float) -> None:
        self.thread_id = thread_id
        self.deadline = deadline
        self.fired = False
        self.done = False


class Watchdog:
    """Interrupts guarded calls that pass their hard deadline (one per process).

    Each thread publishes its call in flight in a dict (one atomic store per call); the watchdog
    thread, started with the first guarded call, looks at them every ``poll_s``.
    """

    def __init__(self, poll_s: float = 0.01) -> None:
        self._poll = poll_s
        self._lock = threading.Lock()
        self._watching: dict[int, _Watch] = {}
        self._thread: threading.Thread | None = None

    def watch(self, hard_limit_s: float) -> _Watch:
        """Publish a call starting now on this thread."""
        if self._thread is None:
            with self._lock:
                if self._thread is None:
                    self._thread = threading.Thread(target=self._run, name="critic-watchdog", daemon=True)
                    self._thread.start()
        w = _Watch(threading.get_ident(), time.perf_counter() + hard_limit_s)
        self._watching[w.thread_id] = w
        return w

    def release(self, w: _Watch) -> None:
        """The call returned: never interrupt it, and cancel an interruption not yet delivered."""
        w.done = True
        # Before its deadline the watchdog cannot have fired: it fires only after reading a clock
        # past the deadline, and then finds ``done`` set (it was set before this clock read), so
        # no lock is needed on that path (one per critic per env step).
        if not w.fired and time.perf_counter() < w.deadline:
            return
        with self._lock:
            w.done = True
            if w.fired:
                ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(w.thread_id), None)

    def _run(self) -> None:
        while True:
            time.sleep(self._poll)
            now = time.perf_counter()
            for w in list(self._watching.values()):
                if w.done or w.fired or now < w.deadline:
                    continue
                with self._lock:
                    if not w.done:
                        w.fired = True
                        ctypes.pythonapi.PyThreadState_SetAsyncExc(
                            ctypes.c_ulong(w.thread_id), ctypes.py_object(CriticTimeout)
                        )


WATCHDOG = Watchdog()


@dataclass
class CallBudget:
    """The limits of one critic for one episode: a soft CPU budget and a hard wall-clock limit.

    Reading a thread's CPU clock is a system call (about 1 to 10 us here, against 1 us for the wall
    clock), so calls are timed with the wall clock until one exceeds the budget; the critic is then
    ``suspect`` and its next call is timed in CPU time: over the budget, it is switched off; within
    it, back to the wall clock. A critic that is slow on every call is switched off on its second
    slow call; a call that was only preempted by the scheduler costs one closer timing.
    """

    budget_s: float
    hard_limit_s: float
    suspect: bool = False


def guarded_call(fn: Callable[..., Any], args: tuple[Any, ...], budget: CallBudget) -> tuple[Any, str]:
    """Run ``fn(*args)`` under ``budget``: (result, "") or (None, why it must be switched off)."""
    clock = time.thread_time if budget.suspect else time.perf_counter
    start = clock()
    watch = WATCHDOG.watch(budget.hard_limit_s)
    try:
        try:
            result = fn(*args)
        finally:
            WATCHDOG.release(watch)
    except CriticTimeout:
        return None, f"interrupted after {budget.hard_limit_s * 1000:.0f} ms (hard limit)"
    except Exception as exc:  # noqa: BLE001 - package code may raise anything; it is switched off
        return None, f"raised {type(exc).__name__}: {exc}"
    if watch.fired:
        return None, f"interrupted after {budget.hard_limit_s * 1000:.0f} ms (hard limit)"
    elapsed = clock() - start
    if elapsed > budget.budget_s:
        if budget.suspect:
            return None, f"used {elapsed * 1000:.1f} ms of CPU, over its {budget.budget_s * 1000:.1f} ms budget"
        budget.suspect = True
    else:
        budget.suspect = False
    return result, ""


#: Default steps between evaluations of a package's code critics: 4 is 5 Hz at LIBERO's 20 Hz
#: control, once per chunk of the shipped VLA (it executes 4 actions per call), as in the paper's
#: critic loop (one proposal per executed chunk, over a window holding each of its steps).
CODE_CRITIC_EVERY = 4


@dataclass(frozen=True)
class PlatformLimits:
    """What a package's critics may cost, set by the platform, not by the package: a package may
    ask for less time (``critic_budget_ms``, ``critic_hard_limit_ms`` in SKILL.md), never more.

    ``code_critic_every``: a package's code critics (tools/*.py, which run in the sandbox child)
    are evaluated on the reset frame, on every step whose number is a multiple of it and on every
    step of an intervention; the frames between are kept in their window all the same. A round
    trip to the child costs more CPU than ten critics' own work (docs/harness.md, "When critics
    run"); 1 evaluates them at every step. ``code_critic_pipelined``: an evaluation under the
    policy runs while the env takes its next step, and its proposals reach the orchestrator with
    that step (one step late; the host does not wait for the child); during an intervention and
    on the reset frame they are awaited."""

    budget_s: float
    hard_limit_s: float
    code_critic_every: int = CODE_CRITIC_EVERY
    code_critic_pipelined: bool = True

    @classmethod
    def from_env(cls, environ: Any = None) -> "PlatformLimits":
        """ZETTA_CRITIC_MAX_BUDGET_MS (50), ZETTA_CRITIC_MAX_HARD_LIMIT_MS (1000),
        ZETTA_CODE_CRITIC_EVERY (4 steps, 1-64) and ZETTA_CODE_CRITIC_PIPELINE (on); ConfigError
        when bad."""
        from services.common.config import EnvReader

        env = EnvReader(environ)
        budget = env.float("ZETTA_CRITIC_MAX_BUDGET_MS", 50.0, minimum=0.01)
        hard = env.float("ZETTA_CRITIC_MAX_HARD_LIMIT_MS", 1000.0, minimum=1.0)
        every = env.int("ZETTA_CODE_CRITIC_EVERY", CODE_CRITIC_EVERY, minimum=1, maximum=64)
        pipelined = env.bool("ZETTA_CODE_CRITIC_PIPELINE", True)
        if hard < budget:
            env.fail(f"ZETTA_CRITIC_MAX_HARD_LIMIT_MS={hard} must be >= ZETTA_CRITIC_MAX_BUDGET_MS={budget}")
        env.finish("harness runtime")
        return cls(budget / 1000.0, hard / 1000.0, every, pipelined)
