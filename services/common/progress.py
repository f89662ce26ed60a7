"""Progress bars of the long commands (tqdm on stderr), shown only where a person watches.

A bar is on when stderr is a terminal, unless the command was given ``--no-progress`` or the
environment sets ``ZETTA_NO_PROGRESS`` (any value but empty, ``0``, ``false`` or ``no``). Bars
write to stderr only, so a command's stdout (tables, JSON) reads the same with or without them.

``--no-progress`` (:func:`add_progress_option`) sets ``ZETTA_NO_PROGRESS=1`` in this process's
environment when it is parsed, so the library code a command calls, and the processes it starts,
see the same choice without passing a flag down.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Iterable, Mapping, Sequence
from typing import IO, Any

from tqdm import tqdm

ENV_VAR = "ZETTA_NO_PROGRESS"
_OFF_VALUES = ("", "0", "false", "no")


def progress_enabled(no_progress: bool = False, stream: IO[str] | None = None,
                     environ: Mapping[str, str] | None = None) -> bool:
    """Whether bars are drawn: not asked off (flag or environment) and ``stream`` (stderr) is a TTY."""
    if no_progress:
        return False
    env = os.environ if environ is None else environ
    if env.get(ENV_VAR, "").strip().lower() not in _OFF_VALUES:
        return False
    out = sys.stderr if stream is None else stream
    try:
        return bool(out.isatty())
    except (AttributeError, ValueError):  # no isatty, or a closed stream
        return False


def progress(iterable: Iterable[Any] | None = None, total: int | None = None, desc: str = "", unit: str = "ep",
             initial: int = 0, leave: bool = True) -> Any:
    """A tqdm bar on stderr (wrapping ``iterable`` when given), disabled by :func:`progress_enabled`.

    A disabled bar draws nothing and costs next to nothing; ``update``/``close`` stay callable."""
    return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, leave=leave, file=sys.stderr, dynamic_ncols=True,
                disable=not progress_enabled())


class _NoProgress(argparse.Action):
    """``--no-progress``: record the flag and turn bars off for this process and its children."""

    def __init__(self, option_strings: Sequence[str], dest: str, **kwargs: Any) -> None:
        super().__init__(option_strings, dest, nargs=0, default=False, **kwargs)

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: str | Sequence[Any] | None, option_string: str | None = None) -> None:
        setattr(namespace, self.dest, True)
        os.environ[ENV_VAR] = "1"


def add_progress_option(parser: argparse.ArgumentParser) -> None:
    """Give a command ``--no-progress``."""
    parser.add_argument("--no-progress", action=_NoProgress,
                        help=f"no progress bars (also {ENV_VAR}=1; they are off when stderr is not a terminal)")


class PhaseBars:
    """One bar per phase, closed when the next phase starts: a ``progress(phase, done, total)``
    callback (the evolver's loops report through one)."""

    def __init__(self, unit: str = "ep") -> None:
        self.unit = unit
        self._phase = ""
        self._bar: Any = None

    def __call__(self, phase: str, done: int, total: int) -> None:
        if phase != self._phase or self._bar is None:
            self.close()
            self._phase = phase
            self._bar = progress(total=total, desc=phase, unit=self.unit)
        self._bar.n = done
        self._bar.refresh()

    def close(self) -> None:
        """Close the current bar."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
