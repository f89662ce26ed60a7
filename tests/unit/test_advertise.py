"""The address an env worker registers: the override, its bind host, or the route to the gateway."""

from __future__ import annotations

import socket

import pytest

from services.env_worker.advertise import advertised_address, join_host_port, split_host_port
from services.env_worker.config import EnvWorkerConfig


def test_wildcard_bind_advertises_the_interface_that_reaches_the_gateway() -> None:
    """0.0.0.0 with a gateway on loopback advertises loopback, never the wildcard."""
    assert advertised_address("0.0.0.0", 50061, "127.0.0.1:50051") == "127.0.0.1:50061"
    assert advertised_address("0.0.0.0", 50061, "localhost:50051") == "127.0.0.1:50061"


def test_ipv6_wildcard_and_literals_keep_their_brackets() -> None:
    """[::] with an IPv6 gateway advertises a bracketed IPv6 address; split/join round-trip."""
    if not socket.has_ipv6:
        pytest.skip("no IPv6 in this kernel")
    try:
        with socket.socket(socket.AF_INET6, socket.SOCK_DGRAM) as s:
            s.connect(("::1", 9))
    except OSError:
        pytest.skip("IPv6 loopback is not configured here")
    assert advertised_address("::", 50061, "[::1]:50051") == "[::1]:50061"
    assert split_host_port("[::1]:50051") == ("::1", 50051) and join_host_port("::1", 7) == "[::1]:7"


def test_explicit_bind_host_and_override_win() -> None:
    """A concrete bind host is advertised as is; ZETTA_ADVERTISE_ADDRESS beats everything."""
    assert advertised_address("10.1.2.3", 50061, "127.0.0.1:50051") == "10.1.2.3:50061"
    assert advertised_address("0.0.0.0", 50061, "127.0.0.1:50051", "worker-7.example:50061") == "worker-7.example:50061"


def test_config_resolves_a_wildcard_bind() -> None:
    """The env worker's configuration fills the advertised address when its port is bound."""
    cfg = EnvWorkerConfig.from_env({"ZETTA_BIND_HOST": "0.0.0.0", "ZETTA_GATEWAY_ADDRESS": "127.0.0.1:50051",
                                    "ZETTA_POLICY_ADDRESSES": "127.0.0.1:50071"})
    assert cfg.resolved(41234).advertise_address == "127.0.0.1:41234"
