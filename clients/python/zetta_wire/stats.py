"""Success-rate statistics shared by the demo, the policy evaluation and the oracle report."""

from __future__ import annotations

import math


def wilson(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """Wilson score interval (95% by default): honest at 0/n and n/n, unlike the normal one."""
    if n == 0:
        return (0.0, 1.0)  # no trials: nothing is ruled out
    p = successes / n
    denom = 1 + z * z / n
    centre = (p + z * z / (2 * n)) / denom
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / denom
    return (max(0.0, centre - half), min(1.0, centre + half))
