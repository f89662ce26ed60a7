"""The instruction text of a stored rollout's task, read from LIBERO's task files (no env built).

An export names each episode's task by what the robot was asked to do, as the env worker gave
it to the policy: ``task.language``, or the BDDL's language line for LIBERO-PRO's task and
language variants (which change it while ``task.language`` keeps the original).
"""

from __future__ import annotations

from collections.abc import Iterable


def libero_instructions(tasks: Iterable[tuple[str, str]]) -> dict[tuple[str, str], str]:
    """``{(suite, task): instruction}`` for LIBERO (suite, task index or name) pairs; others are left out."""
    from services.env_worker.families import libero_instruction

    out: dict[tuple[str, str], str] = {}
    for suite_name, task in set(tasks):
        text = libero_instruction(suite_name, task)
        if text is not None:
            out[(suite_name, task)] = text
    return out
