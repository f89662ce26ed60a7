"""The one error a harness package can fail with, carrying every problem found.

A package written by the evolver or an LLM is rejected as a whole; the person (or the repair
loop) reading the rejection needs every offending file, line and reason at once, not the first.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Problem:
    """One reason to reject: the file (relative path), the line (0 when it is about the whole
    file) and what is wrong."""

    path: str
    line: int
    reason: str

    def __str__(self) -> str:
        return f"{self.path}:{self.line}: {self.reason}" if self.line else f"{self.path}: {self.reason}"


class PackageRejected(ValueError):
    """A harness package failed validation; ``problems`` lists every reason."""

    def __init__(self, problems: Sequence[Problem]) -> None:
        self.problems = list(problems)
        super().__init__("harness package rejected: " + "; ".join(str(p) for p in self.problems))


def reject(path: str, reason: str, line: int = 0) -> PackageRejected:
    """A rejection with a single problem."""
    return PackageRejected([Problem(path, line, reason)])
