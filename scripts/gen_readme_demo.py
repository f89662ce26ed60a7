"""Rebuild the README's `make demo` output from the published demo report.

    zetta up --demo && python scripts/gen_results.py demo --from out/demo/report.json
    .venv/bin/python scripts/gen_readme_demo.py        # rewrites the block between the markers
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "clients" / "python"))

from services.ops.mission_demo import readme_block  # noqa: E402

BEGIN, END = "<!-- demo-output:begin (scripts/gen_readme_demo.py) -->", "<!-- demo-output:end -->"
RESULTS = ROOT / "docs" / "results" / "demo.json"
README = ROOT / "README.md"


def render(readme: str, doc: dict) -> str:
    """``readme`` with the block between the markers replaced by the demo's output."""
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    return f"{head}{BEGIN}\n{readme_block(doc)}\n{END}{tail}"


def main() -> int:
    README.write_text(render(README.read_text(), json.loads(RESULTS.read_text())))
    print(f"README.md: demo output from {RESULTS.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
