"""The three loops end to end for a set of tasks: profile, diagnose/repair/validate, consolidate/gate.

Each task has three disjoint splits on disjoint initial states (services/evolver/store.py): dev
seeds feed profiling, repair, validation, regression and the do-nothing control; held-out (gate)
seeds feed admission; test seeds are measured once, after every round, and no decision reads them
(the store refuses any other rollout on a test seed). Every rollout goes through the store first, so an interrupted evolution resumes where it stopped:
rollouts already filed are read back, never rerun; rejected candidates are never retried; admitted
versions are recorded as events and re-read on resume.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from services.common.policies import policy_env_config, trained_layouts
from services.evolver.cluster import Cluster, ClusterParams, cluster_failures
from services.evolver.consolidate import consolidate
from services.evolver.controls import arm
from services.evolver.diagnose import REENTERED, Case, RepairSpec, repair_spec
from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft
from services.evolver.eod import EOD, EODParams, t_eod
from services.evolver.gate import GateParams, count, judge, regression_gate
from services.evolver.llm import LLMConfig, LLMError, propose
from services.evolver.nominal import NominalPlan, summary
from services.evolver.profile import SuccessIndex, build_profile
from services.evolver.registry_client import RegistryClient
from services.evolver.repair import NOT_EVIDENCE, Candidate, ReplayCase, SearchParams, library, search
from services.evolver.replay import first_fire, resume_frame
from services.evolver.rollout import Runner, RunConfig
from services.evolver.trace import Trace
from services.evolver.store import DEV, HELDOUT, TEST, EpisodeKey, Rollout, RolloutStore

#: progress(phase, done, total): how long-running phases report to a progress bar or a gauge.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class EvolveConfig:
    """One evolution: where, what, how much."""

    suite: str
    tasks: tuple[str, ...]
    rounds: int = 1
    dev_seeds: int = 20
    heldout_seeds: int = 10
    #: Seeds of the reported number (dev + held-out + test <= 50, LIBERO's initial states per task).
    test_seeds: int = 20
    #: The served model that plays the do-nothing policy of the control.
    control_model: str = "do-nothing"
    name: str = "evolved"
    max_clusters: int = 3
    eod: EODParams = EODParams()
    cluster: ClusterParams = ClusterParams()
    search: SearchParams = SearchParams()
    gate: GateParams = GateParams()
    llm: LLMConfig | None = None
    max_edits: int = 3
    #: Internal versions stacked per cluster and round; each validated version that solves more of
    #: the cluster than any before it earns one more, up to twice this (a cluster being solved seed
    #: by seed is worth finishing; one that stalls is not).
    max_depth: int = 3
    #: Bare-policy episodes per task on the original suite of a LIBERO-PRO variant whose successes
    #: count as false positives for a critic that fires on them (services/evolver/nominal.py); 0: none.
    nominal_seeds: int = 2
    #: The instructions the frozen policy was trained on (ListModels): the repair search does not
    #: count a redirection's firing that would ask the episode's own instruction as a false positive,
    #: since the runtime does not start it. Empty: every firing counts.
    policy_instructions: tuple[str, ...] = ()


@dataclass(frozen=True)
class Validation:
    """Closed-loop validation of a cluster's candidates on its medoid: the validated patch (``found``)
    or the best stepping stone (``step``), its harness reference, the medoid's milestones reached
    and that rollout."""

    found: Candidate | None
    step: Candidate | None
    ref: str
    progress: int
    rollout: Rollout | None


@dataclass
class TaskState:
    """The current harness of one task: its draft and published reference ("" = bare policy)."""

    draft: HarnessDraft
    ref: str = ""


@dataclass(frozen=True)
class ClusterRepair:
    """What Loop 2 made of one cluster: its record, the validated patches in the order they were
    stacked, the harness they make on top of the current one (None: nothing validated), the
    cluster's seeds and that harness's historical regression on them, with its reference."""

    record: dict[str, Any]
    stack: list[Candidate]
    draft: HarnessDraft | None
    seeds: list[int]
    regression: tuple[int, int]
    ref: str

    def passes(self, gate: GateParams) -> bool:
        """Whether the stack is validated and solved the share of the cluster the gate asks for."""
        s, n = self.regression
        return (bool(self.stack) and self.draft is not None and len(self.seeds) >= gate.min_cluster
                and n >= gate.min_cluster and s / n >= gate.regression_min)


def _noop(phase: str, done: int, total: int) -> None:
    return None


class Evolution:
    """Runs :class:`EvolveConfig` against a stack (gateway + critic registry) into a store."""

    def __init__(self, cfg: EvolveConfig, store: RolloutStore, run: RunConfig, registry: RegistryClient | None,
                 progress: Progress = _noop) -> None:
        self.cfg = cfg
        self.store = store
        self.runner = Runner(store, run, env_config(cfg.suite, run))
        control = replace(run, model=cfg.control_model)
        #: The same harnesses around the do-nothing policy (the control of every table).
        self.control_runner = Runner(store, control, env_config(cfg.suite, control))
        self.run_cfg = run
        self.registry = registry
        self.progress = progress
        self.nominal_plan = NominalPlan.for_evolution(cfg.suite, cfg.nominal_seeds)
        self._nominal: list[Trace] | None = None
        self.state = {t: TaskState(HarnessDraft(name=_safe(f"{cfg.name}-{t}"), tasks=(t,))) for t in cfg.tasks}
        self._restore()

    # ---- bookkeeping -----------------------------------------------------------------------------

    def _restore(self) -> None:
        """Re-read admitted versions from the store's events (resume)."""
        for ev in self.store.events("admitted"):
            if ev["suite"] == self.cfg.suite and ev["task"] in self.state:
                self.state[ev["task"]] = TaskState(_draft_from(ev["draft"]), ev["ref"])

    def _rollouts(self, keys: Sequence[EpisodeKey], phase: str, round_: int, runner: Runner | None = None
                  ) -> list[Rollout]:
        total = len(keys)
        done = [0]

        def tick(_: Rollout, __: bool) -> None:
            done[0] += 1
            self.progress(phase, done[0], total)

        self.progress(phase, 0, total)
        return asyncio.run((runner or self.runner).run(keys, round_, tick))

    def _keys(self, task: str, seeds: Sequence[int], ref: str, purpose: str) -> list[EpisodeKey]:
        return [EpisodeKey(self.cfg.suite, task, s, ref, purpose) for s in seeds]

    # ---- the loops ---------------------------------------------------------------------------------

    def run(self) -> None:
        """Every round for every task, then the final measurement on the test seeds."""
        trained = trained_layouts(self.run_cfg.model, self.cfg.suite)
        for task in self.cfg.tasks:
            self.store.assign_splits(self.cfg.suite, task, self.cfg.dev_seeds, self.cfg.heldout_seeds,
                                     self.cfg.test_seeds, trained)
        self.nominal_successes()
        for round_ in range(1, self.cfg.rounds + 1):
            for task in self.cfg.tasks:
                if any(e["round"] == round_ and e["task"] == task and e["suite"] == self.cfg.suite
                       for e in self.store.events("round_done")):
                    continue
                self.round(task, round_)
        for task in self.cfg.tasks:
            self.final_eval(task)

    def nominal_successes(self) -> list[Trace]:
        """Traces of the policy's successful nominal episodes (run once, then read from the store):
        the false-positive reference every critic search of this evolution adds to I_succ."""
        if self._nominal is None:
            keys = self.nominal_plan.keys(self.store)
            rollouts: list[Rollout] = []
            if keys:
                runner = Runner(self.store, self.run_cfg, env_config(self.nominal_plan.suite, self.run_cfg))
                rollouts = self._rollouts(keys, f"nominal {self.nominal_plan.suite}", 0, runner)
                self.store.record("nominal", {"for_suite": self.cfg.suite, **summary(self.nominal_plan, rollouts)},
                                  ident=self.cfg.suite)
            self._nominal = [self.store.trace(r) for r in rollouts if r.success]
        return self._nominal

    def round(self, task: str, round_: int) -> None:
        """Loop 1 on dev seeds with the current harness, then Loop 2 and Loop 3 on its failures."""
        t0 = time.time()
        cur = self.state[task]
        dev = self.store.seeds(self.cfg.suite, task, DEV)
        rollouts = self._rollouts(self._keys(task, dev, cur.ref, "profile"), f"r{round_} {task} profile", round_)
        prof = build_profile(self.store, rollouts, self.cfg.suite, task, cur.ref, self.cfg.gate)
        t_profile = time.time()
        self.store.record("profile", {"suite": self.cfg.suite, "task": task, "round": round_, "harness": cur.ref or "bare",
                                      "successes": prof.successes, "episodes": len(rollouts),
                                      "manifest": prof.manifest()}, ident=f"{self.cfg.suite}/{task}/{round_}")
        repairs: list[ClusterRepair] = []
        skipped: list[list[int]] = []
        if prof.failures:
            traces = [self.store.trace(f.rollout) for f in prof.failures]
            index = self._reference_index(task, rollouts, traces)
            eods = [t_eod(tr, index, self.cfg.eod) for tr in traces]
            budget = max(r.steps for r in rollouts)
            clusters = cluster_failures(prof.failures, traces, eods, index, budget, self.cfg.cluster)
            succ_traces = [self.store.trace(r) for r in rollouts if self.cfg.gate.won(r)] + self.nominal_successes()
            chosen, small = clusters_to_repair(clusters, self.cfg.max_clusters, self.cfg.gate.min_cluster)
            skipped = [cl.seeds for cl in small]
            for cl in chosen:
                idx = [prof.failures.index(f) for f in cl.members]
                repairs.append(self._repair_cluster(task, round_, cur, cl, [traces[i] for i in idx],
                                                    [eods[i] for i in idx], succ_traces, index))
        t_repair = time.time()
        passing = [r for r in repairs if r.passes(self.cfg.gate)]
        if passing:
            self.gate(task, round_, cur, passing, [r.record for r in repairs])
        t_end = time.time()
        self.store.record("round_done", {"suite": self.cfg.suite, "task": task, "round": round_, "wall_s": t_end - t0,
                                         "phases_s": {"profile": t_profile - t0, "repair": t_repair - t_profile,
                                                      "gate": t_end - t_repair},
                                         "skipped_clusters": skipped,
                                         "patches": sum(len(r.stack) for r in passing)})

    def _reference_index(self, task: str, rollouts: Sequence[Rollout], failures: Sequence[Trace] = ()) -> SuccessIndex:
        """I_succ for t_EOD and clustering: the successes among this round's profile rollouts plus every
        other successful rollout on a dev seed of the task (with any harness: candidates' validation
        and regression rollouts). A frozen policy that never succeeds alone leaves the profile's
        index empty; successes its harnesses produced still show what a good episode looks like at
        each milestone. Held-out rollouts never enter (dev/held-out separation). With no success
        anywhere, distances are scaled by the spread of the ``failures`` themselves."""
        dev = set(self.store.seeds(self.cfg.suite, task, DEV))
        seen = {r.key for r in rollouts}
        won = self.cfg.gate.won
        succ = [r for r in rollouts if won(r)]
        succ += [r for r in self.store.query(suite=self.cfg.suite, task=task, success=True)
                 if won(r) and r.seed in dev and r.key not in seen and r.purpose not in ("heldout", "control")]
        return SuccessIndex.build([self.store.trace(r) for r in succ], fallback=failures)

    def _repair_cluster(self, task: str, round_: int, cur: TaskState, cl: Cluster, traces: Sequence[Trace],
                        eods: Sequence[EOD], succ_traces: Sequence[Trace], index: SuccessIndex) -> "ClusterRepair":
        """Diagnose one cluster's medoid, search patches for its repair spec and validate them, stacking
        up to ``max_depth`` internal versions until one solves every seed of the cluster.

        Each version stacks one patch on the previous one and is measured on every cluster seed
        (the v0/v1/v2 curves). What the next version repairs: when no candidate succeeded on the
        seed under repair, the candidate that got it furthest along M (a stepping stone, the paper's
        stagnant v1) is kept and its own rollout of that seed is diagnosed; when one succeeded but
        the version still fails other cluster seeds (historical regression below 100 %), the failing
        member closest to the medoid is diagnosed under the version next. The validated stack and
        its regression numbers go to the gate."""
        cases = [self._case(tr, e, f.m_star, cur.draft) for tr, e, f in zip(traces, eods, cl.members)]
        spec = repair_spec(f"{task}/r{round_}/{cl.cid}", cl.medoid_failure.rollout.key, cases[cl.medoid],
                           [c for j, c in enumerate(cases) if j != cl.medoid])
        record = {"suite": self.cfg.suite, "task": task, "round": round_, "cluster": spec.cluster,
                  "size": len(cl.members), "seeds": cl.seeds, "medoid_seed": cl.medoid_failure.rollout.seed,
                  "spec": spec.to_dict(), "eods": [e.to_dict() for e in cl.eods]}
        self.store.record("cluster", record, ident=spec.cluster)
        seeds, cluster = cl.seeds, spec.cluster
        if not spec.repairable:
            return ClusterRepair(record, [], cur.draft, seeds, (0, len(seeds)), cur.ref)
        medoid = ReplayCase.of(traces[cl.medoid], eods[cl.medoid])
        members = [ReplayCase.of(tr, e) for j, (tr, e) in enumerate(zip(traces, eods)) if j != cl.medoid]
        # Cluster seeds by closeness to the medoid: the order in which failing members are taken up.
        order = [seeds[j] for j in np.argsort(np.linalg.norm(cl.features - cl.features[cl.medoid], axis=1), kind="stable")]
        target = cl.medoid_failure.rollout.seed
        base, ref = cur.draft, cur.ref
        progress = len(cl.medoid_failure.rollout.milestones_reached)
        versions = [{"version": "v0", "harness": cur.ref or "bare", "successes": 0, "episodes": len(seeds),
                     "medoid_milestones": progress}]
        stack: list[Candidate] = []
        validated: list[Candidate] = []
        regression = (0, len(seeds))
        tried, depth, budget, best = 0, 0, self.cfg.max_depth, 0
        while depth < budget:
            depth += 1
            cands = self._candidates(spec, base, medoid, members, succ_traces)
            tried += len(cands)
            v = self.validate(task, round_, cluster, base, cands, target, progress)
            pick = v.found or v.step
            if pick is None or v.rollout is None:
                break
            stack.append(pick)
            base, ref = pick.apply(base), v.ref
            reg = self._rollouts(self._keys(task, seeds, v.ref, "regress"), f"r{round_} {cluster} regress", round_)
            regression = self.cfg.gate.successes(reg)
            best_before, best = best, max(best, regression[0])
            version = {"version": f"v{len(versions)}", "harness": v.ref, "successes": regression[0],
                       "episodes": regression[1], "medoid_milestones": v.progress, "seed": target,
                       "validated": v.found is not None}
            versions.append(version)
            if v.found is not None:
                validated = list(stack)
                failing = {r.seed: r for r in reg if not self.cfg.gate.won(r)}
                if not failing:
                    break
                if regression[0] > best_before:
                    budget = min(budget + 1, 2 * self.cfg.max_depth)
                # Validated on the seed under repair, not yet on the whole cluster: the next version
                # repairs the closest member this one still fails.
                target = next(s for s in order if s in failing)
                nxt = failing[target]
                progress = len(nxt.milestones_reached)
                others = [r for s_, r in failing.items() if s_ != target]
            else:
                # The next version repairs what stops the stepping stone: diagnose its own rollout.
                nxt, others = v.rollout, []
                progress = v.progress
            tr = self.store.trace(nxt)
            eod = t_eod(tr, index, self.cfg.eod)
            spec = repair_spec(f"{cluster}/{version['version']}", nxt.key,
                               self._case(tr, eod, nxt.first_missing or "<none>", base), [])
            version["diagnosis"] = spec.to_dict()
            if not spec.repairable:
                break
            medoid = ReplayCase.of(tr, eod)
            # The cluster seeds this version still fails: what the next patch's critic should also catch.
            members = [ReplayCase.of(t, t_eod(t, index, self.cfg.eod)) for t in map(self.store.trace, others)]
        self.store.record("cluster_versions", {"suite": self.cfg.suite, "task": task, "round": round_,
                                               "cluster": cluster, "versions": versions, "tried": tried},
                          ident=cluster)
        if not validated:
            return ClusterRepair(record, [], None, seeds, regression, "")
        if len(validated) < len(stack):  # stepping stones stacked after the last validated version
            last = next(v for v in reversed(versions) if v.get("validated"))
            regression, ref = (last["successes"], last["episodes"]), last["harness"]
            base = cur.draft
            for c in validated:
                base = c.apply(base)
        return ClusterRepair(record, validated, base, seeds, regression, ref)

    def _candidates(self, spec: RepairSpec, base: HarnessDraft, medoid: ReplayCase, members: Sequence[ReplayCase],
                    succ_traces: Sequence[Trace]) -> list[Candidate]:
        """Ranked patches on top of ``base``: the offline search, plus the LLM's when configured."""
        cands = search(spec, base, medoid, members, succ_traces, self.cfg.search, self.store.is_rejected,
                       self.cfg.policy_instructions)
        if self.cfg.llm is None:
            return cands
        try:
            extra, refused = propose(self.cfg.llm, spec, base, medoid, members, succ_traces, self.cfg.search,
                                     self.cfg.max_edits, self.cfg.policy_instructions)
        except LLMError as exc:
            self.store.record("llm", {"cluster": spec.cluster, "error": str(exc)})
            return cands
        extra = [c for c in extra if not self.store.is_rejected(c.apply(base).fingerprint())]
        self.store.record("llm", {"cluster": spec.cluster, "accepted": len(extra), "refused": refused})
        return extra + cands

    def _case(self, trace: Trace, eod: EOD, m_star: str, draft: HarnessDraft) -> Case:
        """A diagnosis case with the current harness's and the library's replay firings, from the last
        hand-back before t_EOD on. A critic whose playbook had used all its uses by then counts as
        silent: it could no longer act on what it saw."""
        preds, _ = library()
        start = resume_frame(trace, eod.step)
        uses = Counter(str(iv.get("evidence", "")) for iv in trace.interventions
                       if 0 <= int(iv.get("start_step", -1)) <= eod.step)
        cur_fired: dict[str, int | None] = {}
        detectable = {}
        for name, spec in preds.items():
            if name in NOT_EVIDENCE:
                continue
            defaults = {k: p.default for k, p in spec.params.items()}
            detectable[name] = first_fire(trace, spec.fn, defaults, start=start)
        for cname, c in draft.critics.items():
            plan = draft.plans.get(c.evidence)
            if plan is not None and uses[c.evidence] >= plan.max_uses:
                cur_fired[cname] = None
            elif c.template in preds:
                cur_fired[cname] = first_fire(trace, preds[c.template].fn, c.params, start=start)
        return Case(trace=trace, eod=eod, success=False, m_star=m_star, fired=cur_fired, detectable=detectable,
                    window=self.cfg.search.window)

    def _candidate_ref(self, draft: HarnessDraft) -> str:
        assert self.registry is not None
        return self.registry.publish(replace(draft, name=draft.name + "-candidate"), evidence={"candidate": True})

    def validate(self, task: str, round_: int, cluster: str, base: HarnessDraft, cands: Sequence[Candidate],
                 medoid_seed: int, progress: int) -> Validation:
        """Fresh closed-loop rollouts of the medoid with each candidate on top of ``base``.

        Returns the first candidate whose rollout succeeds (the cluster's validated patch) with its
        harness reference; failing that, the candidate that got the medoid furthest past
        ``progress`` milestones (an internal version to build on: the paper's early, stagnant v1).
        Between stepping stones that got equally far, one whose recoveries all handed back cleanly
        comes first (what stops it is a new failure a further patch can stack on, not its own
        recovery failing), then the one that left the policy more of the episode. Every candidate
        that fails the medoid is put in the rejected buffer."""
        best = Validation(None, None, "", progress, None)
        best_key: tuple[int, bool, int] = (progress, False, 0)
        if self.registry is None:
            self.store.record("validation", {"cluster": cluster, "skipped": "no harness registry: candidates "
                                             "cannot run closed-loop", "candidates": [c.to_dict() for c in cands]})
            return best
        for cand in cands:
            draft = cand.apply(base)
            ref = self._candidate_ref(draft)
            medoid = self._rollouts(self._keys(task, [medoid_seed], ref, "validate"), f"r{round_} {cluster} validate",
                                    round_)[0]
            reached = len(medoid.milestones_reached)
            self.store.record("validation", {"cluster": cluster, "candidate": cand.to_dict(), "ref": ref,
                                             "medoid_success": medoid.success, "medoid_milestones": reached,
                                             "in_control_at_success": medoid.in_control_at_success,
                                             "validated": self.cfg.gate.won(medoid),
                                             "base_milestones": progress}, ident=f"{cluster}/{ref}")
            if self.cfg.gate.won(medoid):
                return Validation(cand, None, ref, reached, medoid)
            if medoid.success:
                # The recovery finished the task and never handed back: no patch, no stepping stone.
                self.store.reject(draft.fingerprint(), cluster, "the medoid succeeded with an intervention still in "
                                  "control: it never handed back to the policy")
                continue
            self.store.reject(draft.fingerprint(), cluster, "fresh closed-loop rollout of the medoid failed")
            key = step_rank(reached, self.store.trace(medoid).interventions, medoid.recovery_steps)
            if reached > progress and key > best_key:
                best, best_key = Validation(None, cand, ref, reached, medoid), key
        return best

    def gate(self, task: str, round_: int, cur: TaskState, repairs: Sequence["ClusterRepair"],
             specs: Sequence[dict[str, Any]]) -> None:
        """Consolidate the clusters' validated stacks, regress on every seed of the clusters kept, compare
        on held-out seeds, admit or reject.

        Consolidation is a pass over the clusters, largest first: each one's stack already solved all
        of its own seeds (historical regression, measured with its internal versions); it joins the
        merged harness only if the merged harness still solves every seed of every cluster joined so
        far. The result faces the held-out gate once."""
        assert self.registry is not None
        ordered = sorted(repairs, key=lambda r: (-len(r.seeds), r.record["cluster"]))
        merged, ref, seeds, stacks = ordered[0].draft, ordered[0].ref, list(ordered[0].seeds), [ordered[0].stack]
        reg = self._rollouts(self._keys(task, seeds, ref, "regress"), f"r{round_} {task} regression", round_)
        for nxt in ordered[1:]:
            trial = consolidate(cur.draft, [*stacks, nxt.stack])
            if self.store.is_rejected(trial.fingerprint()):
                continue
            trial_ref = self._candidate_ref(trial)
            trial_seeds = sorted(set(seeds) | set(nxt.seeds))
            trial_reg = self._rollouts(self._keys(task, trial_seeds, trial_ref, "regress"),
                                       f"r{round_} {task} regression", round_)
            why = regression_gate(trial_reg, self.cfg.gate)
            self.store.record("consolidation", {"suite": self.cfg.suite, "task": task, "round": round_,
                                                "cluster": nxt.record["cluster"], "candidate": trial_ref,
                                                "regression": list(self.cfg.gate.successes(trial_reg)),
                                                "joined": why is None,
                                                "reason": why or ""}, ident=trial.fingerprint())
            if why is not None:
                self.store.reject(trial.fingerprint(), f"{task}/r{round_}", why)
                continue
            merged, ref, seeds, reg = trial, trial_ref, trial_seeds, trial_reg
            stacks.append(nxt.stack)
        patches = [p for st in stacks for p in st]
        fp = merged.fingerprint()
        if self.store.is_rejected(fp):
            return
        dev_seeds = self.store.seeds(self.cfg.suite, task, DEV)
        control = self._rollouts(self._keys(task, dev_seeds, ref, "control"), f"r{round_} {task} do-nothing control",
                                 round_, self.control_runner)
        held_seeds = self.store.seeds(self.cfg.suite, task, HELDOUT)
        held = self._rollouts(self._keys(task, held_seeds, ref, "heldout"), f"r{round_} {task} held-out", round_)
        current = self._rollouts(self._keys(task, held_seeds, cur.ref, "heldout"), f"r{round_} {task} held-out current",
                                 round_)
        bare = self._rollouts(self._keys(task, held_seeds, "", "heldout"), f"r{round_} {task} held-out bare", round_)
        verdict = judge(reg, held, current, bare, control, self.cfg.gate)
        gate_record = {"suite": self.cfg.suite, "task": task, "round": round_, "candidate": ref, "fingerprint": fp,
                       "patches": [p.to_dict() for p in patches], "verdict": verdict.to_dict()}
        self.store.record("gate", gate_record, ident=fp)
        if not verdict.admitted:
            self.store.reject(fp, f"{task}/r{round_}", verdict.reason)
            return
        evidence = {"round": round_, "clusters": list(specs), "patches": [p.to_dict() for p in patches]}
        validation = {"gate": verdict.to_dict(), "split": self.store.split_manifest(self.cfg.suite, task)}
        admitted = self.registry.publish(merged, parent=cur.ref, evidence=evidence, validation=validation)
        self.registry.pin(f"{self.cfg.suite}/{task}", admitted)
        self._keep_package(admitted)
        self.store.record("admitted", {"suite": self.cfg.suite, "task": task, "round": round_, "ref": admitted,
                                       "parent": cur.ref or "bare", "verdict": verdict.to_dict(),
                                       "draft": _draft_to(merged), "patches": [p.to_dict() for p in patches]})
        self.state[task] = TaskState(merged, admitted)
        # Held-out failures of the admitted harness are what the next round repairs: they move to
        # dev (recorded) and fresh held-out seeds replace them.
        for r in held:
            if not self.cfg.gate.won(r) and round_ < self.cfg.rounds:
                self.store.move_to_dev(self.cfg.suite, task, r.seed,
                                       f"held-out failure of {admitted} (round {round_}) feeds round {round_ + 1}")

    def _keep_package(self, ref: str) -> None:
        """A copy of an admitted version (manifest included) under <store>/harness/<ref>/, so it can be
        evaluated on another stack (`zetta eval --harness-dir`) after this one is gone."""
        assert self.registry is not None
        out = self.store.root / "harness" / ref
        for rel, data in self.registry.files(ref).items():
            (out / rel).parent.mkdir(parents=True, exist_ok=True)
            (out / rel).write_bytes(data)

    def final_eval(self, task: str) -> None:
        """The reported number, after every decision: the bare policy, the final harness and the final
        harness around the do-nothing policy, on the test seeds. Its wall time adds up the calls
        that measured this harness on these seeds: a resumed run that reads every rollout back keeps
        the time the measurement took."""
        t0 = time.time()
        seeds = self.store.seeds(self.cfg.suite, task, TEST)
        ref = self.state[task].ref
        bare = self._rollouts(self._keys(task, seeds, "", "test"), f"final {task} bare", 0)
        final = bare if not ref else self._rollouts(self._keys(task, seeds, ref, "test"), f"final {task} harness", 0)
        control = self._rollouts(self._keys(task, seeds, ref, "control-test"), f"final {task} do-nothing control", 0,
                                 self.control_runner)
        before = next((f for f in self.store.events("final") if f["suite"] == self.cfg.suite and f["task"] == task
                       and f["harness"] == (ref or "bare") and f["seeds"] == seeds), {})
        self.store.record("final", {"suite": self.cfg.suite, "task": task, "harness": ref or "bare",
                                    "bare": list(count(bare)), "final": list(count(final)), "seeds": seeds,
                                    "arms": {"bare": arm(self.store, bare), "final": arm(self.store, final),
                                             "control": arm(self.store, control)},
                                    "split": self.store.split_manifest(self.cfg.suite, task),
                                    "wall_s": float(before.get("wall_s", 0.0)) + time.time() - t0},
                          ident=f"{self.cfg.suite}/{task}")


def clusters_to_repair(clusters: Sequence[Cluster], max_clusters: int, min_cluster: int
                       ) -> tuple[list[Cluster], list[Cluster]]:
    """The clusters Loop 2 repairs (the largest ``max_clusters`` of at least ``min_cluster`` seeds) and
    the smaller ones it leaves: the gate's historical regression refuses a cluster below
    ``min_cluster`` whatever its repair does, so searching one spends validation rollouts on a
    stack that cannot be admitted. The next round clusters their failures again with its own."""
    big = [c for c in clusters if len(c.members) >= min_cluster]
    return big[:max_clusters], [c for c in clusters if len(c.members) < min_cluster]


def step_rank(reached: int, interventions: Sequence[dict[str, Any]], recovery_steps: int) -> tuple[int, bool, int]:
    """How good a stepping stone is (larger is better): milestones reached, then whether every
    recovery handed back cleanly, then how few actions recoveries took."""
    return reached, all(str(iv.get("outcome", "")) in REENTERED for iv in interventions), -recovery_steps


def env_config(suite: str, run: RunConfig) -> dict[str, Any]:
    """Session config: the suite, and the step budget when one is set, so the env worker itself ends
    episodes there (and a harness reports on them)."""
    return {"suite": suite, **policy_env_config(run.model), **({"max_steps": run.max_steps} if run.max_steps else {})}


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "_.-" else "-" for ch in name)[:120]


def _draft_to(d: HarnessDraft) -> dict[str, Any]:
    return {"name": d.name, "tasks": list(d.tasks),
            "critics": {k: {"template": c.template, "params": dict(c.params), "evidence": c.evidence, "mode": c.mode,
                            "priority": c.priority, "missing": list(c.missing), "code": c.code}
                        for k, c in d.critics.items()},
            "plans": {k: {"recovery": p.recovery, "args": dict(p.args), "max_uses": p.max_uses, "max_steps": p.max_steps,
                          "clear_when": p.clear_when, "playbook": p.playbook} for k, p in d.plans.items()},
            "reentry": [d.reentry_gamma, d.reentry_k], "runtime": [d.window, d.cooldown]}


def _draft_from(body: dict[str, Any]) -> HarnessDraft:
    return HarnessDraft(name=body["name"], tasks=tuple(body["tasks"]),
                        critics={k: CriticDraft(**{**v, "missing": tuple(v["missing"])}) for k, v in body["critics"].items()},
                        plans={k: PlanDraft(**v) for k, v in body["plans"].items()},
                        reentry_gamma=body["reentry"][0], reentry_k=body["reentry"][1],
                        **dict(zip(("window", "cooldown"), body.get("runtime", ()))))


def evaluate_transfer(store: RolloutStore, run: RunConfig, suite: str, tasks: Sequence[str], harness: str, seeds: int,
                      progress: Progress = _noop, control_model: str = "do-nothing") -> list[dict[str, Any]]:
    """Zero-shot transfer: the bare policy, ``harness`` and ``harness`` around the do-nothing policy
    on the test seeds of tasks it never saw."""
    control = replace(run, model=control_model)
    runners = {"bare": Runner(store, run, env_config(suite, run)), "harness": Runner(store, run, env_config(suite, run)),
               "control": Runner(store, control, env_config(suite, control))}
    out = []
    for task in tasks:
        store.assign_splits(suite, task, 0, 0, seeds, trained_layouts(run.model, suite))
        held = store.seeds(suite, task, TEST)
        res: dict[str, list[Rollout]] = {}
        for label, ref, purpose in (("bare", "", "test"), ("harness", harness, "test"),
                                    ("control", harness, "control-test")):
            keys = [EpisodeKey(suite, task, s, ref, purpose) for s in held]
            done = [0]

            def tick(_: Rollout, __: bool, label: str = label) -> None:
                done[0] += 1
                progress(f"{task} {label}", done[0], len(keys))

            res[label] = asyncio.run(runners[label].run(keys, 0, tick))
        rec = {"suite": suite, "task": task, "harness": harness, "bare": list(count(res["bare"])),
               "final": list(count(res["harness"])), "seeds": held, "transfer": True,
               "arms": {"bare": arm(store, res["bare"]), "final": arm(store, res["harness"]),
                        "control": arm(store, res["control"])}}
        store.record("final", rec, ident=f"{suite}/{task}/{harness}")
        out.append(rec)
    return out
