"""A warm-up inference per model before the worker says SERVING.

Models load lazily what the first request needs (the VLA's instruction embedder, traced graphs,
allocator pools); on a busy node that first request took longer than the env workers' inference
budget. One inference on zero inputs with an instruction no checkpoint caches pulls all of it in,
so SERVING means the first real request is served in normal time.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from services.policy_worker.models.base import PolicyModel

log = logging.getLogger(__name__)

#: An instruction no checkpoint has cached, so the instruction embedder has to load.
WARM_UP_INSTRUCTION = "zetta warm-up: load the instruction embedder"


class WarmUpError(RuntimeError):
    """A model failed its warm-up inference; the message names the model."""


def zero_batch(model: PolicyModel) -> dict[str, np.ndarray]:
    """One sample of every input the model reads, all zeros (free dimensions as 1)."""
    return {s.name: np.zeros((1, *(d if d > 0 else 1 for d in s.shape)), np.dtype(s.dtype))
            for s in model.input_specs()}


def warm_up(name: str, model: PolicyModel) -> float:
    """Run one inference; returns its seconds, raises WarmUpError naming the model on failure."""
    start = time.perf_counter()
    try:
        out = np.asarray(model.infer(zero_batch(model), [WARM_UP_INSTRUCTION]))
    except Exception as exc:
        raise WarmUpError(f"model {name!r} failed its warm-up inference: {type(exc).__name__}: {exc}") from exc
    if out.ndim != 3 or out.shape[0] != 1:
        raise WarmUpError(f"model {name!r} returned shape {list(out.shape)} for one request; expected [1, chunk, dim]")
    took = time.perf_counter() - start
    log.info("model warm", extra={"fields": {"model": name, "warm_up_s": round(took, 3)}})
    return took
