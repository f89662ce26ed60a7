"""Offline repair: search typed library templates and bounded parameter edits for a patch.

For a repair spec (diagnose.RepairSpec) the search proposes patches {C*, R*}: a critic built from a
library predicate template, with at most ``max_param_edits`` parameters moved off their defaults
by one grid step inside the template's declared range, paired with a plan: one of the library's
typed playbooks meant for the kind of m* (bounded multi-step recoveries such as acquire, place, or
instruction redirection; services/harness/runtime/library/playbooks.py) or a recovery template
compatible with the evidence. A critic qualifies only if a diagnostic replay shows it fires within
``window`` steps of t_EOD on the medoid; critics are ranked by how many cluster members they also
catch near their t_EOD, then by how rarely they fire on successful rollouts (false positives), then
by closeness to t_EOD, then by edit size, and candidates walk the critic and plan orders together.
The search is deterministic and needs no network; an LLM backend (llm.py) may add candidates,
which then face exactly the same checks.
"""

from __future__ import annotations

import functools
import itertools
import logging
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from services.evolver.diagnose import RepairSpec
from services.evolver.draft import CODE_TEMPLATE, CriticDraft, HarnessDraft, PlanDraft, render
from services.evolver.replay import SandboxedCritic, first_fire, frames, resume_frame
from services.evolver.trace import Trace
from services.harness.runtime.api import Frame

#: Which recoveries are worth pairing with which evidence: a typed compatibility table over the
#: library's names ("a+b" is a playbook that runs a, then b); entries whose parts are missing from
#: the installed library are skipped. Evidence with no row may pair with any recovery.
COMPATIBLE: dict[str, tuple[str, ...]] = {
    "grasp_lost": ("regrasp", "release_and_restage"),
    "failed_acquisition": ("regrasp", "release_and_restage"),
    "non_approach": ("pregrasp+regrasp", "redirect_instruction", "pregrasp", "regrasp"),
    "hovering_unacquired": ("regrasp", "pregrasp+regrasp", "release_and_restage"),
    "approach_wrong_object": ("pregrasp", "retreat_until_separated"),
    "drift": ("regrasp", "release_and_restage"),
    "held_near_target": ("lower_until_supported_then_release", "fine_alignment"),
    "held_stalled_transport": ("fine_alignment+lower_until_supported_then_release", "fine_alignment"),
    "blocked_motion": ("retreat_until_separated", "fine_alignment", "release_and_restage"),
    "articulation_stalled": ("redirect_instruction",),
    "stalled_progress": ("pregrasp+regrasp", "redirect_instruction", "release_and_restage", "fine_alignment"),
}
#: Predicates that state a healthy condition (used by re-entry and gating), never failure evidence.
NOT_EVIDENCE = frozenset({"grasp_retained", "supported_placement"})
#: The library's instruction redirection (recoveries.RedirectInstruction).
REDIRECT = "redirect_instruction"


class LibraryUnavailable(RuntimeError):
    """The harness library (services/harness/runtime/library) is not importable."""


def playbooks() -> Mapping[str, Any]:
    """The installed library's typed playbooks (multi-step recoveries with budgets and stages)."""
    try:
        from services.harness.runtime.library.playbooks import PLAYBOOKS
    except ImportError:
        return {}
    return PLAYBOOKS


def library() -> tuple[Mapping[str, Any], Mapping[str, Any]]:
    """The installed library's (PREDICATES, RECOVERIES) registries."""
    try:
        from services.harness.runtime import library as lib
    except ImportError as exc:
        raise LibraryUnavailable(f"the harness library cannot be imported: {exc}") from None
    preds = getattr(lib, "PREDICATES", None)
    recs = getattr(lib, "RECOVERIES", None)
    if preds is None:
        from services.harness.runtime.library.predicates import PREDICATES as preds
    if recs is None:
        try:
            from services.harness.runtime.library.recoveries import RECOVERIES as recs
        except ImportError as exc:
            raise LibraryUnavailable(f"the harness library has no recoveries registry: {exc}") from None
    return preds, recs


@dataclass(frozen=True)
class SearchParams:
    """Bounds of the search."""

    window: int = 40
    max_param_edits: int = 1
    grid_fraction: float = 0.25
    max_false_positive: float = 0.2
    max_candidates: int = 3


def param_grid(schema: Mapping[str, Any], max_edits: int, fraction: float) -> list[dict[str, float]]:
    """Defaults, then every setting that moves at most ``max_edits`` parameters one step up or down,
    clipped to the range: a step is ``fraction`` of the default (of a quarter of the range for a
    zero default), so an edit stays near what the template's author calibrated. Bounded edits by
    construction."""
    defaults = {k: (int(p.default) if p.kind == "int" else float(p.default)) for k, p in schema.items()}
    out = [defaults]
    for names in itertools.chain.from_iterable(itertools.combinations(sorted(schema), r)
                                               for r in range(1, max_edits + 1)):
        for signs in itertools.product((-1, 1), repeat=len(names)):
            cand = dict(defaults)
            for name, sign in zip(names, signs):
                p = schema[name]
                step = fraction * (abs(p.default) or (p.high - p.low) / 4)
                v = min(p.high, max(p.low, p.default + sign * step))
                cand[name] = int(round(v)) if p.kind == "int" else round(float(v), 6)
            if cand not in out:
                out.append(cand)
    return out


@dataclass(frozen=True)
class Candidate:
    """A patch with the replay evidence that made it a candidate."""

    critic_name: str
    critic: CriticDraft
    plan: PlanDraft
    fire_step: int
    coverage: float
    false_positive: float
    edits: int
    source: str = "search"

    def apply(self, parent: HarnessDraft) -> HarnessDraft:
        """The parent harness with this patch."""
        return parent.with_patch({self.critic_name: self.critic}, {self.critic.evidence: self.plan})

    def to_dict(self) -> dict[str, Any]:
        """JSON form for manifests and reports."""
        return {"critic": self.critic_name, "template": self.critic.template, "params": dict(self.critic.params),
                "recovery": self.plan.recovery, "args": dict(self.plan.args), "playbook": self.plan.playbook,
                "max_uses": self.plan.max_uses, "max_steps": self.plan.max_steps, "fire_step": self.fire_step,
                "coverage": self.coverage, "false_positive": self.false_positive, "edits": self.edits,
                "source": self.source}


@dataclass(frozen=True)
class ReplayCase:
    """A failure to replay: its trace, t_EOD step, whether t_EOD was located against I_succ, and the
    frame the replay starts from (after the harness last handed back before t_EOD)."""

    trace: Trace
    t_eod: int
    referenced: bool = True
    start: int = 0

    @classmethod
    def of(cls, trace: Trace, eod: Any) -> "ReplayCase":
        """The case of a failure and its EOD (eod.EOD), replayed from the last hand-back before it."""
        return cls(trace, eod.step, eod.referenced, resume_frame(trace, eod.step))

    def catches(self, step: int | None, window: int) -> bool:
        """Whether a critic firing at ``step`` catches this failure (see diagnose._near)."""
        if step is None:
            return False
        return abs(step - self.t_eod) <= window if self.referenced else step <= self.t_eod + window


class FrameCache:
    """Each trace's replay frames, built once per search (a search replays every trace once per
    template setting and stage set)."""

    def __init__(self) -> None:
        self._frames: dict[int, tuple[Trace, list[Frame]]] = {}

    def __call__(self, trace: Trace) -> list[Frame]:
        hit = self._frames.get(id(trace))
        if hit is None or hit[0] is not trace:
            hit = self._frames[id(trace)] = (trace, frames(trace))
        return hit[1]


def score_critic(fn: Any, params: Mapping[str, float], medoid: ReplayCase,
                 members: Sequence[ReplayCase], successes: Sequence[Trace], window: int,
                 stages: tuple[str, ...] = (), cache: FrameCache | None = None,
                 redirect: Sequence[str] | None = None) -> tuple[int, float, float] | None:
    """(fire step on the medoid, member coverage, false-positive rate) or None when it misses t_EOD.
    Only firings the runtime would act on count, on failures and successes alike: with ``stages``
    (the kinds of first missing milestone the patch's rule is gated on) those the orchestrator
    grants; with ``redirect`` (the plan is an instruction redirection; the policy's trained
    sentences) those whose redirection would not ask the episode's own instruction, which the
    runtime does not start (replay.granted)."""
    cache = cache or FrameCache()

    def fire_on(trace: Trace, start: int = 0) -> int | None:
        return first_fire(trace, fn, params, start=start, cached=cache(trace), stages=stages, redirect=redirect)

    fire = fire_on(medoid.trace, medoid.start)
    if fire is None or not medoid.catches(fire, window):
        return None
    caught = sum(1 for m in members if m.catches(fire_on(m.trace, m.start), window))
    fp = sum(1 for t in successes if fire_on(t) is not None)
    return fire, (1 + caught) / (1 + len(members)), fp / len(successes) if successes else 0.0


def recoveries_for(evidence: str, recoveries: Mapping[str, Any]) -> list[str]:
    """Library recoveries compatible with an evidence kind, in preference order."""
    preferred = [r for r in COMPATIBLE.get(evidence, ()) if all(part in recoveries for part in r.split("+"))]
    return preferred or ([] if evidence in COMPATIBLE else sorted(recoveries))


def plan_of(name: str, args: Mapping[str, Any] | None = None) -> PlanDraft:
    """The plan for a recovery name: a library playbook (its steps, budgets, clearing condition and
    per-step arguments) or a recovery template / "a+b" chain with ``args``."""
    book = playbooks().get(name)
    if book is None:
        return PlanDraft(name, dict(args or {}))
    merged = {step: dict(v) for step, v in book.args.items()}
    for step, v in (args or {}).items():
        merged[step] = {**merged.get(step, {}), **dict(v)}
    if len(book.steps) == 1:
        merged = merged.get(book.steps[0], {})
    return PlanDraft("+".join(book.steps), merged, max_uses=book.max_uses, max_steps=book.max_steps,
                     clear_when=book.clear_when, playbook=book.name)


def plan_redirect(plan: PlanDraft, policy_instructions: Sequence[str]) -> tuple[str, ...] | None:
    """The policy's trained sentences when the plan is an instruction redirection alone (the
    runtime does not start one that would ask the episode's own instruction), else None."""
    return tuple(policy_instructions) if plan.recovery == REDIRECT else None


def plan_stages(plan: PlanDraft, m_star: str) -> tuple[str, ...]:
    """Kinds of first missing milestone under which the plan is granted: a playbook's own stages
    (it was written for all of them, so the patch transfers to seeds that fail one stage earlier or
    later), else the kind of the cluster's m*."""
    book = playbooks().get(plan.playbook)
    return tuple(book.stages) if book is not None else stage_of(m_star)


def recovery_options(evidence: str, m_star: str, recoveries: Mapping[str, Any], singles: int = 2,
                     holding: bool | None = None) -> list[PlanDraft]:
    """Plans worth pairing with a critic of ``evidence`` for a failure at ``m_star``, in preference
    order: the library playbooks meant for m*'s kind that can start from what the evidence implies
    about the grasp (``holding``; the longest first: they carry the episode furthest), then up to
    ``singles`` recovery templates compatible with the evidence."""
    from services.harness.runtime.library.playbooks import serving

    kind = stage_of(m_star)
    books = [plan_of(b.name) for b in serving(kind[0], holding)] if kind else []
    books = [b for b in books if all(part in recoveries for part in b.recovery.split("+"))]
    return books + [plan_of(r) for r in recoveries_for(evidence, recoveries)[:singles]]


def search(spec: RepairSpec, parent: HarnessDraft, medoid: ReplayCase, members: Sequence[ReplayCase],
           successes: Sequence[Trace], params: SearchParams = SearchParams(),
           rejected: Callable[[str], bool] | None = None, policy_instructions: Sequence[str] = ()
           ) -> list[Candidate]:
    """Ranked candidate patches for a repairable spec (empty when nothing qualifies).

    Each critic template keeps its best setting (coverage of the cluster, then false positives,
    closeness to t_EOD, edit size); candidates pair it with the plans of :func:`recovery_options`.
    The ranking walks both orders diagonally (best critic with best plan, then the runner-up of
    either, ...), so a few closed-loop validations try different plans and different detectors
    instead of near-copies of one patch. ``rejected(fingerprint) -> bool`` filters candidates
    whose resulting harness was rejected before, so no candidate is ever evaluated twice.
    ``policy_instructions`` (the frozen policy's trained sentences, ListModels) tell which firings
    of a redirection plan the runtime would not start (:func:`plan_redirect`)."""
    if not spec.repairable:
        return []
    preds, recs = library()
    cache = FrameCache()
    critics = []
    for order, template in enumerate(_templates_for(spec, parent, preds)):
        base = parent.critics.get(f"c_{template}")
        # A plan's stages gate when its rule grants the critic, and a redirection is not started
        # when it would ask the episode's own instruction, so the best setting (and whether one
        # qualifies at all) is found per stage set and redirection: a firing on a success where the
        # runtime would not act is no false positive.
        best_for: dict[tuple[tuple[str, ...], bool], Any] = {}
        viable = []
        for plan in recovery_options(template, spec.m_star, recs, holding=preds[template].holding):
            stages = plan_stages(plan, spec.m_star)
            redirect = plan_redirect(plan, policy_instructions)
            gate = (stages, redirect is not None)
            if gate not in best_for:
                best_for[gate] = _best_setting(preds[template], base.params if base else None, medoid, members,
                                               successes, params, stages, cache, redirect)
            if best_for[gate] is not None:
                viable.append((plan, stages, best_for[gate]))
        if viable:
            critics.append((min(v[2][0] for v in viable), order, template, viable))
    critics.sort(key=lambda c: (c[0], c[1]))
    scored: list[tuple[tuple[int, int], Candidate]] = []
    for ci, (_, _, template, viable) in enumerate(critics):
        for pi, (plan, stages, (_, setting, res)) in enumerate(viable):
            critic = CriticDraft(template, setting, evidence=template, mode=plan.playbook or plan.recovery,
                                 missing=stages)
            patched = parent.with_patch({f"c_{template}": critic}, {template: plan})
            if patched.fingerprint() == parent.fingerprint():
                continue  # the parent's own critic and plan: no patch
            cand = Candidate(f"c_{template}", critic, plan, res[0], res[1], res[2], patched.edits_from(parent))
            if rejected is not None and rejected(patched.fingerprint()):
                continue
            if build_error(patched) is not None:
                continue
            scored.append(((ci + pi, pi), cand))
    scored.sort(key=lambda x: x[0])
    return [c for _, c in scored[: params.max_candidates]]


def _best_setting(spec: Any, current: Mapping[str, float] | None, medoid: ReplayCase, members: Sequence[ReplayCase],
                  successes: Sequence[Trace], params: SearchParams, stages: tuple[str, ...] = (),
                  cache: FrameCache | None = None, redirect: Sequence[str] | None = None
                  ) -> tuple[tuple[float, float, int, int], dict[str, float], tuple[int, float, float]] | None:
    """A predicate template's best setting on the bounded grid for a rule gated on ``stages``, with
    its rank key (cluster coverage, false positives, distance of the firing from t_EOD, parameters
    changed from ``current`` or the defaults) and its replay score; None when no setting catches the
    medoid within the bounds."""
    reference = dict(current) if current is not None else {k: p.default for k, p in spec.params.items()}
    best = None
    for setting in param_grid(spec.params, params.max_param_edits, params.grid_fraction):
        res = score_critic(spec.fn, setting, medoid, members, successes, params.window, stages, cache, redirect)
        if res is None or res[2] > params.max_false_positive:
            continue
        key = (-res[1], res[2], abs(res[0] - medoid.t_eod), sum(reference.get(k) != v for k, v in setting.items()))
        if best is None or key < best[0]:
            best = (key, setting, res)
    return best


def stage_of(m_star: str) -> tuple[str, ...]:
    """The kind of the cluster's first missing milestone ("on(a,b)" -> ("on",)): the orchestrator
    grants the recovery only while that kind of milestone is the one missing, a task-independent
    condition that transfers to other tasks."""
    from services.harness.runtime.orchestrator import milestone_kind

    return (milestone_kind(m_star),) if m_star and m_star != "<none>" else ()


def _templates_for(spec: RepairSpec, parent: HarnessDraft, preds: Mapping[str, Any]) -> list[str]:
    """Which predicate templates the layer allows, preferred first (they win ties in the ranking):
    new detectors for a critic failure (those seen firing near t_EOD first) or a plan failure (the
    motion detectors first: a blocked or stalled arm is what the layer saw; the others still
    qualify by replay, as the failure may show first in another signal), the parent's own critics
    (re-parameterized or re-paired) for a recovery/param failure."""
    evidence = sorted(t for t in preds if t not in NOT_EVIDENCE)
    if spec.layer in ("critic", "plan"):
        first = spec.detect_near if spec.layer == "critic" else ("blocked_motion", "stalled_progress")
        near = [t for t in first if t in evidence]
        return near + [t for t in evidence if t not in near]
    if spec.layer in ("recovery", "param"):
        return sorted({c.template for c in parent.critics.values() if c.template in preds}) or evidence
    return []


def check_patch(parent: HarnessDraft, cand: Candidate, max_edits: int) -> str | None:
    """Why a patch (from the search or an LLM) is refused, or None: the templates exist, the
    parameters are in range, the patch is bounded."""
    from services.harness.runtime.library.schema import ParamError, resolve

    preds, recs = library()
    if cand.critic.code and cand.critic.template != CODE_TEMPLATE:
        return f"a code critic's template is {CODE_TEMPLATE!r}, not {cand.critic.template!r}"
    if not cand.critic.code and cand.critic.template not in preds:
        return f"unknown predicate template {cand.critic.template!r}"
    parts = cand.plan.recovery.split("+")
    unknown = [p for p in parts if p not in recs]
    if unknown:
        return f"unknown recovery template {unknown[0]!r}"
    if cand.plan.clear_when and cand.plan.clear_when not in preds:
        return f"unknown clear_when predicate {cand.plan.clear_when!r}"
    if cand.plan.max_steps < 1 or cand.plan.max_uses < 1:
        return "max_steps and max_uses must be >= 1"
    try:
        if cand.critic.code:
            if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in cand.critic.params.values()):
                return f"{cand.critic_name}: a code critic's params must be numbers"
        else:
            resolve(preds[cand.critic.template].params, cand.critic.params, cand.critic_name)
        for part in parts:
            args = cand.plan.args.get(part, {}) if len(parts) > 1 else cand.plan.args
            resolve(recs[part].params, args, part)
    except ParamError as exc:
        return str(exc)
    edits = cand.apply(parent).edits_from(parent)
    if edits > max_edits:
        return f"patch changes {edits} critics/plans/parameters; at most {max_edits} allowed"
    return build_error(cand.apply(parent))


@functools.cache
def _warn_in_process() -> None:
    logging.getLogger("evolver").warning(
        "ZETTA_HARNESS_SANDBOX=off: candidate package code runs inside this process (trusted code only)")


def _sandboxed() -> bool:
    """Whether package code runs in the harness sandbox (ZETTA_HARNESS_SANDBOX, default on)."""
    from services.harness.sandbox import client as sandbox

    on = sandbox.enabled()
    if not on:
        _warn_in_process()
    return on


def code_detector(draft: HarnessDraft, name: str) -> Any:
    """Code critic ``name`` of the draft, for :func:`replay.first_fire`: past the package loader's
    static checks (raises PackageRejected for code they refuse), loaded in a sandbox child
    (a :class:`replay.SandboxedCritic`: close it when done; ReplayFailed when it does not load
    there). With ``ZETTA_HARNESS_SANDBOX=off`` (trusted code only): its ``detect`` function,
    imported in this process."""
    from services.harness.package.loader import load_files

    if not _sandboxed():
        return load_files(render(draft)).tools[name].detect
    pkg = load_files(render(draft), import_tools=False)  # the static checks; nothing runs here
    return SandboxedCritic(name, pkg.sources[name], pkg.params.get(name, {}))


def build_error(draft: HarnessDraft) -> str | None:
    """Why the draft's package would not load or build a runtime (the critic service's own checks), or None.
    The package's tools are imported in a sandbox child, not here (``ZETTA_HARNESS_SANDBOX=off``: here)."""
    from services.harness.package.errors import PackageRejected
    from services.harness.package.loader import load_files, unload
    from services.harness.runtime.engine import HarnessError, HarnessRuntime

    try:
        pkg = load_files(render(draft), import_tools=not _sandboxed())
    except PackageRejected as exc:
        return f"package rejected: {exc}"
    try:
        HarnessRuntime(pkg).close()  # a runtime with package code kills its sandbox child
    except HarnessError as exc:
        return f"harness does not build: {exc}"
    finally:
        unload(pkg)
    return None
