"""Harness packages from Python and the command line: the registry client, Evaluate and `zetta harness`.

  zetta harness publish DIR [--parent REF] [--evidence FILE] [--validation FILE]
  zetta harness list [NAME]
  zetta harness get REF [--task TASK] [--out DIR]
  zetta harness diff BASE HEAD
  zetta harness pin TASK [REF]          (without REF: print the task's pin)

A reference is NAME@VERSION, NAME@latest (or NAME), or NAME@pinned with --task. The critic
service address comes from --critic or ZETTA_CRITIC_ADDR (default 127.0.0.1:50081). With TLS on
(docs/security.md) give the CA and a client certificate the critic service accepts: --tls-ca,
--tls-cert, --tls-key or ZETTA_TLS_CA, ZETTA_TLS_CERT, ZETTA_TLS_KEY, as for the SDK
(zetta.ClientCredentials).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import grpc
import numpy as np

from services.harness.package.format import read_tree
from zetta.client import ZettaError
from zetta.credentials import ClientCredentials, add_credential_flags, credentials_from_args
from zetta_wire.channel import CHANNEL_OPTIONS
from zetta_wire.codec import decode, encode, encode_observation
from zetta_wire.v1 import critic_pb2, critic_pb2_grpc, types_pb2

DEFAULT_ADDRESS = "127.0.0.1:50081"


def default_address() -> str:
    """ZETTA_CRITIC_ADDR or the service's default port on loopback."""
    return os.environ.get("ZETTA_CRITIC_ADDR") or DEFAULT_ADDRESS


@dataclass(frozen=True)
class Manifest:
    """A published version: identity, ancestry and what admitted it."""

    name: str
    version: int
    parent: str
    content_hash: str
    lineage: list[str]
    evidence: Any
    validation: Any
    created_at: str

    @property
    def ref(self) -> str:
        """``NAME@VERSION``."""
        return f"{self.name}@{self.version}"

    @classmethod
    def from_proto(cls, m: critic_pb2.HarnessManifest) -> "Manifest":
        """Decode the message (its JSON fields included)."""
        return cls(
            name=m.name,
            version=m.version,
            parent=m.parent,
            content_hash=m.content_hash,
            lineage=list(m.lineage),
            evidence=json.loads(m.evidence_json) if m.evidence_json else None,
            validation=json.loads(m.validation_json) if m.validation_json else None,
            created_at=m.created_at,
        )


def write_package(files: Mapping[str, bytes], out: str | Path) -> None:
    """Write a package's files under ``out`` (created; must be empty), refusing paths that
    would land outside it."""
    root = Path(out).resolve()
    if root.exists() and any(root.iterdir()):
        raise FileExistsError(f"{root} is not empty")
    for rel, data in files.items():
        target = (root / rel).resolve()
        if root not in target.parents:
            raise ValueError(f"refusing to write {rel!r} outside {root}")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)


class HarnessRegistry:
    """Blocking client of HarnessRegistryService (publishing is not on any hot path)."""

    def __init__(self, address: str | None = None, timeout: float = 120.0,
                 credentials: ClientCredentials | None = None) -> None:
        """``credentials``: TLS settings (None: from ZETTA_TLS_CA, ZETTA_TLS_CERT, ZETTA_TLS_KEY)."""
        self.address = address or default_address()
        self.timeout = timeout
        creds = credentials if credentials is not None else ClientCredentials.from_env()
        self._channel = creds.sync_channel(self.address, CHANNEL_OPTIONS)
        self._stub = critic_pb2_grpc.HarnessRegistryServiceStub(self._channel)

    def __enter__(self) -> "HarnessRegistry":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Close the channel."""
        self._channel.close()

    def _call(self, method: str, request: Any) -> Any:
        try:
            return getattr(self._stub, method)(request, timeout=self.timeout)
        except grpc.RpcError as err:
            raise ZettaError(err.code(), err.details() or "") from None

    def publish(
        self, package: str | Path | Mapping[str, bytes], parent: str = "", evidence: Any = None, validation: Any = None
    ) -> tuple[Manifest, bool]:
        """Publish a package directory (or its files by relative path); returns the manifest
        and whether a new version was created (False: identical content was already there)."""
        files = read_tree(Path(package)) if isinstance(package, (str, Path)) else dict(package)
        request = critic_pb2.PublishRequest(
            files=files,
            parent=parent,
            evidence_json="" if evidence is None else json.dumps(evidence),
            validation_json="" if validation is None else json.dumps(validation),
        )
        response = self._call("Publish", request)
        return Manifest.from_proto(response.manifest), response.created

    def get(self, ref: str, task: str = "", manifest_only: bool = False) -> tuple[Manifest, dict[str, bytes]]:
        """A version's manifest and files (manifest.json included)."""
        response = self._call("Get", critic_pb2.GetRequest(ref=ref, task=task, manifest_only=manifest_only))
        return Manifest.from_proto(response.manifest), dict(response.files)

    def download(self, ref: str, out: str | Path, task: str = "") -> Manifest:
        """Write a version's files into the empty directory ``out``."""
        manifest, files = self.get(ref, task)
        write_package(files, out)
        return manifest

    def list(self, name: str = "") -> tuple[list[Manifest], dict[str, str]]:
        """Versions (of ``name`` when given) and the pins, task key -> ref."""
        response = self._call("List", critic_pb2.ListRequest(name=name))
        return [Manifest.from_proto(m) for m in response.versions], {p.task: p.ref for p in response.pins}

    def diff(self, base: str, head: str) -> critic_pb2.DiffResponse:
        """Per-file unified diffs and changed params between two versions."""
        return self._call("Diff", critic_pb2.DiffRequest(base=base, head=head))

    def pin(self, task: str, ref: str) -> tuple[str, str]:
        """Pin a version for a task key; returns (pinned ref, previous ref or "")."""
        response = self._call("Pin", critic_pb2.PinRequest(task=task, ref=ref))
        return response.ref, response.previous

    def get_pin(self, task: str) -> str:
        """The version pinned for a task key."""
        return self._call("GetPin", critic_pb2.GetPinRequest(task=task)).ref


@dataclass(frozen=True)
class Proposal:
    """A critic's proposal as the service reported it."""

    critic: str
    evidence: str
    suggested_mode: str
    details: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class Decision:
    """The orchestrator's answer to one step: the mode in control, every proposal, the
    recovery's action when a recovery is in control, and the instruction to run the policy under
    when a recovery redirects it (``action`` None then)."""

    step: int
    mode: str
    proposals: list[Proposal]
    action: np.ndarray | None
    intervention_id: str
    instruction: str = ""


class Evaluation:
    """One episode on CriticService.Evaluate: send each env step, get the decision back.

    Use ``async with evaluate(...) as ev`` so the stream is closed when the episode ends."""

    def __init__(self, address: str, harness: str, instruction: str, milestone_names: Sequence[str], task: str,
                 credentials: ClientCredentials | None = None, policy_instructions: Sequence[str] = ()) -> None:
        creds = credentials if credentials is not None else ClientCredentials.from_env()
        self._channel = creds.aio_channel(address, CHANNEL_OPTIONS)
        self._call = critic_pb2_grpc.CriticServiceStub(self._channel).Evaluate()
        self._start = critic_pb2.EvaluateStart(
            harness=harness, task=task, instruction=instruction, milestone_names=list(milestone_names),
            policy_instructions=list(policy_instructions),
        )
        self.manifest: Manifest | None = None

    async def _read(self) -> critic_pb2.EvaluateResponse:
        try:
            response = await self._call.read()
        except grpc.aio.AioRpcError as err:
            raise ZettaError(err.code(), err.details() or "") from None
        if response is grpc.aio.EOF:
            status = await self._call.code()
            raise ZettaError(status, await self._call.details() or "stream ended")
        return response

    async def open(self) -> "Evaluation":
        """Send the start and wait for the resolved harness version."""
        await self._call.write(critic_pb2.EvaluateRequest(start=self._start))
        self.manifest = Manifest.from_proto((await self._read()).started.manifest)
        return self

    async def step(
        self, observation: Mapping[str, np.ndarray], action: np.ndarray | None, milestones: Iterable[str] = ()
    ) -> Decision:
        """Report one env step (``action`` None for the state right after the reset)."""
        step = critic_pb2.EvaluateStep(milestones=list(milestones))
        encode_observation(observation, step.observation)
        if action is not None:
            encode(action, step.action)
        await self._call.write(critic_pb2.EvaluateRequest(step=step))
        d = (await self._read()).decision
        return Decision(
            step=d.step,
            mode=d.mode,
            proposals=[Proposal(p.critic, p.evidence, p.suggested_mode, dict(p.details)) for p in d.proposals],
            action=decode(d.action) if d.HasField("action") else None,
            intervention_id=d.intervention_id,
            instruction=d.instruction,
        )

    async def finish(self, success: bool) -> types_pb2.HarnessReport:
        """Close the episode: the report of who acted (policy vs recoveries) and every intervention."""
        await self._call.write(critic_pb2.EvaluateRequest(end=critic_pb2.EvaluateEnd(success=success)))
        return (await self._read()).report

    async def close(self) -> None:
        """End the stream (without a report unless :meth:`finish` was called)."""
        try:
            await self._call.done_writing()
        except grpc.aio.AioRpcError:
            pass
        await self._channel.close()

    async def __aenter__(self) -> "Evaluation":
        try:
            return await self.open()
        except BaseException:
            await self.close()
            raise

    async def __aexit__(self, *exc: object) -> None:
        await self.close()


def evaluate(
    harness: str, instruction: str, milestone_names: Sequence[str] = (), task: str = "", address: str | None = None,
    credentials: ClientCredentials | None = None, policy_instructions: Sequence[str] = (),
) -> Evaluation:
    """An Evaluate stream for one episode of ``harness`` (a reference; empty uses ``task``'s pin).
    ``policy_instructions``: what your policy was trained on, so a redirection asks it under one."""
    return Evaluation(address or default_address(), harness, instruction, milestone_names, task, credentials,
                      policy_instructions)


# ---- command line -----------------------------------------------------------------------------


def _read_json_file(path: str | None) -> Any:
    return None if path is None else json.loads(Path(path).read_text())


def _cmd_publish(reg: HarnessRegistry, args: argparse.Namespace) -> int:
    manifest, created = reg.publish(
        args.dir, parent=args.parent, evidence=_read_json_file(args.evidence), validation=_read_json_file(args.validation)
    )
    state = "published" if created else "already published as"
    print(f"{state} {manifest.ref}  sha256 {manifest.content_hash}" + (f"  parent {manifest.parent}" if manifest.parent else ""))
    return 0


def _cmd_list(reg: HarnessRegistry, args: argparse.Namespace) -> int:
    versions, pins = reg.list(args.name or "")
    print(f"{'version':<32} {'sha256':<14} {'parent':<32} created")
    for m in versions:
        print(f"{m.ref:<32} {m.content_hash[:12]:<14} {m.parent or '-':<32} {m.created_at}")
    if pins:
        print("\npins:")
        for task, ref in sorted(pins.items()):
            print(f"  {task:<60} {ref}")
    return 0


def _cmd_get(reg: HarnessRegistry, args: argparse.Namespace) -> int:
    if args.out:
        manifest = reg.download(args.ref, args.out, task=args.task)
        print(f"wrote {manifest.ref} to {args.out}")
        return 0
    manifest, files = reg.get(args.ref, task=args.task)
    print(json.dumps(json.loads(files["manifest.json"]), indent=2, sort_keys=True))
    for path in sorted(files):
        print(f"  {len(files[path]):>8}  {path}")
    return 0


def _cmd_diff(reg: HarnessRegistry, args: argparse.Namespace) -> int:
    response = reg.diff(args.base, args.head)
    base, head = Manifest.from_proto(response.base), Manifest.from_proto(response.head)
    print(f"{base.ref} -> {head.ref}: {len(response.files)} files changed, {len(response.params)} params changed")
    for p in response.params:
        print(f"  params/{p.file}.toml {p.key}: {p.base_json or '(absent)'} -> {p.head_json or '(absent)'}")
    for f in response.files:
        change = critic_pb2.FileChange.Name(f.change).removeprefix("FILE_CHANGE_").lower()
        print(f"\n{change}: {f.path}")
        if f.unified_diff:
            print(f.unified_diff, end="" if f.unified_diff.endswith("\n") else "\n")
    return 0


def _cmd_pin(reg: HarnessRegistry, args: argparse.Namespace) -> int:
    if args.ref is None:
        print(reg.get_pin(args.task))
        return 0
    ref, previous = reg.pin(args.task, args.ref)
    print(f"{args.task} -> {ref}" + (f" (was {previous})" if previous else ""))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """`zetta harness ...`: exit 1 with the service's message when a call fails."""
    parser = argparse.ArgumentParser(prog="zetta harness", description="Versioned harness packages in the registry")
    parser.add_argument("--critic", default=None, help=f"critic service address (default $ZETTA_CRITIC_ADDR or {DEFAULT_ADDRESS})")
    add_credential_flags(parser)
    sub = parser.add_subparsers(dest="cmd", required=True)
    p = sub.add_parser("publish", help="validate and publish a package directory")
    p.add_argument("dir")
    p.add_argument("--parent", default="", help="version this one derives from (NAME@VERSION)")
    p.add_argument("--evidence", help="JSON file: the evidence that admitted this version")
    p.add_argument("--validation", help="JSON file: the validation results that admitted this version")
    p.set_defaults(func=_cmd_publish)
    p = sub.add_parser("list", help="list versions and pins")
    p.add_argument("name", nargs="?", help="only this package name")
    p.set_defaults(func=_cmd_list)
    p = sub.add_parser("get", help="print a version's manifest and files, or write them with --out")
    p.add_argument("ref")
    p.add_argument("--task", default="", help="task key for NAME@pinned")
    p.add_argument("--out", help="write the package into this (empty or new) directory")
    p.set_defaults(func=_cmd_get)
    p = sub.add_parser("diff", help="changed files and params between two versions")
    p.add_argument("base")
    p.add_argument("head")
    p.set_defaults(func=_cmd_diff)
    p = sub.add_parser("pin", help="pin a version for a task key (without REF: show the pin)")
    p.add_argument("task")
    p.add_argument("ref", nargs="?")
    p.set_defaults(func=_cmd_pin)
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    try:
        with HarnessRegistry(args.critic, credentials=credentials_from_args(args)) as reg:
            return int(args.func(reg, args))
    except (ZettaError, OSError, ValueError) as exc:
        print(f"zetta harness {args.cmd}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
