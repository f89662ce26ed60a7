"""An openpi-protocol websocket endpoint in front of Zetta's policy workers.

An openpi client (``openpi_client.WebsocketClientPolicy``, openpi's LIBERO example unchanged)
connects as to openpi's own server: it gets the metadata, then sends one observation dict per
message and gets ``{"actions": [chunk, 7]}`` back. Each observation becomes one gRPC ``Infer``
item for a policy worker, so the observations of every connected client are batched together
by the worker's scheduler (openpi's own server runs them one after another). Observations are
mapped by :mod:`services.policy_worker.openpi.observation`; the metadata names the served model,
its chunk size and its inputs. A bad observation is answered with openpi's error convention, a
text frame holding the message (``openpi_client`` raises it as RuntimeError), and the connection
stays open.
"""

from __future__ import annotations

import itertools
import logging
import time
from typing import Any

import grpc
import numpy as np
import websockets
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.http11 import Request, Response

from services.policy_worker.openpi import metrics, msgpack_numpy
from services.common.spec_codec import spec_from_wire
from services.policy_worker.openpi.observation import from_openpi, server_metadata
from zetta_wire.codec import decode, encode_observation
from zetta_wire.v1 import policy_worker_pb2, policy_worker_pb2_grpc

log = logging.getLogger("openpi_endpoint")


class OpenPIEndpoint:
    """Serves the openpi protocol on ``host:port`` through the policy workers at ``policy_addresses``."""

    def __init__(self, policy_addresses: list[str], model: str = "", timeout_ms: int = 10_000) -> None:
        if not policy_addresses:
            raise ValueError("no policy worker address: set ZETTA_POLICY_ADDRESSES")
        self.addresses = list(policy_addresses)
        self._channels = [grpc.aio.insecure_channel(a) for a in policy_addresses]
        self._stubs = [policy_worker_pb2_grpc.PolicyWorkerServiceStub(c) for c in self._channels]
        self._next = itertools.cycle(range(len(self._stubs)))
        self.model = model
        self.timeout_ms = timeout_ms
        self.metadata: dict[str, Any] = {}
        self._inputs: list[str] = []
        self._server: Server | None = None
        self._tokens = itertools.count()

    async def start(self, host: str, port: int) -> int:
        """Read the model's signature from a policy worker and listen; returns the bound port."""
        try:
            models = (await self._stubs[0].ListModels(policy_worker_pb2.ListModelsRequest(), timeout=10)).models
        except grpc.aio.AioRpcError as exc:
            raise ValueError(f"policy worker {self.addresses[0]} did not list its models: {exc.code().name}: "
                             f"{exc.details()} (ZETTA_POLICY_ADDRESSES)") from None
        chosen = [m for m in models if (m.name == self.model if self.model else m.is_default)]
        if not chosen:
            raise ValueError(f"the policy worker serves no model {self.model!r}; it serves "
                             f"{', '.join(m.name for m in models)} (ZETTA_OPENPI_MODEL)")
        info = chosen[0]
        self.model = info.name
        self._inputs = [s.name for s in info.inputs]
        self.metadata = server_metadata(info.name, info.chunk_size, [spec_from_wire(s) for s in info.inputs])
        self._server = await serve(self._handle, host, port, compression=None, max_size=None,
                                   process_request=_healthz)
        return self._server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        """Stop listening, close client connections and the gRPC channels."""
        if self._server is not None:
            self._server.close()
            await self._server.wait_closed()
        for c in self._channels:
            await c.close()

    async def _handle(self, ws: ServerConnection) -> None:
        packer = msgpack_numpy.Packer()
        metrics.ENDPOINT_CLIENTS.inc()
        try:
            await ws.send(packer.pack(self.metadata))
            async for message in ws:
                start = time.monotonic()
                try:
                    reply = await self._infer(message)
                except _Refused as exc:
                    metrics.ENDPOINT_REQUESTS.labels(exc.outcome).inc()
                    await ws.send(str(exc))
                    continue
                metrics.ENDPOINT_REQUESTS.labels("ok").inc()
                metrics.ENDPOINT_LATENCY.observe(time.monotonic() - start)
                await ws.send(packer.pack(reply))
        except websockets.ConnectionClosed:
            pass
        finally:
            metrics.ENDPOINT_CLIENTS.dec()

    async def _infer(self, message: str | bytes) -> dict[str, Any]:
        if isinstance(message, str):
            raise _Refused("invalid", "send msgpack-numpy binary frames (openpi_client's packer), not text")
        try:
            obs, prompt = from_openpi(msgpack_numpy.unpackb(message))
        except Exception as exc:  # noqa: BLE001 - any undecodable frame is the client's error
            raise _Refused("invalid", f"cannot read the observation: {exc}") from None
        missing = [n for n in self._inputs if n not in obs]
        if missing:
            raise _Refused("invalid", f"model {self.model!r} needs {', '.join(missing)}; the observation has "
                                      f"{', '.join(sorted(obs)) or 'nothing'} (docs/policies.md lists the keys)")
        try:
            observation = encode_observation({n: np.ascontiguousarray(obs[n]) for n in self._inputs})
        except (TypeError, ValueError) as exc:
            raise _Refused("invalid", f"cannot encode the observation: {exc}") from None
        item = policy_worker_pb2.InferItem(token=str(next(self._tokens)), model=self.model, observation=observation,
                                           instruction=prompt, timeout_ms=self.timeout_ms)
        stub = self._stubs[next(self._next)]
        try:
            resp = await stub.Infer(policy_worker_pb2.InferRequest(items=[item]), timeout=self.timeout_ms / 1000 + 5)
        except grpc.aio.AioRpcError as exc:
            raise _Refused(exc.code().name.lower(), f"policy worker: {exc.code().name}: {exc.details()}") from None
        return {"actions": decode(resp.outputs[0].actions)}


class _Refused(Exception):
    """A request answered with an error text frame; ``outcome`` labels the metric."""

    def __init__(self, outcome: str, message: str) -> None:
        super().__init__(message)
        self.outcome = outcome


def _healthz(conn: ServerConnection, request: Request) -> Response | None:
    """GET /healthz answers 200 without a websocket upgrade (openpi's health route)."""
    if request.path == "/healthz":
        return conn.respond(200, "OK\n")
    return None
