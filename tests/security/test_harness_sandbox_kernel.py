"""The kernel layer of the harness sandbox on its own: package code that never went through the
static checks (loaded unchecked, straight into the sandbox runner) tries to write files, start
processes, open sockets, signal the host and take the machine's memory. Every attempt fails inside
the child, and the test checks from outside that nothing happened: no marker file, no connection
on a listener it opened, the host process alive; and one child cannot signal another (each has a
uid of its own). Needs root (to change uid and chroot); without it the child runs degraded and
these tests are skipped with the reason."""

from __future__ import annotations

import os
import socket
import time
from pathlib import Path

import numpy as np
import pytest

from services.harness.sandbox.client import UID_BASE, SandboxClient, SandboxError
from tests.security.escape_attempts import COMMON, LAST, PRELUDE
from tests.security.escape_attempts import targets as escape_targets

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(os.geteuid() != 0, reason="the sandbox changes uid and chroots only when started as root"),
]

ATTEMPTS = PRELUDE + r'''
import subprocess


def critic_system(window, params):
    status = os.system(f"touch {params['marker']}.system")
    return Proposal("system", f"exit status {status}", "", {"blocked": float(status != 0)})


def critic_write_tmp(window, params):
    def write():
        with open("/tmp/zetta-sandbox-escape", "w") as f:
            f.write("x")
    return _try("write_tmp", write)


def critic_fork(window, params):
    def fork():
        pid = os.fork()
        if pid == 0:
            open(params["marker"] + ".fork", "w").close()
            os._exit(0)
        return pid
    return _try("fork", fork)


def critic_subprocess(window, params):
    return _try("subprocess", lambda: subprocess.run(["/bin/sh", "-c", f"touch {params['marker']}.subprocess"]))
''' + COMMON + LAST


@pytest.fixture
def targets(tmp_path: Path):
    """A world-writable directory (only the sandbox may stop a write there), a TCP listener and a
    Unix socket listener on this host."""
    shared = tmp_path / "shared"
    shared.mkdir()
    with escape_targets(shared) as (params, tcp, unix):
        yield {**params, "host_pid": os.getpid()}, shared, tcp, unix


def _run_all(params: dict) -> tuple[SandboxClient, dict]:
    child = SandboxClient()
    loaded = child.load(4, {"attempts": ATTEMPTS}, {"attempts": params}, checked=False)
    child.start("", [])
    results = child.step(0, {"robot0_eef_pos": np.zeros(3)}, None, frozenset(),
                         [(i, False) for i in range(len(loaded.critics))], lambda i: 5.0)
    out = {}
    for name, res in zip(loaded.critics, results):
        assert res.proposal is not None, (name, res.error)
        evidence, _, details = res.proposal
        out[name.removeprefix("attempts.")] = (evidence, details)
    return child, out


def test_unchecked_package_code_cannot_escape_the_sandbox(targets) -> None:
    params, shared, tcp, unix = targets
    child, out = _run_all(params)
    for name, (evidence, details) in sorted(out.items()):
        print(f"{name:>13}: {evidence}  {details}")  # shown with -s: what each attempt got
    try:
        evidence, ids = out["whoami"]
        own = float(UID_BASE + child.pid)
        assert ids == {"uid": own, "gid": own, "euid": own, "groups": 0.0}
        assert evidence == "/"  # its own scratch dir, as its root
        assert child.isolation["mode"] == "root" and child.isolation["filesystem"] == "chroot"
        assert child.isolation["uid"] == UID_BASE + child.pid and child.isolation["chroot"]
        assert child.isolation["network_isolated"]
        assert child.isolation["degraded"] == []
        for attempt in ("system", "write_marker", "write_tmp", "read_passwd", "connect", "unix", "fork",
                        "subprocess", "thread", "signal_host", "setuid_root", "big_file", "memory_bomb"):
            evidence, details = out[attempt]
            assert details["blocked"] == 1.0, (attempt, evidence)
        # the reasons are the kernel's, not a missing module or a Python-level guard
        assert "Operation not permitted" in out["connect"][0]  # the seccomp filter: no socket at all
        assert "Operation not permitted" in out["unix"][0]
        assert "Resource temporarily unavailable" in out["fork"][0]
        assert "Operation not permitted" in out["signal_host"][0] and "Operation not permitted" in out["setuid_root"][0]
        assert "File too large" in out["big_file"][0]
        assert "MemoryError" in out["memory_bomb"][0]
        assert out["scratch"] == ("succeeded: 'allowed'", {"blocked": 0.0})  # its scratch space works
    finally:
        child.close()
    # From outside: nothing happened.
    assert sorted(p.name for p in shared.iterdir()) == ["listener.sock"]
    assert not Path("/tmp/zetta-sandbox-escape").exists()
    for listener in (tcp, unix):
        with pytest.raises(socket.timeout):
            listener.accept()


def test_a_runaway_call_is_killed_at_its_hard_limit_and_the_child_is_gone() -> None:
    spin = "def critic_spin(window, params):\n    sum(range(400_000_000))\n"
    child = SandboxClient()
    child.load(4, {"spin": spin}, checked=False)
    child.start("", [])
    pid = child.pid
    t0 = time.perf_counter()
    with pytest.raises(SandboxError) as err:
        child.step(0, {}, None, frozenset(), [(0, False)], lambda i: 0.2)
    took = time.perf_counter() - t0
    assert err.value.index == 0 and "hard limit" in err.value.reason
    assert took < 0.2 + 0.3, took
    for _ in range(100):  # SIGKILL is asynchronous; the zygote reaps it
        if not Path(f"/proc/{pid}").exists():
            break
        time.sleep(0.02)
    assert not Path(f"/proc/{pid}").exists()


def test_the_static_checks_still_apply_inside_the_sandbox() -> None:
    """Checked loading (what the services do) refuses the same code before running it."""
    from services.harness.sandbox.client import CallFailed

    child = SandboxClient()
    try:
        with pytest.raises(CallFailed, match="not allowed|only allowed|may not import"):
            child.load(4, {"attempts": ATTEMPTS}, {}, checked=True)
    finally:
        child.close()


SIGNAL_OTHER = r'''
import os
import signal

from services.harness.runtime.api import Proposal


def critic_signal_other(window, params):
    target = int(params["pid"])
    try:
        os.kill(target, 0)  # permission check only
        os.kill(target, signal.SIGKILL)
    except BaseException as exc:
        return Proposal("signal_other", f"{type(exc).__name__}: {exc}", "", {"blocked": 1.0})
    return Proposal("signal_other", "succeeded", "", {"blocked": 0.0})
'''


def test_one_child_cannot_signal_another() -> None:
    victim, attacker = SandboxClient(), SandboxClient()
    try:
        assert victim.isolation["uid"] != attacker.isolation["uid"]
        attacker.load(4, {"attack": SIGNAL_OTHER}, {"attack": {"pid": victim.pid}}, checked=False)
        attacker.start("", [])
        (res,) = attacker.step(0, {}, None, frozenset(), [(0, False)], lambda i: 5.0)
        assert res.proposal is not None, res.error
        evidence, _, details = res.proposal
        assert details["blocked"] == 1.0 and "Operation not permitted" in evidence, evidence
        # The victim still answers.
        victim.load(4, {"ok": "def critic_ok(window, params):\n    return None\n"}, checked=False)
        victim.start("", [])
        (ok,) = victim.step(0, {}, None, frozenset(), [(0, False)], lambda i: 5.0)
        assert ok.kind == 0 and not victim.dead
    finally:
        victim.close()
        attacker.close()
