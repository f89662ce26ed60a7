"""Publishing drafts through the critic service's harness registry (gRPC), the only way a harness
reaches the env workers: they load versions by reference ("NAME@VERSION")."""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from typing import Any

import grpc

from services.common.tls import sync_channel
from services.evolver.draft import HarnessDraft, render
from zetta_wire.v1 import critic_pb2, critic_pb2_grpc

#: Codes worth a retry: the service was busy or restarting (publishing the same content twice is harmless).
TRANSIENT = frozenset({grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED, grpc.StatusCode.UNKNOWN})
RETRIES = 3


class RegistryClient:
    """A channel to HarnessRegistryService."""

    def __init__(self, address: str) -> None:
        self._channel = sync_channel(address)
        self._stub = critic_pb2_grpc.HarnessRegistryServiceStub(self._channel)

    def close(self) -> None:
        """Close the channel."""
        self._channel.close()

    def publish(self, draft: HarnessDraft, parent: str = "", evidence: Mapping[str, Any] | None = None,
                validation: Mapping[str, Any] | None = None) -> str:
        """Publish a draft (idempotent by content, so a retried call is safe) and return its reference."""
        req = critic_pb2.PublishRequest(files=render(draft), parent=parent,
                                        evidence_json=json.dumps(evidence or {}, sort_keys=True),
                                        validation_json=json.dumps(validation or {}, sort_keys=True))
        for attempt in range(RETRIES):
            try:
                resp = self._stub.Publish(req, timeout=60)
                return f"{resp.manifest.name}@{resp.manifest.version}"
            except grpc.RpcError as exc:
                if exc.code() not in TRANSIENT or attempt == RETRIES - 1:
                    raise
                time.sleep(1.0 + attempt)
        raise AssertionError("unreachable")

    def pin(self, task: str, ref: str) -> None:
        """Pin ``ref`` for a task key."""
        self._stub.Pin(critic_pb2.PinRequest(task=task, ref=ref), timeout=10)

    def manifest(self, ref: str) -> critic_pb2.HarnessManifest:
        """The manifest of a version."""
        return self._stub.Get(critic_pb2.GetRequest(ref=ref, manifest_only=True), timeout=10).manifest

    def files(self, ref: str) -> dict[str, bytes]:
        """The files of a version."""
        return dict(self._stub.Get(critic_pb2.GetRequest(ref=ref), timeout=10).files)
