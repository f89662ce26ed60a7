"""The three loops end to end for a set of tasks: profile, diagnose/repair/validate, consolidate/gate.

Every rollout goes through the store first, so an interrupted evolution resumes where it stopped:
rollouts already filed are read back, never rerun; rejected candidates are never retried; admitted
versions are recorded as events and re-read on resume.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from services.evolver.cluster import Cluster, ClusterParams, cluster_failures
from services.evolver.consolidate import consolidate
from services.evolver.diagnose import Case, RepairSpec, repair_spec
from services.evolver.draft import CriticDraft, HarnessDraft, PlanDraft
from services.evolver.eod import EOD, EODParams, t_eod
from services.evolver.gate import GateParams, count, judge
from services.evolver.llm import LLMConfig, LLMError, propose
from services.evolver.profile import SuccessIndex, build_profile
from services.evolver.registry_client import RegistryClient
from services.evolver.repair import NOT_EVIDENCE, Candidate, ReplayCase, SearchParams, library, search
from services.evolver.replay import first_fire
from services.evolver.rollout import Runner, RunConfig
from services.evolver.trace import Trace
from services.evolver.store import DEV, HELDOUT, EpisodeKey, Rollout, RolloutStore

#: progress(phase, done, total): how long-running phases report to a progress bar or a gauge.
Progress = Callable[[str, int, int], None]


@dataclass(frozen=True)
class EvolveConfig:
    """One evolution: where, what, how much."""

    suite: str
    tasks: tuple[str, ...]
    rounds: int = 1
    dev_seeds: int = 50
    heldout_seeds: int = 20
    name: str = "evolved"
    max_clusters: int = 2
    eod: EODParams = EODParams()
    cluster: ClusterParams = ClusterParams()
    search: SearchParams = SearchParams()
    gate: GateParams = GateParams()
    llm: LLMConfig | None = None
    max_edits: int = 3
    #: Internal versions stacked per cluster and round while no candidate succeeds on the medoid.
    max_depth: int = 2


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


def _noop(phase: str, done: int, total: int) -> None:
    return None


class Evolution:
    """Runs :class:`EvolveConfig` against a stack (gateway + critic registry) into a store."""

    def __init__(self, cfg: EvolveConfig, store: RolloutStore, run: RunConfig, registry: RegistryClient | None,
                 progress: Progress = _noop) -> None:
        self.cfg = cfg
        self.store = store
        self.runner = Runner(store, run, env_config(cfg.suite, run))
        self.run_cfg = run
        self.registry = registry
        self.progress = progress
        self.state = {t: TaskState(HarnessDraft(name=_safe(f"{cfg.name}-{t}"), tasks=(t,))) for t in cfg.tasks}
        self._restore()

    # ---- bookkeeping -----------------------------------------------------------------------------

    def _restore(self) -> None:
        """Re-read admitted versions from the store's events (resume)."""
        for ev in self.store.events("admitted"):
            if ev["suite"] == self.cfg.suite and ev["task"] in self.state:
                self.state[ev["task"]] = TaskState(_draft_from(ev["draft"]), ev["ref"])

    def _rollouts(self, keys: Sequence[EpisodeKey], phase: str, round_: int) -> list[Rollout]:
        total = len(keys)
        done = [0]

        def tick(_: Rollout, __: bool) -> None:
            done[0] += 1
            self.progress(phase, done[0], total)

        self.progress(phase, 0, total)
        return asyncio.run(self.runner.run(keys, round_, tick))

    def _keys(self, task: str, seeds: Sequence[int], ref: str, purpose: str) -> list[EpisodeKey]:
        return [EpisodeKey(self.cfg.suite, task, s, ref, purpose) for s in seeds]

    # ---- the loops ---------------------------------------------------------------------------------

    def run(self) -> None:
        """Every round for every task, then the final held-out evaluation."""
        for task in self.cfg.tasks:
            self.store.assign_splits(self.cfg.suite, task, self.cfg.dev_seeds, self.cfg.heldout_seeds)
        for round_ in range(1, self.cfg.rounds + 1):
            for task in self.cfg.tasks:
                if any(e["round"] == round_ and e["task"] == task and e["suite"] == self.cfg.suite
                       for e in self.store.events("round_done")):
                    continue
                self.round(task, round_)
        for task in self.cfg.tasks:
            self.final_eval(task)

    def round(self, task: str, round_: int) -> None:
        """Loop 1 on dev seeds with the current harness, then Loop 2 and Loop 3 on its failures."""
        t0 = time.time()
        cur = self.state[task]
        dev = self.store.seeds(self.cfg.suite, task, DEV)
        rollouts = self._rollouts(self._keys(task, dev, cur.ref, "profile"), f"r{round_} {task} profile", round_)
        prof = build_profile(self.store, rollouts, self.cfg.suite, task, cur.ref)
        self.store.record("profile", {"suite": self.cfg.suite, "task": task, "round": round_, "harness": cur.ref or "bare",
                                      "successes": prof.successes, "episodes": len(rollouts),
                                      "manifest": prof.manifest()}, ident=f"{self.cfg.suite}/{task}/{round_}")
        patches: list[Candidate] = []
        cluster_seeds: list[int] = []
        specs: list[dict[str, Any]] = []
        if prof.failures:
            traces = [self.store.trace(f.rollout) for f in prof.failures]
            eods = [t_eod(tr, prof.index, self.cfg.eod) for tr in traces]
            budget = max(r.steps for r in rollouts)
            clusters = cluster_failures(prof.failures, traces, eods, prof.index, budget, self.cfg.cluster)
            succ_traces = [self.store.trace(r) for r in rollouts if r.success]
            for cl in clusters[: self.cfg.max_clusters]:
                idx = [prof.failures.index(f) for f in cl.members]
                record, found = self._repair_cluster(task, round_, cur, cl, [traces[i] for i in idx],
                                                     [eods[i] for i in idx], succ_traces, prof.index)
                specs.append(record)
                if found:
                    patches.extend(found)
                    cluster_seeds.extend(cl.seeds)
        if patches:
            self.gate(task, round_, cur, patches, sorted(set(cluster_seeds)), specs)
        self.store.record("round_done", {"suite": self.cfg.suite, "task": task, "round": round_,
                                         "wall_s": time.time() - t0, "patches": len(patches)})

    def _repair_cluster(self, task: str, round_: int, cur: TaskState, cl: Cluster, traces: Sequence[Trace],
                        eods: Sequence[EOD], succ_traces: Sequence[Trace],
                        index: SuccessIndex) -> tuple[dict[str, Any], list[Candidate]]:
        """Diagnose one cluster's medoid, search patches for its repair spec and validate them, stacking
        up to ``max_depth`` internal versions (v1 = the candidate that got the medoid furthest, v2 =
        a patch on top of it for what stopped v1, diagnosed on v1's own medoid rollout, ...) until one
        succeeds on the medoid; returns the cluster's record and the stacked patches when the last
        one was validated (else none)."""
        cases = [self._case(tr, e, f.m_star, cur.draft) for tr, e, f in zip(traces, eods, cl.members)]
        spec = repair_spec(f"{task}/r{round_}/{cl.cid}", cl.medoid_failure.rollout.key, cases[cl.medoid],
                           [c for j, c in enumerate(cases) if j != cl.medoid])
        record = {"suite": self.cfg.suite, "task": task, "round": round_, "cluster": spec.cluster,
                  "size": len(cl.members), "seeds": cl.seeds, "medoid_seed": cl.medoid_failure.rollout.seed,
                  "spec": spec.to_dict(), "eods": [e.to_dict() for e in cl.eods]}
        self.store.record("cluster", record, ident=spec.cluster)
        if not spec.repairable:
            return record, []
        medoid = ReplayCase(traces[cl.medoid], eods[cl.medoid].step, eods[cl.medoid].referenced)
        members = [ReplayCase(tr, e.step, e.referenced)
                   for j, (tr, e) in enumerate(zip(traces, eods)) if j != cl.medoid]
        seeds, medoid_seed, cluster = cl.seeds, cl.medoid_failure.rollout.seed, spec.cluster
        base = cur.draft
        progress = len(cl.medoid_failure.rollout.milestones_reached)
        versions = [{"version": "v0", "harness": cur.ref or "bare", "successes": 0, "episodes": len(seeds),
                     "medoid_milestones": progress}]
        stack: list[Candidate] = []
        tried = 0
        for _ in range(self.cfg.max_depth):
            cands = self._candidates(spec, base, medoid, members, succ_traces)
            tried += len(cands)
            v = self.validate(task, round_, cluster, base, cands, medoid_seed, progress)
            pick = v.found or v.step
            if pick is None or v.rollout is None:
                break
            stack.append(pick)
            base = pick.apply(base)
            reg = self._rollouts(self._keys(task, seeds, v.ref, "regress"), f"r{round_} {cluster} regress", round_)
            s_, n_ = count(reg)
            version = {"version": f"v{len(versions)}", "harness": v.ref, "successes": s_, "episodes": n_,
                       "medoid_milestones": v.progress, "validated": v.found is not None}
            versions.append(version)
            if v.found is not None:
                break
            # The next version repairs what stops the stepping stone: diagnose its own medoid rollout.
            progress = v.progress
            tr = self.store.trace(v.rollout)
            eod = t_eod(tr, index, self.cfg.eod)
            spec = repair_spec(f"{cluster}/{version['version']}", v.rollout.key,
                               self._case(tr, eod, v.rollout.first_missing or "<none>", base), [])
            version["diagnosis"] = spec.to_dict()
            if not spec.repairable:
                break
            medoid, members = ReplayCase(tr, eod.step, eod.referenced), []
        self.store.record("cluster_versions", {"suite": self.cfg.suite, "task": task, "round": round_,
                                               "cluster": cluster, "versions": versions, "tried": tried},
                          ident=cluster)
        validated = bool(stack) and versions[-1].get("validated", False)
        return record, stack if validated else []

    def _candidates(self, spec: RepairSpec, base: HarnessDraft, medoid: ReplayCase, members: Sequence[ReplayCase],
                    succ_traces: Sequence[Trace]) -> list[Candidate]:
        """Ranked patches on top of ``base``: the offline search, plus the LLM's when configured."""
        cands = search(spec, base, medoid, members, succ_traces, self.cfg.search, self.store.is_rejected)
        if self.cfg.llm is None:
            return cands
        try:
            extra, refused = propose(self.cfg.llm, spec, base, medoid, members, succ_traces, self.cfg.search,
                                     self.cfg.max_edits)
        except LLMError as exc:
            self.store.record("llm", {"cluster": spec.cluster, "error": str(exc)})
            return cands
        extra = [c for c in extra if not self.store.is_rejected(c.apply(base).fingerprint())]
        self.store.record("llm", {"cluster": spec.cluster, "accepted": len(extra), "refused": refused})
        return extra + cands

    def _case(self, trace: Trace, eod: EOD, m_star: str, draft: HarnessDraft) -> Case:
        """A diagnosis case with the current harness's and the library's replay firings."""
        preds, _ = library()
        cur_fired = {}
        detectable = {}
        for name, spec in preds.items():
            if name in NOT_EVIDENCE:
                continue
            defaults = {k: p.default for k, p in spec.params.items()}
            detectable[name] = first_fire(trace, spec.fn, defaults)
        for cname, c in draft.critics.items():
            if c.template in preds:
                cur_fired[cname] = first_fire(trace, preds[c.template].fn, c.params)
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
        Every candidate that fails the medoid is put in the rejected buffer."""
        best = Validation(None, None, "", progress, None)
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
                                             "base_milestones": progress}, ident=f"{cluster}/{ref}")
            if medoid.success:
                return Validation(cand, None, ref, reached, medoid)
            self.store.reject(draft.fingerprint(), cluster, "fresh closed-loop rollout of the medoid failed")
            if reached > best.progress:
                best = Validation(None, cand, ref, reached, medoid)
        return best

    def gate(self, task: str, round_: int, cur: TaskState, patches: Sequence[Candidate], seeds: Sequence[int],
             specs: Sequence[dict[str, Any]]) -> None:
        """Consolidate, regress on every cluster seed, compare on held-out seeds, admit or reject."""
        assert self.registry is not None
        merged = consolidate(cur.draft, patches)
        fp = merged.fingerprint()
        if self.store.is_rejected(fp):
            return
        ref = self._candidate_ref(merged)
        reg = self._rollouts(self._keys(task, seeds, ref, "regress"), f"r{round_} {task} regression", round_)
        held_seeds = self.store.seeds(self.cfg.suite, task, HELDOUT)
        held = self._rollouts(self._keys(task, held_seeds, ref, "heldout"), f"r{round_} {task} held-out", round_)
        current = self._rollouts(self._keys(task, held_seeds, cur.ref, "heldout"), f"r{round_} {task} held-out current",
                                 round_)
        bare = self._rollouts(self._keys(task, held_seeds, "", "heldout"), f"r{round_} {task} held-out bare", round_)
        verdict = judge(reg, held, current, bare, self.cfg.gate)
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
            if not r.success and round_ < self.cfg.rounds:
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
        """Held-out success of the bare policy and the final harness on the final held-out seeds."""
        seeds = self.store.seeds(self.cfg.suite, task, HELDOUT)
        ref = self.state[task].ref
        bare = self._rollouts(self._keys(task, seeds, "", "heldout"), f"final {task} bare", 0)
        final = bare if not ref else self._rollouts(self._keys(task, seeds, ref, "heldout"), f"final {task} harness", 0)
        self.store.record("final", {"suite": self.cfg.suite, "task": task, "harness": ref or "bare",
                                    "bare": list(count(bare)), "final": list(count(final)), "seeds": seeds},
                          ident=f"{self.cfg.suite}/{task}")


def env_config(suite: str, run: RunConfig) -> dict[str, Any]:
    """Session config: the suite, and the step budget when one is set, so the env worker itself ends
    episodes there (and a harness reports on them)."""
    return {"suite": suite, **({"max_steps": run.max_steps} if run.max_steps else {})}


def _safe(name: str) -> str:
    return "".join(ch if ch.isalnum() or ch in "_.-" else "-" for ch in name)[:120]


def _draft_to(d: HarnessDraft) -> dict[str, Any]:
    return {"name": d.name, "tasks": list(d.tasks),
            "critics": {k: {"template": c.template, "params": dict(c.params), "evidence": c.evidence, "mode": c.mode,
                            "priority": c.priority, "missing": list(c.missing)} for k, c in d.critics.items()},
            "plans": {k: {"recovery": p.recovery, "args": dict(p.args), "max_uses": p.max_uses}
                      for k, p in d.plans.items()},
            "reentry": [d.reentry_gamma, d.reentry_k]}


def _draft_from(body: dict[str, Any]) -> HarnessDraft:
    return HarnessDraft(name=body["name"], tasks=tuple(body["tasks"]),
                        critics={k: CriticDraft(**{**v, "missing": tuple(v["missing"])}) for k, v in body["critics"].items()},
                        plans={k: PlanDraft(v["recovery"], v["args"], v["max_uses"]) for k, v in body["plans"].items()},
                        reentry_gamma=body["reentry"][0], reentry_k=body["reentry"][1])


def evaluate_transfer(store: RolloutStore, run: RunConfig, suite: str, tasks: Sequence[str], harness: str, seeds: int,
                      progress: Progress = _noop) -> list[dict[str, Any]]:
    """Zero-shot transfer: the bare policy and ``harness`` on the held-out seeds of tasks it never saw."""
    runner = Runner(store, run, env_config(suite, run))
    out = []
    for task in tasks:
        _, held = store.assign_splits(suite, task, 0, seeds)
        res = {}
        for label, ref in (("bare", ""), ("harness", harness)):
            keys = [EpisodeKey(suite, task, s, ref, "heldout") for s in held]
            done = [0]

            def tick(_: Rollout, __: bool, label: str = label) -> None:
                done[0] += 1
                progress(f"{task} {label}", done[0], len(keys))

            res[label] = count(asyncio.run(runner.run(keys, 0, tick)))
        rec = {"suite": suite, "task": task, "harness": harness, "bare": list(res["bare"]),
               "final": list(res["harness"]), "seeds": held, "transfer": True}
        store.record("final", rec, ident=f"{suite}/{task}/{harness}")
        out.append(rec)
    return out
