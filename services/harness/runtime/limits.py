"""The bounds every harness runs under, whatever its package asks for.

A recovery corrects the policy; it must never become the solver. One intervention may take at most
:data:`INTERVENTION_CAP` actions: 80 is about a quarter of LIBERO-Goal's 300-step episode budget,
enough for a regrasp (restage, pregrasp, descend, close, lift check: 40-70 steps measured) or a
placement (align, lower, release, retreat: 30-60), far too few to carry an object across the
table and place it from a standing start. A playbook whose ``max_steps`` is larger is refused at
publish.

An instruction redirection alone (a playbook whose only recovery is ``redirect_instruction``) has
its own cap, :data:`REDIRECTION_CAP`: while it lasts the frozen policy acts, under a sentence it was
trained on, and no recovery moves the arm, so what bounds it is the policy's own time to a
sub-goal. In the shipped VLA's nominal successes on libero_goal that is 83-140 steps from the start
to open the middle drawer and 61-102 to turn on the stove; 160 covers the slowest with margin and is
about half the episode. Those actions still count as the harness's in every report (recoveries'
share, and the redirected share beside it), so a harness that leans on long redirections shows it.
"""

from __future__ import annotations

from collections.abc import Sequence

#: Most actions one intervention may take (see the module docstring for why 80).
INTERVENTION_CAP = 80
#: Most actions one intervention that only redirects the policy may take (see the module docstring).
REDIRECTION_CAP = 160
#: The library recovery whose actions are the frozen policy's own, under another instruction.
REDIRECTION = "redirect_instruction"


def intervention_cap(steps: Sequence[str]) -> int:
    """The cap of an intervention that runs the recoveries ``steps`` in order."""
    return REDIRECTION_CAP if list(steps) == [REDIRECTION] else INTERVENTION_CAP
