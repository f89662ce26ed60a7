"""The sandbox child's seccomp filter (services/harness/sandbox/seccomp.py), checked from inside a
real child: package code loaded unchecked (past the static checks, as an escape from them would
be) calls the system calls the filter refuses, straight through libc's ``syscall()``, and gets
EPERM; it may signal only itself, not a sibling child of the same uid; what the interpreter needs
still works, and so do normal (checked) critics. Needs root, like the other kernel-layer tests."""

from __future__ import annotations

import os
import platform
import re
from pathlib import Path

import numpy as np
import pytest

from services.harness.sandbox import seccomp
from services.harness.sandbox.client import SandboxClient

pytestmark = [
    pytest.mark.timeout(120),
    pytest.mark.skipif(os.geteuid() != 0, reason="the sandbox changes uid and chroots only when started as root"),
    pytest.mark.skipif(platform.machine() != "x86_64", reason="the filter has a system call table for x86_64 only"),
]

PROBES = r'''
import ctypes
import os
import resource
import socket
import threading

import numpy as np

from services.harness.runtime.api import Proposal

libc = ctypes.CDLL(None, use_errno=True)


def _errno(nr, *args):
    ctypes.set_errno(0)
    ret = libc.syscall(ctypes.c_long(nr), *[ctypes.c_long(a) for a in args])
    return 0 if ret >= 0 else ctypes.get_errno()


def critic_raw(window, params):
    # every refused call with harmless arguments: the filter answers before the kernel looks at them
    out = {name: float(_errno(nr, 0, 0, 0, 0)) for name, nr in params["denied"].items()}
    return Proposal("raw", "", "", out)


def _try(fn):
    try:
        fn()
    except OSError as exc:
        return float(exc.errno or -1)
    except BaseException:  # noqa: BLE001
        return -1.0
    return 0.0


def critic_calls(window, params):
    sibling = int(params["sibling"])
    out = {
        "socket_inet": _try(lambda: socket.socket(socket.AF_INET, socket.SOCK_STREAM)),
        "socket_unix": _try(lambda: socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)),
        "socket_netlink": _try(lambda: socket.socket(socket.AF_NETLINK, socket.SOCK_RAW, 0)),
        "socketpair": _try(lambda: socket.socketpair()),
        "execve": _try(lambda: os.execv("/bin/sh", ["sh"])),
        "kill_sibling": _try(lambda: os.kill(sibling, 0)),
        "kill_all": _try(lambda: os.kill(-1, 0)),
        "kill_group": _try(lambda: os.kill(0, 0)),
        "prlimit_sibling": _try(lambda: resource.prlimit(sibling, resource.RLIMIT_CPU, (1, 1))),
        "clone_newuser": float(_errno(params["clone"], 0x10000000 | 17, 0, 0, 0)),
        # what the interpreter itself does still works
        "kill_self": _try(lambda: os.kill(os.getpid(), 0)),
        "prlimit_self": _try(lambda: resource.prlimit(0, resource.RLIMIT_NOFILE)),
        "numpy": 0.0 if float(np.linalg.norm(np.ones(4))) == 2.0 else 1.0,
        "thread": _try(lambda: threading.Thread(target=lambda: None).start()),
    }
    return Proposal("calls", "", "", out)


def critic_whoami(window, params):
    return Proposal("whoami", "", "", {"pid": float(os.getpid())})
'''

#: The calls the brief of issue #21 names, plus the rest of the refused list (every one is checked).
DENIED = {name: seccomp.X86_64[name] for name in seccomp.DENIED}


def _results(child: SandboxClient, loaded_critics: tuple[str, ...]) -> dict[str, dict[str, float]]:
    results = child.step(0, {"robot0_eef_pos": np.zeros(3)}, None, frozenset(),
                         [(i, False) for i in range(len(loaded_critics))], lambda i: 10.0)
    out = {}
    for name, res in zip(loaded_critics, results):
        assert res.proposal is not None, (name, res.error)
        out[name.removeprefix("probes.")] = res.proposal[2]
    return out


def test_refused_system_calls_get_eperm_and_signals_reach_only_the_child_itself() -> None:
    sibling = SandboxClient()  # another session's child (its own uid; the filter stops this even where uids are shared)
    child = SandboxClient()
    try:
        assert child.isolation["seccomp"] is True and child.isolation["degraded"] == []
        params = {"denied": DENIED, "sibling": sibling.pid, "clone": seccomp.X86_64["clone"]}
        loaded = child.load(4, {"probes": PROBES}, {"probes": params}, checked=False)
        child.start("", [])
        out = _results(child, loaded.critics)
        for name in ("ptrace", "mount", "kexec_load", "bpf", "perf_event_open", "keyctl", "unshare", "setns",
                     "execve", "socket", "io_uring_setup", "open_by_handle_at"):
            assert out["raw"][name] == 1.0, (name, out["raw"][name])  # EPERM
        refused = {name: e for name, e in out["raw"].items() if e != 1.0}
        assert refused == {}, refused
        calls = out["calls"]
        for name in ("socket_inet", "socket_unix", "socket_netlink", "socketpair", "execve", "kill_sibling",
                     "kill_all", "kill_group", "prlimit_sibling", "clone_newuser"):
            assert calls[name] == 1.0, (name, calls[name])
        assert calls["kill_self"] == 0.0 and calls["prlimit_self"] == 0.0 and calls["numpy"] == 0.0
        assert calls["thread"] == -1.0  # RuntimeError: RLIMIT_NPROC still refuses it (clone3 -> ENOSYS -> clone)
        assert out["whoami"]["pid"] == float(child.pid)
    finally:
        child.close()
    # the sibling is untouched and still serves
    loaded = sibling.load(4, {"probes": "from services.harness.runtime.api import Proposal\n\n"
                                        "def critic_ok(window, params):\n    return Proposal('ok', '', '', {})\n"},
                          checked=False)
    sibling.start("", [])
    assert _results(sibling, loaded.critics)["ok"] == {}
    sibling.close()


def test_a_call_of_another_abi_kills_the_child() -> None:
    """An i386 system call (``int 0x80``) would dodge a table of x86_64 numbers: the filter kills
    the child instead (the host sees it die and reports it)."""
    code = r'''
import ctypes
import mmap


def critic_int80(window, params):
    # mov eax, 20 (getpid on i386); int 0x80; ret
    body = bytes([0xB8, 20, 0, 0, 0, 0xCD, 0x80, 0xC3])
    mem = mmap.mmap(-1, mmap.PAGESIZE, prot=mmap.PROT_READ | mmap.PROT_WRITE | mmap.PROT_EXEC)
    mem.write(body)
    addr = ctypes.addressof(ctypes.c_char.from_buffer(mem))
    return ctypes.CFUNCTYPE(ctypes.c_int)(addr)()
'''
    from services.harness.sandbox.client import SandboxError

    child = SandboxClient()
    try:
        child.load(4, {"abi": code}, checked=False)
        child.start("", [])
        with pytest.raises(SandboxError, match="died"):
            child.step(0, {}, None, frozenset(), [(0, False)], lambda i: 10.0)
    finally:
        child.close()


def test_the_table_matches_the_kernel_headers() -> None:
    header = Path("/usr/include/x86_64-linux-gnu/asm/unistd_64.h")
    if not header.exists():
        pytest.skip("no asm/unistd_64.h here to compare with")
    numbers = {m.group(1): int(m.group(2)) for m in re.finditer(r"#define __NR_(\w+) (\d+)", header.read_text())}
    assert {name: numbers.get(name) for name in seccomp.X86_64} == seccomp.X86_64


def test_the_program_is_well_formed() -> None:
    prog = seccomp.program(1234)
    assert len(prog) % 8 == 0 and len(prog) // 8 < 4096  # BPF_MAXINSNS
