"""Worker processes of the long local jobs (demo collection, evaluation): telling a finished pool
from one that lost a process."""

from __future__ import annotations

from collections.abc import Sequence
from multiprocessing.process import BaseProcess


def still_running(procs: Sequence[BaseProcess], what: str, left: int, resume: str) -> bool:
    """After a wait that brought no result: whether any of ``procs`` still runs. Raises when one
    exited with an error (the OOM killer takes one, say) while ``left`` episodes were due, instead
    of letting the job finish with the survivors' share: ``what`` names the process, ``resume`` says
    how to continue."""
    dead = [p for p in procs if not p.is_alive() and p.exitcode not in (0, None)]
    if dead:
        raise RuntimeError(f"{what} died (exit code {dead[0].exitcode}) with {left} episodes left; {resume}")
    return any(p.is_alive() for p in procs)
