"""Render the pages under docs/results/ from their results files (docs/results/<topic>.json -> .md).

  python scripts/gen_results.py                      # every page whose results file is there
  python scripts/gen_results.py oracle throughput    # only these topics
  python scripts/gen_results.py evolution --from runs/experiment/results.json   # publish a run, then render
      # (an evolution run's store indexes are packed beside its page too: docs/results/evolution-stores/)
  python scripts/gen_results.py --check              # exit 1 when a page differs from its results file
  python scripts/gen_results.py evolution --superseded "rerun: zetta evolve experiment ..."
      # the shipped checkpoint changed and the run is not re-measured yet: its page says so

A results file records the command that measured it and the commit the code ran at; the commands
that write them are listed in docs/results/README.md. Pages are never edited by hand.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import json
import shutil
import sys
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT), str(ROOT / "clients" / "python")]

from services.common.provenance import RESULTS_DIR, page_header, superseded  # noqa: E402 - after the path set-up above

#: topic -> (module or script path, the function rendering a results file's page).
TOPICS: dict[str, tuple[str, str]] = {
    "vla": ("services.policy_worker.vla.results", "render"),
    "evolution": ("services.evolver.results", "page"),
    "evolution-goal": ("services.evolver.results", "page_own_suite"),
    "throughput": ("bench.bench_report", "page"),
    "bench-rollout": ("bench.bench_rollout", "page"),
    "harness-cost": ("bench.bench_harness", "page"),
    "policy-bench": ("bench.bench_policy", "page"),
    "oracle": ("scripts/oracle_report.py", "page"),
    "harness": ("scripts/eval_harness.py", "page"),
    "demo": ("services.ops.mission_demo", "page"),
}

#: Topics whose run keeps stores: publishing one packs their indexes (services/evolver/store_archive.py).
STORE_TOPICS = ("evolution", "evolution-goal")


def renderer(topic: str) -> Callable[[Mapping[str, Any]], str]:
    """The page function of a topic."""
    where, name = TOPICS[topic]
    if where.endswith(".py"):
        spec = importlib.util.spec_from_file_location(f"_results_{topic.replace('-', '_')}", ROOT / where)
        assert spec is not None and spec.loader is not None
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
    else:
        module = importlib.import_module(where)
    fn: Callable[[Mapping[str, Any]], str] = getattr(module, name)
    return fn


def render(topic: str, doc: Mapping[str, Any]) -> str:
    """A topic's page. A results file that kept only the text its command rendered (``rendered``,
    from a run whose raw measurements were not kept) is shown as that text under the common head."""
    if "rendered" in doc:
        return page_header(topic, str(doc.get("title", topic)), doc) + "\n" + str(doc["rendered"])
    return renderer(topic)(doc)


def _rewrite(path: Path, doc: dict) -> None:
    """Write a marked results file in the layout it had (its indentation, sorted keys or not), so
    the mark is the whole diff."""
    text = path.read_text()
    second = text.splitlines()[1] if text.count("\n") > 1 else ""
    indent = len(second) - len(second.lstrip(" ")) or 1
    keys = list(json.loads(text))
    path.write_text(json.dumps(doc, indent=indent, sort_keys=keys == sorted(keys)) + "\n")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    p.add_argument("topics", nargs="*", help=f"topics to render (default: every results file; known: {', '.join(TOPICS)})")
    p.add_argument("--from", dest="source", type=Path, default=None,
                   help="copy this results file to docs/results/<topic>.json first (one topic)")
    p.add_argument("--results-dir", type=Path, default=RESULTS_DIR, help="where the results files are")
    p.add_argument("--out-dir", type=Path, default=None, help="write the pages here (default: beside their files)")
    p.add_argument("--check", action="store_true", help="write nothing; exit 1 when a page is out of date")
    p.add_argument("--superseded", metavar="NOTE", default=None,
                   help="mark the topic's results file as measured on weights that are no longer the shipped ones "
                        "(one topic; NOTE says what re-measures it)")
    p.add_argument("--code-changed", metavar="NOTE", default=None,
                   help="mark the topic's results file as measured by code that has changed since, at HEAD (one "
                        "topic; NOTE says what changed and what re-measures it)")
    a = p.parse_args(argv)
    unknown = [t for t in a.topics if t not in TOPICS]
    found = sorted(f.stem for f in a.results_dir.glob("*.json"))
    strays = [t for t in found if t not in TOPICS]
    if unknown or strays:
        p.error(f"unknown topic(s) {unknown + strays}; known: {', '.join(TOPICS)}")
    if a.source is not None:
        if len(a.topics) != 1:
            p.error("--from goes with exactly one topic")
        if a.topics[0] in STORE_TOPICS:
            from services.evolver import store_archive

            try:
                for path in store_archive.pack(a.source.parent, json.loads(a.source.read_text()), a.results_dir,
                                               a.topics[0]):
                    print(f"wrote {path} ({path.stat().st_size} bytes)")
            except ValueError as exc:
                p.error(f"{a.source}: {exc}")
        shutil.copyfile(a.source, a.results_dir / f"{a.topics[0]}.json")
        found = sorted({*found, a.topics[0]})
    if a.superseded is not None:
        if len(a.topics) != 1:
            p.error("--superseded goes with exactly one topic")
        from services.common.policies import default_checkpoint
        from services.common.provenance import weights_sha256

        data = a.results_dir / f"{a.topics[0]}.json"
        _rewrite(data, superseded(json.loads(data.read_text()), weights_sha256(default_checkpoint()), a.superseded))
    if a.code_changed is not None:
        if len(a.topics) != 1:
            p.error("--code-changed goes with exactly one topic")
        from services.common.provenance import code_changed, git_source

        data = a.results_dir / f"{a.topics[0]}.json"
        _rewrite(data, code_changed(json.loads(data.read_text()), str(git_source(ROOT).get("commit") or ""),
                                    a.code_changed))
    topics = a.topics or found
    stale = []
    for topic in topics:
        data = a.results_dir / f"{topic}.json"
        if not data.exists():
            p.error(f"{data} does not exist")
        page = render(topic, json.loads(data.read_text()))
        target = (a.out_dir or a.results_dir) / f"{topic}.md"
        if a.check:
            if not target.exists() or target.read_text() != page:
                stale.append(str(target))
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_text(page)
        print(f"wrote {target}")
    for path in stale:
        print(f"{path}: out of date with its results file; run {' '.join(['python scripts/gen_results.py', *a.topics])}",
              file=sys.stderr)
    return 1 if stale else 0


if __name__ == "__main__":
    sys.exit(main())
