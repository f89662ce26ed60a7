"""Writes deploy/seccomp/zetta-sandbox-host.json, the container seccomp profile of the services that
host harness sandboxes (env worker, critic service, evolver); ``--check`` fails if it is stale.

The container runtimes' default profiles (Kubernetes ``RuntimeDefault``, Docker's default) refuse
``unshare`` and ``mount`` to a container without CAP_SYS_ADMIN, so a non-root service under them
cannot give its sandbox children a user namespace and they run degraded (docs/security.md). This
profile allows every call except a deny list, like the children's own filter
(services/harness/sandbox/seccomp.py): that filter's list, minus what the host itself does (sockets,
processes and threads, exec, signals and pidfds to its children, CPU affinity) and minus the four
calls the sandbox's set-up needs (``unshare``, ``mount``, ``umount2``, ``pivot_root``; ``chroot``
as the fallback). Each child installs the full filter after its set-up, so package code still gets
EPERM for all of them. Being a deny list, it does not refuse calls added to the kernel later, as an
allow list would.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from services.harness.sandbox import seccomp  # noqa: E402

PROFILE = ROOT / "deploy" / "seccomp" / "zetta-sandbox-host.json"
#: What the sandbox's set-up needs (services/harness/sandbox/userns.py).
SET_UP = ("unshare", "mount", "umount2", "pivot_root", "chroot")
#: What the host process itself does.
HOST = ("socket", "socketpair", "fork", "vfork", "execve", "execveat", "pidfd_open", "pidfd_send_signal",
        "setpriority", "ioprio_set")


def denied() -> list[str]:
    return [name for name in seccomp.DENIED if name not in SET_UP + HOST]


def profile() -> str:
    body = {
        "defaultAction": "SCMP_ACT_ALLOW",
        "architectures": ["SCMP_ARCH_X86_64", "SCMP_ARCH_X86", "SCMP_ARCH_X32", "SCMP_ARCH_AARCH64", "SCMP_ARCH_ARM"],
        "syscalls": [{"names": denied(), "action": "SCMP_ACT_ERRNO", "errnoRet": 1}],
    }
    return json.dumps(body, indent=2) + "\n"


def main() -> int:
    text = profile()
    if "--check" in sys.argv[1:]:
        if not PROFILE.exists() or PROFILE.read_text() != text:
            print(f"{PROFILE.relative_to(ROOT)} is stale: run python scripts/gen_seccomp_profile.py", file=sys.stderr)
            return 1
        return 0
    PROFILE.parent.mkdir(parents=True, exist_ok=True)
    PROFILE.write_text(text)
    print(f"wrote {PROFILE.relative_to(ROOT)} ({len(denied())} calls refused)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
