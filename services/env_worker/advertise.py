"""The address an env worker gives the gateway to dial it back.

A worker bound to a wildcard (``0.0.0.0``, ``::``) listens on every interface, but the wildcard
itself cannot be dialled. The worker advertises the local address its kernel routes to the
gateway from (a UDP socket ``connect`` picks the route and sends nothing): the interface the
gateway already reaches it through, on a second host, in a container or in a network namespace.
``ZETTA_ADVERTISE_ADDRESS`` overrides it (NAT, a load balancer, a pod IP from the downward API).
"""

from __future__ import annotations

import socket

WILDCARDS = ("0.0.0.0", "::", "[::]", "")


def split_host_port(address: str) -> tuple[str, int]:
    """``host:port`` or ``[v6]:port`` -> (host without brackets, port)."""
    host, _, port = address.rpartition(":")
    return host.strip("[]"), int(port)


def join_host_port(host: str, port: int) -> str:
    """(host, port) -> ``host:port``, brackets around an IPv6 literal."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def route_source(peer: str, ipv4_only: bool) -> str | None:
    """The local address the kernel would send from to reach ``peer`` (host:port), or None."""
    try:
        host, port = split_host_port(peer)
        infos = socket.getaddrinfo(host, port, socket.AF_INET if ipv4_only else socket.AF_UNSPEC, socket.SOCK_DGRAM)
    except (OSError, ValueError):
        return None
    for family, _, _, _, sockaddr in infos:
        try:
            with socket.socket(family, socket.SOCK_DGRAM) as s:
                s.connect(sockaddr)
                return str(s.getsockname()[0])
        except OSError:
            continue
    return None


def advertised_address(bind_host: str, bound_port: int, gateway: str, override: str = "") -> str:
    """What the worker registers: the override, else its bind host, else (wildcard) the route to the gateway."""
    if override:
        return override
    if bind_host not in WILDCARDS:
        return join_host_port(bind_host.strip("[]"), bound_port)
    source = route_source(gateway, ipv4_only=bind_host == "0.0.0.0")
    return join_host_port(source or socket.gethostname(), bound_port)
