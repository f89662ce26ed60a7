"""The sandbox child's seccomp filter: the system calls package code never needs, refused by the kernel.

A classic BPF program installed with ``prctl(PR_SET_SECCOMP, SECCOMP_MODE_FILTER)`` through
ctypes (no library needed; libseccomp is not a dependency), as the last step of
services/harness/sandbox/child.py ``jail``, after the child dropped to its own uid (root host) or
its capabilities (user namespace) and set no-new-privileges. From then on, and for every call the child makes:

- a system call of another ABI (i386 through ``int 0x80``, x32) kills the child;
- :data:`DENIED` fail with EPERM: every socket (the child's channel to its host is already open),
  process creation by exec, fork or vfork, namespaces (unshare, setns, clone with a CLONE_NEW*
  flag), ptrace and cross-process memory access, mounts and chroot, kexec and kernel modules, bpf,
  perf_event_open, the kernel keyring, io_uring (its operations bypass this filter), file handles
  (open_by_handle_at), userfaultfd, pidfds, clock and host settings;
- ``clone3`` fails with ENOSYS, so that the C library falls back to ``clone``, whose flags this
  filter can read (RLIMIT_NPROC 0 refuses the new process or thread anyway);
- :data:`SELF_ONLY` (kill, tkill, tgkill, rt_sigqueueinfo, rt_tgsigqueueinfo) may target only the
  child itself: the children of a non-root host all run as the host's uid outside their user
  namespace, so without this one package could signal another session's child (a root host's
  children each have a uid of their own, 200000 + pid, and the kernel refuses that already);
- :data:`SELF_OR_ZERO` (prlimit64, sched_set*) may target only the child (pid 0 or its own pid):
  not another child's limits or scheduling.

Everything else is allowed: the interpreter, numpy and the channel need read/write, mmap, poll,
futex and the like. Only x86_64 has a table here; elsewhere the child runs without the filter and
reports that in its isolation report (``degraded``).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import errno
import os
import platform
import struct

PR_SET_SECCOMP = 22
SECCOMP_MODE_FILTER = 2
AUDIT_ARCH_X86_64 = 0xC000003E
X32_SYSCALL_BIT = 0x40000000

RET_KILL_PROCESS = 0x80000000
RET_ERRNO = 0x00050000
RET_ALLOW = 0x7FFF0000

# classic BPF opcodes
LD_W_ABS = 0x20
JEQ_K = 0x15
JGE_K = 0x35
JSET_K = 0x45
RET_K = 0x06

# struct seccomp_data: int nr; u32 arch; u64 instruction_pointer; u64 args[6] (little endian)
OFF_NR = 0
OFF_ARCH = 4
OFF_ARG0_LO = 16
OFF_ARG0_HI = 20

#: clone() flags that make a new namespace (NEWTIME, NEWNS, NEWCGROUP, NEWUTS, NEWIPC, NEWUSER, NEWPID, NEWNET).
CLONE_NEW_MASK = 0x00000080 | 0x00020000 | 0x02000000 | 0x04000000 | 0x08000000 | 0x10000000 | 0x20000000 | 0x40000000

#: x86_64 system call numbers (asm/unistd_64.h; tests/security/test_harness_seccomp.py checks them
#: against the header where it is installed).
X86_64 = {
    "socket": 41, "socketpair": 53, "fork": 57, "vfork": 58, "execve": 59, "execveat": 322,
    "clone": 56, "clone3": 435, "unshare": 272, "setns": 308,
    "ptrace": 101, "process_vm_readv": 310, "process_vm_writev": 311, "kcmp": 312, "process_madvise": 440,
    "migrate_pages": 256, "move_pages": 279,
    "mount": 165, "umount2": 166, "pivot_root": 155, "chroot": 161, "open_tree": 428, "move_mount": 429,
    "fsopen": 430, "fsconfig": 431, "fsmount": 432, "fspick": 433, "mount_setattr": 442,
    "kexec_load": 246, "kexec_file_load": 320, "init_module": 175, "finit_module": 313, "delete_module": 176,
    "uselib": 134, "bpf": 321, "perf_event_open": 298, "keyctl": 250, "add_key": 248, "request_key": 249,
    "io_uring_setup": 425, "io_uring_enter": 426, "io_uring_register": 427,
    "open_by_handle_at": 304, "name_to_handle_at": 303, "userfaultfd": 323, "fanotify_init": 300,
    "pidfd_open": 434, "pidfd_getfd": 438, "pidfd_send_signal": 424,
    "reboot": 169, "swapon": 167, "swapoff": 168, "syslog": 103, "acct": 163, "quotactl": 179,
    "settimeofday": 164, "clock_settime": 227, "clock_adjtime": 305, "adjtimex": 159,
    "sethostname": 170, "setdomainname": 171, "iopl": 172, "ioperm": 173, "vhangup": 153, "lookup_dcookie": 212,
    "setpriority": 141, "ioprio_set": 251,
    "kill": 62, "tkill": 200, "tgkill": 234, "rt_sigqueueinfo": 129, "rt_tgsigqueueinfo": 297,
    "prlimit64": 302, "sched_setaffinity": 203, "sched_setscheduler": 144, "sched_setparam": 142,
    "sched_setattr": 314,
}

#: Refused with EPERM, whatever the arguments.
DENIED = (
    "socket", "socketpair", "fork", "vfork", "execve", "execveat", "unshare", "setns",
    "ptrace", "process_vm_readv", "process_vm_writev", "kcmp", "process_madvise", "migrate_pages", "move_pages",
    "mount", "umount2", "pivot_root", "chroot", "open_tree", "move_mount", "fsopen", "fsconfig", "fsmount", "fspick",
    "mount_setattr", "kexec_load", "kexec_file_load", "init_module", "finit_module", "delete_module", "uselib",
    "bpf", "perf_event_open", "keyctl", "add_key", "request_key", "io_uring_setup", "io_uring_enter",
    "io_uring_register", "open_by_handle_at", "name_to_handle_at", "userfaultfd", "fanotify_init",
    "pidfd_open", "pidfd_getfd", "pidfd_send_signal", "reboot", "swapon", "swapoff", "syslog", "acct", "quotactl",
    "settimeofday", "clock_settime", "clock_adjtime", "adjtimex", "sethostname", "setdomainname", "iopl", "ioperm",
    "vhangup", "lookup_dcookie", "setpriority", "ioprio_set",
)
#: Allowed only when their first argument is the child's own pid.
SELF_ONLY = ("kill", "tkill", "tgkill", "rt_sigqueueinfo", "rt_tgsigqueueinfo")
#: Allowed only when their first argument is 0 (the caller) or the child's own pid.
SELF_OR_ZERO = ("prlimit64", "sched_setaffinity", "sched_setscheduler", "sched_setparam", "sched_setattr")

_INSN = struct.Struct("<HBBI")
#: Loaded when the zygote imports this module: after the chroot nothing can be read from disk.
_libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _stmt(code: int, k: int) -> tuple[int, object, object, int]:
    return (code, 0, 0, k)


def program(pid: int, table: dict[str, int] | None = None) -> bytes:
    """The filter for the process ``pid`` as an array of ``struct sock_filter``."""
    nr = X86_64 if table is None else table
    # (code, jt, jf, k) with jt/jf a label name (resolved below) or 0 (the next instruction)
    ops: list[tuple[int, object, object, int]] = []
    labels: dict[str, int] = {}

    def label(name: str) -> None:
        labels[name] = len(ops)

    ops.append(_stmt(LD_W_ABS, OFF_ARCH))
    ops.append((JEQ_K, 0, "kill", AUDIT_ARCH_X86_64))
    ops.append(_stmt(LD_W_ABS, OFF_NR))
    ops.append((JGE_K, "deny", 0, X32_SYSCALL_BIT))
    for name in DENIED:
        ops.append((JEQ_K, "deny", 0, nr[name]))
    ops.append((JEQ_K, "enosys", 0, nr["clone3"]))
    for name in SELF_ONLY:
        ops.append((JEQ_K, "self_only", 0, nr[name]))
    for name in SELF_OR_ZERO:
        ops.append((JEQ_K, "self_or_zero", 0, nr[name]))
    ops.append((JEQ_K, 0, "allow", nr["clone"]))
    ops.append(_stmt(LD_W_ABS, OFF_ARG0_LO))  # clone(flags, ...): no new namespace
    ops.append((JSET_K, "deny", "allow", CLONE_NEW_MASK))
    label("self_only")
    ops.append(_stmt(LD_W_ABS, OFF_ARG0_HI))
    ops.append((JEQ_K, 0, "deny", 0))
    ops.append(_stmt(LD_W_ABS, OFF_ARG0_LO))
    ops.append((JEQ_K, "allow", "deny", pid))
    label("self_or_zero")
    ops.append(_stmt(LD_W_ABS, OFF_ARG0_HI))
    ops.append((JEQ_K, 0, "deny", 0))
    ops.append(_stmt(LD_W_ABS, OFF_ARG0_LO))
    ops.append((JEQ_K, "allow", 0, pid))
    ops.append((JEQ_K, "allow", "deny", 0))
    label("allow")
    ops.append(_stmt(RET_K, RET_ALLOW))
    label("deny")
    ops.append(_stmt(RET_K, RET_ERRNO | errno.EPERM))
    label("enosys")
    ops.append(_stmt(RET_K, RET_ERRNO | errno.ENOSYS))
    label("kill")
    ops.append(_stmt(RET_K, RET_KILL_PROCESS))

    out = bytearray()
    for pc, (code, jt, jf, k) in enumerate(ops):
        def offset(target: object) -> int:
            if target == 0:
                return 0
            off = labels[str(target)] - pc - 1
            if not 0 <= off < 256:
                raise ValueError(f"seccomp program: jump from {pc} to {target} out of range")
            return off

        out += _INSN.pack(code, offset(jt), offset(jf), k)
    return bytes(out)


class _SockFprog(ctypes.Structure):
    _fields_ = [("len", ctypes.c_ushort), ("filter", ctypes.c_void_p)]


def install() -> str:
    """Install the filter on this process: "" when done, else why not (the child then runs without
    it and says so). Requires no-new-privileges (or CAP_SYS_ADMIN), which ``jail`` set before."""
    machine = platform.machine()
    if machine not in ("x86_64", "AMD64"):
        return f"seccomp: no system call table for {machine}; the child runs without a syscall filter"
    prog = program(os.getpid())
    buf = ctypes.create_string_buffer(prog, len(prog))
    fprog = _SockFprog(len(prog) // _INSN.size, ctypes.cast(buf, ctypes.c_void_p))
    if _libc.prctl(PR_SET_SECCOMP, ctypes.c_ulong(SECCOMP_MODE_FILTER), ctypes.byref(fprog), 0, 0) != 0:
        err = ctypes.get_errno()
        return f"seccomp: prctl(PR_SET_SECCOMP) refused: {os.strerror(err)}; the child runs without a syscall filter"
    return ""
