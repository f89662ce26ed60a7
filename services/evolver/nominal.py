"""The frozen policy's nominal behaviour: its successful bare rollouts on the suite it was made for.

A critic that fires on a policy doing its job is a false positive. The repair search counts false
positives on the task's own successful rollouts (I_succ), but on a variant the policy never solves
alone there are none, so a critic that fires on every episode (one that reads the arm's first
steps as a blocked motion, say) looks free there; carried to a task the policy does solve, it
interrupts every episode. The nominal set closes that gap: the bare policy on the original suite of
a LIBERO-PRO variant (libero_goal for libero_goal_task), the same scenes and robot on tasks the
policy does. Its successes join I_succ wherever the search measures false positives. It is a dev
set of another suite on the last initial states (49, 48, ...): the splits that report numbers draw
theirs from the first ones (test seeds 1-20 of the evolved suite and of every transfer suite, whose
layouts are the original suite's), so no reported episode shares a layout with a nominal one while
test or transfer seeds plus nominal seeds fit in 50 (``zetta evolve experiment`` refuses more).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from services.evolver.store import DEV, INIT_STATES, EpisodeKey, Rollout, RolloutStore

#: The rollouts' purpose in the store.
NOMINAL = "nominal"
#: LIBERO-PRO's perturbed suites are named <base>_<variant> (services/env_worker/families/libero.py).
_LIBERO_PRO_SUFFIXES = ("_task", "_swap", "_lan", "_object")
#: LIBERO-PRO perturbs LIBERO's 10-task suites (goal, spatial, object, 10): the reference runs all ten,
#: whichever of them an evolution works on, so its size and its verdicts do not depend on ``--tasks``.
ORIGINAL_TASKS = tuple(str(i) for i in range(10))


def nominal_suite(suite: str) -> str:
    """The original suite of a LIBERO-PRO variant ("" for any other suite: its own successes are
    already the policy's nominal behaviour)."""
    for suffix in _LIBERO_PRO_SUFFIXES:
        if suite.startswith("libero_") and suite.endswith(suffix):
            return suite[: -len(suffix)]
    return ""


@dataclass(frozen=True)
class NominalPlan:
    """Which nominal episodes to run: ``seeds`` per task of ``suite`` (no plan when either is empty)."""

    suite: str
    tasks: tuple[str, ...]
    seeds: int

    @classmethod
    def for_evolution(cls, suite: str, seeds: int) -> "NominalPlan":
        """The plan for an evolution on ``suite``: every task of its original suite."""
        return cls(nominal_suite(suite), ORIGINAL_TASKS, max(0, seeds))

    @property
    def empty(self) -> bool:
        return not (self.suite and self.tasks and self.seeds)

    def keys(self, store: RolloutStore) -> list[EpisodeKey]:
        """The episode keys, after fixing their seeds as dev seeds of the nominal suite."""
        if self.empty:
            return []
        seeds = nominal_seeds(self.seeds)
        out = []
        for task in self.tasks:
            store.assign_seeds(self.suite, task, DEV, seeds)
            out += [EpisodeKey(self.suite, task, s, "", NOMINAL) for s in seeds]
        return out


def nominal_seeds(n: int) -> list[int]:
    """The ``n`` seeds of the reference, on the last initial states: 49, 48, ..."""
    if not 0 <= n <= INIT_STATES:
        raise ValueError(f"nominal seeds: {n} is not between 0 and {INIT_STATES} (LIBERO's initial states per task)")
    return [INIT_STATES - 1 - i for i in range(n)]


def summary(plan: NominalPlan, rollouts: Sequence[Rollout]) -> dict[str, object]:
    """The event a store records about the set (the results page reports it)."""
    return {"suite": plan.suite, "tasks": list(plan.tasks), "seeds_per_task": plan.seeds,
            "seeds": sorted({r.seed for r in rollouts}), "episodes": len(rollouts),
            "successes": sum(1 for r in rollouts if r.success)}

