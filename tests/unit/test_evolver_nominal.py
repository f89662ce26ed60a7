"""The nominal reference: which suite and seeds it uses, that it never touches a split of the
evolved suite, that its successes count as false positives in the repair search, and how the
results page reports it."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.evolver import results
from services.evolver.nominal import NOMINAL, NominalPlan, nominal_seeds, nominal_suite, summary
from services.evolver.repair import SearchParams, search
from services.evolver.store import DEV, HELDOUT, TEST, EpisodeKey, RolloutStore, StoreError
from tests.unit.test_evolver_fixtures import make_trace
from tests.unit.test_evolver_repair import PARENT, drop_cluster
from tests.unit.test_evolver_results import SUITE, experiment
from tests.unit.test_evolver_store import outcome


@pytest.mark.parametrize("suite, base", [("libero_goal_task", "libero_goal"), ("libero_goal_swap", "libero_goal"),
                                         ("libero_goal_lan", "libero_goal"), ("libero_spatial_object", "libero_spatial"),
                                         ("libero_goal", ""), ("robosuite_lift", ""), ("libero_10", "")])
def test_the_nominal_suite_is_a_variants_original(suite: str, base: str) -> None:
    assert nominal_suite(suite) == base


def test_the_plan_runs_every_task_of_the_original_suite_on_its_last_initial_states(tmp_path: Path) -> None:
    """Two seeds per task, dev seeds 49 and 48 of libero_goal's ten tasks (the last initial states:
    test seeds take the first), fixed once and whatever tasks the evolution works on; the evolved
    suite's splits are untouched; an original suite or 0 seeds plan nothing."""
    store = RolloutStore(tmp_path)
    store.assign_splits("libero_goal_task", "8", 10, 10, 20)
    plan = NominalPlan.for_evolution("libero_goal_task", 2)
    keys = plan.keys(store)
    assert [(k.suite, k.task, k.seed, k.harness, k.purpose) for k in keys] == [
        ("libero_goal", str(t), s, "", NOMINAL) for t in range(10) for s in (49, 48)]
    assert plan.keys(store) == keys
    for task in map(str, range(10)):
        assert (store.seeds("libero_goal", task, DEV), store.seeds("libero_goal", task, HELDOUT),
                store.seeds("libero_goal", task, TEST)) == ([48, 49], [], [])
    assert len(store.seeds("libero_goal_task", "8", TEST)) == 20
    store.add(keys[0], outcome("success", 1))
    store.add(keys[1], outcome("miss", 2))
    rows = [store.get(k) for k in keys[:2]]
    assert summary(plan, [r for r in rows if r]) == {"suite": "libero_goal", "tasks": [str(t) for t in range(10)],
                                                     "seeds_per_task": 2, "seeds": [48, 49], "episodes": 2,
                                                     "successes": 1}
    assert NominalPlan.for_evolution("libero_goal", 2).empty
    assert NominalPlan.for_evolution("libero_goal_task", 0).keys(store) == []


def test_a_critic_that_fires_on_nominal_successes_is_not_proposed() -> None:
    """The drop cluster's critics (non_approach and grasp_lost) fire where the object is let go;
    when the policy's nominal successes show the same signals at a stage the rules grant (an
    object let go and picked up again on a task it solves), both are false positives above the
    search's bound and no candidate uses them."""
    spec, medoid, members, succ = drop_cluster()
    found = {c.critic.template for c in search(spec, PARENT, medoid, members, succ, SearchParams(max_candidates=3))}
    assert {"grasp_lost", "non_approach"} <= found
    nominal = [make_trace("drop", s) for s in range(20, 24)]
    cands = search(spec, PARENT, medoid, members, succ + nominal, SearchParams(max_candidates=3))
    assert not {c.critic.template for c in cands} & {"grasp_lost", "non_approach"}
    assert all(c.false_positive <= SearchParams().max_false_positive for c in cands)


def test_the_results_page_reports_the_reference(tmp_path: Path) -> None:
    """The reference's rollouts are counted by purpose, kept out of the evolved task's rollout count,
    and described under the suite's table."""
    store = RolloutStore(tmp_path / SUITE)
    plan = NominalPlan(SUITE.removesuffix("_task"), ("6",), 2)
    keys = plan.keys(store)
    rows = [store.add(k, outcome("success" if k.seed == 49 else "miss", k.seed)) for k in keys]
    store.record("nominal", {"for_suite": SUITE, **summary(plan, rows)}, ident=SUITE)
    store.close()
    data = experiment(tmp_path)
    assert data["suites"][SUITE]["nominal"]["successes"] == 1
    assert data["suites"][SUITE]["tasks"][0]["rollouts"] == 3  # task 6's own: the nominal ones are libero_goal's
    assert data["rollouts_by_purpose"][SUITE]["purposes"][NOMINAL]["rollouts"] == 2
    text = results.render(data)
    assert ("False-positive reference: 1 of 2 bare-policy episodes on libero_goal (tasks 6, seeds 48-49) succeeded; "
            "a critic that fires on one counts a false positive as on the task's own successes.") in text
    assert EpisodeKey("libero_goal", "6", 49, "", NOMINAL) in keys


def test_seeds_are_the_last_initial_states_and_never_shared_with_another_split(tmp_path: Path) -> None:
    assert nominal_seeds(3) == [49, 48, 47] and nominal_seeds(0) == []
    with pytest.raises(ValueError, match="between 0 and 50"):
        nominal_seeds(51)
    store = RolloutStore(tmp_path)
    store.assign_splits("libero_goal", "2", dev=0, heldout=0, test=49)  # test seeds 1-49 hold init states 1-49
    with pytest.raises(StoreError, match="seed 49 shares initial state 49 with seed 49 of another split"):
        NominalPlan.for_evolution("libero_goal_task", 1).keys(store)


def test_an_evolver_job_asks_for_it_like_the_cli() -> None:
    """EvolutionSpec.nominal_seeds: unset selects the CLI's default, 0 runs none, a budget that would
    share a layout with a test seed is refused naming the fields."""
    from services.evolver.evolve import EvolveConfig
    from services.evolver.jobs import JobError, check_spec

    spec = {"suite": "libero_goal_task", "tasks": ["2"], "rounds": 1, "dev_seeds": 2, "heldout_seeds": 2,
            "test_seeds": 20}
    assert check_spec(spec)["nominal_seeds"] == EvolveConfig.nominal_seeds == 2
    assert check_spec({**spec, "nominal_seeds": 0})["nominal_seeds"] == 0
    with pytest.raises(JobError, match="spec.nominal_seeds 31 \\+ test_seeds 20"):
        check_spec({**spec, "nominal_seeds": 31})
