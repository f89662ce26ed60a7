"""The bounds every harness runs under, whatever its package asks for.

A recovery corrects the policy; it must never become the solver. One intervention may take at most
:data:`INTERVENTION_CAP` actions: 80 is about a quarter of LIBERO-Goal's 300-step episode budget,
enough for a regrasp (restage, pregrasp, descend, close, lift check: 40-70 steps measured) or a
placement (align, lower, release, retreat: 30-60), far too few to carry an object across the
table and place it from a standing start. A playbook whose ``max_steps`` is larger is refused at
publish.
"""

from __future__ import annotations

#: Most actions one intervention may take (see the module docstring for why 80).
INTERVENTION_CAP = 80
