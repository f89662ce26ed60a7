"""The harness runtime: critics over every env step, the orchestrator's verdict, recoveries, re-entry.

One :class:`HarnessRuntime` per slot and harness package. The env worker calls :meth:`start` at
reset and :meth:`step` after every executed action (and once on the reset observation). Library
critics run at every step; the package's code critics on the reset frame, every
``ZETTA_CODE_CRITIC_EVERY`` steps (budget.PlatformLimits) and at every step of an intervention,
always over a window that holds every step. The
returned :class:`Decision` says who acts next: the policy, or a recovery with its action. The
runtime records every intervention (proposer, evidence, decision, start and end steps, outcome)
and, per episode, how many actions the policy and each recovery took, so a success that came from
recoveries doing the work is visible as such (:class:`EpisodeReport`).

Package conventions (the loader checks and imports the code; this module gives it meaning):

* SKILL.md front matter: ``[runtime]`` (``window`` frames, ``critic_budget_ms``,
  ``critic_hard_limit_ms``, ``cooldown`` steps after an intervention), ``[reentry]`` (``gamma``,
  ``k``, ``clears``, ``[reentry.stability]``),
  ``[[critics]]`` (library-predicate critics: ``name``, ``predicate``, ``evidence``, ``mode``,
  ``params``, ``budget_ms``), ``[[adjudication]]`` (orchestrator.Rule);
* ``tools/<stem>.py``: every module-level function ``critic_<name>(window, params)`` returning an
  ``api.Proposal`` or None is a critic named ``<stem>.<name>``; ``params`` is params/<stem>.toml;
* ``plans/*.toml``: each top-level table with a ``recovery`` key is a playbook, named by its key:
  ``recovery`` (a library recovery, a list of them run in order, or ``"<stem>:<factory>"`` for
  package code), ``params`` (for a list: one table per part), ``max_steps``, ``max_uses``,
  ``clear_when`` (a library predicate that must hold before re-entry) and ``clear_params``.
"""

from __future__ import annotations

import types
from collections import Counter, deque
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.harness.package.model import LoadedPackage
from services.harness.runtime import signals
from services.harness.runtime.api import Frame, Proposal, Window
from services.harness.runtime.budget import CallBudget, PlatformLimits, guarded_call
from services.harness.runtime.library import PREDICATES, RECOVERIES, EpisodeMemory, Recovery, resolve
from services.harness.runtime.library.recoveries import DONE, FAILED, Chain, PolicyUnder
from services.harness.runtime.library.schema import ParamError
from services.harness.runtime.limits import REDIRECTION_CAP, intervention_cap
from services.harness.runtime.orchestrator import POLICY, Orchestrator, Rule
from services.harness.runtime.perception import Perception, episode_seed, noise_from_table
from services.harness.runtime.reentry import ReentryContract
from services.harness.sandbox import codec as sandbox_codec
from services.harness.sandbox.client import CallFailed, SandboxError, SandboxLimits
from services.harness.sandbox.host import SandboxedCode, to_proposal

_HOLD = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
#: The outcome of an intervention still in control when the episode succeeded: the recovery, not
#: the policy, finished the task, and it never handed back (the report counts it as such).
IN_CONTROL_AT_SUCCESS = "in_control_at_success"


class HarnessError(ValueError):
    """A package that loaded but does not make a runnable harness (unknown template, bad rule)."""


@dataclass
class Critic:
    """A runtime critic: ``fn(window)`` returns a Proposal or None; switched off on misbehaviour."""

    name: str
    fn: Callable[[Window], Any] | None
    budget: CallBudget
    enabled: bool = True
    #: Index of the critic in the runtime's sandbox child (package code), -1 for one run here.
    remote: int = -1
    #: Package code (tools/*.py), evaluated at the platform's cadence (PlatformLimits.code_critic_every);
    #: library critics run at every step.
    code: bool = False


@dataclass(frozen=True)
class Plan:
    """A recovery playbook: how to build the recovery, its budgets and its clearing condition."""

    mode: str
    build: Callable[[], Recovery]
    max_steps: int
    max_uses: int
    clear_when: Callable[[Window], bool] | None


@dataclass
class Intervention:
    """One recovery that took control: who proposed it, on what evidence, the verdict, its span."""

    id: str
    kind: str
    proposer: str
    evidence: str
    details: dict[str, float]
    decision: str
    start_step: int
    end_step: int = -1
    outcome: str = ""
    actions: int = 0
    #: The instruction the policy acted under, when the recovery redirected it.
    instruction: str = ""


@dataclass(frozen=True)
class DisabledCritic:
    """A critic switched off for the rest of the episode, when and why."""

    name: str
    step: int
    reason: str


@dataclass
class EpisodeReport:
    """Per episode: who acted, every intervention, and which critics were switched off."""

    harness: str
    version: str
    content_hash: str
    policy_actions: int = 0
    recovery_actions: int = 0
    actions_by_mode: Counter[str] = field(default_factory=Counter)
    interventions: list[Intervention] = field(default_factory=list)
    disabled_critics: list[DisabledCritic] = field(default_factory=list)
    proposals: int = 0
    rejected: int = 0

    @property
    def interventions_by_kind(self) -> Counter[str]:
        return Counter(iv.kind for iv in self.interventions)

    @property
    def policy_share(self) -> float:
        """Share of the episode's actions taken by the policy (1.0 when nothing was executed)."""
        total = self.policy_actions + self.recovery_actions
        return self.policy_actions / total if total else 1.0


@dataclass(frozen=True)
class Decision:
    """Who acts next: ``mode`` ("policy" or a playbook), the recovery's ``action`` when a recovery
    has control, this step's proposals and the active intervention's id ("" under the policy).
    ``instruction`` is set when a recovery redirects the policy: the policy acts (``action`` None)
    under that instruction instead of the episode's."""

    mode: str
    proposals: tuple[Proposal, ...]
    action: np.ndarray | None
    intervention_id: str
    instruction: str = ""


#: The policy acts next and no critic proposed anything: most steps (a Decision is immutable).
_POLICY_NEXT = Decision(POLICY, (), None, "")


def _library_critic(entry: Mapping[str, Any]) -> tuple[str, Callable[[Window], Any], float | None]:
    known = {"name", "predicate", "evidence", "mode", "params", "budget_ms"}
    unknown = sorted(set(entry) - known)
    if unknown:
        raise HarnessError(f"[[critics]] entry has unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    pred_name = entry.get("predicate")
    if pred_name not in PREDICATES:
        raise HarnessError(f"[[critics]] predicate {pred_name!r} is not in the library ({', '.join(PREDICATES)})")
    spec = PREDICATES[pred_name]
    name = str(entry.get("name", pred_name))
    evidence = str(entry.get("evidence", pred_name))
    mode = str(entry.get("mode", ""))
    try:
        params = resolve(spec.params, entry.get("params", {}), f"critic {name}")
    except ParamError as exc:
        raise HarnessError(str(exc)) from None
    fn = spec.fn

    def critic(w: Window) -> Proposal | None:
        details = fn(w, params)
        return None if details is None else Proposal(name, evidence, mode, details)

    budget = entry.get("budget_ms")
    return name, critic, None if budget is None else float(budget) / 1000.0


def _code_critics(package: LoadedPackage) -> list[tuple[str, Callable[[Window], Any]]]:
    out = []
    for stem, module in sorted(package.tools.items()):
        params = dict(package.params.get(stem, {}))
        for attr, fn in sorted(vars(module).items()):
            if attr.startswith("critic_") and isinstance(fn, types.FunctionType) and fn.__module__ == module.__name__:
                out.append((f"{stem}.{attr.removeprefix('critic_')}", _bind(fn, params)))
    return out


def _bind(fn: Callable[[Window, Mapping[str, Any]], Any], params: Mapping[str, Any]) -> Callable[[Window], Any]:
    return lambda w: fn(w, params)


def _library_recovery(name: str, overrides: Mapping[str, Any], mode: str) -> Callable[[], Recovery]:
    if name not in RECOVERIES:
        raise HarnessError(f"playbook {mode}: recovery {name!r} is not in the library ({', '.join(RECOVERIES)})")
    spec = RECOVERIES[name]
    try:
        params = resolve(spec.params, overrides, f"playbook {mode}, recovery {name}")
    except ParamError as exc:
        raise HarnessError(str(exc)) from None
    return lambda: spec.factory(params)


def _plan(mode: str, table: Mapping[str, Any], package: LoadedPackage,
          remote: Callable[[str, Mapping[str, Any]], Recovery] | None = None,
          remote_callables: frozenset[str] = frozenset()) -> Plan:
    known = {"recovery", "params", "max_steps", "max_uses", "clear_when", "clear_params", "description"}
    unknown = sorted(set(table) - known)
    if unknown:
        raise HarnessError(f"playbook {mode}: unknown key(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    recovery = table["recovery"]
    params = table.get("params", {})
    build: Callable[[], Recovery]
    if isinstance(recovery, list):
        if not recovery or not all(isinstance(r, str) for r in recovery):
            raise HarnessError(f"playbook {mode}: 'recovery' list must name library recoveries")
        parts = [_library_recovery(r, params.get(r, {}), mode) for r in recovery]
        build = lambda: Chain([make() for make in parts])  # noqa: E731 - a fresh chain per intervention
    elif isinstance(recovery, str) and ":" in recovery:
        stem, attr = recovery.split(":", 1)
        if remote is not None:  # package code runs in the runtime's sandbox child
            if recovery not in remote_callables:
                raise HarnessError(f"playbook {mode}: tools/{stem}.py has no recovery factory {attr!r}")
            make_remote = remote
            build = lambda: make_remote(recovery, dict(params))  # noqa: E731
        else:
            factory = getattr(package.tools.get(stem), attr, None)
            if not callable(factory):
                raise HarnessError(f"playbook {mode}: tools/{stem}.py has no recovery factory {attr!r}")
            build = lambda: factory(dict(params))  # noqa: E731
    elif isinstance(recovery, str):
        build = _library_recovery(recovery, params, mode)
    else:
        raise HarnessError(f"playbook {mode}: 'recovery' must be a name or a list of names, got {recovery!r}")
    clear: Callable[[Window], bool] | None = None
    if "clear_when" in table:
        spec = PREDICATES.get(table["clear_when"])
        if spec is None:
            raise HarnessError(f"playbook {mode}: clear_when {table['clear_when']!r} is not a library predicate")
        try:
            cparams = resolve(spec.params, table.get("clear_params", {}), f"playbook {mode} clear_when")
        except ParamError as exc:
            raise HarnessError(str(exc)) from None
        clear = lambda w: spec.fn(w, cparams) is not None  # noqa: E731
    cap = intervention_cap(recovery if isinstance(recovery, list) else [recovery])
    max_steps, max_uses = int(table.get("max_steps", cap)), int(table.get("max_uses", 3))
    if max_steps < 1 or max_uses < 1:
        raise HarnessError(f"playbook {mode}: max_steps and max_uses must be >= 1")
    if max_steps > cap:
        what = "redirection cap" if cap == REDIRECTION_CAP else "intervention cap"
        raise HarnessError(f"playbook {mode}: max_steps {max_steps} is over the {what} of {cap} "
                           "actions (a recovery corrects the policy, it does not run the task; docs/harness.md)")
    return Plan(mode, build, max_steps, max_uses, clear)


class HarnessRuntime:
    """Runs one harness package over the episodes of one slot (single-threaded: the slot's thread).

    ``sandboxed``: the package's code (tools/*.py: code critics, package recoveries) runs in a
    sandbox child process (services/harness/sandbox/) instead of this process; library critics
    and recoveries (platform code) run here either way. None (the default): sandboxed when the
    package's tools were not imported in this process (``load_files(..., import_tools=False)``,
    what the env worker and the critic service do unless ``ZETTA_HARNESS_SANDBOX=off``).
    Call :meth:`close` when done with a sandboxed runtime (its child is killed when the runtime
    is collected otherwise).
    """

    def __init__(self, package: LoadedPackage, sandboxed: bool | None = None,
                 sandbox_limits: SandboxLimits | None = None) -> None:
        self.package = package
        skill = package.skill
        runtime = skill.get("runtime", {})
        self.window_size = int(runtime.get("window", 32))
        self.budget_s = float(runtime.get("critic_budget_ms", 2.0)) / 1000.0
        self.hard_limit_s = float(runtime.get("critic_hard_limit_ms", 250.0)) / 1000.0
        #: Steps after an intervention ends during which no new one starts: the policy gets the
        #: chance the re-entry contract promised it before old evidence in the window counts again.
        self.cooldown = int(runtime.get("cooldown", 0))
        if self.window_size < 1 or self.budget_s <= 0 or self.hard_limit_s < self.budget_s or self.cooldown < 0:
            raise HarnessError("[runtime]: window >= 1, cooldown >= 0 and 0 < critic_budget_ms <= critic_hard_limit_ms "
                               "are required")
        declared = runtime.get("signals", [])
        if not isinstance(declared, list) or not all(isinstance(n, str) for n in declared):
            raise HarnessError("[runtime] signals must be a list of observation names")
        problems = signals.check_package({f"tools/{k}.py": v for k, v in package.sources.items()}, declared)
        if problems:
            raise HarnessError("reads what a harness may not know: " + "; ".join(problems))
        #: The camera tensors the package asked for: only those ride in its frames.
        self.cameras = frozenset(n for n in declared if signals.is_camera(n))
        try:
            self.noise = noise_from_table(skill.get("perception", {}))
        except (TypeError, ValueError) as exc:
            raise HarnessError(str(exc)) from None
        # The platform's limits bound what the package asked for (it may ask for less, never more).
        self.limits = PlatformLimits.from_env()
        self.code_every = self.limits.code_critic_every
        self.code_pipelined = self.limits.code_critic_pipelined
        self._policy_instructions: tuple[str, ...] = ()
        self.budget_s = min(self.budget_s, self.limits.budget_s)
        self.hard_limit_s = min(self.hard_limit_s, self.limits.hard_limit_s)
        try:
            self._contract = ReentryContract.from_skill(skill.get("reentry", {}))
        except (ValueError, ParamError) as exc:
            raise HarnessError(str(exc)) from None
        #: (name, function (None: in the sandbox child), budget, package code) per critic.
        self._critic_defs: list[tuple[str, Callable[[Window], Any] | None, float | None, bool]] = [
            (*_library_critic(e), False) for e in skill.get("critics", [])
        ]
        if sandboxed is None:
            sandboxed = bool(set(package.sources) - set(package.tools))
        self._code: SandboxedCode | None = None
        self._remote: dict[str, int] = {}
        if sandboxed and package.sources:
            try:
                self._code = SandboxedCode(package.sources, package.params, self.window_size, sandbox_limits)
            except (SandboxError, CallFailed) as exc:
                raise HarnessError(f"the package's tools do not load in the sandbox: {exc}") from None
            self._remote = {n: i for i, n in enumerate(self._code.critics)}
            self._critic_defs += [(n, None, None, True) for n in self._code.critics]
        else:
            self._critic_defs += [(n, fn, None, True) for n, fn in _code_critics(package)]
        names = [n for n, _, _, _ in self._critic_defs]
        if len(set(names)) != len(names):
            self.close()
            raise HarnessError(f"critic names must be unique, got {names}")
        try:
            self._build_plans(package, skill)
        except HarnessError:
            self.close()
            raise
        #: Shape of one env action, when the caller knows it: a recovery action of another shape
        #: fails its intervention instead of reaching the env.
        self.action_shape: tuple[int, ...] | None = None
        self.start("", [])

    @property
    def sandbox(self) -> SandboxedCode | None:
        """The sandbox child running this runtime's package code (None: in-process or no code)."""
        return self._code

    def close(self) -> None:
        """Kill the sandbox child, if any (idempotent)."""
        if self._code is not None:
            self._code.close()

    def _remote_recovery(self, ref: str, params: Mapping[str, Any]) -> Recovery:
        assert self._code is not None
        return self._code.recovery(ref, params, self.hard_limit_s, lambda: tuple(self._frames))  # type: ignore[return-value]

    def _build_plans(self, package: LoadedPackage, skill: Mapping[str, Any]) -> None:
        remote = self._remote_recovery if self._code is not None else None
        callables = self._code.callables if self._code is not None else frozenset()
        self.plans: dict[str, Plan] = {}
        for stem, tables in sorted(package.plans.items()):
            for mode, table in tables.items():
                if isinstance(table, Mapping) and "recovery" in table:
                    if mode in self.plans or mode == POLICY:
                        raise HarnessError(f"playbook name {mode!r} (plans/{stem}.toml) is reserved or used twice")
                    self.plans[mode] = _plan(mode, table, package, remote, callables)
        try:
            rules = [Rule.from_table(t) for t in skill.get("adjudication", [])]
        except ValueError as exc:
            raise HarnessError(str(exc)) from None
        for rule in rules:
            if rule.mode not in self.plans:
                raise HarnessError(f"adjudication rule for {rule.evidence!r} grants mode {rule.mode!r}, which no plan defines")
        self.orchestrator = Orchestrator(rules)

    @property
    def policy_instructions(self) -> tuple[str, ...]:
        """What the frozen policy was trained on (Window.policy_instructions): the host sets it
        once it knows the model that serves the episodes; it outlives episodes."""
        return self._policy_instructions

    @policy_instructions.setter
    def policy_instructions(self, instructions: Sequence[str]) -> None:
        instructions = tuple(instructions)
        if instructions != self._policy_instructions:
            self._policy_instructions = instructions
            if self._code is not None:
                self._code.set_policy_instructions(instructions)

    # ---- episode lifecycle -------------------------------------------------------------------

    def start(self, instruction: str, milestone_names: Sequence[str]) -> None:
        """Begin an episode: fresh window, memory, critics (all re-enabled) and report."""
        self.instruction = instruction
        self.milestone_names = tuple(milestone_names)
        self.critics = [
            Critic(n, fn, CallBudget(min(b, self.limits.budget_s) if b is not None else self.budget_s, self.hard_limit_s),
                   remote=self._remote.get(n, -1) if fn is None else -1, code=code)
            for n, fn, b, code in self._critic_defs
        ]
        if self._code is not None:
            self._code.start(instruction, self.milestone_names, self._policy_instructions)
        self._frames: deque[Frame] = deque(maxlen=self.window_size)
        self._memory = EpisodeMemory()
        self._uses: Counter[str] = Counter()
        self._active: Intervention | None = None
        self._recovery: Recovery | None = None
        self._plan: Plan | None = None
        self._waiting = False
        self._mode = POLICY
        self._step = 0
        self._quiet_until = -1
        self._perception: Perception | None = None
        #: A pipelined evaluation of the code critics: the in-process ones' proposals, and the
        #: sandboxed ones sent to the child, both delivered with the next step.
        self._held: dict[int, Proposal] = {}
        self._awaiting: tuple[dict[int, tuple[int, Critic]], int] | None = None
        self.report = EpisodeReport(self.package.name, self.package.version, self.package.content_hash)

    @property
    def mode(self) -> str:
        """Who produces the next action."""
        return self._mode

    @property
    def active(self) -> Intervention | None:
        """The intervention in control, if any."""
        return self._active

    def step(self, obs: Mapping[str, np.ndarray], action: np.ndarray | None, milestones: frozenset[str]) -> Decision:
        """Observe the state the last action led to (``action`` None at reset) and decide who acts next."""
        if action is not None:
            self._step += 1
            if self._mode == POLICY:
                self.report.policy_actions += 1
            else:
                self.report.recovery_actions += 1
                if self._active is not None:
                    self._active.actions += 1
            self.report.actions_by_mode[self._mode] += 1
        if self._perception is None:
            self._perception = Perception(episode_seed(obs, self.instruction), self.noise)
        self._frames.append(Frame(self._step, signals.visible(obs, self.cameras), action, milestones,
                                  self._perception.sensor(obs)))
        window = Window(tuple(self._frames), self.instruction, self.milestone_names, self.policy_instructions)
        # Code critics: on the reset frame, at the platform's cadence and through an intervention
        # (its re-entry needs fresh evidence); the frames between reach their window regardless.
        # Under the policy the evaluation is pipelined (its proposals come with the next step).
        due = action is None or self._active is not None or self._step % self.code_every == 0
        defer = self.code_pipelined and action is not None and self._active is None
        proposals = self._run_critics(window, due, defer)
        if self._active is not None:
            return self._decision(self._continue(window, proposals), proposals)
        if not proposals:
            return _POLICY_NEXT
        if self._step <= self._quiet_until:
            return Decision(POLICY, proposals, None, "")
        verdict = self.orchestrator.adjudicate(
            proposals, milestones, self.milestone_names,
            {m: self._uses[m] >= p.max_uses for m, p in self.plans.items()},
        )
        self.report.rejected += len(verdict.rejected)
        if verdict.accepted is None or verdict.rule is None:
            return Decision(POLICY, proposals, None, "")
        return self._decision(self._begin(window, verdict.accepted, verdict.rule, proposals), proposals)

    def finish(self, success: bool) -> EpisodeReport:
        """End the episode: an intervention still in control ends with it."""
        if self._active is not None:
            self._end(IN_CONTROL_AT_SUCCESS if success else "episode_end")
        return self.report

    # ---- internals ---------------------------------------------------------------------------

    def _decision(self, next_action: np.ndarray | PolicyUnder | None, proposals: tuple[Proposal, ...]) -> Decision:
        if next_action is None or self._active is None:
            return Decision(POLICY, proposals, None, "")
        if isinstance(next_action, PolicyUnder):
            return Decision(self._mode, proposals, None, self._active.id, next_action.instruction)
        return Decision(self._mode, proposals, next_action, self._active.id)

    def _disable(self, critic: Critic, error: str, step: int | None = None) -> None:
        """Switch ``critic`` off for the episode, recorded at the step it misbehaved on."""
        critic.enabled = False
        self.report.disabled_critics.append(DisabledCritic(critic.name, self._step if step is None else step, error))

    def _run_critics(self, window: Window, due: bool = True, defer: bool = False) -> tuple[Proposal, ...]:
        """Every enabled library critic, and the code critics when ``due``: their proposals now,
        or with the next step when ``defer`` (the sandbox child then works while the env steps).
        A pipelined evaluation of the last step comes first; this step's own results replace it."""
        found: dict[int, Proposal] = {}
        if self._held:
            found.update(self._held)
            self._held = {}
        if self._awaiting is not None:
            self._collect_remote(found)
        held: dict[int, Proposal] = {} if defer else found
        remote: dict[int, tuple[int, Critic]] = {}
        for i, critic in enumerate(self.critics):
            if not critic.enabled or (critic.code and not due):
                continue
            if critic.fn is None:
                remote[critic.remote] = (i, critic)
                continue
            result, error = guarded_call(critic.fn, (window,), critic.budget)
            if not error and result is not None and not isinstance(result, Proposal):
                error = f"returned {type(result).__name__}, not a Proposal or None"
            if error:
                self._disable(critic, error)
                continue
            if result is not None:
                (held if critic.code else found)[i] = result
        if self._code is not None and remote:
            self._send_remote(remote, window.frames)
            if not defer:
                self._collect_remote(found)
        if defer:
            self._held = held
        out = tuple(found[i] for i in sorted(found))
        self.report.proposals += len(out)
        return out

    def _send_remote(self, remote: dict[int, tuple[int, Critic]], frames: Sequence[Frame]) -> None:
        """The package's critics, to the sandbox child: one message for all of them, carrying the
        frames the child has not seen yet; :meth:`_collect_remote` takes their results."""
        assert self._code is not None
        runs = []
        cap = 2.0  # the whole step may take the sum of the critics' hard limits plus 2 s
        for r, (_, c) in remote.items():
            runs.append((r, c.budget.suspect))
            cap += c.budget.hard_limit_s

        def hard_limit(r: int) -> float:
            hit = remote.get(r)
            return hit[1].budget.hard_limit_s if hit is not None else self.hard_limit_s

        try:
            self._code.send(frames, runs, hard_limit, cap)
        except (SandboxError, CallFailed) as exc:
            self._remote_failed(remote, exc, self._step)
            return
        self._awaiting = (remote, self._step)

    def _remote_failed(self, remote: dict[int, tuple[int, Critic]], exc: SandboxError | CallFailed, step: int) -> None:
        hit = remote.get(exc.index) if isinstance(exc, SandboxError) else None
        for _, critic in [hit] if hit is not None else list(remote.values()):
            self._disable(critic, str(exc), step)

    def _collect_remote(self, found: dict[int, Proposal]) -> None:
        """The results of the critics sent to the child, into ``found``; budgets and errors as in-process."""
        assert self._code is not None and self._awaiting is not None
        (remote, step), self._awaiting = self._awaiting, None
        if not self._code.inflight:  # the child was replaced since: nothing will answer
            return
        try:
            results = self._code.collect()
        except (SandboxError, CallFailed) as exc:
            self._remote_failed(remote, exc, step)
            return
        R_ERROR, R_PROPOSAL = sandbox_codec.R_ERROR, sandbox_codec.R_PROPOSAL
        for index, kind, elapsed, proposal, error in results:
            i, critic = remote[index]
            budget = critic.budget
            if kind == R_ERROR:
                self._disable(critic, error, step)
                continue
            if elapsed > budget.budget_s:
                if budget.suspect:
                    self._disable(critic, f"used {elapsed * 1000:.1f} ms of CPU, over its "
                                          f"{budget.budget_s * 1000:.1f} ms budget", step)
                    continue
                budget.suspect = True
            else:
                budget.suspect = False
            if kind == R_PROPOSAL:
                found[i] = to_proposal(critic.name, proposal)

    def _begin(self, window: Window, proposal: Proposal, rule: Rule, proposals: Sequence[Proposal]
               ) -> np.ndarray | PolicyUnder | None:
        plan = self.plans[rule.mode]
        if self._awaiting is not None:  # before a package recovery's call: still due with the next step
            self._collect_remote(self._held)
        failure = ""
        recovery: Recovery | None = None
        try:
            recovery = plan.build()
            recovery.start(window, self._memory)
        except Exception as exc:  # noqa: BLE001 - package recovery code: the intervention fails, not the episode
            failure = f"recovery_failed: raised {type(exc).__name__}: {exc}"
        if not failure and isinstance(recovery, Recovery) and recovery.redundant():
            # It would ask the policy what it is already asked: no interruption, nothing recorded.
            self.report.rejected += 1
            return None
        self._uses[rule.mode] += 1
        iv = Intervention(
            id=f"iv{len(self.report.interventions) + 1}",
            kind=rule.mode,
            proposer=proposal.critic,
            evidence=proposal.evidence,
            details={k: float(v) for k, v in proposal.details.items()},
            decision=f"accepted: rule {rule.evidence}->{rule.mode} (priority {rule.priority}), "
                     f"use {self._uses[rule.mode]}/{plan.max_uses}",
            start_step=self._step,
        )
        self.report.interventions.append(iv)
        self._active, self._plan, self._waiting = iv, plan, False
        self._mode = rule.mode
        self._recovery = recovery
        if failure:
            self._end(failure)
            return None
        return self._continue(window, proposals)

    def _continue(self, window: Window, proposals: Sequence[Proposal]) -> np.ndarray | PolicyUnder | None:
        """The active recovery's next action (or a redirection of the policy), or None when control
        goes back to the policy."""
        iv, plan, recovery = self._active, self._plan, self._recovery
        assert iv is not None and plan is not None and recovery is not None
        if iv.actions >= plan.max_steps:
            self._end("budget_exhausted")
            return None
        if not self._waiting:
            try:
                action = recovery.act(window)
                if isinstance(action, PolicyUnder):
                    iv.instruction = action.instruction
                    return action
                if action is not None:
                    action = np.asarray(action, dtype=np.float64)
                    if self.action_shape is not None and action.shape != self.action_shape:
                        raise ValueError(f"action of shape {action.shape}, the env takes {self.action_shape}")
                    return action
            except Exception as exc:  # noqa: BLE001 - package recovery code: the intervention fails, not the episode
                self._end(f"recovery_failed: raised {type(exc).__name__}: {exc}")
                return None
            if getattr(recovery, "status", DONE) == FAILED:
                self._end(f"recovery_failed: {getattr(recovery, 'reason', '')}")
                return None
            self._waiting = True
            self._contract.reset()
        clears = self._contract.clears
        cleared = not any((p.critic == iv.proposer and p.evidence == iv.evidence) or p.evidence in clears
                          for p in proposals)
        if cleared and plan.clear_when is not None:
            cleared = plan.clear_when(window)
        if self._contract.holds(window, cleared):
            self._end("reentered")
            return None
        return _HOLD.copy()

    def _end(self, outcome: str) -> None:
        iv = self._active
        assert iv is not None
        iv.end_step, iv.outcome = self._step, outcome
        self._quiet_until = self._step + self.cooldown
        self._active, self._recovery, self._plan, self._waiting = None, None, None, False
        self._mode = POLICY
