"""The evolver runs candidate package code (critics an LLM wrote, tools/c_llm_<hash>.py) only in the
harness sandbox: building a candidate's runtime imports its tools in a sandbox child, and the
diagnostic replay runs its critic there frame by frame. A critic that raises, spins or attacks the
machine is refused with the reason (what the evolver records as the LLM's refused patches) and the
repair goes on with the next patch; nothing it tried happened. The kernel-layer test bypasses the
static checks (as an escape from them would) so that the attacks reach the kernel; these need root (the
sandbox changes uid and chroots only then). scripts/eval_harness.py never imports the
package it evaluates (its env workers run it in their sandbox)."""

from __future__ import annotations

import json
import os
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any, cast

import pytest

from services.harness.sandbox.host import SandboxedCode
from services.evolver.llm import LLMConfig, propose
from services.evolver.repair import ReplayCase
from tests.unit.test_evolver_repair import DROP_CODE, PARENT, _Handler, drop_cluster, llm_server

pytestmark = [pytest.mark.timeout(180)]
needs_root = pytest.mark.skipif(os.geteuid() != 0,
                                reason="the sandbox changes uid and chroots only when started as root")
ROOT = Path(__file__).resolve().parents[2]

__all__ = ["llm_server"]  # the fixture, used by name


@pytest.fixture
def targets(tmp_path: Path) -> Iterator[tuple[Path, socket.socket]]:
    """A world-writable directory (only the sandbox can stop a write there) and a TCP listener."""
    shared = tmp_path / "shared"
    shared.mkdir()
    shared.chmod(0o777)
    tcp = socket.create_server(("127.0.0.1", 0))
    tcp.settimeout(0.5)
    yield shared, tcp
    tcp.close()


def _patch(code: str, evidence: str = "x") -> dict:
    return {"critic": {"code": code, "params": {"confirm": 3}, "evidence": evidence},
            "recovery": {"template": "acquire"}}


def _propose(llm_server: str, patches: list[dict]) -> tuple[list, list[str]]:
    spec, medoid, members, succ = cast(tuple[Any, ReplayCase, list[ReplayCase], list[Any]], drop_cluster())
    _Handler.reply = json.dumps({"patches": patches})
    return propose(LLMConfig(llm_server, "tiny"), spec, PARENT, medoid, members, succ)


@needs_root
def test_failing_critics_are_refused_with_the_reason_and_the_repair_goes_on(
        llm_server: str, targets: tuple[Path, socket.socket], monkeypatch: pytest.MonkeyPatch) -> None:
    """Through the checks the services apply: code the static checks refuse never runs; a critic
    that raises or spins on the replay, or whose module-level code hangs, is stopped in its child
    and refused with why; the good patch among them is still accepted."""
    monkeypatch.setenv("ZETTA_CRITIC_MAX_HARD_LIMIT_MS", "300")
    monkeypatch.setenv("ZETTA_SANDBOX_LOAD_TIMEOUT_S", "1")
    shared, _ = targets
    marker = shared / "marker"
    patches = [
        _patch(f"import os\n\ndef detect(window, params):\n    os.system('touch {marker}')\n"),
        _patch(f"def detect(window, params):\n    open({str(marker)!r}, 'w').write('x')\n"),
        _patch("def detect(window, params):\n    raise ValueError('boom')\n"),
        _patch("def detect(window, params):\n    while True:\n        pass\n"),
        _patch("while True:\n    pass\n\n\ndef detect(window, params):\n    return None\n"),
        _patch(DROP_CODE, "dropped"),
    ]
    accepted, refused = _propose(llm_server, patches)
    print(*refused, sep="\n")
    assert [c.critic.code for c in accepted] == [DROP_CODE]
    assert len(refused) == 5, refused
    assert "'os' is not allowed" in refused[0]
    assert "open" in refused[1] and "not allowed" in refused[1]
    assert "raised ValueError: boom" in refused[2] and "in the sandbox" in refused[2]
    assert "hard limit" in refused[3] and "killed" in refused[3]
    assert "does not build" in refused[4] and "sandbox" in refused[4]
    assert sorted(shared.iterdir()) == []


def _unchecked(monkeypatch: pytest.MonkeyPatch) -> None:
    """Take the static checks and restricted builtins away (host and child): only the kernel is left."""
    import services.harness.package.loader as loader
    import services.harness.runtime.engine as engine
    import services.harness.sandbox.host as host

    class Unchecked(SandboxedCode):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            kwargs["checked"] = False
            super().__init__(*args, **kwargs)

    monkeypatch.setattr(loader, "check_source", lambda path, text: None)
    monkeypatch.setattr(engine, "SandboxedCode", Unchecked)
    monkeypatch.setattr(host, "SandboxedCode", Unchecked)


@needs_root
def test_a_malicious_critic_cannot_act_when_the_evolver_replays_it(
        llm_server: str, targets: tuple[Path, socket.socket], monkeypatch: pytest.MonkeyPatch) -> None:
    """With the Python-level checks gone, critics that write a marker file, connect to a listener
    on this host, read /etc/passwd (firing, so that it would become a candidate, if it could) or
    do harm at import are all stopped by the kernel, in the child: the reasons are the kernel's
    errors, and from outside nothing happened."""
    _unchecked(monkeypatch)
    shared, tcp = targets
    marker, port = shared / "marker", tcp.getsockname()[1]
    patches = [
        _patch(f"def detect(window, params):\n    open({str(marker)!r}, 'w').write('escaped')\n"),
        _patch(f"import socket\n\ndef detect(window, params):\n"
               f"    socket.create_connection(('127.0.0.1', {port}), timeout=1.0)\n"),
        _patch("def detect(window, params):\n    return {'bytes': float(len(open('/etc/passwd').read()))}\n"),
        _patch(f"open({str(marker) + '.import'!r}, 'w').write('escaped')\n\n\n"
               "def detect(window, params):\n    return None\n"),
    ]
    accepted, refused = _propose(llm_server, patches)
    print(*refused, sep="\n")
    assert accepted == [] and len(refused) == 4, refused
    assert "FileNotFoundError" in refused[0] and "in the sandbox" in refused[0]  # chroot: the path is not there
    assert "PermissionError" in refused[1] and "Operation not permitted" in refused[1]  # seccomp: no socket
    assert "FileNotFoundError" in refused[2] and "/etc/passwd" in refused[2]  # chroot
    assert "does not build" in refused[3] and "FileNotFoundError" in refused[3]  # module-level code, at load
    assert sorted(shared.iterdir()) == []
    with pytest.raises(socket.timeout):
        tcp.accept()


def test_eval_harness_never_imports_the_package_it_evaluates(tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """A tool whose module-level code would fail (or do anything) if imported here: the script
    hashes and checks the package without importing it (--rebuild: no stack, the table only)."""
    import importlib.util
    import shutil

    pkg = tmp_path / "pkg"
    shutil.copytree(ROOT / "examples" / "harnesses" / "libero-goal-pick-place", pkg)
    (pkg / "tools" / "tripwire.py").write_text("raise ValueError('imported in the evaluating process')\n")
    out = tmp_path / "eval.jsonl"
    out.write_text("")
    spec = importlib.util.spec_from_file_location("eval_harness_under_test", ROOT / "scripts" / "eval_harness.py")
    assert spec is not None and spec.loader is not None
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    assert script.main(["--harness", str(pkg), "--out", str(out), "--rebuild"]) == 0
    assert "| suite | task |" in capsys.readouterr().out
