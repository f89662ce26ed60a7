"""The vocabulary of the task tensors: stage kinds, milestone templates and the fixed sizes.

The env worker derives milestones from these templates and fills the task tensors; the harness and
the oracle read the one-hot tensors they index. All of them import the vocabulary from here so
they cannot disagree.
"""

from __future__ import annotations

#: Predicate kinds in the fixed order of the ``task_stage`` one-hot tensor.
STAGE_KINDS: tuple[str, ...] = ("on", "in", "open", "close", "turnon", "turnoff", "up", "other")
#: Milestone vectors in observations have this fixed length (zero-padded) so the schema does not
#: depend on the task; LIBERO's longest goal (3 predicates of pick-and-place) needs 18.
MAX_MILESTONES = 24
#: Rows of ``task_obstacle_bbox``: boxes of the obstacles near the stage's object and target (zero-padded).
OBSTACLE_SLOTS = 32

#: Milestone templates per template name: (kind, name pattern). ``{p}`` is the predicate name.
TEMPLATES: dict[str, tuple[tuple[str, str], ...]] = {
    "pick_place": (
        ("reached", "reached({x})"),
        ("grasped", "grasped({x})"),
        ("lifted", "lifted({x})"),
        ("above", "above({x},{y})"),
        ("goal", "{p}({x},{y})"),
        ("released", "released({x})"),
    ),
    "slide": (
        ("reached", "reached({x})"),
        ("contact", "contact({x})"),
        ("toward", "toward({x},{y})"),
        ("goal", "{p}({x},{y})"),
        ("released", "released({x})"),
    ),
    "articulate": (
        ("reached_handle", "reached({x}.handle)"),
        ("contact_handle", "contact({x}.handle)"),
        ("goal", "{p}({x})"),
    ),
    "lift": (
        ("reached", "reached({x})"),
        ("grasped", "grasped({x})"),
        ("lifted", "lifted({x})"),
        ("goal", "{p}({x})"),
    ),
    "predicate": (("goal", "{p}({args})"),),
}
#: Template names in the fixed order of the ``task_template`` one-hot tensor.
TEMPLATE_NAMES: tuple[str, ...] = tuple(TEMPLATES)

__all__ = ["MAX_MILESTONES", "OBSTACLE_SLOTS", "STAGE_KINDS", "TEMPLATES", "TEMPLATE_NAMES"]
