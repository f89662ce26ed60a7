"""Rewrite docs/evolution.md's results block from a `zetta evolve experiment` results file.

  python scripts/gen_evolution_tables.py runs/experiment/results.json            # rewrite the block
  python scripts/gen_evolution_tables.py runs/experiment/results.json --check    # exit 1 if it differs

The block sits between the BEGIN/END GENERATED marks (services/evolver/results.py); nothing in it is
typed by hand, so every number on the page is one the command produced.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from services.evolver.results import render, replace_block  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("results", type=Path, help="results.json written by `zetta evolve experiment`")
    p.add_argument("--doc", type=Path, default=ROOT / "docs" / "evolution.md")
    p.add_argument("--check", action="store_true", help="only compare; exit 1 when the page is out of date")
    a = p.parse_args(argv)
    data = json.loads(a.results.read_text())
    page = a.doc.read_text()
    new = replace_block(page, render(data))
    if a.check:
        if new != page:
            print(f"{a.doc}: the results block does not match {a.results}", file=sys.stderr)
            return 1
        return 0
    a.doc.write_text(new)
    print(f"{a.doc}: results block rewritten from {a.results}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
