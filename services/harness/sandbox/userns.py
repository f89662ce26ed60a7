"""How a sandbox child is isolated, decided once by the zygote: as root, or in a user namespace.

Three modes, strongest first (services/harness/sandbox/child.py ``jail`` applies them):

``root``
    The host runs as root. The zygote leaves the host's network (``unshare(CLONE_NEWNET)``); each
    child chroots into its scratch directory and drops to a uid and gid of its own (client.UID_BASE,
    200000, plus its pid): no host user and no other live child has it.

``userns``
    The host is not root (the Kubernetes base runs every pod as uid 10001 without capabilities).
    The zygote enters a user namespace of its own together with a network and an IPC namespace
    (``unshare(CLONE_NEWUSER | CLONE_NEWNET | CLONE_NEWIPC)``, no privilege needed) and maps the
    one id an unprivileged process may map, its own uid and gid, to 65534 inside (``setgroups``
    denied first). Each child then, with the capabilities it holds in that namespace only, makes a
    mount namespace of its own and ``pivot_root``\\ s into its scratch directory, detaching the
    host's file system from its view (``chroot`` where mounting is refused, e.g. by an AppArmor
    profile), and drops every capability (bounding set, ambient, permitted, effective: it can never
    regain one: 65534 is the only id mapped, and nothing is executed). Outside the namespace the
    child is still the host's uid: the seccomp filter (seccomp.py) keeps it from signalling,
    tracing or re-limiting any process but itself, and what the uid owns on disk is out of its
    view.

``degraded``
    Neither works (not root, and the kernel, a seccomp profile of the container runtime or an
    AppArmor policy refuses user namespaces): no change of user and no private root; the child
    keeps the rlimits, no-new-privileges and the seccomp filter, and the host logs "harness
    sandbox DEGRADED" with the reason (the ``zetta_harness_sandbox_mode`` and
    ``zetta_harness_sandbox_isolation`` gauges say the same).

There is no PID namespace: children are forked by the zygote and the host tracks and kills them
by their pid in its own namespace; a PID namespace needs an init process per namespace (the first
child forked into it; when it exits no further fork succeeds) and pid translation for the host.
The filter already confines signals, ptrace and prlimit to the child itself, and /proc is not in
its root.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import platform
from dataclasses import dataclass

CLONE_NEWNS = 0x00020000
CLONE_NEWIPC = 0x08000000
CLONE_NEWUSER = 0x10000000
CLONE_NEWNET = 0x40000000

MS_RDONLY = 0x1
MS_NOSUID = 0x2
MS_NODEV = 0x4
MS_NOEXEC = 0x8
MS_REMOUNT = 0x20
MS_NOATIME = 0x400
MS_NODIRATIME = 0x800
MS_BIND = 0x1000
MS_REC = 0x4000
MS_PRIVATE = 1 << 18
MS_RELATIME = 1 << 21
MNT_DETACH = 2
#: pivot_root has no C library wrapper: its number, per machine (else chroot is used).
SYS_PIVOT_ROOT = {"x86_64": 155, "AMD64": 155, "aarch64": 41, "arm64": 41}.get(platform.machine(), -1)
PR_CAPBSET_DROP = 24
PR_GET_DUMPABLE = 3
PR_CAP_AMBIENT = 47
PR_CAP_AMBIENT_CLEAR_ALL = 4
LINUX_CAPABILITY_VERSION_3 = 0x20080522

#: The uid and gid a child has inside its user namespace (the only ids mapped there).
INNER_ID = 65534

_libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


@dataclass(frozen=True)
class Isolation:
    """What the zygote set up for its children."""

    mode: str  # "root", "userns" or "degraded"
    #: Why the children have no network namespace of their own ("" when they have one).
    network_degraded: str = ""
    #: Why there is no user namespace (mode "degraded").
    userns_refused: str = ""
    #: The host's uid and gid, which the inner 65534 maps to (mode "userns").
    outer_uid: int = -1
    outer_gid: int = -1


#: Set by :func:`enter` in the zygote; its children inherit it with the fork.
CURRENT: Isolation | None = None


def current() -> Isolation:
    """The zygote's set-up (in a process that is not a zygote's child: what its uid implies)."""
    if CURRENT is not None:
        return CURRENT
    return Isolation("root" if os.geteuid() == 0 else "degraded", userns_refused="no zygote set up the namespaces")


def _err(call: str) -> str:
    return f"{call} refused: {os.strerror(ctypes.get_errno())}"


def _write(path: str, text: str) -> None:
    with open(path, "w") as f:
        f.write(text)


def _enter_userns() -> None:
    """unshare a user, network and IPC namespace and map this process's uid and gid to 65534."""
    uid, gid = os.geteuid(), os.getegid()
    if _libc.prctl(PR_GET_DUMPABLE, 0, 0, 0, 0) != 1:
        # /proc/self/uid_map belongs to root in a process that is not dumpable.
        raise OSError(errno.EPERM, "the process is not dumpable, so it cannot write its own uid_map")
    if _libc.unshare(CLONE_NEWUSER | CLONE_NEWNET | CLONE_NEWIPC) != 0:
        raise OSError(ctypes.get_errno(), _err("unshare(CLONE_NEWUSER | CLONE_NEWNET | CLONE_NEWIPC)"))
    _write("/proc/self/setgroups", "deny")
    _write("/proc/self/uid_map", f"{INNER_ID} {uid} 1")
    _write("/proc/self/gid_map", f"{INNER_ID} {gid} 1")


def _probe() -> str:
    """Try the user namespace in a throw-away child first: once this process has entered one it
    cannot go back, and a half-made one (no uid map) would be worse than none. "" if it works."""
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the forked probe
        os.close(r)
        try:
            _enter_userns()
            os.chroot("/")  # the capability a child needs for its private root
            os.write(w, b"ok")
        except BaseException as exc:  # noqa: BLE001 - reported to the zygote
            os.write(w, str(exc).encode()[:1000] or type(exc).__name__.encode())
        os._exit(0)
    os.close(w)
    chunks = []
    while chunk := os.read(r, 4096):
        chunks.append(chunk)
    os.close(r)
    os.waitpid(pid, 0)
    answer = b"".join(chunks).decode(errors="replace")
    return "" if answer == "ok" else (answer or "the probe died")


def enter() -> Isolation:
    """In the zygote, before any child is forked: leave the host's network, and when not root
    enter a user namespace (see the module's docstring). Sets and returns :data:`CURRENT`."""
    global CURRENT
    if os.geteuid() == 0:
        # Root keeps its stronger set-up (children drop to a distinct uid). A user namespace made
        # by root would map the children to uid 0 outside, so there is no fallback through one.
        net = "" if _libc.unshare(CLONE_NEWNET) == 0 else _err("unshare(CLONE_NEWNET)")
        CURRENT = Isolation("root", network_degraded=net)
        return CURRENT
    uid, gid = os.geteuid(), os.getegid()
    refused = _probe()
    if not refused:
        try:
            _enter_userns()
        except OSError as exc:  # the probe passed, so this is not expected
            refused = f"user namespace: {exc}"
        else:
            CURRENT = Isolation("userns", outer_uid=uid, outer_gid=gid)
            return CURRENT
    # Last resort: the network alone, if this process may (CAP_SYS_ADMIN without root).
    net = "" if _libc.unshare(CLONE_NEWNET) == 0 else (
        f"{_err('unshare(CLONE_NEWNET)')}; user namespace: {refused}")
    CURRENT = Isolation("degraded", network_degraded=net, userns_refused=refused)
    return CURRENT


def _mount(source: str | None, target: str, flags: int) -> None:
    if _libc.mount(source.encode() if source else None, target.encode(), None, ctypes.c_ulong(flags), None) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"mount({source!r}, {target!r}, {flags:#x}): {os.strerror(err)}")


def private_root(scratch: str) -> str:
    """Make ``scratch`` this process's root, the rest of the file system out of reach: a mount
    namespace of its own, ``pivot_root`` and the old root detached ("pivot_root"); ``chroot``
    where mounting is refused ("chroot"). Needs the user namespace's capabilities."""
    try:
        if _libc.unshare(CLONE_NEWNS) != 0:
            raise OSError(ctypes.get_errno(), _err("unshare(CLONE_NEWNS)"))
        _mount(None, "/", MS_REC | MS_PRIVATE)  # nothing propagates back to the host's mounts
        _mount(scratch, scratch, MS_BIND)  # pivot_root needs a mount point
        # nosuid, nodev, noexec on the new root; the flags it had are kept (a user namespace may
        # not clear them), so this is best effort.
        kept = os.statvfs(scratch).f_flag & (MS_RDONLY | MS_NOSUID | MS_NODEV | MS_NOEXEC | MS_NOATIME
                                             | MS_NODIRATIME | MS_RELATIME)
        try:
            _mount(None, scratch, MS_REMOUNT | MS_BIND | kept | MS_NOSUID | MS_NODEV | MS_NOEXEC)
        except OSError:
            pass
        os.chdir(scratch)
        if SYS_PIVOT_ROOT < 0:
            raise OSError(errno.ENOSYS, f"no pivot_root number for {platform.machine()}")
        if _libc.syscall(ctypes.c_long(SYS_PIVOT_ROOT), b".", b".") != 0:
            raise OSError(ctypes.get_errno(), _err("pivot_root"))
    except OSError:
        os.chroot(scratch)  # an error here leaves the child unable to set up: it never runs code
        os.chdir("/")
        return "chroot"
    # The old root is stacked on the new one: detach it (with every mount under it).
    if _libc.umount2(b".", MNT_DETACH) != 0:
        raise OSError(ctypes.get_errno(), _err("umount2(old root)"))
    os.chdir("/")
    return "pivot_root"


class _CapHeader(ctypes.Structure):
    _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]


class _CapData(ctypes.Structure):
    _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32), ("inheritable", ctypes.c_uint32)]


def capabilities() -> int:
    """This process's effective and permitted capabilities, OR-ed (0: none)."""
    header = _CapHeader(LINUX_CAPABILITY_VERSION_3, 0)
    data = (_CapData * 2)()
    if _libc.capget(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), _err("capget"))
    return sum((d.effective | d.permitted) << (32 * i) for i, d in enumerate(data))


def drop_capabilities() -> int:
    """Drop every capability for good: bounding set, ambient set, then effective, permitted and
    inheritable. Returns what is left (0)."""
    for cap in range(64):
        if _libc.prctl(PR_CAPBSET_DROP, ctypes.c_ulong(cap), 0, 0, 0) != 0:
            if ctypes.get_errno() == errno.EINVAL:
                break  # past the kernel's last capability
            raise OSError(ctypes.get_errno(), _err(f"PR_CAPBSET_DROP({cap})"))
    _libc.prctl(PR_CAP_AMBIENT, ctypes.c_ulong(PR_CAP_AMBIENT_CLEAR_ALL), 0, 0, 0)  # EINVAL before 4.3
    header = _CapHeader(LINUX_CAPABILITY_VERSION_3, 0)
    data = (_CapData * 2)()
    if _libc.capset(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), _err("capset"))
    left = capabilities()
    if left:
        raise OSError(errno.EPERM, f"capabilities left after dropping them: {left:#x}")
    return left
