"""The critic-governed action loop of an env worker: a harness over a slot's episodes.

A reset whose ResetSpec names a harness (``harness``: a registry reference fetched from the
critic service; ``harness_dir``: a package directory on this worker) binds a
:class:`SlotHarness` to the slot. From then on every executed action goes through it: the critics
run on every env step (inside the chunk, at action frequency), and while a recovery has control
its actions replace the policy's until the re-entry contract hands control back. When control
comes back in the middle of a chunk the rest of that chunk is dropped (it was planned before the
recovery moved the robot) and the policy is asked again. A slot without a harness never enters
this module: its step path is unchanged.
"""

from __future__ import annotations

import re
import threading
import time
from collections import OrderedDict
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from services.common import grpc_errors as ge
from services.common.tls import sync_channel
from services.env_worker import metrics
from services.harness.package import format as fmt
from services.harness.package.errors import PackageRejected
from services.harness.package.loader import load_files, unload
from services.harness.package.model import LoadedPackage
from services.harness.runtime.engine import Decision, EpisodeReport, HarnessError, HarnessRuntime
from services.harness.runtime.orchestrator import POLICY
from services.harness.sandbox import client as sandbox
from services.harness.report_proto import report_to_proto
from zetta_wire.v1 import types_pb2

#: A registry reference that names one immutable version (cacheable for the worker's life).
_EXACT_REF = re.compile(r"^[^@]+@\d+$")
#: Chunk length run by a recovery when the policy is not asked (no execute_steps given).
RECOVERY_CHUNK = 8


class HarnessSource:
    """Loads harness packages for resets: from directories, or from the critic service's registry.

    Loaded packages are cached by content hash and manifest (a directory is re-read at each reset,
    so an edit takes effect on the next episode; an exact registry version is fetched once).
    """

    def __init__(self, critic_address: str = "", timeout_s: float = 10.0, max_cached: int = 32,
                 sandboxed: bool | None = None) -> None:
        self.critic_address = critic_address
        #: Package code runs in sandbox children (ZETTA_HARNESS_SANDBOX, default on): its tools are
        #: checked here but never imported into this process.
        self.sandboxed = sandbox.enabled() if sandboxed is None else sandboxed
        self.timeout_s = timeout_s
        #: Loaded versions kept, least recently used first out (an evolver tries many versions).
        self.max_cached = max_cached
        self._by_hash: OrderedDict[tuple[str, bytes], LoadedPackage] = OrderedDict()
        self._by_ref: dict[str, LoadedPackage] = {}
        self._lock = threading.Lock()
        self._stub: Any = None

    def load(self, spec: types_pb2.ResetSpec, session_id: str) -> LoadedPackage | None:
        """The package the reset asks for, None when it asks for none."""
        if spec.harness and spec.harness_dir:
            raise ge.invalid(f"reset of session {session_id}: set harness or harness_dir, not both", [session_id])
        try:
            if spec.harness_dir:
                return self._from_dir(spec.harness_dir, session_id)
            if spec.harness:
                return self._from_registry(spec.harness, session_id)
        except PackageRejected as exc:
            raise ge.invalid(f"reset of session {session_id}: {exc}", [session_id]) from None
        return None

    def _cached(self, files: Mapping[str, bytes]) -> LoadedPackage:
        # The same content published (with a manifest: a version) and in a directory (none) are
        # two packages to the report, so the manifest is part of the key.
        key = (fmt.content_hash(files), files.get(fmt.MANIFEST, b""))
        with self._lock:
            package = self._by_hash.get(key)
            if package is not None:
                self._by_hash.move_to_end(key)
                return package
        package = load_files(files, import_tools=not self.sandboxed)
        with self._lock:
            self._by_hash[key] = package
            while len(self._by_hash) > self.max_cached:
                _, old = self._by_hash.popitem(last=False)
                self._by_ref = {r: p for r, p in self._by_ref.items() if p is not old}
                unload(old)  # runtimes already built from it keep its modules alive
        return package

    def _from_dir(self, path: str, session_id: str) -> LoadedPackage:
        root = Path(path)
        if not root.is_dir():
            raise ge.invalid(f"reset of session {session_id}: harness_dir {path!r} is not a directory on this worker",
                             [session_id])
        return self._cached(fmt.read_tree(root))

    def _from_registry(self, ref: str, session_id: str) -> LoadedPackage:
        if not self.critic_address:
            raise ge.failed_precondition(
                f"reset of session {session_id} names harness {ref!r} but this env worker has no ZETTA_CRITIC_ADDR",
                [session_id],
            )
        with self._lock:
            hit = self._by_ref.get(ref)
        if hit is not None:
            return hit
        from zetta_wire.v1 import critic_pb2, critic_pb2_grpc

        if self._stub is None:
            self._stub = critic_pb2_grpc.HarnessRegistryServiceStub(sync_channel(self.critic_address))
        try:
            resp = self._stub.Get(critic_pb2.GetRequest(ref=ref), timeout=self.timeout_s)
        except grpc.RpcError as exc:
            code = exc.code() if hasattr(exc, "code") else grpc.StatusCode.UNAVAILABLE
            raise ge.ServiceError(code, f"harness {ref!r} from the critic service: {exc.details()}",
                                  [session_id]) from None
        package = self._cached(dict(resp.files))
        if _EXACT_REF.match(ref):
            with self._lock:
                self._by_ref[ref] = package
        return package


def milestone_set(obs: Mapping[str, np.ndarray], names: Sequence[str]) -> frozenset[str]:
    """Names of the milestones reached so far, from the ``milestones_reached`` tensor."""
    reached = obs.get("milestones_reached")
    if reached is None or not names:
        return frozenset()
    return frozenset(n for n, v in zip(names, reached) if v > 0.5)


class SlotHarness:
    """A harness runtime bound to one slot, with the bookkeeping of the episode in progress."""

    def __init__(self, package: LoadedPackage) -> None:
        try:
            self.runtime = HarnessRuntime(package)
        except HarnessError as exc:
            raise ge.invalid(f"harness {package.name}: {exc}") from None
        self.package = package
        self.names: tuple[str, ...] = ()
        self.decision = Decision(POLICY, (), None, "")
        self.finished: EpisodeReport | None = None

    def close(self) -> None:
        """Kill the runtime's sandbox child, if it has one."""
        self.runtime.close()

    def reset(self, obs: Mapping[str, np.ndarray], instruction: str, milestone_names: Sequence[str]) -> None:
        """A new episode: fresh runtime state, critics run on the reset observation."""
        self.names = tuple(milestone_names)
        self.finished = None
        self.runtime.start(instruction, self.names)
        self.decision = self.runtime.step(obs, None, milestone_set(obs, self.names))

    @property
    def in_recovery(self) -> bool:
        """A recovery has control: the next actions are its own, the policy need not be asked."""
        return self.decision.action is not None

    @property
    def policy_instructions(self) -> tuple[str, ...]:
        """The instructions the model serving this slot was trained on (Window.policy_instructions)."""
        return self.runtime.policy_instructions

    @policy_instructions.setter
    def policy_instructions(self, instructions: Sequence[str]) -> None:
        self.runtime.policy_instructions = tuple(instructions)

    @property
    def redirect(self) -> str:
        """The instruction the policy is asked under while a recovery redirects it ("" otherwise)."""
        return self.decision.instruction

    def run_chunk(self, env: Any, chunk: np.ndarray, max_steps: int, step_hist: Any,
                  on_step: Callable[[Mapping[str, np.ndarray]], None] | None = None
                  ) -> tuple[Any, np.ndarray, float, int]:
        """Execute up to ``len(chunk)`` actions, each the recovery's when one has control (``on_step``
        sees each step's observation).

        Returns the last outcome, the actions actually executed ([n, dim]), the summed reward and
        how many of them a recovery chose. Stops early at the end of the episode, when a recovery
        hands control back and when the instruction the policy acts under changes (instruction
        redirection begins or ends): the rest of the policy's chunk is stale.
        """
        self.runtime.action_shape = tuple(chunk.shape[1:])
        executed: list[np.ndarray] = []
        reward, by_recovery = 0.0, 0
        outcome = None
        last = len(chunk) - 1
        asked_under = self.decision.instruction
        for i, planned in enumerate(chunk):
            recovering = self.decision.action is not None
            action = self.decision.action.astype(chunk.dtype) if recovering else planned
            by_recovery += recovering
            start = time.perf_counter()
            outcome = env.step(action, render=i == last)
            step_hist.observe(time.perf_counter() - start)
            reward += outcome.reward
            executed.append(action)
            if on_step is not None:
                on_step(outcome.observation)
            self.decision = self.runtime.step(outcome.observation, action, milestone_set(outcome.observation, self.names))
            if outcome.terminated or outcome.truncated or env.episode_step >= max_steps:
                break
            if recovering and self.decision.action is None:
                break
            if not recovering and self.decision.action is None and self.decision.instruction != asked_under:
                break
        assert outcome is not None
        return outcome, np.stack(executed), reward, by_recovery

    def end_episode(self, success: bool) -> None:
        """The episode ended: its report is final from now on, and counted once."""
        self.finished = report = self.runtime.finish(success)
        metrics.count_harness_episode(report.policy_actions, report.recovery_actions,
                                      [(iv.kind, iv.outcome) for iv in report.interventions],
                                      len(report.disabled_critics))

    def annotate(self, result: types_pb2.StepResult, recovery_actions: int) -> None:
        """Fill a StepResult's harness fields; the episode's report on the result that ended it."""
        result.harness_mode = self.decision.mode
        result.harness_intervention = self.decision.intervention_id
        result.recovery_actions = recovery_actions
        if self.finished is not None:
            report_to_proto(self.finished, result.harness_report)

    def report(self) -> types_pb2.HarnessReport:
        """The episode's report so far (final once the episode ended)."""
        out = types_pb2.HarnessReport()
        report_to_proto(self.finished or self.runtime.report, out)
        return out


def bind(current: SlotHarness | None, package: LoadedPackage | None) -> SlotHarness | None:
    """The slot's harness for the next episode: reuse the runtime when the package is unchanged."""
    if package is None:
        if current is not None:
            current.close()  # its sandbox child
        return None
    if current is not None and current.package is package:  # HarnessSource returns one object per version
        return current
    harness = SlotHarness(package)
    if current is not None:
        current.close()
    return harness


def placeholder_chunk(length: int, dim: int, dtype: np.dtype) -> np.ndarray:
    """The chunk a recovery runs instead of asking the policy (its entries are never executed)."""
    return np.zeros((max(1, length), dim), dtype=dtype)
