"""Other revisions of this repository as runnable trees, for benchmarks that measure two side by side.

A benchmark that compares this tree with REV in one run (so the machine's drift weighs on both)
exports REV with ``git archive`` into a temporary directory (the working tree is not touched) and
builds that tree's own gRPC stubs from its ``proto/``, which are build output and not committed.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def export(rev: str, into: Path) -> Path:
    """The tree of ``rev`` in ``into/tree``, with its generated stubs."""
    root = into / "tree"
    root.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", rev], check=True, capture_output=True).stdout
    subprocess.run(["tar", "-x", "-C", str(root)], input=archive, check=True)
    subprocess.run([sys.executable, str(root / "scripts" / "gen_proto.py")], cwd=root, check=True,
                   stdout=subprocess.DEVNULL)
    return root


def import_env(root: Path) -> dict[str, str]:
    """Environment variables that make a Python process (``python -m services...``) import ``root``'s
    code: its paths first, and no current directory in front of them (``PYTHONSAFEPATH``), which
    would otherwise put the working tree's packages first when run from the repository."""
    return {"PYTHONPATH": os.pathsep.join([str(root), str(root / "clients" / "python")]), "PYTHONSAFEPATH": "1"}
