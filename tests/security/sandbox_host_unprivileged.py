"""A harness sandbox host that is not root: tests/security/test_harness_sandbox_userns.py runs it.

``python tests/security/sandbox_host_unprivileged.py [--drop=UID:GID] PARAMS_JSON``

With ``--drop`` (the test runs as root) it first makes the interpreter reachable for that uid and
then becomes it: the test's interpreter may live under a directory only root may enter (here the
venv's Python is under /root, mode 0700). In a mount namespace of this process alone, the blocked
directory is covered by a read-only, world-traversable tmpfs that holds a bind mount of the
interpreter's tree; nothing changes for any other process, and the mounts are gone when this
process tree exits. Then it drops every privilege (groups, gid, uid) and executes itself again.

As the unprivileged user it starts a sandbox child the way the services do (SandboxClient), loads
package code without the static checks (the kernel layer alone), runs every critic once and prints
one line ``RESULT {json}``: the child's isolation report and pid, what each attempt got, the
gauges and the sandbox log. It then waits for a line on stdin (the test inspects the child from
outside meanwhile), closes the child and exits.

``PARAMS_JSON``: ``params`` for the package (marker path, listener port, ...), ``source`` (the
package's tools/attempts.py), ``deny_userns`` (a seccomp filter on this host that refuses
``unshare`` and ``mount`` as a container runtime's default profile does: the degraded mode) and
``host_profile`` (the same with the deny list of deploy/seccomp/zetta-sandbox-host.json).
"""

from __future__ import annotations

import ctypes
import json
import logging
import os
import stat
import sys
import tempfile

CLONE_NEWNS = 0x00020000
MS_RDONLY = 0x1
MS_BIND = 0x1000
MS_REC = 0x4000
MS_PRIVATE = 1 << 18


def _mount(libc: ctypes.CDLL, source: str | None, target: str, fstype: str | None, flags: int, data: str | None = None
           ) -> None:
    if libc.mount(source and source.encode(), target.encode(), fstype and fstype.encode(), ctypes.c_ulong(flags),
                  data and data.encode()) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount {source} on {target}: {os.strerror(err)}")


def _blocked(paths: list[str]) -> dict[str, set[str]]:
    """Directories other users may not traverse on the way to ``paths``: {dir: {entries needed}}.

    A needed path that is itself such a directory (a checkout at the root of a mode-0700 temporary
    directory, on ``sys.path``) needs every entry it has."""
    out: dict[str, set[str]] = {}
    for path in paths:
        parts = os.path.realpath(path).split(os.sep)[1:]
        for i in range(len(parts)):
            here = os.sep + os.sep.join(parts[:i + 1])
            if not os.stat(here).st_mode & stat.S_IXOTH:
                if i + 1 < len(parts):
                    out.setdefault(here, set()).add(parts[i + 1])
                elif os.path.isdir(here):
                    out.setdefault(here, set()).update(os.listdir(here))
                break
    return out


def _hold(libc: ctypes.CDLL, source: str) -> str:
    """A bind mount of ``source`` (a directory or a file) outside the directory about to be covered."""
    if os.path.isdir(source):
        hold = tempfile.mkdtemp(prefix="zetta-userns-hold-")
    else:
        fd, hold = tempfile.mkstemp(prefix="zetta-userns-hold-")
        os.close(fd)
    _mount(libc, source, hold, None, MS_BIND | MS_REC)
    return hold


def _restore(libc: ctypes.CDLL, hold: str, target: str) -> None:
    """Bind ``hold`` on a new entry ``target`` of the covering tmpfs and drop the hold."""
    if os.path.isdir(hold):
        os.mkdir(target, 0o755)
    else:
        os.close(os.open(target, os.O_CREAT | os.O_WRONLY, 0o644))
    _mount(libc, hold, target, None, MS_BIND | MS_REC)
    libc.umount2(hold.encode(), 2)  # MNT_DETACH: the bind on target stays
    if os.path.isdir(hold):
        os.rmdir(hold)
    else:
        os.unlink(hold)


def drop_to(uid: int, gid: int) -> None:
    """Make the interpreter and this script reachable for ``uid`` in a private mount namespace,
    become it, re-exec."""
    libc = ctypes.CDLL(None, use_errno=True)
    needed = [sys.executable, sys.base_prefix, sys.prefix, os.path.abspath(sys.argv[0]), *sys.path[1:]]
    blocked = _blocked([p for p in needed if p and os.path.exists(p)])
    if blocked:
        if libc.unshare(CLONE_NEWNS) != 0:
            raise OSError(ctypes.get_errno(), "unshare(CLONE_NEWNS)")
        _mount(libc, None, "/", None, MS_REC | MS_PRIVATE)
        for directory, entries in blocked.items():
            links = {e: os.readlink(os.path.join(directory, e)) for e in entries
                     if os.path.islink(os.path.join(directory, e))}
            holds = {e: _hold(libc, os.path.join(directory, e)) for e in entries if e not in links}
            _mount(libc, "tmpfs", directory, "tmpfs", 0, "mode=0755,size=64k")
            for entry, link in links.items():
                os.symlink(link, os.path.join(directory, entry))
            for entry, hold in holds.items():
                _restore(libc, hold, os.path.join(directory, entry))
            _mount(libc, None, directory, None, 0x20 | MS_RDONLY)  # MS_REMOUNT: read-only
    os.setgroups([])
    os.setgid(gid)
    os.setuid(uid)
    args = [a for a in sys.argv[1:] if not a.startswith("--drop")]
    os.execv(sys.executable, [sys.executable, sys.argv[0], *args])


def _install_filter(names: list[str]) -> None:
    """A seccomp filter on this host (inherited by the zygote and its children) that refuses
    ``names`` with EPERM and allows everything else, as a container runtime applies a profile."""
    import struct

    from services.harness.sandbox import seccomp

    insn = struct.Struct("<HBBI")
    n = len(names)
    prog = [insn.pack(seccomp.LD_W_ABS, 0, 0, seccomp.OFF_NR)]
    prog += [insn.pack(seccomp.JEQ_K, n - i, 0, seccomp.X86_64[name]) for i, name in enumerate(names)]
    prog += [insn.pack(seccomp.RET_K, 0, 0, seccomp.RET_ALLOW), insn.pack(seccomp.RET_K, 0, 0, seccomp.RET_ERRNO | 1)]
    code = b"".join(prog)
    buf = ctypes.create_string_buffer(code, len(code))
    fprog = seccomp._SockFprog(len(prog), ctypes.cast(buf, ctypes.c_void_p))
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(38, 1, 0, 0, 0) != 0 or libc.prctl(seccomp.PR_SET_SECCOMP, ctypes.c_ulong(seccomp.SECCOMP_MODE_FILTER),
                                                      ctypes.byref(fprog), 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "could not install the test's seccomp filter")


def main(spec: dict) -> None:
    import numpy as np
    from prometheus_client import REGISTRY

    from services.harness.sandbox.client import SandboxClient

    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            records.append(f"{record.levelname} {record.getMessage()}")

    logger = logging.getLogger("zetta.harness.sandbox")
    logger.addHandler(Keep())
    logger.setLevel(logging.INFO)
    if spec.get("deny_userns"):  # what the runtimes' default profiles do to a container without CAP_SYS_ADMIN
        _install_filter(["unshare", "mount", "umount2", "pivot_root", "setns"])
    if spec.get("host_profile"):  # the profile deploy/ ships for the sandbox hosts
        with open(spec["host_profile"]) as f:
            rules = json.load(f)
        assert rules["defaultAction"] == "SCMP_ACT_ALLOW" and len(rules["syscalls"]) == 1
        _install_filter(rules["syscalls"][0]["names"])
    params = dict(spec["params"], host_pid=os.getpid())
    child = SandboxClient()
    loaded = child.load(4, {"attempts": spec["source"]}, {"attempts": params}, checked=False)
    child.start("", [])
    results = child.step(0, {"robot0_eef_pos": np.zeros(3)}, None, frozenset(),
                         [(i, False) for i in range(len(loaded.critics))], lambda i: 5.0)
    out = {}
    for name, res in zip(loaded.critics, results):
        out[name.removeprefix("attempts.")] = list(res.proposal) if res.proposal is not None else ["error", "", {
            "error": res.error}]
    gauges = {
        "mode": {m: REGISTRY.get_sample_value("zetta_harness_sandbox_mode", {"mode": m}) for m in
                 ("root", "userns", "degraded")},
        "isolation": {f: REGISTRY.get_sample_value("zetta_harness_sandbox_isolation", {"feature": f}) for f in
                      ("unprivileged_user", "distinct_uid", "network", "filesystem", "no_new_privs", "seccomp")},
    }
    report = {"host": {"uid": os.getuid(), "gid": os.getgid(), "pid": os.getpid()}, "pid": child.pid,
              "isolation": {k: v for k, v in child.isolation.items()}, "results": out, "gauges": gauges, "log": records}
    print("RESULT " + json.dumps(report, default=str), flush=True)
    sys.stdin.readline()
    child.close()


if __name__ == "__main__":
    drop = [a for a in sys.argv[1:] if a.startswith("--drop")]
    if drop:
        uid, gid = (int(x) for x in drop[0].split("=", 1)[1].split(":"))
        drop_to(uid, gid)
    main(json.loads(sys.argv[-1]))
