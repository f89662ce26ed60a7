"""Import a package's tools in a child process with a deadline, before a server trusts them.

With the harness sandbox on (the default, services/harness/sandbox/client.py) that child is a
sandbox child: the package's module-level code runs under a uid of its own, without network, in a
private scratch root, under the sandbox's resource limits, and is killed at the deadline. With
``ZETTA_HARNESS_SANDBOX=off`` it is a plain child forked from the fork server described below.

The static checks cannot tell whether module-level code of a tool finishes (a loop, a huge
comprehension); importing it inside a server would block that thread for good. So the registry
imports every new package once in a short-lived child process, builds a harness runtime from it
(which checks the critics, playbooks and adjudication rules against the runtime's library) and
kills the child at the deadline: a package whose import hangs or fails, or that makes no runnable
harness, is rejected with the reason, and the server never runs its module-level code before that
check passed. Children are forked from a fork server that preloaded the runtime, so a check costs
a fork rather than an interpreter start and numpy import (0.17 s instead of 0.55 s on the two
loaded cores here). As with any multiprocessing start method but fork, the calling program's main
module must be safe to import (``if __name__ == "__main__":``).
"""

from __future__ import annotations

import asyncio
import multiprocessing
import multiprocessing.forkserver
import sys
import warnings
from collections.abc import Mapping
from multiprocessing.connection import Connection

from services.harness.package import format as fmt
from services.harness.package.errors import PackageRejected, Problem


def _preload() -> list[str]:
    """This module and the runtime, plus the parent's main module when it runs as ``python -m``:
    multiprocessing re-runs that module in every child, which is then a cache hit, not an import."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    main = [spec.name] if spec is not None and spec.name else []
    return [__name__, "services.harness.runtime.engine", *main]


# Re-running a preloaded main module makes runpy warn once per child; the re-run is intended.
warnings.filterwarnings("ignore", message=".*found in sys.modules after import of package", category=RuntimeWarning)


_CTX = multiprocessing.get_context("forkserver")
_CTX.set_forkserver_preload(_preload())


def start_fork_server() -> None:
    """Start the fork server (or the sandbox zygote) now (1-3 s: it imports the runtime), so that
    the first publish does not wait for it."""
    from services.harness.sandbox import client as sandbox

    if sandbox.enabled():
        sandbox.start_zygote(wait=True)
    else:
        multiprocessing.forkserver.ensure_running()


def _run_sandboxed(files: dict[str, bytes], timeout_s: float, max_bytes: int) -> list[tuple[str, int, str]]:
    from services.harness.sandbox.client import CallFailed, SandboxClient, SandboxError, SandboxLimits

    limits = SandboxLimits.from_env()
    child = SandboxClient(SandboxLimits(limits.memory_mb, limits.cpu_s, limits.nofile, limits.fsize_bytes,
                                        load_timeout_s=max(limits.load_timeout_s, timeout_s)))
    try:
        return child.check(files, max_bytes, timeout_s)
    except SandboxError as exc:
        if child.dead and "no answer" in exc.reason or "hard limit" in exc.reason:
            raise PackageRejected(
                [Problem("tools/", 0, f"importing the tools took longer than {timeout_s:g} s; module-level code must be quick")]
            ) from None
        raise PackageRejected([Problem("tools/", 0, f"import check crashed in the sandbox: {exc.reason}")]) from None
    except CallFailed as exc:
        raise PackageRejected([Problem("tools/", 0, f"import check failed in the sandbox: {exc}")]) from None
    finally:
        child.close()


def _child(conn: Connection, files: dict[str, bytes], max_bytes: int) -> None:
    """Child side: load, build a runtime, send back the problems (empty when it all worked)."""
    from services.harness.package.loader import load_files
    from services.harness.runtime.engine import HarnessError, HarnessRuntime

    problems: list[tuple[str, int, str]] = []
    try:
        HarnessRuntime(load_files(files, max_bytes))
    except PackageRejected as exc:
        problems = [(p.path, p.line, p.reason) for p in exc.problems]
    except HarnessError as exc:
        problems = [(fmt.SKILL, 0, f"does not make a runnable harness: {exc}")]
    conn.send(problems)
    conn.close()


def _run(files: dict[str, bytes], timeout_s: float, max_bytes: int) -> list[tuple[str, int, str]]:
    receiver, sender = _CTX.Pipe(duplex=False)
    proc = _CTX.Process(target=_child, args=(sender, files, max_bytes), daemon=True)
    proc.start()
    sender.close()
    try:
        if not receiver.poll(timeout_s):
            proc.kill()
            raise PackageRejected(
                [Problem("tools/", 0, f"importing the tools took longer than {timeout_s:g} s; module-level code must be quick")]
            )
        try:
            return receiver.recv()
        except EOFError:
            proc.join(5)
            raise PackageRejected(
                [Problem("tools/", 0, f"import check crashed (exit code {proc.exitcode})")]
            ) from None
    finally:
        receiver.close()
        proc.join(5)


async def probe_import(files: Mapping[str, bytes], timeout_s: float, max_bytes: int) -> None:
    """Load ``files`` in a child process; raises PackageRejected with its problems, or when it
    does not finish within ``timeout_s`` seconds."""
    from services.harness.sandbox import client as sandbox

    run = _run_sandboxed if sandbox.enabled() else _run
    problems = await asyncio.to_thread(run, dict(files), timeout_s, max_bytes)
    if problems:
        raise PackageRejected([Problem(p, line, reason) for p, line, reason in problems])
