"""Resource-sharing groups: one compiled model per scene, shared read-only by every slot.

The paper's ModelTemplate: a group compiles a scene once and each slot forks its own ``MjData``
from it, so slots share the immutable model (a LIBERO scene is about 207 MB, 143 MB of it
textures) and keep only their simulation state private. Stepping reads the model and never
writes it, so any number of slot threads can step one shared ``MjModel`` at once.

What a reset writes into the model
    robosuite's Lift and Stack write nothing but ``site_rgba`` (every reset hides the
    visualization sites: the same values in every slot, so it may reach the shared model);
    tests/unit/test_sharing.py checks every other model array after resets and steps. LIBERO
    writes the sampled poses of its fixtures (tables, cabinets, stoves: static bodies with no
    joint) into ``model.body_pos``/``body_quat`` on every reset; the poses depend on the seed.
    A slot must not do that to a model other slots step, so:

    * :func:`capture_model_writes` hands the reset a scratch copy of those two arrays (through a
      proxy of robosuite's ``sim.model`` wrapper) instead of the model's own;
    * :meth:`ModelTemplate.settle` then finds the model that holds exactly those poses: the one
      the slot already uses (nothing to do: the usual case when an evaluation reruns one seed),
      another slot's (share it), the slot's own private model rewritten in place (no copy), an
      idle model rewritten in place, or, only when none of these exists, a fresh copy of the
      template. Models are therefore copied at most once per slot, never per reset, and slots
      whose episodes use the same seed share one model.

Copies release the GIL
    ``copy.copy(MjModel)`` holds the GIL for the whole copy (about 0.15-0.4 s for a LIBERO scene),
    which stalls the worker's event loop and its heartbeats. :func:`copy_model` calls
    ``mj_copyModel`` through ctypes, which releases the GIL, and hands the new model to the
    bindings, which take ownership of it.
"""

from __future__ import annotations

import copy
import ctypes
import hashlib
import logging
import threading
import weakref
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from services.env_worker import libmujoco
from services.env_worker.busy import busy

log = logging.getLogger(__name__)

_COPY_MODEL: Any = None
_COPY_LOCK = threading.Lock()


def _mj_copy_model() -> Any:
    global _COPY_MODEL
    with _COPY_LOCK:
        if _COPY_MODEL is None:
            import mujoco

            lib = libmujoco.library()
            if lib is None or not hasattr(mujoco.MjModel, "_from_model_ptr"):
                _COPY_MODEL = False
            else:
                fn = lib.mj_copyModel
                fn.restype = ctypes.c_void_p
                fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
                _COPY_MODEL = fn
        return _COPY_MODEL


def copy_model(model: Any) -> Any:
    """A deep copy of an ``MjModel``, made with the GIL released (``copy.copy`` as a fallback)."""
    import mujoco

    fn = _mj_copy_model()
    if fn:
        ptr = fn(None, model._address)
        if ptr:
            return mujoco.MjModel._from_model_ptr(ptr)
    with busy(5_000, "model copy"):  # holds the GIL (0.15-0.4 s for a LIBERO scene)
        return copy.copy(model)


def model_key(xml: str) -> str:
    """Key of a compiled scene: the hash of its XML."""
    return hashlib.sha256(xml.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------
# Capturing what a reset writes into the model


class _ModelWriteProxy:
    """Stands in for robosuite's ``sim.model`` wrapper during a reset.

    Reads of the captured arrays return scratch copies (so writes land there); everything else is
    the real wrapper's.
    """

    def __init__(self, real: Any, fields: Sequence[str]) -> None:
        object.__setattr__(self, "_real", real)
        object.__setattr__(self, "_scratch", {f: np.array(getattr(real._model, f)) for f in fields})

    def __getattr__(self, name: str) -> Any:
        scratch = object.__getattribute__(self, "_scratch")
        if name in scratch:
            return scratch[name]
        return getattr(object.__getattribute__(self, "_real"), name)

    def __setattr__(self, name: str, value: Any) -> None:
        scratch = object.__getattribute__(self, "_scratch")
        if name in scratch:
            scratch[name][...] = value
        else:
            setattr(object.__getattribute__(self, "_real"), name, value)


@dataclass
class ModelWrites:
    """Values a reset wrote into (a scratch copy of) model arrays, filled by :func:`capture_model_writes`."""

    values: dict[str, np.ndarray] = field(default_factory=dict)

    def key(self) -> bytes:
        """Identity of these values: models holding the same values are interchangeable."""
        digest = hashlib.sha256()
        for name in sorted(self.values):
            digest.update(name.encode())
            digest.update(np.ascontiguousarray(self.values[name]).tobytes())
        return digest.digest()


@contextmanager
def capture_model_writes(sim: Any, fields: Sequence[str]) -> Iterator[ModelWrites]:
    """Within the block, ``sim.model.<field>`` is a scratch copy; the model itself is not written.

    Physics called inside the block (``mj_step1`` in LIBERO's reset, ``sim.forward()``) still sees
    the model as it was; apply the captured values with :meth:`ModelTemplate.settle` before
    anything depends on them.
    """
    real = sim.model
    proxy = _ModelWriteProxy(real, fields)
    writes = ModelWrites()
    sim.model = proxy
    try:
        yield writes
    finally:
        sim.model = real
        writes.values = dict(object.__getattribute__(proxy, "_scratch"))


# ---------------------------------------------------------------------------------------------
# Templates and their variants


@dataclass(eq=False)
class _Variant:
    model: Any
    key: bytes
    users: set[int] = field(default_factory=set)
    pinned: bool = False  # the template itself: never rewritten


class ModelTemplate:
    """A compiled scene shared by every environment of a group that uses it.

    Environments start on the template model itself. Families whose resets write into the model
    (declared ``mutable`` fields) call :meth:`settle` after each reset with the captured values.
    """

    #: Idle private models kept for reuse (each is a full model: about 200 MB for LIBERO).
    MAX_IDLE = 2

    def __init__(self, model: Any, mutable: Sequence[str] = ()) -> None:
        self.model = model
        self.mutable = tuple(mutable)
        self._lock = threading.Lock()
        self._by_key: dict[bytes, _Variant] = {}
        self._by_user: dict[int, _Variant] = {}
        self._idle: list[_Variant] = []  # no users, still findable by key, reused oldest first
        self._base = _Variant(model, self._key_of(model), pinned=True)
        self._by_key[self._base.key] = self._base
        self._models: list[Any] = [model]  # every model of this template, kept alive with it
        _register(model, self)
        self.copies = 0
        self.rewrites = 0
        self.shared_hits = 0

    def _key_of(self, model: Any) -> bytes:
        return ModelWrites({f: getattr(model, f) for f in self.mutable}).key()

    def attach(self, user: int) -> Any:
        """Register an environment (by ``id``) on the template model; returns the model to use."""
        with self._lock:
            previous = self._by_user.get(user)
            if previous is not None:
                self._release(previous, user)
            self._base.users.add(user)
            self._by_user[user] = self._base
            return self.model

    def detach(self, user: int) -> None:
        """The environment is gone (closed or dropped): its model may be reused."""
        with self._lock:
            variant = self._by_user.pop(user, None)
            if variant is not None:
                self._release(variant, user)

    def settle(self, user: int, writes: ModelWrites) -> Any:
        """The model holding ``writes`` for environment ``user``; switches the user to it.

        Returns the model the environment must use from now on (often the one it already has).
        """
        key = writes.key()
        with self._lock:
            current = self._by_user[user]
            if current.key == key:
                return current.model
            match = self._by_key.get(key)
            if match is not None:  # another slot's model holds exactly these values: share it
                self._switch(user, current, match)
                self.shared_hits += 1
                return match.model
            if not current.pinned and current.users == {user}:  # private: rewrite in place
                self._rekey(current, key, writes)
                return current.model
            if self._idle:
                reuse = self._idle.pop(0)
                self._rekey(reuse, key, writes)
                self._switch(user, current, reuse)
                return reuse.model
        fresh = copy_model(self.model)  # outside the lock: about 0.2 s for a LIBERO scene, GIL released
        for name, value in writes.values.items():
            getattr(fresh, name)[...] = value
        with self._lock:
            self.copies += 1
            self._models.append(fresh)
            _register(fresh, self)
            current = self._by_user[user]
            match = self._by_key.get(key)
            if match is None:
                match = _Variant(fresh, key)
                self._by_key[key] = match
            self._switch(user, current, match)
            return match.model

    def holds(self, model: Any) -> bool:
        """Whether ``model`` is this template's model or one of its variants."""
        with self._lock:
            return any(m is model for m in self._models)

    def stats(self) -> dict[str, int]:
        """Models held (template included), copies made, in-place rewrites, resets that shared."""
        with self._lock:
            held = len(self._by_key)
        return {
            "models_held": held,
            "model_copies": self.copies,
            "model_rewrites": self.rewrites,
            "model_shared_hits": self.shared_hits,
        }

    # -- under the lock -----------------------------------------------------------------------

    def _rekey(self, variant: _Variant, key: bytes, writes: ModelWrites) -> None:
        self._by_key.pop(variant.key, None)
        for name, value in writes.values.items():
            getattr(variant.model, name)[...] = value
        variant.key = key
        self._by_key[key] = variant
        self.rewrites += 1

    def _switch(self, user: int, old: _Variant, new: _Variant) -> None:
        if new in self._idle:
            self._idle.remove(new)
        new.users.add(user)
        self._by_user[user] = new
        if old is not new:
            self._release(old, user)

    def _release(self, variant: _Variant, user: int) -> None:
        variant.users.discard(user)
        if variant.users or variant.pinned:
            return
        self._idle.append(variant)
        while len(self._idle) > self.MAX_IDLE:  # drop the oldest; freed once no env points at it
            dropped = self._idle.pop(0)
            if self._by_key.get(dropped.key) is dropped:
                del self._by_key[dropped.key]
            self._models = [m for m in self._models if m is not dropped.model]


def switch_model(sim: Any, model: Any) -> None:
    """Point a robosuite ``MjSim`` at another model of the same template (its data stays)."""
    if sim.model._model is not model:
        sim.model._model = model


#: id(model) -> its template, for the models made here (weak: a closed group frees its models).
_TEMPLATES_BY_MODEL: dict[int, weakref.ref[ModelTemplate]] = {}
_REGISTRY_LOCK = threading.Lock()


def _register(model: Any, template: ModelTemplate) -> None:
    with _REGISTRY_LOCK:
        for key in [k for k, ref in _TEMPLATES_BY_MODEL.items() if ref() is None]:
            del _TEMPLATES_BY_MODEL[key]
        _TEMPLATES_BY_MODEL[id(model)] = weakref.ref(template)


def interchangeable(a: Any, b: Any) -> bool:
    """Whether two models are the same template's (they differ at most in its mutable arrays).

    A renderer may then keep its GL context and uploaded textures when a slot's model changes
    from one to the other (only body poses differ); see docs/simulation.md.
    """
    if a is b:
        return True
    with _REGISTRY_LOCK:
        ra, rb = _TEMPLATES_BY_MODEL.get(id(a)), _TEMPLATES_BY_MODEL.get(id(b))
    ta, tb = ra() if ra else None, rb() if rb else None
    return ta is not None and ta is tb and ta.holds(a) and ta.holds(b)


#: Attribute of a robosuite ``MjSim`` naming the template its model comes from.
TEMPLATE_ATTR = "_zetta_template"


def template_of(sim: Any) -> ModelTemplate | None:
    """The template ``sim`` was forked from, if it came from a :class:`ModelTemplate`."""
    return getattr(sim, TEMPLATE_ATTR, None)


@contextmanager
def private_model_writes(sim: Any) -> Iterator[None]:
    """Run a reset so its model writes reach only this simulation's model (see the module doc).

    A no-op for simulations whose template declares no mutable fields. If the block raises, the
    captured values are dropped and the simulation keeps its model.
    """
    template = template_of(sim)
    if template is None or not template.mutable:
        yield
        return
    with capture_model_writes(sim, template.mutable) as writes:
        yield
    switch_model(sim, template.settle(id(sim), writes))
