"""Configuration fails fast and names the variable: EnvReader and each service's from_env.

Every service reads its settings once at start-up; these tests pin down that a typo surfaces as a
ConfigError that names the variable (all of them at once), never as a silent default.
"""

from __future__ import annotations

import pytest

from services.common.config import ConfigError, EnvReader
from services.common.policies import DEFAULT_POLICY
from services.common.cpus import usable_cpus
from services.env_worker.config import EnvWorkerConfig
from services.env_worker.policy_client import InferHold
from services.gateway.config import GatewayConfig
from services.policy_worker.config import PolicyWorkerConfig

# ---- EnvReader ------------------------------------------------------------------------------


def test_reader_typed_values_and_defaults() -> None:
    """Set variables are parsed to their type; unset and empty ones fall back to the default."""
    env = EnvReader({"A": "x", "N": "42", "F": "0.25", "B": "yes", "EMPTY": "", "ADDR": "host:123"})
    assert env.str("A") == "x"
    assert env.str("MISSING", "dflt") == "dflt"
    assert env.str("EMPTY", "dflt") == "dflt"
    assert env.int("N", 0) == 42
    assert env.int("MISSING", 7) == 7
    assert env.float("F", 1.0) == 0.25
    assert env.bool("B", False) is True
    assert env.bool("MISSING", True) is True
    assert env.address("ADDR") == "host:123"
    env.finish("svc")  # nothing wrong: no exception


@pytest.mark.parametrize("raw,expected", [("1", True), ("TRUE", True), ("on", True), ("0", False), ("no", False),
                                          (" Off ", False)])
def test_reader_bool_spellings(raw: str, expected: bool) -> None:
    """Every documented boolean spelling is understood, case-insensitively."""
    assert EnvReader({"B": raw}).bool("B", not expected) is expected


def test_reader_collects_every_problem_before_failing() -> None:
    """One ConfigError lists all bad variables, so a deployment is fixed in one round."""
    env = EnvReader({"N": "ten", "F": "x", "B": "maybe", "LOW": "3", "HIGH": "99", "ADDR": "nohostport"})
    assert env.int("N", 5) == 5  # bad value keeps the default while collecting the error
    env.float("F", 1.0)
    env.bool("B", False)
    assert env.int("LOW", 0, minimum=10) == 3
    env.int("HIGH", 0, maximum=50)
    env.str("REQ", required=True)
    env.address("ADDR")
    env.fail("A and B disagree")
    with pytest.raises(ConfigError) as info:
        env.finish("my service")
    msg = str(info.value)
    assert msg.startswith("my service: invalid configuration")
    for needle in ("N='ten' is not an integer", "F='x' is not a number", "B='maybe' is not a boolean",
                   "LOW=3 is below the minimum 10", "HIGH=99 is above the maximum 50", "REQ is required but not set",
                   "ADDR='nohostport' is not a host:port address", "A and B disagree"):
        assert needle in msg, needle


def test_reader_required_empty_counts_as_missing() -> None:
    """An empty required variable is as bad as an unset one."""
    env = EnvReader({"REQ": ""})
    env.str("REQ", required=True)
    with pytest.raises(ConfigError, match="REQ is required"):
        env.finish("svc")


# ---- GatewayConfig ---------------------------------------------------------------------------


def test_gateway_defaults_need_only_redis() -> None:
    """ZETTA_REDIS_URL is the one required setting; the rest has working defaults."""
    cfg = GatewayConfig.from_env({"ZETTA_REDIS_URL": "redis://127.0.0.1:6379/0"})
    assert cfg.redis_url == "redis://127.0.0.1:6379/0"
    assert cfg.port == 50051
    assert cfg.heartbeat_interval_ms == 1000
    assert cfg.heartbeat_timeout_ms == 3000  # three intervals by default
    assert cfg.monitor_interval_ms == 500  # half an interval
    assert cfg.default_lease_seconds <= cfg.max_lease_seconds


def test_gateway_reads_every_override() -> None:
    """Overrides land in the right fields, and the monitor follows the heartbeat interval."""
    cfg = GatewayConfig.from_env({
        "ZETTA_REDIS_URL": "redis://r:1/2", "ZETTA_GATEWAY_PORT": "0", "ZETTA_HEARTBEAT_INTERVAL_MS": "200",
        "ZETTA_HEARTBEAT_TIMEOUT_MS": "1000", "ZETTA_DEFAULT_LEASE_SECONDS": "30", "ZETTA_RETRY_AFTER_MS": "123",
        "ZETTA_GRACE_SECONDS": "1.5", "ZETTA_REDIS_PREFIX": "t1",
    })
    assert (cfg.port, cfg.heartbeat_interval_ms, cfg.heartbeat_timeout_ms) == (0, 200, 1000)
    assert cfg.monitor_interval_ms == 100
    assert (cfg.default_lease_seconds, cfg.retry_after_ms, cfg.grace_seconds, cfg.redis_prefix) == (30, 123, 1.5, "t1")


def test_gateway_missing_redis_fails() -> None:
    """Without Redis the gateway cannot hold a session: refuse to start."""
    with pytest.raises(ConfigError, match="ZETTA_REDIS_URL is required"):
        GatewayConfig.from_env({})


@pytest.mark.parametrize("timeout", ["1000", "500"])
def test_gateway_timeout_must_exceed_interval(timeout: str) -> None:
    """A heartbeat timeout not above the interval would declare healthy workers dead."""
    with pytest.raises(ConfigError) as info:
        GatewayConfig.from_env({"ZETTA_REDIS_URL": "redis://x:1", "ZETTA_HEARTBEAT_INTERVAL_MS": "1000",
                                "ZETTA_HEARTBEAT_TIMEOUT_MS": timeout})
    assert "ZETTA_HEARTBEAT_TIMEOUT_MS" in str(info.value)
    assert "ZETTA_HEARTBEAT_INTERVAL_MS" in str(info.value)


def test_gateway_lists_all_errors() -> None:
    """Several bad variables are reported together."""
    with pytest.raises(ConfigError) as info:
        GatewayConfig.from_env({"ZETTA_GATEWAY_PORT": "70000", "ZETTA_HEARTBEAT_INTERVAL_MS": "10",
                                "ZETTA_DEFAULT_LEASE_SECONDS": "100", "ZETTA_MAX_LEASE_SECONDS": "10"})
    msg = str(info.value)
    for name in ("ZETTA_REDIS_URL", "ZETTA_GATEWAY_PORT", "ZETTA_HEARTBEAT_INTERVAL_MS", "ZETTA_DEFAULT_LEASE_SECONDS"):
        assert name in msg, name


# ---- EnvWorkerConfig -------------------------------------------------------------------------


def test_env_worker_parses_lists_and_resolves_identity() -> None:
    """Comma lists are split and trimmed; id and advertised address come from the bound port."""
    cfg = EnvWorkerConfig.from_env({
        "ZETTA_GATEWAY_ADDRESS": "127.0.0.1:50051", "ZETTA_POLICY_ADDRESSES": " a:1 , b:2 ,",
        "ZETTA_ENV_FAMILIES": "robosuite, libero", "ZETTA_SLOTS": "3", "ZETTA_BIND_HOST": "127.0.0.1",
        "ZETTA_ENV_WORKER_PORT": "0",
    })
    assert cfg.policy_addresses == ("a:1", "b:2")
    assert cfg.families == ("robosuite", "libero")
    assert cfg.slots == 3
    assert cfg.infer_hold == InferHold(max_ms=200.0, min_busy=2) and cfg.step_concurrency == usable_cpus()
    resolved = cfg.resolved(40123)
    assert resolved.port == 40123
    assert resolved.advertise_address == "127.0.0.1:40123"
    assert resolved.worker_id.endswith("-40123")
    named = EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "g:1", "ZETTA_WORKER_ID": "env-7",
                                      "ZETTA_ADVERTISE_ADDRESS": "10.0.0.1:9"}).resolved(5)
    assert (named.worker_id, named.advertise_address) == ("env-7", "10.0.0.1:9")


def test_env_worker_requires_gateway_and_valid_values() -> None:
    """Missing gateway, bad addresses, no families and zero slots are all named."""
    with pytest.raises(ConfigError) as info:
        EnvWorkerConfig.from_env({"ZETTA_POLICY_ADDRESSES": "nocolon", "ZETTA_ENV_FAMILIES": " , ",
                                  "ZETTA_SLOTS": "0", "ZETTA_INFER_HOLD_MS": "-1", "ZETTA_INFER_HOLD_MIN_BUSY": "0",
                                  "ZETTA_STEP_CONCURRENCY": "-1"})
    msg = str(info.value)
    assert msg.startswith("env worker:")
    for needle in ("ZETTA_GATEWAY_ADDRESS is required", "ZETTA_POLICY_ADDRESSES: 'nocolon'",
                   "ZETTA_ENV_FAMILIES is empty", "ZETTA_SLOTS=0 is below the minimum 1",
                   "ZETTA_INFER_HOLD_MS=-1", "ZETTA_INFER_HOLD_MIN_BUSY=0 is below the minimum 1",
                   "ZETTA_STEP_CONCURRENCY=-1"):
        assert needle in msg, needle


def test_env_worker_rejects_malformed_gateway_address() -> None:
    """A gateway address without a port cannot be dialled."""
    with pytest.raises(ConfigError, match="ZETTA_GATEWAY_ADDRESS='gateway' is not a host:port"):
        EnvWorkerConfig.from_env({"ZETTA_GATEWAY_ADDRESS": "gateway"})


# ---- PolicyWorkerConfig ----------------------------------------------------------------------


def test_policy_worker_defaults_and_scheduler() -> None:
    """The shipped model is the default; the queue delay is converted from ms to seconds."""
    cfg = PolicyWorkerConfig.from_env({"ZETTA_MAX_BATCH": "8", "ZETTA_MAX_QUEUE": "16", "ZETTA_MAX_QUEUE_DELAY_MS": "5"})
    assert cfg.models == (DEFAULT_POLICY,)
    assert cfg.scheduler.max_batch == 8
    assert cfg.scheduler.max_queue == 16
    assert cfg.scheduler.max_queue_delay == pytest.approx(0.005)


def test_policy_worker_unknown_model_names_known_ones() -> None:
    """A typo in ZETTA_MODELS is named together with the models that exist."""
    with pytest.raises(ConfigError) as info:
        PolicyWorkerConfig.from_env({"ZETTA_MODELS": "scripted-pick-place,nope"})
    msg = str(info.value)
    assert "ZETTA_MODELS: unknown model 'nope'" in msg
    assert "scripted-pick-place" in msg


def test_policy_worker_queue_must_hold_a_batch() -> None:
    """A queue shorter than one batch could never fill a batch."""
    with pytest.raises(ConfigError, match="ZETTA_MAX_QUEUE=4 must be >= ZETTA_MAX_BATCH=8"):
        PolicyWorkerConfig.from_env({"ZETTA_MAX_BATCH": "8", "ZETTA_MAX_QUEUE": "4"})


def test_policy_worker_empty_models() -> None:
    """An empty model list is refused instead of serving nothing."""
    with pytest.raises(ConfigError, match="ZETTA_MODELS is empty"):
        PolicyWorkerConfig.from_env({"ZETTA_MODELS": " , "})


def test_policy_worker_vla_split_is_a_checked_boolean() -> None:
    """ZETTA_VLA_SPLIT is off by default, on for 1/true, and a typo stops the worker."""
    assert PolicyWorkerConfig.from_env({}).vla_split is False
    assert PolicyWorkerConfig.from_env({"ZETTA_VLA_SPLIT": "1"}).vla_split is True
    with pytest.raises(ConfigError, match="ZETTA_VLA_SPLIT='maybe' is not a boolean"):
        PolicyWorkerConfig.from_env({"ZETTA_VLA_SPLIT": "maybe"})


def test_policy_worker_early_dispatch_is_a_checked_boolean() -> None:
    """ZETTA_EARLY_DISPATCH is on by default, off for false/0, and a typo stops the worker."""
    assert PolicyWorkerConfig.from_env({}).scheduler.early_dispatch is True
    assert PolicyWorkerConfig.from_env({"ZETTA_EARLY_DISPATCH": "false"}).scheduler.early_dispatch is False
    with pytest.raises(ConfigError, match="ZETTA_EARLY_DISPATCH='soon' is not a boolean"):
        PolicyWorkerConfig.from_env({"ZETTA_EARLY_DISPATCH": "soon"})
