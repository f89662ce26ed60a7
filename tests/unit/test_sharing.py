"""Resource-sharing groups: slots share one compiled model and never disturb each other.

Slots of one group step the same read-only MjModel with their own MjData; LIBERO's resets write
fixture poses, which go to a per-seed model variant instead of the shared one. These tests check
the bookkeeping on a tiny model, then on real groups: one model object for many slots, template
arrays untouched by resets and steps, interleaved slots with different actions equal to solo
replays, and the same episode key giving the same episode in any slot.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest

from services.env_worker.families import ResetSpec, get_family

CREAM_CHEESE = "put_the_cream_cheese_in_the_bowl"
_TINY = """<mujoco><worldbody>
  <body name="fixture" pos="0 0 0"><geom size=".1"/></body>
  <body name="ball" pos="0 0 1"><freejoint/><geom size=".05"/></body>
</worldbody></mujoco>"""


def _writes(x: float):
    from services.env_worker.sharing import ModelWrites

    body_pos = np.zeros((3, 3))
    body_pos[1, 0] = x
    body_pos[2, 2] = 1.0
    return ModelWrites({"body_pos": body_pos})


def _arrays(model) -> dict[str, np.ndarray]:
    out = {}
    for name in dir(model):
        if name.startswith("_"):
            continue
        try:
            value = getattr(model, name)
        except Exception:  # noqa: BLE001 - some attributes are not readable on every model
            continue
        if isinstance(value, np.ndarray):
            out[name] = np.array(value)
    return out


def _unchanged(before: dict[str, np.ndarray], model) -> list[str]:
    after = _arrays(model)
    return [n for n in before if not np.array_equal(before[n], after[n], equal_nan=True)]


# ---- bookkeeping on a tiny model --------------------------------------------------------------


def test_copy_model_is_a_deep_independent_copy() -> None:
    import mujoco

    from services.env_worker.sharing import copy_model

    model = mujoco.MjModel.from_xml_string(_TINY)
    twin = copy_model(model)
    assert twin is not model and twin._address != model._address
    assert all(np.array_equal(v, getattr(twin, k)) for k, v in _arrays(model).items())
    twin.body_pos[1, 0] = 5.0
    assert model.body_pos[1, 0] == 0.0
    del twin  # owned by the bindings: freed without a crash


def test_template_variants_share_rewrite_and_copy() -> None:
    import mujoco

    from services.env_worker.sharing import ModelTemplate

    template = ModelTemplate(mujoco.MjModel.from_xml_string(_TINY), mutable=("body_pos",))
    pristine = np.array(template.model.body_pos)
    a, b, c = 1, 2, 3
    assert template.attach(a) is template.model and template.attach(b) is template.model
    # A reset that writes new values needs a model of its own: one copy, the template untouched.
    ma = template.settle(a, _writes(0.5))
    assert ma is not template.model and ma.body_pos[1, 0] == 0.5
    assert np.array_equal(template.model.body_pos, pristine)
    # Another slot with the same values shares that model: no copy.
    assert template.settle(b, _writes(0.5)) is ma
    assert template.stats()["model_copies"] == 1 and template.stats()["model_shared_hits"] == 1
    # A shared model is never rewritten: a new value for one of its users makes a new model...
    mb = template.settle(b, _writes(0.7))
    assert mb is not ma and ma.body_pos[1, 0] == 0.5 and mb.body_pos[1, 0] == 0.7
    # ... while a private one is rewritten in place (no copy, the env keeps its model object).
    assert template.settle(b, _writes(0.9)) is mb and mb.body_pos[1, 0] == 0.9
    assert template.stats()["model_copies"] == 2
    # The same values again: nothing to do.
    assert template.settle(b, _writes(0.9)) is mb
    # A model nobody uses any more is recycled instead of copying.
    template.attach(c)
    template.detach(a)  # ma is now idle
    mc = template.settle(c, _writes(0.1))
    assert mc is ma and mc.body_pos[1, 0] == 0.1
    assert template.stats()["model_copies"] == 2
    assert np.array_equal(template.model.body_pos, pristine)
    # Variants of one template are interchangeable for a renderer; an unrelated model is not.
    from services.env_worker.sharing import interchangeable

    assert interchangeable(ma, template.model) and interchangeable(mb, ma)
    assert not interchangeable(template.model, mujoco.MjModel.from_xml_string(_TINY))


def test_capture_keeps_reset_writes_off_the_model() -> None:
    from robosuite.utils.binding_utils import MjSim

    import mujoco

    from services.env_worker.sharing import ModelTemplate, TEMPLATE_ATTR, private_model_writes

    template = ModelTemplate(mujoco.MjModel.from_xml_string(_TINY), mutable=("body_pos", "body_quat"))
    sim = MjSim(template.model)
    setattr(sim, TEMPLATE_ATTR, template)
    template.attach(id(sim))
    with private_model_writes(sim):
        body = sim.model.body_name2id("fixture")  # the rest of the wrapper works as usual
        sim.model.body_pos[body] = [0.3, 0.0, 0.0]  # as LIBERO's reset writes fixture poses
        assert template.model.body_pos[body, 0] == 0.0
        sim.forward()
    assert template.model.body_pos[body, 0] == 0.0
    assert sim.model._model is not template.model and sim.model._model.body_pos[body, 0] == 0.3
    sim.forward()
    assert sim.data.body_xpos[body, 0] == pytest.approx(0.3)
    with pytest.raises(RuntimeError), private_model_writes(sim):
        sim.model.body_pos[body] = [9.0, 0.0, 0.0]
        raise RuntimeError("reset failed")
    assert sim.model._model.body_pos[body, 0] == 0.3  # a failed reset changes no model


# ---- real groups ------------------------------------------------------------------------------


def _rollout(slot, spec: ResetSpec, actions: np.ndarray) -> list[dict[str, np.ndarray]]:
    first, _ = slot.reset(spec)
    return [first] + [slot.step(a).observation for a in actions]


def _interleaved(a, b, spec_a: ResetSpec, spec_b: ResetSpec, xa: np.ndarray, xb: np.ndarray):
    out_a, _ = a.reset(spec_a)
    b.reset(spec_b)
    trace = [out_a]
    for act_a, act_b in zip(xa, xb, strict=True):
        trace.append(a.step(act_a).observation)
        b.step(act_b)
    return trace


def _same(x: list[dict[str, np.ndarray]], y: list[dict[str, np.ndarray]]) -> None:
    for t, (p, q) in enumerate(zip(x, y, strict=True)):
        for name in p:
            assert np.array_equal(p[name], q[name]), f"{name} differs at step {t}"


@pytest.fixture(scope="module")
def lift():
    family = get_family("robosuite")({"env_name": "Lift"})
    yield family
    family.close()


@pytest.fixture(scope="module")
def libero():
    family = get_family("libero")({"suite": "libero_goal", "task": CREAM_CHEESE, "settle_steps": 5})
    yield family
    family.close()


def test_lift_slots_share_one_model_and_stay_independent(lift) -> None:
    a, b, c = lift.init(), lift.init(), lift.init()
    model = a._env.sim.model._model
    assert b._env.sim.model._model is model and c._env.sim.model._model is model
    assert a._env.sim.data._data is not b._env.sim.data._data
    c.reset(ResetSpec(task="", seed=99))  # the first reset hides robosuite's sites (site_rgba), in every slot alike
    before = _arrays(model)
    rng = np.random.default_rng(0)
    xa, xb = (rng.uniform(-1, 1, (25, 7)).astype(np.float32) for _ in range(2))
    spec_a, spec_b = ResetSpec(task="", seed=1), ResetSpec(task="", seed=2)
    together = _interleaved(a, b, spec_a, spec_b, xa, xb)
    alone = _rollout(c, spec_a, xa)  # another slot, nobody else stepping
    _same(together, alone)
    assert _unchanged(before, model) == []
    stats = lift.sharing_stats()
    assert stats["models_compiled"] == 1 and stats["model_copies"] == 0
    for s in (a, b, c):
        s.close()


def test_libero_slots_share_per_seed_models_and_replay(libero) -> None:
    a, b = libero.init(), libero.init()
    template = a._env.sim.model._model
    assert b._env.sim.model._model is template
    a.reset(ResetSpec(task="", seed=99))  # the first reset hides robosuite's sites (site_rgba), in every slot alike
    before = _arrays(template)
    rng = np.random.default_rng(1)
    xa, xb = (rng.uniform(-1, 1, (20, 7)).astype(np.float32) for _ in range(2))
    spec_a, spec_b = ResetSpec(task="", seed=4, init_state_index=1), ResetSpec(task="", seed=9)
    together = _interleaved(a, b, spec_a, spec_b, xa, xb)
    # Different seeds place the fixtures differently: two private models, the template untouched.
    ma, mb = a._env.sim.model._model, b._env.sim.model._model
    assert ma is not mb and template not in (ma, mb)
    assert not np.array_equal(ma.body_pos, mb.body_pos)
    assert _unchanged(before, template) == []
    # The same key in the other slot (whose model must change) replays the episode exactly...
    _same(together, _rollout(b, spec_a, xa))
    # ... and then both slots run that seed on one shared model.
    assert b._env.sim.model._model is a._env.sim.model._model
    assert libero.sharing_stats()["model_copies"] <= 2
    # Only the declared arrays differ between a variant and the template.
    changed = {n for n in before if not np.array_equal(before[n], getattr(ma, n), equal_nan=True)}
    assert changed <= {"body_pos", "body_quat"}
    a.close()
    b.close()


def test_libero_reset_matches_a_private_model_copy(libero) -> None:
    """Capturing the fixture writes changes nothing: same state as an env writing its own model."""
    slot = libero.init()
    spec = ResetSpec(task="", seed=21, init_state_index=3)
    slot.reset(spec)
    shared_qpos = np.array(slot._env.sim.data.qpos)
    shared_model = slot._env.sim.model._model
    # Replay the same reset on a private copy with capture switched off (the pre-sharing path).
    env = slot._env
    template = env.sim._zetta_template
    private = copy.copy(template.model)
    env.sim.model._model = private
    env.sim._zetta_template = None
    try:
        slot.reset(spec)
        assert np.array_equal(private.body_pos, shared_model.body_pos)
        assert np.array_equal(env.sim.data.qpos, shared_qpos)
    finally:
        env.sim._zetta_template = template
        env.sim.model._model = shared_model
    slot.close()
