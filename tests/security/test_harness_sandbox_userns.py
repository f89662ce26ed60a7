"""The harness sandbox of a host that is not root (the Kubernetes base runs every pod as uid 10001
without capabilities): its children are isolated through a user namespace, not degraded.

The host runs as uid and gid 10001 (tests/security/sandbox_host_unprivileged.py; when the test
runs as root it drops to that uid in a process of its own, in a private mount namespace that makes
the interpreter reachable, and changes nothing else on the machine). Package code loaded without
the static checks then tries to read /etc/passwd and the repository, write outside its scratch
space, connect to a TCP and a Unix listener of the test, signal its host (which, outside the user
namespace, is the same uid), fork, make a namespace or a mount, and take memory: each fails with
the kernel's error, its rlimits are in place, and from outside (root reads /proc) the child has no
capability, is in its own user, network, IPC and mount namespaces with 65534 mapped to 10001, sees
one mount (its scratch directory), and nothing happened to the test's files and listeners. The
gauges and the log say "userns". With unshare refused (a seccomp filter on the host, as a
container runtime's default profile does) the same host runs degraded and says so.
"""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import pytest

from tests.security.escape_attempts import COMMON, LAST, PRELUDE
from tests.security.escape_attempts import targets as escape_targets

ROOT = Path(__file__).resolve().parents[2]
HOST = Path(__file__).with_name("sandbox_host_unprivileged.py")
UID = GID = 10001  # the uid of the Kubernetes base's pods

pytestmark = [pytest.mark.timeout(180)]

ATTEMPTS = PRELUDE + r'''
import ctypes
import errno
import resource

_libc = ctypes.CDLL(None, use_errno=True)


def _raw(name, nr, *args):
    """A system call straight through libc: blocked when it returns -1 (its errno in the evidence)."""
    r = _libc.syscall(nr, *args)
    err = ctypes.get_errno()
    return Proposal(name, f"{r} {errno.errorcode.get(err, err) if r == -1 else ''}", "",
                    {"blocked": float(r == -1)})


def critic_list_root(window, params):
    return Proposal("list_root", repr(sorted(os.listdir("/"))), "", {})


def critic_rlimits(window, params):
    names = ("RLIMIT_AS", "RLIMIT_CPU", "RLIMIT_NOFILE", "RLIMIT_FSIZE", "RLIMIT_NPROC", "RLIMIT_CORE")
    return Proposal("rlimits", "", "", {n: float(resource.getrlimit(getattr(resource, n))[1]) for n in names})


def critic_read_repo(window, params):
    return _try("read_repo", lambda: open(params["repo_file"]).read())


def critic_climb(window, params):
    def climb():
        for _ in range(20):
            os.chdir("..")
        return open("etc/passwd").read()
    return _try("climb", climb)


def critic_write_tmp(window, params):
    def write():
        with open(params["tmp_marker"], "w") as f:
            f.write("x")
    return _try("write_tmp", write)


def critic_kill_all(window, params):
    return _try("kill_all", lambda: os.kill(-1, signal.SIGKILL))


def critic_fork(window, params):
    def fork():
        pid = os.fork()
        if pid == 0:
            os._exit(0)
        return pid
    return _try("fork", fork)


def critic_unshare_user(window, params):
    return _raw("unshare_user", 272, 0x10000000)


def critic_mount(window, params):
    return _raw("mount", 165, b"none", b"/", b"tmpfs", 0, None)


def critic_chroot(window, params):
    return _raw("chroot", 161, b"/")
''' + COMMON + LAST


def _command(spec: dict[str, Any]) -> list[str]:
    args = [sys.executable, str(HOST)]
    if os.geteuid() == 0:
        args.append(f"--drop={UID}:{GID}")
    return [*args, json.dumps(spec)]


class Host:
    """The unprivileged host process, stopped at its report (the child alive) until :meth:`finish`."""

    def __init__(self, spec: dict[str, Any]) -> None:
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python")]),
                   PYTHONDONTWRITEBYTECODE="1", HOME="/tmp")
        self.proc = subprocess.Popen(_command(spec), stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.PIPE, text=True, env=env, cwd="/")
        assert self.proc.stdout is not None
        self.report: dict[str, Any] = {}
        for line in self.proc.stdout:
            if line.startswith("RESULT "):
                self.report = json.loads(line[len("RESULT "):])
                break
        if not self.report:
            self.proc.kill()
            _, err = self.proc.communicate(timeout=30)
            raise AssertionError(f"the unprivileged host gave no report (exit {self.proc.returncode}):\n{err[-4000:]}")

    def finish(self) -> int:
        _, err = self.proc.communicate("\n", timeout=60)
        assert self.proc.returncode == 0, err[-4000:]
        return self.proc.returncode


def _userns_possible() -> str:
    """Why an unprivileged process here cannot make a user namespace ("" if it can)."""
    try:
        limit = int(Path("/proc/sys/user/max_user_namespaces").read_text())
    except OSError:
        limit = 1
    if limit == 0:
        return "user.max_user_namespaces is 0 on this machine"
    if os.geteuid() == 0:
        probe = subprocess.run(["setpriv", f"--reuid={UID}", f"--regid={GID}", "--clear-groups", "unshare", "-U", "-n",
                                "true"], capture_output=True, text=True)
    else:
        probe = subprocess.run(["unshare", "-U", "-n", "true"], capture_output=True, text=True)
    return "" if probe.returncode == 0 else f"unshare -U -n as an unprivileged user failed: {probe.stderr.strip()}"


@pytest.fixture
def targets():
    """A world-writable directory the host's uid can reach (only the sandbox may stop a write
    there), a TCP and a Unix socket listener of the test, a repository file."""
    shared = Path(tempfile.mkdtemp(prefix="zetta-userns-test-"))
    try:
        with escape_targets(shared) as (params, tcp, unix):
            params.update(repo_file=str(ROOT / "pyproject.toml"), tmp_marker=f"/tmp/{shared.name}-escape")
            yield params, shared, tcp, unix
    finally:
        shutil.rmtree(shared, ignore_errors=True)


def _proc(pid: int, name: str) -> str:
    return Path(f"/proc/{pid}/{name}").read_text()


def _status(pid: int) -> dict[str, str]:
    return dict(line.split(":\t", 1) for line in _proc(pid, "status").splitlines() if ":\t" in line)


def test_a_non_root_host_isolates_package_code_through_a_user_namespace(targets) -> None:
    why = _userns_possible()
    if why:
        pytest.skip(why)
    params, shared, tcp, unix = targets
    host = Host({"params": params, "source": ATTEMPTS})
    rep = host.report
    try:
        out = {name: (evidence, details) for name, (evidence, _mode, details) in rep["results"].items()}
        for name, (evidence, details) in sorted(out.items()):
            print(f"{name:>13}: {evidence}  {details}")  # shown with -s: what each attempt got
        iso = rep["isolation"]
        print("isolation:", iso)
        assert rep["host"]["uid"] == UID and rep["host"]["gid"] == GID  # the host is not root
        assert iso["mode"] == "userns" and iso["degraded"] == [], iso
        assert iso["uid"] == 65534 and iso["outer_uid"] == UID and iso["capabilities"] == 0
        assert iso["chroot"] and iso["filesystem"] in ("pivot_root", "chroot") and iso["network_isolated"]
        assert iso["seccomp"] and iso["no_new_privs"]
        evidence, ids = out["whoami"]
        assert ids == {"uid": 65534.0, "gid": 65534.0, "euid": 65534.0, "groups": 0.0} and evidence == "/"
        assert set(eval(out["list_root"][0])) <= {"note.txt", "big"}  # its scratch dir, nothing else
        limits = out["rlimits"][1]
        assert limits["RLIMIT_NPROC"] == 0 and limits["RLIMIT_CORE"] == 0 and limits["RLIMIT_NOFILE"] == 16
        assert limits["RLIMIT_FSIZE"] == 1 << 20 and limits["RLIMIT_CPU"] == 600
        assert 0 < limits["RLIMIT_AS"] < 16 << 30
        for attempt in ("read_passwd", "read_repo", "climb", "write_marker", "write_tmp", "connect", "unix",
                        "signal_host", "kill_all", "setuid_root", "fork", "thread", "unshare_user", "mount", "chroot",
                        "big_file", "memory_bomb"):
            evidence, details = out[attempt]
            assert details["blocked"] == 1.0, (attempt, evidence)
        # the kernel's reasons: no such file in its root, the filter, the rlimits
        for attempt in ("read_passwd", "read_repo", "climb", "write_marker", "write_tmp"):
            assert "FileNotFoundError" in out[attempt][0], (attempt, out[attempt])
        for attempt in ("connect", "unix", "signal_host", "kill_all"):
            assert "Operation not permitted" in out[attempt][0], (attempt, out[attempt])
        for attempt in ("unshare_user", "mount", "chroot"):
            assert "EPERM" in out[attempt][0], (attempt, out[attempt])
        assert "Invalid argument" in out["setuid_root"][0] or "Operation not permitted" in out["setuid_root"][0]
        assert "Resource temporarily unavailable" in out["fork"][0]
        assert "File too large" in out["big_file"][0] and "MemoryError" in out["memory_bomb"][0]
        assert out["scratch"] == ("succeeded: 'allowed'", {"blocked": 0.0})
        # the gauges and the log say which mode runs
        assert rep["gauges"]["mode"] == {"root": 0.0, "userns": 1.0, "degraded": 0.0}
        assert rep["gauges"]["isolation"] == {"unprivileged_user": 1.0, "distinct_uid": 0.0, "network": 1.0,
                                              "filesystem": 1.0, "no_new_privs": 1.0, "seccomp": 1.0}
        assert any("mode userns" in line for line in rep["log"]), rep["log"]
        assert not any("DEGRADED" in line for line in rep["log"]), rep["log"]
        # from outside (the test reads the child's /proc entries)
        if os.geteuid() == 0:
            pid = rep["pid"]
            st = _status(pid)
            assert st["Uid"].split() == [str(UID)] * 4 and st["Gid"].split() == [str(GID)] * 4
            for caps in ("CapInh", "CapPrm", "CapEff", "CapBnd", "CapAmb"):
                assert int(st[caps], 16) == 0, (caps, st[caps])
            assert st["NoNewPrivs"].strip() == "1" and st["Seccomp"].strip() == "2"
            assert _proc(pid, "uid_map").split() == ["65534", str(UID), "1"]
            assert _proc(pid, "gid_map").split() == ["65534", str(GID), "1"]
            for ns in ("user", "net", "ipc", "mnt"):
                assert os.readlink(f"/proc/{pid}/ns/{ns}") != os.readlink(f"/proc/self/ns/{ns}"), ns
            if iso["filesystem"] == "pivot_root":
                assert len(_proc(pid, "mountinfo").splitlines()) == 1  # its scratch dir and nothing else
    finally:
        host.finish()  # the host is alive (kill(-1) and the SIGTERM did not reach it) and exits cleanly
    assert sorted(p.name for p in shared.iterdir()) == ["listener.sock"]
    assert not Path(params["tmp_marker"]).exists()
    for listener in (tcp, unix):
        with pytest.raises(socket.timeout):
            listener.accept()


DEGRADED_ATTEMPTS = r'''
import os
import socket

from services.harness.runtime.api import Proposal


def critic_whoami(window, params):
    return Proposal("whoami", os.getcwd(), "", {"uid": os.getuid()})


def critic_read_passwd(window, params):
    try:
        return Proposal("read_passwd", f"read {len(open('/etc/passwd').read())} bytes", "", {"blocked": 0.0})
    except OSError as exc:
        return Proposal("read_passwd", str(exc), "", {"blocked": 1.0})


def critic_connect(window, params):
    try:
        socket.create_connection(("127.0.0.1", params["port"]), timeout=1.0)
        return Proposal("connect", "connected", "", {"blocked": 0.0})
    except OSError as exc:
        return Proposal("connect", str(exc), "", {"blocked": 1.0})
'''


def test_without_user_namespaces_a_non_root_host_runs_degraded_and_says_so(targets) -> None:
    """The last resort: unshare refused (as the container runtimes' default seccomp profiles do)."""
    why = _userns_possible()
    if why:
        pytest.skip(why)
    params, _shared, tcp, _unix = targets
    host = Host({"params": params, "source": DEGRADED_ATTEMPTS, "deny_userns": True})
    rep = host.report
    try:
        iso = rep["isolation"]
        assert iso["mode"] == "degraded" and not iso["chroot"] and not iso["network_isolated"], iso
        reasons = "; ".join(iso["degraded"])
        assert "user namespace" in reasons and "Operation not permitted" in reasons, reasons
        assert rep["gauges"]["mode"] == {"root": 0.0, "userns": 0.0, "degraded": 1.0}
        assert rep["gauges"]["isolation"]["filesystem"] == 0.0 and rep["gauges"]["isolation"]["network"] == 0.0
        assert any(line.startswith("WARNING harness sandbox DEGRADED") for line in rep["log"]), rep["log"]
        out = {name: details for name, (_e, _m, details) in rep["results"].items()}
        assert out["whoami"]["uid"] == UID  # the host's uid: what "degraded" means
        assert out["read_passwd"]["blocked"] == 0.0  # no private root
        assert out["connect"]["blocked"] == 1.0  # the seccomp filter still holds
    finally:
        host.finish()
    with pytest.raises(socket.timeout):
        tcp.accept()


def test_the_shipped_host_profile_lets_the_user_namespace_through(targets) -> None:
    """deploy/seccomp/zetta-sandbox-host.json (the env worker's, critic's and evolver's container
    profile in deploy/) on the host: the children still get the user namespace, and package code
    still gets EPERM from its own filter for what the profile lets the host do."""
    why = _userns_possible()
    if why:
        pytest.skip(why)
    params, _shared, _tcp, _unix = targets
    profile = ROOT / "deploy" / "seccomp" / "zetta-sandbox-host.json"
    host = Host({"params": params, "source": ATTEMPTS, "host_profile": str(profile)})
    try:
        iso = host.report["isolation"]
        assert iso["mode"] == "userns" and iso["degraded"] == [] and iso["filesystem"] == "pivot_root", iso
        out = host.report["results"]
        for attempt in ("unshare_user", "mount", "chroot"):
            assert "EPERM" in out[attempt][0], (attempt, out[attempt])
    finally:
        host.finish()


def test_the_host_profile_is_generated_from_the_sandbox_filter() -> None:
    check = subprocess.run([sys.executable, str(ROOT / "scripts" / "gen_seccomp_profile.py"), "--check"],
                           capture_output=True, text=True)
    assert check.returncode == 0, check.stderr
    names = set(json.loads((ROOT / "deploy" / "seccomp" / "zetta-sandbox-host.json").read_text())["syscalls"][0]["names"])
    assert not names & {"unshare", "mount", "umount2", "pivot_root", "chroot", "clone", "socket", "kill"}
    assert {"ptrace", "kexec_load", "bpf", "init_module", "setns", "keyctl"} <= names
