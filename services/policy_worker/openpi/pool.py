"""A served model whose inference runs on openpi policy servers: ``ZETTA_MODELS=openpi``.

Users serve pi0.5 with openpi's websocket policy server (``scripts/serve_policy.py``), which
answers one observation at a time. The policy worker batches requests as for any model; this
backend then spreads the batch over every connection to every configured server
(``ZETTA_OPENPI_SERVERS``, ``ZETTA_OPENPI_CONNECTIONS`` per server, so per-server concurrency is
bounded), each connection an ``openpi_client.WebsocketClientPolicy``. A sample that gets no answer
within ``ZETTA_OPENPI_TIMEOUT_MS`` fails the batch with a TimeoutError (the policy worker turns it
into INTERNAL for those callers) and its connection is closed and replaced, since its late reply
would otherwise be read as the next answer.
"""

from __future__ import annotations

import os
import queue
import socket
import time
from collections.abc import Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout
from dataclasses import dataclass
from typing import Any

import numpy as np

from services.common.specs import TensorSpec
from services.policy_worker.openpi import metrics
from services.policy_worker.openpi.observation import specs_from_metadata, to_openpi
from services.policy_worker.vla.features import PROPRIO_INPUTS


@dataclass(frozen=True)
class PoolConfig:
    """Where the openpi servers are and how the pool uses them (docs/policies.md)."""

    servers: tuple[str, ...]
    connections: int = 1
    timeout_s: float = 10.0
    chunk_size: int = 5
    image_size: int = 224
    wrist_image: bool = False
    #: ZETTA_OPENPI_CHUNK was given: it wins over the chunk size a Zetta server declares.
    chunk_size_set: bool = False

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> "PoolConfig":
        """ZETTA_OPENPI_* variables; raises ValueError naming the bad one."""
        env = os.environ if environ is None else environ
        servers = tuple(s.strip() for s in env.get("ZETTA_OPENPI_SERVERS", "").split(",") if s.strip())
        if not servers:
            raise ValueError("ZETTA_OPENPI_SERVERS is empty: list the openpi policy servers as host:port,host:port")
        for s in servers:
            host, _, port = s.rpartition(":")
            if not host or not port.isdigit():
                raise ValueError(f"ZETTA_OPENPI_SERVERS: {s!r} is not host:port")

        def number(name: str, default: float, kind: type = int) -> Any:
            raw = env.get(name, "")
            try:
                value = kind(raw) if raw else default
            except ValueError:
                raise ValueError(f"{name}={raw!r} is not a number") from None
            if value <= 0:
                raise ValueError(f"{name} must be > 0, got {raw}")
            return value

        return cls(servers=servers, connections=number("ZETTA_OPENPI_CONNECTIONS", 1),
                   timeout_s=number("ZETTA_OPENPI_TIMEOUT_MS", 10_000) / 1000.0,
                   chunk_size=number("ZETTA_OPENPI_CHUNK", 5), image_size=number("ZETTA_OPENPI_IMAGE_SIZE", 224),
                   wrist_image=env.get("ZETTA_OPENPI_WRIST_IMAGE", "0").lower() in ("1", "true", "yes"),
                   chunk_size_set=bool(env.get("ZETTA_OPENPI_CHUNK")))


class _Connection:
    """One websocket to one server; used by one thread at a time."""

    def __init__(self, server: str) -> None:
        from openpi_client.websocket_client_policy import WebsocketClientPolicy

        host, _, port = server.rpartition(":")
        self.server = server
        self.client = WebsocketClientPolicy(host=host, port=int(port))
        #: The caller gave up on this connection's request: whatever it reads next is stale.
        self.abandoned = False

    def abandon(self) -> None:
        """Mark the connection stale and cut its socket, so a thread blocked in recv fails now
        (a websocket close handshake would wait for the busy server)."""
        self.abandoned = True
        try:
            self.client._ws.socket.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass

    def close(self) -> None:
        """Close the socket without a handshake."""
        try:
            self.client._ws.socket.close()
        except OSError:
            pass


class OpenPIPool:
    """A :class:`PolicyModel` answered by openpi policy servers."""

    name = "openpi"

    def __init__(self, config: PoolConfig) -> None:
        try:
            import openpi_client  # noqa: F401
        except ImportError:
            raise ValueError("model 'openpi' needs PyPI openpi-client: pip install --no-deps openpi-client "
                             "(see docs/policies.md)") from None
        self.config = config
        self.chunk_size = config.chunk_size
        connections = []
        for server in config.servers:
            for _ in range(config.connections):
                try:
                    connections.append(_Connection(server))
                except OSError as exc:
                    raise ValueError(f"openpi server {server} is not reachable: {exc}") from None
        self._idle: queue.Queue[_Connection] = queue.Queue()
        for conn in connections:
            self._idle.put(conn)
        first = connections[0].client.get_server_metadata()
        self._specs = specs_from_metadata(first)
        if self._specs is not None and not config.chunk_size_set:
            self.chunk_size = int(first.get("chunk_size", self.chunk_size))
        self._slots = len(config.servers) * config.connections
        self._pool = ThreadPoolExecutor(self._slots, thread_name_prefix="openpi")

    def input_specs(self) -> Sequence[TensorSpec]:
        """What the servers declare (Zetta's do), else the camera(s) and proprioception of openpi's LIBERO format."""
        if self._specs is not None:
            return self._specs
        size = self.config.image_size
        specs = [TensorSpec("agentview_image", "uint8", (size, size, 3))]
        if self.config.wrist_image:
            specs.append(TensorSpec("eye_in_hand_image", "uint8", (size, size, 3)))
        specs += [TensorSpec(n, "float32", (w,)) for n, w in PROPRIO_INPUTS if n != "robot0_joint_pos"]
        return specs

    def infer(self, batch: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        """One request per sample, spread over the idle connections; [B, chunk, 7] in batch order."""
        deadline = time.monotonic() + self.config.timeout_s
        samples = [{k: v[i] for k, v in batch.items()} for i in range(len(instructions))]
        held: list[list[_Connection]] = [[] for _ in samples]
        futures = [self._pool.submit(self._one, s, text, h) for s, text, h in zip(samples, instructions, held)]
        out = []
        for f in futures:
            try:
                out.append(f.result(timeout=max(0.0, deadline - time.monotonic())))
            except FutureTimeout:
                for f2, h in zip(futures, held):
                    if not f2.done() and h:
                        h[0].abandon()  # its thread's recv fails, and _one replaces the connection
                raise TimeoutError(f"openpi servers gave no answer within {self.config.timeout_s * 1000:.0f} ms "
                                   f"(ZETTA_OPENPI_TIMEOUT_MS)") from None
        return np.stack(out)

    def _one(self, sample: dict[str, np.ndarray], instruction: str, held: list[_Connection]) -> np.ndarray:
        conn = self._idle.get()
        held.append(conn)
        metrics.IN_FLIGHT.labels(conn.server).inc()
        start = time.monotonic()
        failure: Exception | None = None
        try:
            reply = conn.client.infer(to_openpi(sample, instruction))
        except Exception as exc:  # noqa: BLE001 - re-raised below once the connection is replaced
            failure = exc
        finally:
            metrics.IN_FLIGHT.labels(conn.server).dec()
        if failure is not None or conn.abandoned:
            metrics.ERRORS.labels(conn.server).inc()
            self._idle.put(self._replace(conn))
            raise failure or TimeoutError(f"openpi server {conn.server} answered after the deadline")
        self._idle.put(conn)
        metrics.LATENCY.labels(conn.server).observe(time.monotonic() - start)
        actions = np.asarray(reply["actions"], np.float32)
        if actions.ndim != 2 or actions.shape[1] != 7 or len(actions) < self.chunk_size:
            raise ValueError(f"openpi server {conn.server} answered actions of shape {actions.shape}; "
                             f"need [>= {self.chunk_size}, 7] (ZETTA_OPENPI_CHUNK)")
        return actions[: self.chunk_size]

    def _replace(self, conn: _Connection) -> _Connection:
        """A fresh connection to the same server after a failure (the old one may be mid-reply)."""
        conn.close()
        try:
            return _Connection(conn.server)
        except OSError:  # the server is down: keep the broken one, its next use fails fast and retries
            return conn


def make_openpi_pool() -> OpenPIPool:
    """The ``openpi`` model, configured from ZETTA_OPENPI_* variables."""
    return OpenPIPool(PoolConfig.from_env())
