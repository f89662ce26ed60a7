"""Package critics: the retained-object check of the Goal-T2 case study.

The library's ``grasp_lost`` needs a grasp that was held; a policy that closes early and carries
nothing never had one. This critic tells transport with an empty, shut gripper from real transport.
"""

import numpy as np

from services.harness.runtime.api import Proposal, Window
from services.harness.runtime.library import tools


def critic_empty_carry(window: Window, params: dict) -> Proposal | None:
    """The gripper is shut on nothing, raised above the object, and the hand keeps travelling."""
    horizon = int(params["horizon"])
    if len(window.frames) < horizon:
        return None
    now = window.now
    if tools.grasped(now) or tools.scalar(now, "phi_gripper_aperture") > params["closed_gap"]:
        return None
    box = tools.object_box(now)  # the perception tool's estimate
    if not tools.has_box(box):
        return None
    eef = tools.vec(now, "robot0_eef_pos")
    if eef[2] - box[2] < params["min_height"]:
        return None
    travel = float(np.linalg.norm(eef - tools.vec(window.frames[-horizon], "robot0_eef_pos")))
    if travel < params["min_travel"]:
        return None
    return Proposal("critics.empty_carry", "empty_carry", "acquire",
                    {"aperture": tools.scalar(now, "phi_gripper_aperture"), "travel": travel})
