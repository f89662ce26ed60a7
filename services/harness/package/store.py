"""Package bytes on disk, addressed by content hash: the durable half of the harness registry.

Redis holds the pointers (names, versions, pins); the files live here, one directory per content
hash, so a restart of the service (or of Redis) loses no package. Every write goes to a private
temporary directory first and appears with one rename, and a manifest is created only if none
exists (a hard link fails on an existing name), so a published version can never be overwritten,
not even by two replicas racing.
"""

from __future__ import annotations

import json
import logging
import os
import shutil
import tempfile
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

from services.harness.package import format as fmt

log = logging.getLogger(__name__)


class StoreCorrupted(RuntimeError):
    """Files on disk no longer match the hash they are stored under."""


class PackageStore:
    """``<root>/packages/<content_hash>/`` holds a package's files and, once it has a version,
    its manifest.json."""

    def __init__(self, root: Path) -> None:
        self.root = Path(root)
        self._packages = self.root / "packages"
        self._tmp = self.root / "tmp"
        self._packages.mkdir(parents=True, exist_ok=True)
        self._tmp.mkdir(parents=True, exist_ok=True)

    def check_writable(self) -> None:
        """Fail now, with the path in the message, rather than at the first publish."""
        fd, probe = tempfile.mkstemp(dir=self._tmp)
        os.close(fd)
        os.unlink(probe)

    def _dir(self, digest: str) -> Path:
        if len(digest) != 64 or any(c not in "0123456789abcdef" for c in digest):
            raise ValueError(f"not a content hash: {digest!r}")
        return self._packages / digest

    def put_files(self, digest: str, files: Mapping[str, bytes]) -> None:
        """Store the files of ``digest`` (manifest.json excluded) unless they are already there."""
        target = self._dir(digest)
        if target.exists():
            return
        staging = Path(tempfile.mkdtemp(prefix=digest[:12] + "-", dir=self._tmp))
        try:
            for rel, data in files.items():
                if rel == fmt.MANIFEST:
                    continue
                path = staging / rel
                path.parent.mkdir(parents=True, exist_ok=True)
                path.write_bytes(data)
            os.rename(staging, target)
        except OSError:
            if not target.is_dir():  # not another writer that won the race
                raise
        finally:
            shutil.rmtree(staging, ignore_errors=True)

    def put_manifest(self, digest: str, manifest: Mapping[str, Any]) -> dict[str, Any]:
        """Write the manifest of ``digest`` if it has none; returns the one that is stored."""
        final = self._dir(digest) / fmt.MANIFEST
        fd, tmp = tempfile.mkstemp(dir=self._tmp)
        try:
            with os.fdopen(fd, "wb") as fh:
                fh.write(fmt.manifest_bytes(manifest))
                fh.flush()
                os.fsync(fh.fileno())
            try:
                os.link(tmp, final)
            except FileExistsError:
                pass
        finally:
            os.unlink(tmp)
        stored = self.manifest(digest)
        assert stored is not None
        return stored

    def manifest(self, digest: str) -> dict[str, Any] | None:
        """The manifest of ``digest``; None while it has no version yet."""
        path = self._dir(digest) / fmt.MANIFEST
        try:
            return json.loads(path.read_bytes())
        except FileNotFoundError:
            return None

    def files(self, digest: str) -> dict[str, bytes]:
        """Every file of ``digest`` (manifest.json included), checked against the hash."""
        root = self._dir(digest)
        if not root.is_dir():
            raise StoreCorrupted(f"package {digest} is missing from {self._packages}")
        files = fmt.read_tree(root)
        actual = fmt.content_hash(files)
        if actual != digest:
            raise StoreCorrupted(f"package files under {self._dir(digest)} hash to {actual}, not {digest}")
        return files

    def manifests(self) -> Iterator[dict[str, Any]]:
        """Every stored manifest (to rebuild Redis pointers after Redis lost them)."""
        for path in sorted(self._packages.glob(f"*/{fmt.MANIFEST}")):
            try:
                yield json.loads(path.read_bytes())
            except (OSError, json.JSONDecodeError) as exc:
                log.warning("unreadable manifest skipped", extra={"fields": {"path": str(path), "error": str(exc)}})
