"""The published stores of an experiment: each store's sqlite index, compacted and xz-compressed.

A results page is generated from ``results.json``; the rollouts and events behind it live in the
run's stores (``<out>/<suite>/index.sqlite``, ``<out>/transfer-<suite>/index.sqlite``). Publishing
a run packs those indexes beside the page (``docs/results/<topic>-stores/<store>.index.sqlite.xz``)
so a reader can query every rollout the page counts. Traces and videos stay out (about 40 KB per
rollout); the run's command regenerates them. The archives of all pages together stay under
:data:`LIMIT_BYTES`, so the repository does not grow with every re-measurement.
"""

from __future__ import annotations

import lzma
import sqlite3
import tempfile
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Most bytes the archives of every published page may take together (docs/results/README.md).
LIMIT_BYTES = 200_000
SUFFIX = ".index.sqlite.xz"


def stores_dir(results_dir: Path, topic: str) -> Path:
    """Where a page's archives live."""
    return results_dir / f"{topic}-stores"


def published_stores(doc: Mapping[str, Any]) -> list[str]:
    """Names of the stores a results file counts rollouts in (a transfer store that ran nothing has none)."""
    return sorted(name for name, counts in doc.get("rollouts_by_purpose", {}).items() if counts.get("purposes"))


def compress_index(index: Path) -> bytes:
    """The index compacted (``VACUUM INTO``: no free pages, no WAL) and xz-compressed at the strongest preset."""
    with tempfile.TemporaryDirectory() as tmp:
        compact = Path(tmp) / "index.sqlite"
        db = sqlite3.connect(index)
        try:
            db.execute("VACUUM INTO ?", (str(compact),))
        finally:
            db.close()
        return lzma.compress(compact.read_bytes(), preset=9 | lzma.PRESET_EXTREME)


def pack(run_dir: Path, doc: Mapping[str, Any], results_dir: Path, topic: str) -> list[Path]:
    """Replace ``topic``'s archives with the stores of the run under ``run_dir``; returns the files.

    Raises ValueError, writing nothing, when a store is missing or the archives of every page
    would exceed :data:`LIMIT_BYTES`."""
    names = published_stores(doc)
    missing = [str(run_dir / n / "index.sqlite") for n in names if not (run_dir / n / "index.sqlite").exists()]
    if missing:
        raise ValueError(f"the run's stores are not beside its results file: {', '.join(missing)}")
    packed = {n: compress_index(run_dir / n / "index.sqlite") for n in names}
    target = stores_dir(results_dir, topic)
    others = sum(f.stat().st_size for f in results_dir.glob(f"*-stores/*{SUFFIX}") if f.parent != target)
    total = others + sum(len(b) for b in packed.values())
    if total > LIMIT_BYTES:
        raise ValueError(f"the published stores would take {total} bytes, over the {LIMIT_BYTES} limit")
    if target.exists():
        for old in target.glob(f"*{SUFFIX}"):
            old.unlink()
    target.mkdir(parents=True, exist_ok=True)
    out = []
    for name, blob in packed.items():
        path = target / f"{name}{SUFFIX}"
        path.write_bytes(blob)
        out.append(path)
    return out


def rollout_counts(archive: Path) -> dict[str, int]:
    """Rollouts by purpose in an archive (what a results file's ``rollouts_by_purpose`` counts)."""
    with tempfile.TemporaryDirectory() as tmp:
        index = Path(tmp) / "index.sqlite"
        index.write_bytes(lzma.decompress(archive.read_bytes()))
        db = sqlite3.connect(index)
        try:
            return dict(db.execute("SELECT purpose, count(*) FROM rollouts GROUP BY purpose"))
        finally:
            db.close()
