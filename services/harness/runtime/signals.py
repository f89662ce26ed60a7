"""What a harness may read at run time: the whitelist of observation signals, enforced.

A runtime critic or recovery reads proprioception, physical signals (contacts, forces, grasp,
slip, the gripper's opening, commanded vs realized motion), camera images, and the task knowledge
the paper gives the orchestrator (which milestones hold, the stage being worked on). Objects are
known only through the perception tool (services/harness/runtime/perception.py). The simulator's
exact poses and the goal's object and target boxes (``task_object_*``, ``task_target_*``,
``task_motion_dir``, ``task_obstacle_bbox``, ``object_state``, the distance and velocity of the
task object) never reach a frame: :func:`visible` drops them before any package code runs, and
:func:`check_package` refuses at publish a package whose code or SKILL.md names one, so its author
learns it then, not from a critic that never fires. Offline diagnosis (the evolver) reads traces,
which keep everything.
"""

from __future__ import annotations

import ast
import re
from collections.abc import Iterable, Mapping

import numpy as np

#: Exact names a harness may read.
ALLOWED = frozenset({
    # task knowledge K: milestone truth values and the stage of the goal being worked on
    "milestones", "milestones_reached", "task_stage", "task_template", "task_grasped",
    # physical signals
    "phi_finger_contact", "phi_grasp", "phi_object_gripper_drift", "phi_contact_force", "phi_collision_intensity",
    "phi_gripper_aperture", "phi_eef_motion",
})
#: Name patterns a harness may read: proprioception and camera images.
ALLOWED_PATTERNS = (re.compile(r"^robot0_[a-z0-9_]+$"), re.compile(r"^[a-z0-9_]+_image$"),
                    re.compile(r"^[a-z0-9_]+_depth$"))
#: Names that look like observation signals: a string literal of this shape in package code that is
#: not allowed is a read of something the harness may not know.
_SIGNAL_SHAPE = re.compile(r"^(task_[a-z_]+|phi_[a-z_]+|object_state|robot0_[a-z0-9_]+)$")


def allowed(name: str) -> bool:
    """Whether a harness may read the observation tensor ``name``."""
    return name in ALLOWED or any(p.match(name) for p in ALLOWED_PATTERNS)


#: Camera tensors: a frame carries them only for a package that names them in ``[runtime]
#: signals`` (an image is most of a frame's bytes, copied to the sandbox child at every step).
_CAMERA = re.compile(r"^[a-z0-9_]+_(image|depth)$")

#: The names a harness may read, in order, by the names an observation carries and the cameras
#: asked for (a few key sets per family): every env step filters its observation, and the
#: patterns cost more than a lookup.
_VISIBLE: dict[tuple[tuple[str, ...], frozenset[str]], tuple[str, ...]] = {}


def is_camera(name: str) -> bool:
    """Whether ``name`` is a camera tensor (an image or a depth map)."""
    return _CAMERA.match(name) is not None


def visible(obs: Mapping[str, np.ndarray], cameras: frozenset[str] = frozenset()) -> dict[str, np.ndarray]:
    """The part of an observation a harness sees: what it may read, camera tensors only when named
    in ``cameras``."""
    names = tuple(obs)
    keep = _VISIBLE.get((names, cameras))
    if keep is None:
        keep = tuple(k for k in names if allowed(k) and (k in cameras or not is_camera(k)))
        if len(_VISIBLE) < 256:
            _VISIBLE[(names, cameras)] = keep
    return {k: obs[k] for k in keep}


def denied_reads(names: Iterable[str]) -> list[str]:
    """The names that look like signals and are not on the whitelist, sorted."""
    return sorted({n for n in names if _SIGNAL_SHAPE.match(n) and not allowed(n)})


def _literals(source: str) -> list[str]:
    try:
        tree = ast.parse(source)
    except SyntaxError:
        return []  # the loader reports syntax errors
    return [n.value for n in ast.walk(tree) if isinstance(n, ast.Constant) and isinstance(n.value, str)]


def check_package(sources: Mapping[str, str], declared: Iterable[str]) -> list[str]:
    """Why a package asks for more than a harness may read: one message per file (empty: nothing).

    ``sources`` maps tools/*.py paths to their text; ``declared`` is SKILL.md ``[runtime] signals``.
    """
    problems = []
    bad = [n for n in declared if not allowed(n)]
    if bad:
        problems.append(f"SKILL.md [runtime] signals: {', '.join(sorted(bad))} may not be read at run time")
    for path, text in sorted(sources.items()):
        denied = denied_reads(_literals(text))
        if denied:
            problems.append(f"{path}: reads {', '.join(denied)}, which a harness may not read at run time")
    if problems:
        problems.append("a harness reads proprioception, physical signals (phi_grasp, phi_contact_force, ...), "
                        "milestones and task_stage; objects only through frame.perceive('object'|'target'|'others') "
                        "(docs/harness.md, 'What a harness may know')")
    return problems
