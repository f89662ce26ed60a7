"""The do-nothing policy of the controls: served by name, zero actions for every row."""

from __future__ import annotations

import numpy as np

from services.policy_worker.models.base import load_model


def test_do_nothing_is_a_served_model_that_outputs_zero_actions() -> None:
    model = load_model("do-nothing")
    batch = {"robot0_eef_pos": np.random.default_rng(0).normal(size=(3, 3)).astype(np.float32)}
    actions = model.infer(batch, ["put the bowl on the plate"] * 3)
    assert actions.shape == (3, model.chunk_size, 7) and actions.dtype == np.float32 and not actions.any()
    assert [s.name for s in model.input_specs()] == ["robot0_eef_pos"]
