"""Phase III gates: historical regression on clusters of 3 or more, the do-nothing control, then a
strict held-out improvement on the same seeds."""

from __future__ import annotations

import pytest

from services.evolver.gate import GateParams, control_gate, judge, regression_gate
from services.evolver.store import Rollout


def runs(outcomes: str, harness: str = "h@1", first_seed: int = 1) -> list[Rollout]:
    """Rollouts on consecutive seeds; '1' success, '0' failure, 'c' a success with an intervention
    still in control at the success step."""
    return [Rollout(key=f"g/6/{first_seed + i}/{harness}/heldout", suite="g", task="6", seed=first_seed + i,
                    init_state=(first_seed + i) % 50, split="heldout", harness=harness, purpose="heldout", round=1,
                    success=c in "1c", steps=100, first_missing="", milestones_reached=[], policy_steps=100,
                    recovery_steps=0, interventions=int(c == "c"), trace_path="", video_path="", wall_s=1.0,
                    in_control_at_success=c == "c")
            for i, c in enumerate(outcomes)]


#: A do-nothing control that never succeeds, on 20 dev seeds.
NOTHING = runs("0" * 20, "h@1/control")


def test_admits_only_a_strict_improvement_after_full_regression() -> None:
    """3/4 vs the current 2/4 (bare 1/4) with the whole cluster solved: admitted, delta over bare +50%."""
    v = judge(runs("111"), runs("1101"), runs("1001", "cur"), runs("1000", ""), NOTHING)
    assert v.admitted and abs(v.delta_over_bare - 0.5) < 1e-9
    assert v.to_dict()["heldout"]["wilson95"][0] < 0.75 < v.to_dict()["heldout"]["wilson95"][1]


def test_refuses_equal_or_worse_heldout() -> None:
    """Equal held-out success is not an improvement; neither is worse."""
    assert not judge(runs("111"), runs("1001"), runs("1001", "cur"), runs("0000", ""), NOTHING).admitted
    v = judge(runs("111"), runs("1000"), runs("1001", "cur"), runs("0000", ""), NOTHING)
    assert not v.admitted and "not a strict improvement" in v.reason


def test_refuses_a_candidate_that_fails_historical_regression() -> None:
    """A candidate that leaves one cluster seed failing is refused before held-out counts, by default;
    a lower regression bar is an explicit parameter."""
    v = judge(runs("110"), runs("1111"), runs("0000", "cur"), runs("0000", ""), NOTHING)
    assert not v.admitted and "historical regression 2/3" in v.reason
    assert judge(runs("110"), runs("1111"), runs("0000", "cur"), runs("0000", ""), NOTHING, GateParams(0.5)).admitted
    assert "at least 3" in (regression_gate([]) or "")
    v = judge(runs("11"), runs("1111"), runs("0000", "cur"), runs("0000", ""), NOTHING)
    assert not v.admitted and "historical regression on 2 seed(s): it needs clusters of at least 3" in v.reason


def test_refuses_a_harness_that_solves_the_task_around_a_do_nothing_policy() -> None:
    """1 of 20 dev seeds (5 %) is tolerated; 2 of 20 is a harness doing the task by itself."""
    assert control_gate(runs("1" + "0" * 19, "h@1/control")) is None
    v = judge(runs("111"), runs("1111"), runs("0000", "cur"), runs("0000", ""), runs("11" + "0" * 18, "h@1/control"))
    assert not v.admitted and "do-nothing policy succeeds on 2/20 dev seeds" in v.reason
    assert v.to_dict()["control"]["successes"] == 2
    assert "no do-nothing control" in (control_gate([]) or "")


def test_heldout_comparison_must_share_seeds() -> None:
    """Comparing success on different held-out seeds is refused outright."""
    with pytest.raises(ValueError, match="different seeds"):
        judge(runs("111"), runs("11"), runs("11", "cur", first_seed=5), runs("11", ""), NOTHING)


def test_a_success_an_intervention_finished_counts_unless_a_hand_back_is_required() -> None:
    """A success with an intervention still in control (a placement recovery that finished the task)
    counts by default, as in the paper; with ``require_hand_back`` it counts in neither the historical
    regression nor the held-out comparison. The do-nothing control counts it either way."""
    strict = GateParams(require_hand_back=True)
    assert judge(runs("11c"), runs("1111"), runs("0000", "cur"), runs("0000", ""), NOTHING).admitted
    v = judge(runs("11c"), runs("1111"), runs("0000", "cur"), runs("0000", ""), NOTHING, strict)
    assert not v.admitted and "historical regression 2/3" in v.reason
    assert judge(runs("111"), runs("cc10"), runs("1000", "cur"), runs("0000", ""), NOTHING).heldout == (3, 4)
    v = judge(runs("111"), runs("cc10"), runs("1000", "cur"), runs("0000", ""), NOTHING, strict)
    assert not v.admitted and "held-out 1/4 is not a strict improvement" in v.reason
    v = judge(runs("111"), runs("11c0"), runs("1000", "cur"), runs("0000", ""), NOTHING, strict)
    assert v.admitted and v.heldout == (2, 4)
    v = judge(runs("111"), runs("1111"), runs("0000", "cur"), runs("0000", ""), runs("cc" + "0" * 18, "h@1/control"),
              strict)
    assert not v.admitted and "do-nothing policy succeeds on 2/20 dev seeds" in v.reason


def test_an_evolver_job_and_the_cli_ask_for_a_hand_back_alike() -> None:
    """EvolutionSpec.require_hand_back and --require-hand-back reach the gate's parameters; unset,
    neither requires one."""
    import argparse

    from services.evolver.cmd_common import add_search_args, evolve_config
    from services.evolver.jobs import check_spec

    spec = {"suite": "libero_goal_task", "tasks": ["2"], "rounds": 1, "dev_seeds": 2, "heldout_seeds": 2}
    assert check_spec(spec)["require_hand_back"] is False
    assert check_spec({**spec, "require_hand_back": True})["require_hand_back"] is True
    parser = argparse.ArgumentParser()
    add_search_args(parser)
    for argv, want in (([], False), (["--require-hand-back"], True)):
        a = parser.parse_args(argv)
        assert evolve_config(a, "libero_goal_task", ("2",), "e").gate.require_hand_back is want
