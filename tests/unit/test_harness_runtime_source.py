"""The env worker's harness source: directory packages, caching by content and its bound."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.common.grpc_errors import ServiceError
from services.env_worker.harness_loop import HarnessSource, bind
from zetta_wire.v1 import types_pb2

SKILL = '+++\nname = "src-test"\ndescription = "d"\n[runtime]\nwindow = {w}\n+++\nbody\n'


def package_dir(root: Path, window: int) -> Path:
    root.mkdir(parents=True)
    (root / "SKILL.md").write_text(SKILL.format(w=window))
    return root


def test_directory_packages_are_cached_by_content_and_the_cache_is_bounded(tmp_path: Path) -> None:
    source = HarnessSource(max_cached=2)
    a = package_dir(tmp_path / "a", 5)
    spec = types_pb2.ResetSpec(harness_dir=str(a))
    first = source.load(spec, "s")
    assert source.load(spec, "s") is first  # unchanged content: the same loaded package
    runtime = bind(None, first)
    assert bind(runtime, first) is runtime  # and the slot keeps its runtime
    (a / "SKILL.md").write_text(SKILL.format(w=6))
    edited = source.load(spec, "s")
    assert edited is not first and edited.skill["runtime"]["window"] == 6
    assert bind(runtime, edited) is not runtime
    package_dir(tmp_path / "b", 7)
    source.load(types_pb2.ResetSpec(harness_dir=str(tmp_path / "b")), "s")
    (a / "SKILL.md").write_text(SKILL.format(w=5))
    assert source.load(spec, "s") is not first  # evicted: loaded again


def test_no_harness_and_bad_references(tmp_path: Path) -> None:
    source = HarnessSource()
    assert source.load(types_pb2.ResetSpec(), "s") is None
    with pytest.raises(ServiceError, match="not both"):
        source.load(types_pb2.ResetSpec(harness="x@1", harness_dir=str(tmp_path)), "s")
    with pytest.raises(ServiceError, match="no ZETTA_CRITIC_ADDR") as err:
        source.load(types_pb2.ResetSpec(harness="x@1"), "s")
    assert err.value.code.name == "FAILED_PRECONDITION"
