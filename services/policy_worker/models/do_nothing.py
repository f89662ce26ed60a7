"""The do-nothing policy: zero actions, whatever it is shown.

It is the control of every evolution result: the same harness around a policy that never moves
must fail (services/evolver/gate.py refuses a harness whose do-nothing success on its dev seeds is
over 5 %). A zero action is a zero OSC_POSE delta with the gripper command 0, which keeps the
fingers as they are (open after a reset).
"""

from __future__ import annotations

import numpy as np

from services.common.specs import TensorSpec


class DoNothingPolicy:
    """Batched zero actions of shape [B, chunk_size, 7]."""

    name = "do-nothing"

    def __init__(self, chunk_size: int = 8) -> None:
        if chunk_size < 1:
            raise ValueError(f"chunk_size must be >= 1, got {chunk_size}")
        self.chunk_size = chunk_size

    @staticmethod
    def input_specs() -> list[TensorSpec]:
        """The only tensor read: the batch size comes from it."""
        return [TensorSpec("robot0_eef_pos", "float32", (3,))]

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """Zeros for every row."""
        return np.zeros((len(batch["robot0_eef_pos"]), self.chunk_size, 7), dtype=np.float32)
