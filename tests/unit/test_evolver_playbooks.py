"""Typed playbooks in the repair search: which plans a failure is offered, how they render and run,
and what the runtime gets (budgets, clearing condition, a window long enough for every critic)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from services.harness.package.loader import load_files
from services.harness.runtime.engine import HarnessRuntime
from services.harness.runtime.library import PREDICATES, RECOVERIES
from services.harness.runtime.library.playbooks import PLAYBOOKS, check_playbooks, serving
from services.evolver.diagnose import Case, repair_spec
from services.evolver.draft import CriticDraft, HarnessDraft, render
from services.evolver.eod import t_eod
from services.evolver.evolve import ClusterRepair, EvolveConfig, Evolution, step_rank
from services.evolver.gate import GateParams
from services.evolver.profile import SuccessIndex
from services.evolver.repair import Candidate, ReplayCase, SearchParams, plan_of, search
from services.evolver.replay import first_fire, resume_frame
from services.evolver.rollout import RunConfig
from services.evolver.store import EpisodeKey, Outcome, RolloutStore
from tests.unit.test_evolver_fixtures import make_trace
from tests.unit.test_evolver_store import outcome

PARENT = HarnessDraft("evolved-9", ("9",))


def test_library_playbooks_are_well_typed() -> None:
    """Every playbook runs library recoveries with in-range arguments and a library clearing predicate."""
    check_playbooks()
    assert {s for p in PLAYBOOKS.values() for s in p.steps} <= set(RECOVERIES)
    assert all(p.clear_when in PREDICATES for p in PLAYBOOKS.values() if p.clear_when)


def test_serving_matches_the_stage_and_what_the_evidence_says_about_the_grasp() -> None:
    """A playbook that needs the object in hand is never offered for a drop; for an object in hand
    the playbook written for it comes before those that let go first; otherwise the longest first;
    no pick-and-place playbook serves a drawer (instruction redirection does)."""
    assert [p.name for p in serving("reached", holding=False)] == ["acquire", "redirect"]
    assert [p.name for p in serving("on", holding=False)] == ["acquire", "redirect"]
    assert [p.name for p in serving("on", holding=True)] == ["place", "acquire", "redirect"]
    assert [p.name for p in serving("on", holding=None)] == ["place", "acquire", "redirect"]
    assert [p.name for p in serving("open")] == ["redirect"]


def test_no_playbook_runs_the_task_or_outlasts_the_intervention_cap() -> None:
    """The whole-task playbooks are gone: nothing both acquires and places, nothing exceeds the cap."""
    from services.harness.runtime.limits import INTERVENTION_CAP, REDIRECTION, intervention_cap

    assert not any("regrasp" in p.steps and "lower_until_supported_then_release" in p.steps for p in PLAYBOOKS.values())
    assert all(p.max_steps <= intervention_cap(p.steps) for p in PLAYBOOKS.values())
    assert max(p.max_steps for p in PLAYBOOKS.values() if list(p.steps) != [REDIRECTION]) <= INTERVENTION_CAP
    assert "operate_handle" not in RECOVERIES


def test_plan_of_a_playbook_carries_its_budgets_and_steps() -> None:
    """A playbook name becomes the chain of its steps with its budgets; a template name stays itself."""
    place = plan_of("place")
    assert place.recovery.split("+") == list(PLAYBOOKS["place"].steps) and place.playbook == "place"
    assert (place.max_steps, place.max_uses) == (PLAYBOOKS["place"].max_steps, PLAYBOOKS["place"].max_uses)
    acquire = plan_of("acquire", {"regrasp": {"max_attempts": 2}})
    assert acquire.recovery == "regrasp" and acquire.clear_when == "grasp_retained"
    assert acquire.args == {"max_attempts": 2}
    assert plan_of("pregrasp").playbook == "" and plan_of("pregrasp").recovery == "pregrasp"


def test_a_policy_that_never_reaches_the_object_is_offered_acquisition_then_redirection() -> None:
    """A miss cluster (m* = reached, no success to compare with) gets a non_approach critic paired
    first with a bounded acquisition, then with instruction redirection, granted at every
    pick-and-place stage; nothing that needs the object in hand is offered."""
    misses = [make_trace("miss", s) for s in range(4, 8)]
    index = SuccessIndex.build([])
    eods = [t_eod(t, index) for t in misses]
    detect = {n: first_fire(misses[0], p.fn, {k: v.default for k, v in p.params.items()})
              for n, p in PREDICATES.items() if n not in ("grasp_retained", "supported_placement")}
    spec = repair_spec("9/r1/K1", "key", Case(misses[0], eods[0], False, "reached(a)", {}, detect, 40), [])
    medoid = ReplayCase(misses[0], eods[0].step, eods[0].referenced)
    members = [ReplayCase(t, e.step, e.referenced) for t, e in zip(misses[1:], eods[1:])]
    cands = search(spec, PARENT, medoid, members, [], SearchParams(max_candidates=4))
    assert [c.plan.playbook for c in cands[:2]] == ["acquire", "redirect"]
    assert cands[0].critic.template == "non_approach" and cands[0].coverage == 1.0
    assert {"reached", "on"} <= set(cands[0].critic.missing)
    assert all(c.plan.playbook != "place" for c in cands)
    runtime = HarnessRuntime(load_files(render(cands[0].apply(PARENT))))
    plan = runtime.plans["acquire_on_non_approach"]
    assert plan.max_steps == PLAYBOOKS["acquire"].max_steps and plan.max_uses == PLAYBOOKS["acquire"].max_uses


def test_rendered_window_covers_every_critic_horizon() -> None:
    """The runtime gives critics at least their horizon in frames (a longer one would never fire
    there, though the replay saw it fire), and the plan's clearing condition reaches the runtime."""
    d = PARENT.with_patch({"c_stalled_progress": CriticDraft("stalled_progress", {"horizon": 120, "min_motion": 0.1},
                                                             "stalled_progress", "acquire")},
                          {"stalled_progress": plan_of("acquire")})
    runtime = HarnessRuntime(load_files(render(d)))
    assert d.window_frames() == 121 and runtime.window_size == 121
    assert runtime.cooldown == PARENT.cooldown
    assert runtime.plans["acquire_on_stalled_progress"].clear_when is not None
    assert HarnessRuntime(load_files(render(PARENT))).window_size == PARENT.window


def test_a_cluster_repair_passes_only_when_validated_and_solving_its_whole_cluster() -> None:
    """Historical regression is measured per cluster with its own stack; 4/5 does not pass at 100 %;
    a cluster of fewer than 3 seeds never passes."""
    cand = Candidate("c_non_approach", CriticDraft("non_approach", {}, "non_approach", "acquire"), plan_of("acquire"),
                     40, 1.0, 0.0, 2)
    assert ClusterRepair({}, [cand], cand.apply(PARENT), [1, 2, 3], (3, 3), "e@1").passes(GateParams(1.0))
    assert not ClusterRepair({}, [cand], cand.apply(PARENT), [1, 2, 3, 4, 5], (4, 5), "e@1").passes(GateParams(1.0))
    assert ClusterRepair({}, [cand], cand.apply(PARENT), [1, 2, 3, 4, 5], (4, 5), "e@1").passes(GateParams(0.8))
    assert not ClusterRepair({}, [], None, [1], (0, 1), "").passes(GateParams(0.0))
    # One- and two-seed clusters prove nothing, whatever they solve.
    assert not ClusterRepair({}, [cand], cand.apply(PARENT), [1, 2], (2, 2), "e@1").passes(GateParams(1.0))


def test_reference_index_takes_dev_successes_of_any_harness_but_never_heldout(tmp_path: Path) -> None:
    """With a bare policy that never succeeds, I_succ comes from harnessed successes on dev seeds;
    a held-out success, even on a seed that later moved to dev, never enters."""
    store = RolloutStore(tmp_path)
    dev, held = store.assign_splits("g", "9", dev=3, heldout=2)
    profile = [store.add(EpisodeKey("g", "9", s, "", "profile"), outcome("miss", s)) for s in dev]
    store.add(EpisodeKey("g", "9", dev[0], "e-candidate@1", "validate"), outcome("success", 1))
    store.add(EpisodeKey("g", "9", dev[1], "e-candidate@1", "regress"), outcome("success", 2))
    store.add(EpisodeKey("g", "9", held[0], "e@1", "heldout"), outcome("success", 3))
    store.move_to_dev("g", "9", held[0], "test")
    evo = Evolution(EvolveConfig("g", ("9",)), store, RunConfig(gateway="127.0.0.1:1"), None)
    index = evo._reference_index("9", profile)
    assert index.rollouts == 2 and index.states


def test_stepping_stones_rank_by_progress_then_clean_hand_backs() -> None:
    """Equally far, a stone whose recoveries handed back beats one whose recovery failed (a further
    patch can stack on it), and fewer recovery actions break the last tie; progress comes first."""
    failed = [{"outcome": "recovery_failed: fine_alignment: blocked short of the target"}]
    clean = [{"outcome": "reentered"}]
    assert step_rank(3, clean, 80) > step_rank(3, failed, 10)
    assert step_rank(3, clean, 10) > step_rank(3, clean, 80)
    assert step_rank(4, failed, 200) > step_rank(3, clean, 0)


def test_replay_resumes_after_the_last_hand_back_before_the_failure() -> None:
    """What a new critic must catch is what followed the last intervention that ended before t_EOD."""
    tr = make_trace("drop", 4)
    tr.interventions = [{"evidence": "grasp_lost", "start_step": 10, "end_step": 30, "outcome": "reentered"}]
    assert resume_frame(tr, 50) == 16 and tr.frame_step[16] == 32
    assert resume_frame(tr, 20) == 0  # not over yet at step 20
    assert resume_frame(make_trace("drop", 4), 50) == 0


def test_a_critic_whose_playbook_is_used_up_counts_as_silent(tmp_path: Path) -> None:
    """Diagnosing a stepping stone: its critic fired again after its one use, but could not act; the
    diagnosis treats it as silent, so the failure is a critic-layer miss a new critic can fill."""
    tr = make_trace("drop", 4)
    tr.interventions = [{"evidence": "grasp_lost", "start_step": 2, "end_step": 4, "outcome": "reentered"}]
    eod = t_eod(tr, SuccessIndex.build([make_trace("success", s) for s in range(4)]))
    critic = CriticDraft("grasp_lost", {"confirm": 3, "min_held": 5}, "grasp_lost", "acquire")
    evo = Evolution(EvolveConfig("g", ("9",)), RolloutStore(tmp_path), RunConfig(gateway="127.0.0.1:1"), None)
    once = PARENT.with_patch({"c_grasp_lost": critic}, {"grasp_lost": plan_of("acquire")})
    again = PARENT.with_patch({"c_grasp_lost": critic}, {"grasp_lost": plan_of("carry")})
    assert evo._case(tr, eod, "on(a,b)", once).fired["c_grasp_lost"] is None
    assert evo._case(tr, eod, "on(a,b)", again).fired["c_grasp_lost"] is not None


def test_a_plan_layer_prefers_motion_detectors_but_searches_all() -> None:
    """A blocked or stalled arm is what the plan layer saw, so those detectors come first; any other
    template may still qualify by replay instead of leaving the cluster without a candidate."""
    from services.evolver.diagnose import RepairSpec
    from services.evolver.repair import _templates_for

    spec = RepairSpec("7/r1/K1", "plan", "reached(a)", 100, "key", (), 1.0, ())
    names = _templates_for(spec, PARENT, PREDICATES)
    assert names[:2] == ["blocked_motion", "stalled_progress"] and "non_approach" in names
    assert not {"grasp_retained", "supported_placement"} & set(names)


def _finished_by_recovery(seed: int) -> Outcome:
    """A success whose trace says an intervention was still in control at the success step."""
    won = outcome("success", seed)
    held = {"id": "iv1", "recovery": "fine_alignment", "evidence": "blocked_motion", "start_step": 30,
            "end_step": 48, "outcome": "in_control_at_success", "actions": 18}
    return dataclasses.replace(won, trace=dataclasses.replace(won.trace, interventions=[held]))


class _Registry:
    """Names published drafts as the critic service does (name@version); validation only publishes."""

    def __init__(self) -> None:
        self.versions: dict[str, int] = {}

    def publish(self, draft: HarnessDraft, **_: object) -> str:
        self.versions[draft.name] = self.versions.get(draft.name, 0) + 1
        return f"{draft.name}@{self.versions[draft.name]}"


def test_a_medoid_success_a_recovery_finished_validates_only_without_require_hand_back(tmp_path: Path) -> None:
    """By default a medoid success with the recovery still in control validates its candidate (the
    paper's placement recoveries finish tasks). With ``require_hand_back`` that candidate is rejected,
    and is no stepping stone either; the next one, which handed back, is the validated one; I_succ
    leaves such a success out."""
    store = RolloutStore(tmp_path)
    dev, _ = store.assign_splits("g", "9", dev=3, heldout=1)
    strict = EvolveConfig("g", ("9",), gate=GateParams(require_hand_back=True))
    evo = Evolution(strict, store, RunConfig(gateway="127.0.0.1:1"), _Registry())  # type: ignore[arg-type]
    grasp = Candidate("c_grasp_lost", CriticDraft("grasp_lost", {"confirm": 3}, "grasp_lost", "regrasp"),
                      plan_of("regrasp"), 40, 1.0, 0.0, 1)
    approach = Candidate("c_non_approach", CriticDraft("non_approach", {}, "non_approach", "acquire"),
                         plan_of("acquire"), 40, 1.0, 0.0, 1)
    # What the two candidates' fresh rollouts of the medoid were (filed: validation reads them back).
    store.add(EpisodeKey("g", "9", dev[0], f"{PARENT.name}-candidate@1", "validate"), _finished_by_recovery(1))
    store.add(EpisodeKey("g", "9", dev[0], f"{PARENT.name}-candidate@2", "validate"), outcome("success", 2))
    v = evo.validate("9", 1, "9/r1/K1", PARENT, [grasp, approach], dev[0], 1)
    assert v.found == approach and v.ref == f"{PARENT.name}-candidate@2"
    assert store.is_rejected(grasp.apply(PARENT).fingerprint())
    first = store.events("validation")[0]
    assert first["medoid_success"] and first["in_control_at_success"] and not first["validated"]
    alone = Evolution(strict, store, RunConfig(gateway="127.0.0.1:1"), _Registry())  # type: ignore[arg-type]
    v = alone.validate("9", 1, "9/r1/K2", PARENT, [grasp], dev[0], 1)
    assert v.found is None and v.step is None
    profile = [store.add(EpisodeKey("g", "9", s, "", "profile"), outcome("miss", s)) for s in dev]
    assert evo._reference_index("9", profile).rollouts == 1  # the candidate@2 success only
    lenient = Evolution(EvolveConfig("g", ("9",)), RolloutStore(tmp_path), RunConfig(gateway="127.0.0.1:1"),
                        _Registry())  # type: ignore[arg-type]
    assert lenient.validate("9", 1, "9/r1/K3", PARENT, [grasp], dev[0], 1).found == grasp
    assert lenient._reference_index("9", profile).rollouts == 2
