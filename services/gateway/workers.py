"""Channels to env workers: one reused channel and stub per worker, looked up from Redis once."""

from __future__ import annotations

import asyncio

import grpc

from services.common import grpc_errors as ge
from services.common.tls import aio_channel
from zetta_wire.channel import CHANNEL_OPTIONS
from services.gateway.registry import Registry
from zetta_wire.v1 import env_worker_pb2_grpc


class WorkerPool:
    """Caches a stub per worker id; a re-registration with a new address replaces it."""

    def __init__(self, registry: Registry) -> None:
        self._registry = registry
        self._stubs: dict[str, tuple[str, grpc.aio.Channel, env_worker_pb2_grpc.EnvWorkerServiceStub]] = {}
        self._lock = asyncio.Lock()

    async def stub(self, worker_id: str) -> env_worker_pb2_grpc.EnvWorkerServiceStub:
        """The stub of a worker, dialling it on first use."""
        cached = self._stubs.get(worker_id)
        if cached is not None:
            return cached[2]
        async with self._lock:
            cached = self._stubs.get(worker_id)
            if cached is not None:
                return cached[2]
            address = await self._registry.r.hget(f"{self._registry.p}:worker:{worker_id}", "address")
            if not address:
                raise ge.unavailable(f"env worker {worker_id} is not registered")
            return self._connect(worker_id, address.decode())

    def _connect(self, worker_id: str, address: str) -> env_worker_pb2_grpc.EnvWorkerServiceStub:
        channel = aio_channel(address, CHANNEL_OPTIONS)
        stub = env_worker_pb2_grpc.EnvWorkerServiceStub(channel)
        self._stubs[worker_id] = (address, channel, stub)
        return stub

    async def update(self, worker_id: str, address: str) -> None:
        """Called on (re)registration: drop a stale channel if the address changed."""
        cached = self._stubs.get(worker_id)
        if cached is not None and cached[0] != address:
            self._stubs.pop(worker_id)
            await cached[1].close()

    async def close(self) -> None:
        """Close every channel."""
        for _, channel, _ in self._stubs.values():
            await channel.close()
        self._stubs.clear()
