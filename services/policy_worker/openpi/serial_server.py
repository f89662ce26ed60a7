"""An openpi-protocol policy server that answers one request at a time, as openpi's own does.

openpi's ``WebsocketPolicyServer`` sends the policy's metadata when a client connects, then for
every message unpacks an observation dict (msgpack-numpy), runs ``policy.infer`` on its event loop
and sends back the packed output; several clients take turns, one inference each. This server
does the same around any Zetta :class:`PolicyModel` (one sample, batch of one), so tests and
bench/bench_openpi.py can start a real openpi-protocol server on loopback: the openpi pool's
test target and the baseline Zetta's batching endpoint is measured against.
"""

from __future__ import annotations

import asyncio
import threading
import time
import traceback
from typing import Any

import numpy as np
import websockets
from websockets.asyncio.server import ServerConnection, serve
from websockets.http11 import Request, Response

from services.policy_worker.models.base import PolicyModel
from services.policy_worker.openpi import msgpack_numpy
from services.policy_worker.openpi.observation import from_openpi, server_metadata


class SerialOpenPIServer:
    """Serves ``model`` on ``ws://host:port`` from a background thread until :meth:`stop`."""

    def __init__(self, model: PolicyModel, host: str = "127.0.0.1", port: int = 0) -> None:
        self.model = model
        self.host = host
        self.port = port
        self.requests = 0
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._run, name="openpi-serial-server", daemon=True)

    def start(self) -> "SerialOpenPIServer":
        """Start serving; returns once the port is bound (``self.port`` then holds it)."""
        self._thread.start()
        if not self._ready.wait(30):
            raise RuntimeError("openpi serial server did not start within 30 s")
        return self

    def stop(self) -> None:
        """Close every connection and the listening socket."""
        if self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)

    @property
    def address(self) -> str:
        """host:port of the server."""
        return f"{self.host}:{self.port}"

    def _run(self) -> None:
        self._loop.run_until_complete(self._serve())

    async def _serve(self) -> None:
        self._stop = asyncio.Event()
        async with serve(self._handle, self.host, self.port, compression=None, max_size=None,
                         process_request=_healthz) as server:
            self.port = server.sockets[0].getsockname()[1]
            self._ready.set()
            await self._stop.wait()

    async def _handle(self, ws: ServerConnection) -> None:
        packer = msgpack_numpy.Packer()
        await ws.send(packer.pack(server_metadata(self.model.name, self.model.chunk_size, self.model.input_specs())))
        while True:
            try:
                message = await ws.recv()
            except websockets.ConnectionClosed:
                return
            start = time.monotonic()
            try:
                inputs, prompt = from_openpi(msgpack_numpy.unpackb(message))
                batch = {s.name: np.asarray(inputs[s.name])[None] for s in self.model.input_specs()}
                # On the event loop, like openpi's server: the next request waits for this one.
                actions = self.model.infer(batch, [prompt])[0]
            except Exception:  # noqa: BLE001 - openpi's protocol: the traceback as a text frame, then close
                await ws.send(traceback.format_exc())
                await ws.close(1011, "inference failed")
                return
            self.requests += 1
            reply: dict[str, Any] = {"actions": np.asarray(actions, np.float32),
                                     "server_timing": {"infer_ms": (time.monotonic() - start) * 1000}}
            try:
                await ws.send(packer.pack(reply))
            except websockets.ConnectionClosed:  # the client gave up while the model ran
                return


def _healthz(_conn: ServerConnection, request: Request) -> Response | None:
    """openpi's health route: GET /healthz answers 200 OK without a websocket upgrade."""
    if request.path == "/healthz":
        return _conn.respond(200, "OK\n")
    return None
