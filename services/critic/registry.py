"""The harness registry: Redis pointers over the content-addressed package store.

Keys (under ``<prefix>:critic:``):
  names                 SET of package names
  versions:<name>       HASH version -> content hash (a version is visible once it is here)
  next:<name>           counter: the last version number handed out for the name
  hash:<content hash>   the version that content was published as (what makes publish idempotent)
  pins                  HASH task key -> "NAME@VERSION"

Publishing claims a version for a content hash in one Lua script, so concurrent publishers
(several replicas included) never hand out one number twice nor publish the same content twice.
The package bytes and manifest are written to disk before the version becomes visible, and
:meth:`HarnessRegistry.restore` puts back the pointers of every stored manifest at start-up, so
neither a crash mid-publish nor a Redis restart loses a published version (pins live in Redis
only).
"""

from __future__ import annotations

import asyncio
import datetime as dt
import json
import logging
import re
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import grpc
import redis.asyncio as aioredis

from services.common import grpc_errors as ge
from services.harness.package.store import PackageStore, StoreCorrupted

log = logging.getLogger(__name__)

_CLAIM = """
local v = redis.call('GET', KEYS[1])
if v then return {tonumber(v), 0} end
v = redis.call('INCR', KEYS[2])
redis.call('SET', KEYS[1], v)
return {v, 1}
"""

_RESTORE = """
redis.call('SETNX', KEYS[1], ARGV[1])
redis.call('HSETNX', KEYS[2], ARGV[1], ARGV[2])
redis.call('SADD', KEYS[3], ARGV[3])
local n = tonumber(redis.call('GET', KEYS[4]) or '0')
if n < tonumber(ARGV[1]) then redis.call('SET', KEYS[4], ARGV[1]) end
return redis.call('HGET', KEYS[2], ARGV[1])
"""

_REF = re.compile(r"^(?P<name>[^@\s]+)(?:@(?P<version>[0-9]+|latest|pinned))?$")
#: Longest task key accepted (a suite and task name, with room to spare).
MAX_TASK_KEY = 256


@dataclass(frozen=True)
class Resolved:
    """A concrete version: name, number and content hash."""

    name: str
    version: int
    content_hash: str

    @property
    def ref(self) -> str:
        """``NAME@VERSION``."""
        return f"{self.name}@{self.version}"


def parse_json(what: str, text: str) -> Any:
    """An optional JSON document from a request; INVALID_ARGUMENT when malformed."""
    if not text:
        return None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ge.invalid(f"{what} is not valid JSON: {exc}") from None


def check_task(task: str) -> str:
    """A task key: non-empty, printable, bounded."""
    if not task or len(task) > MAX_TASK_KEY or not task.isprintable() or task != task.strip():
        raise ge.invalid(f"task key {task!r} must be 1-{MAX_TASK_KEY} printable characters without surrounding spaces")
    return task


class HarnessRegistry:
    """Publish, resolve, list and pin harness versions."""

    def __init__(self, client: aioredis.Redis, prefix: str, store: PackageStore) -> None:
        self.redis = client
        self.store = store
        self._p = f"{prefix}:critic:"
        self._claim = client.register_script(_CLAIM)
        self._restore = client.register_script(_RESTORE)

    def _key(self, *parts: str) -> str:
        return self._p + ":".join(parts)

    # ---- references -----------------------------------------------------------------------------

    async def resolve(self, ref: str, task: str = "") -> Resolved:
        """``NAME@VERSION``, ``NAME@latest``, ``NAME``, ``NAME@pinned`` (with ``task``) or an
        empty ref (the task's pin) to a stored version."""
        if not ref:
            if not task:
                raise ge.invalid("give a harness reference (NAME@VERSION) or a task key whose pin to use")
            return await self.resolve(await self.get_pin(task))
        match = _REF.match(ref)
        if match is None:
            raise ge.invalid(f"malformed harness reference {ref!r}; use NAME@VERSION, NAME@latest or NAME@pinned")
        name, version = match.group("name"), match.group("version") or "latest"
        if version == "pinned":
            if not task:
                raise ge.invalid(f"{ref} needs a task key: the pin is per task")
            pinned = await self.resolve(await self.get_pin(task))
            if pinned.name != name:
                raise ge.failed_precondition(f"task {task!r} is pinned to {pinned.ref}, not to a version of {name}")
            return pinned
        versions = await self.redis.hgetall(self._key("versions", name))
        if not versions:
            raise ge.not_found(f"no harness named {name!r} in the registry")
        if version == "latest":
            number = max(int(v) for v in versions)
        else:
            number = int(version)
        digest = versions.get(str(number).encode())
        if digest is None:
            latest = max(int(v) for v in versions)
            raise ge.not_found(f"harness {name} has no version {number} (latest is {name}@{latest})")
        return Resolved(name, number, digest.decode())

    def manifest(self, resolved: Resolved) -> dict[str, Any]:
        """The stored manifest of a resolved version."""
        manifest = self.store.manifest(resolved.content_hash)
        if manifest is None:
            raise ge.ServiceError(
                grpc.StatusCode.DATA_LOSS, f"{resolved.ref}: manifest missing from the package store"
            )
        return manifest

    async def files(self, resolved: Resolved) -> dict[str, bytes]:
        """The stored files of a resolved version (manifest.json included), checked against its
        hash; DATA_LOSS when the store lost or corrupted them."""
        try:
            return await asyncio.to_thread(self.store.files, resolved.content_hash)
        except (FileNotFoundError, StoreCorrupted) as exc:
            raise ge.ServiceError(grpc.StatusCode.DATA_LOSS, f"{resolved.ref}: {exc}") from None

    # ---- publish --------------------------------------------------------------------------------

    async def published(self, digest: str) -> dict[str, Any] | None:
        """The manifest of the visible version with this content, if any (a re-publish of it
        needs no further checks)."""
        version = await self.redis.get(self._key("hash", digest))
        manifest = self.store.manifest(digest) if version is not None else None
        if manifest is None or not await self.redis.hexists(self._key("versions", manifest["name"]), version.decode()):
            return None
        return manifest

    async def publish(
        self, files: Mapping[str, bytes], name: str, digest: str, parent: str, evidence: Any, validation: Any
    ) -> tuple[dict[str, Any], bool]:
        """Store checked package files and give them a version; returns (manifest, created).

        Identical content returns the version it already has, whatever parent or evidence
        accompany it this time: a version's manifest is written once."""
        lineage: list[str] = []
        parent_ref = ""
        if parent:
            try:
                parent_resolved = await self.resolve(parent)
            except ge.ServiceError as exc:
                if exc.code == grpc.StatusCode.NOT_FOUND:
                    raise ge.failed_precondition(f"parent {parent!r} is not in the registry: {exc.message}") from None
                raise
            parent_ref = parent_resolved.ref
            lineage = [*self.manifest(parent_resolved).get("lineage", []), parent_ref]
        await asyncio.to_thread(self.store.put_files, digest, files)
        raw_version, created = await self._claim(keys=[self._key("hash", digest), self._key("next", name)])
        version = int(raw_version)
        manifest = self.store.manifest(digest)
        if manifest is None:
            manifest = await asyncio.to_thread(
                self.store.put_manifest,
                digest,
                {
                    "name": name,
                    "version": version,
                    "parent": parent_ref,
                    "content_hash": digest,
                    "lineage": lineage,
                    "evidence": evidence,
                    "validation": validation,
                    "created_at": dt.datetime.now(dt.timezone.utc).isoformat(timespec="milliseconds"),
                },
            )
        pipe = self.redis.pipeline(transaction=True)
        pipe.hset(self._key("versions", name), str(version), digest)
        pipe.sadd(self._key("names"), name)
        await pipe.execute()
        return manifest, bool(created)

    async def restore(self) -> int:
        """Put back the pointers of every manifest in the store that Redis does not know
        (Redis was flushed or restarted without persistence, or a publish crashed midway);
        returns how many versions were restored."""
        restored = 0
        for manifest in await asyncio.to_thread(lambda: list(self.store.manifests())):
            name, version, digest = manifest.get("name"), manifest.get("version"), manifest.get("content_hash")
            if not isinstance(name, str) or not isinstance(version, int) or not isinstance(digest, str):
                continue
            if await self.redis.hexists(self._key("versions", name), str(version)):
                continue
            stored = await self._restore(
                keys=[self._key("hash", digest), self._key("versions", name), self._key("names"), self._key("next", name)],
                args=[version, digest, name],
            )
            if stored is not None and stored.decode() != digest:
                log.warning(
                    "registry and store disagree; keeping the registry's pointer",
                    extra={"fields": {"ref": f"{name}@{version}", "store_hash": digest, "registry_hash": stored.decode()}},
                )
                continue
            restored += 1
        return restored

    # ---- listing and pins -----------------------------------------------------------------------

    async def list(self, name: str = "") -> list[Resolved]:
        """Every version (of ``name`` when given), by name then version."""
        names = [name] if name else sorted(n.decode() for n in await self.redis.smembers(self._key("names")))
        out: list[Resolved] = []
        for n in names:
            versions = await self.redis.hgetall(self._key("versions", n))
            out.extend(Resolved(n, int(v), h.decode()) for v, h in sorted(versions.items(), key=lambda kv: int(kv[0])))
        return out

    async def pins(self) -> dict[str, str]:
        """Every task key's pinned ref."""
        return {k.decode(): v.decode() for k, v in (await self.redis.hgetall(self._key("pins"))).items()}

    async def pin(self, task: str, ref: str) -> tuple[Resolved, str]:
        """Pin a concrete version for ``task``; returns it and the ref pinned before ("" if none)."""
        check_task(task)
        if ref.endswith("@pinned") or not ref:
            raise ge.invalid("pin a concrete version (NAME@VERSION or NAME@latest), not a pin")
        resolved = await self.resolve(ref)
        pipe = self.redis.pipeline(transaction=True)
        pipe.hget(self._key("pins"), task)
        pipe.hset(self._key("pins"), task, resolved.ref)
        previous, _ = await pipe.execute()
        return resolved, previous.decode() if previous else ""

    async def get_pin(self, task: str) -> str:
        """The ref pinned for ``task``; NOT_FOUND when it has none."""
        check_task(task)
        ref = await self.redis.hget(self._key("pins"), task)
        if ref is None:
            raise ge.not_found(f"no harness is pinned for task {task!r}")
        return ref.decode()
