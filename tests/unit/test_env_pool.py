"""The warm-env pool: reuse per key, and a bound on what waits so a worker visiting many LIBERO
tasks does not keep every task's environments (and their textures) forever."""

from __future__ import annotations

from services.env_worker.families.pool import EnvPool, IdleBudget
from services.env_worker.families.robosuite_lift import retire_env
from services.env_worker.sharing import TEMPLATE_ATTR


def test_parked_envs_are_reused_per_key() -> None:
    pool: EnvPool[str] = EnvPool()
    assert pool.acquire("a", lambda: "a1") == "a1" and pool.built == 1
    assert pool.release("a", "a1") == []
    assert pool.acquire("b", lambda: "b1") == "b1"
    assert pool.acquire("a", lambda: "new") == "a1" and pool.reused == 1
    assert pool.idle_count() == 0


def test_the_env_parked_longest_ago_is_evicted_beyond_the_bound() -> None:
    pool: EnvPool[str] = EnvPool(max_idle=2)
    assert pool.release(0, "t0") == [] and pool.release(1, "t1") == []
    assert pool.release(2, "t2") == ["t0"]
    assert pool.acquire(1, lambda: "new") == "t1"  # taken back: no longer a candidate for eviction
    assert pool.release(3, "t3") == []
    assert pool.release(4, "t4") == ["t2"]
    assert pool.acquire(0, lambda: "t0-again") == "t0-again"
    assert sorted(pool.drain()) == ["t3", "t4"] and pool.idle_count() == 0 and pool.evicted == 2


def test_pools_that_share_a_budget_are_bounded_together() -> None:
    """A worker's LIBERO groups (one per suite) share one bound: parking in one evicts the
    environment parked longest ago in any of them, and draining one leaves the others' parked."""
    budget = IdleBudget(max_idle=3)
    a: EnvPool[str] = EnvPool(budget=budget)
    b: EnvPool[str] = EnvPool(budget=budget)
    assert a.release(0, "a0") == [] and a.release(1, "a1") == [] and b.release(0, "b0") == []
    assert b.release(1, "b1") == ["a0"], "the oldest of either pool goes"
    assert (a.idle_count(), b.idle_count()) == (1, 2)
    assert a.acquire(0, lambda: "a0-new") == "a0-new" and a.built == 1, "an evicted env is not handed out"
    assert b.acquire(0, lambda: "new") == "b0" and b.reused == 1
    assert a.release(2, "a2") == [] and len(budget.order) == 3
    assert sorted(a.drain()) == ["a1", "a2"] and b.idle_count() == 1 and len(budget.order) == 1
    assert b.release(2, "b2") == [] and b.release(3, "b3") == [] and b.release(4, "b4") == ["b1"]
    assert b.evicted == 2 and a.evicted == 0


class _Template:
    def __init__(self) -> None:
        self.detached: list[int] = []

    def detach(self, user: int) -> None:
        self.detached.append(user)


class _Sim:
    pass


class _Env:
    def __init__(self) -> None:
        self.sim = _Sim()
        self.closed = False

    def close(self) -> None:
        self.closed = True


def test_a_retired_env_lets_go_of_its_model_and_closes() -> None:
    env, template = _Env(), _Template()
    setattr(env.sim, TEMPLATE_ATTR, template)
    retire_env(env)
    assert template.detached == [id(env.sim)] and env.closed
