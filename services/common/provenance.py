"""Where a published figure came from, and the pages under docs/results/ that show it.

A topic's results file ``docs/results/<topic>.json`` holds the measurements with the command that
made them and the commit the code ran at (``source``); ``docs/results/<topic>.md`` is rendered
from it and never edited (``python scripts/gen_results.py`` renders them all; ``--check`` says
which are out of date). :func:`page_header` is the head every such page shares.
"""

from __future__ import annotations

import hashlib
import json
import os
import platform
import subprocess
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

#: The folder of the results files and their pages.
RESULTS_DIR = Path(__file__).resolve().parents[2] / "docs" / "results"
#: The command that renders every page from its results file.
RENDER_COMMAND = "python scripts/gen_results.py"


def git_source(root: Path) -> dict[str, Any]:
    """The commit the code ran at, and whether the tree had uncommitted changes ("" outside git)."""
    def git(*args: str) -> str:
        try:
            return subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, timeout=30,
                                  check=True).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    return {"commit": git("rev-parse", "HEAD"), "dirty": bool(git("status", "--porcelain", "--untracked-files=no"))}


def weights_sha256(checkpoint: str | Path | None) -> str:
    """sha256 of a checkpoint's weights (``model.pt``), the hash every results file reports, so a
    reader matches an evolution run to the policy evaluation of the same weights ("" without one)."""
    path = Path(checkpoint) / "model.pt" if checkpoint else None
    return hashlib.sha256(path.read_bytes()).hexdigest() if path is not None and path.is_file() else ""


def machine() -> str:
    """The machine a figure was measured on, down to what changes its floats: torch's CPU kernels
    (MKL and oneDNN on AVX2 or AVX-512) round differently in the last bits, and closed-loop episodes
    amplify that, so a seed's episode replays bit for bit on the same kind of CPU only."""
    model, family = "", ""
    try:
        lines = Path("/proc/cpuinfo").read_text().splitlines()[:30]  # the first CPU's block
        info = {k.strip(): v.strip() for k, v in (line.split(":", 1) for line in lines if ":" in line)}
        model = info.get("model name", "")
        if "cpu family" in info:
            family = f" (family {info['cpu family']} model {info.get('model', '?')})"
    except OSError:
        pass
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    try:  # an image without torch (gateway, critic) has no kernels to name
        import torch

        kernels = f", torch CPU kernels {torch.backends.cpu.get_cpu_capability()}"
    except ImportError:
        kernels = ""
    return f"{platform.machine()}, {cpus} CPUs" + (f", {model}{family}" if model else "") + kernels


def provenance(command: str, root: Path) -> dict[str, Any]:
    """What every results file records about its run: the command, the commit, the date, the machine."""
    return {"command": command, "source": git_source(root), "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
            "machine": machine()}


def page_header(topic: str, title: str, doc: Mapping[str, Any]) -> str:
    """The head of a generated page: what it is generated from and by which command, and the run's
    command and commit as its results file records them."""
    src = doc.get("source") or {}
    commit = str(src.get("commit") or "unknown")
    dirty = " (with uncommitted changes)" if src.get("dirty") else ""
    lines = [f"# {title} (generated)", "",
             f"Generated from [`{topic}.json`]({topic}.json) by `{RENDER_COMMAND} {topic}`; do not edit by hand.", "",
             f"- measured by: `{doc.get('command', 'unknown')}`",
             f"- commit: `{commit[:12]}`{dirty}" + (f", {doc['date']}" if doc.get("date") else "")
             + (f", on {doc['machine']}" if isinstance(doc.get("machine"), str) else "")]
    if src.get("note"):
        lines.append(f"- {src['note']}")
    if doc.get("superseded"):
        old = doc["superseded"]
        lines.append(f"- **Measured with earlier weights** (model.pt sha256 `{old['measured_sha256'][:12]}`), not the "
                     f"shipped checkpoint's (`{old['shipped_sha256'][:12]}`): the figures reproduce at commit "
                     f"`{commit[:12]}`, not with the shipped policy, until the command above is rerun. {old.get('note', '')}"
                     .rstrip())
    if doc.get("code_changed"):
        change = doc["code_changed"]
        lines.append(f"- **The code that measures it changed after this run** (at commit `{change['commit'][:12]}`): "
                     f"the figures were measured at commit `{commit[:12]}` and need not reproduce at `{change['commit'][:12]}` "
                     f"or later until the command above is rerun. {change.get('note', '')}".rstrip())
    return "\n".join(lines) + "\n"


def code_changed(doc: Mapping[str, Any], commit: str, note: str = "") -> dict[str, Any]:
    """``doc`` marked as measured by code that has changed since (at ``commit``) in a way that moves
    its figures; its page says so at the top until the command is rerun."""
    measured = str((doc.get("source") or {}).get("commit") or "")
    if not commit or commit == measured:
        raise ValueError("the change must be a commit other than the one the results were measured at")
    return {**doc, "code_changed": {"commit": commit, "note": note}}


def superseded(doc: Mapping[str, Any], shipped_sha256: str, note: str = "") -> dict[str, Any]:
    """``doc`` marked as measured on weights that are no longer the shipped ones (its page says so
    at the top); the results file's figures stay those of the weights it names."""
    policy = doc["policy"] if isinstance(doc.get("policy"), Mapping) else doc
    measured = str(policy.get("checkpoint_sha256") or "")
    if not measured or measured == shipped_sha256:
        raise ValueError("the results file names no weights, or the shipped ones: nothing is superseded")
    return {**doc, "superseded": {"measured_sha256": measured, "shipped_sha256": shipped_sha256, "note": note}}


def publish(topic: str, title: str, script: str, argv: list[str], doc: Mapping[str, Any],
            render: Callable[[Mapping[str, Any]], str], root: Path, directory: Path = RESULTS_DIR) -> list[Path]:
    """Write a bench's measurements as ``<topic>.json`` and its page, with the command that reruns
    them (``python <script> <argv>``) and the commit they ran at."""
    command = " ".join(["python", script, *argv])
    full = {"title": title, **provenance(command, root), **doc}
    return write_results(topic, full, render(full), directory)


def write_results(topic: str, doc: Mapping[str, Any], page: str, directory: Path = RESULTS_DIR) -> list[Path]:
    """Write ``<topic>.json`` and its page ``<topic>.md`` into ``directory``."""
    directory.mkdir(parents=True, exist_ok=True)
    data, md = directory / f"{topic}.json", directory / f"{topic}.md"
    data.write_text(json.dumps(doc, indent=1, default=float) + "\n")
    md.write_text(page)
    return [data, md]
