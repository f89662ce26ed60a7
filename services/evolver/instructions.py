"""The instruction text of a stored rollout's task, read from LIBERO's task files (no env built).

An export names each episode's task by what the robot was asked to do, as the env worker gave
it to the policy: ``task.language``, or the BDDL's language line for LIBERO-PRO's task and
language variants (which change it while ``task.language`` keeps the original).
"""

from __future__ import annotations

from collections.abc import Iterable


def libero_instructions(tasks: Iterable[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """``{(suite, task): instruction}`` for LIBERO (suite, task index or name) pairs; others are left out."""
    from libero.libero import benchmark
    from libero.libero.envs.bddl_utils import get_problem_info

    from services.env_worker.families.libero import _BDDL_INSTRUCTION_SUFFIXES, _bddl_path, _resolve_task

    suites = benchmark.get_benchmark_dict()
    out: dict[tuple[str, str], str] = {}
    for suite_name, task in set(tasks):
        if suite_name not in suites:
            continue
        suite = suites[suite_name]()
        t = suite.get_task(_resolve_task(list(suite.get_task_names()), task))
        bddl = get_problem_info(_bddl_path(t))["language_instruction"] if suite_name.endswith(_BDDL_INSTRUCTION_SUFFIXES) else ""
        out[(suite_name, task)] = bddl or t.language
    return out
