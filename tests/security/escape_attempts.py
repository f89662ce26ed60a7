"""Escape attempts shared by the harness sandbox tests (tests/security/test_harness_sandbox_kernel.py
runs them in a root host's child, tests/security/test_harness_sandbox_userns.py in an unprivileged
host's user-namespace child). Each is package-code source, loaded unchecked into the sandbox: a test
concatenates ``PRELUDE``, its own extra imports and attempts, ``COMMON`` and ``LAST`` into one
module. Only the attempts are shared; what each test expects of them (which error, in which mode)
stays in the test.

``params`` the attempts read: ``marker`` (a path prefix in a world-writable directory of the test),
``port`` and ``unix`` (a TCP and a Unix listener of the test; ``targets`` makes these three),
``host_pid`` (the sandbox's host).
"""

from __future__ import annotations

import contextlib
import os
import socket
from collections.abc import Iterator
from pathlib import Path
from typing import Any


@contextlib.contextmanager
def targets(shared: Path) -> Iterator[tuple[dict[str, Any], socket.socket, socket.socket]]:
    """What the attempts aim at: ``shared`` (an existing directory) made world-writable (only the
    sandbox may stop a write there), a TCP listener on loopback and a Unix socket listener in
    ``shared``; yields their ``params`` (marker, port, unix) and the two listeners, closed after."""
    shared.chmod(0o777)
    tcp = socket.create_server(("127.0.0.1", 0))
    tcp.settimeout(0.5)
    unix_path = str(shared / "listener.sock")
    unix = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    unix.bind(unix_path)
    os.chmod(unix_path, 0o777)
    unix.listen()
    unix.settimeout(0.5)
    try:
        yield {"marker": str(shared / "marker"), "port": tcp.getsockname()[1], "unix": unix_path}, tcp, unix
    finally:
        tcp.close()
        unix.close()

#: The imports every attempt needs and ``_try``: runs one attempt, ``blocked`` 1.0 when it raised.
PRELUDE = r'''
import os
import signal
import socket
import threading

from services.harness.runtime.api import Proposal


def _try(name, fn):
    try:
        out = fn()
    except BaseException as exc:
        return Proposal(name, f"{type(exc).__name__}: {exc}", "", {"blocked": 1.0})
    return Proposal(name, f"succeeded: {out!r}", "", {"blocked": 0.0})


def critic_whoami(window, params):
    return Proposal("whoami", os.getcwd(), "", {"uid": os.getuid(), "gid": os.getgid(), "euid": os.geteuid(),
                                               "groups": len(os.getgroups())})
'''

#: Reading, writing, connecting, signalling and changing uid: each should fail inside the child.
COMMON = r'''

def critic_read_passwd(window, params):
    return _try("read_passwd", lambda: open("/etc/passwd").read())


def critic_write_marker(window, params):
    def write():
        with open(params["marker"] + ".open", "w") as f:
            f.write("x")
    return _try("write_marker", write)


def critic_connect(window, params):
    return _try("connect", lambda: socket.create_connection(("127.0.0.1", params["port"]), timeout=1.0))


def critic_unix(window, params):
    def connect():
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.connect(params["unix"])
        return s
    return _try("unix", connect)


def critic_signal_host(window, params):
    return _try("signal_host", lambda: os.kill(params["host_pid"], signal.SIGTERM))


def critic_setuid_root(window, params):
    return _try("setuid_root", lambda: os.setuid(0))


def critic_thread(window, params):
    def start():
        t = threading.Thread(target=lambda: None)
        t.start()
        return t
    return _try("thread", start)
'''

#: The resource limits (file size, memory), then the one thing allowed: the child's scratch space.
LAST = r'''

def critic_big_file(window, params):
    def write():
        with open("big", "wb") as f:  # in the scratch dir, the one writable place: but limited
            f.write(b"x" * (8 << 20))
    return _try("big_file", write)


def critic_memory_bomb(window, params):
    return _try("memory_bomb", lambda: bytearray(4 << 30))


def critic_scratch(window, params):
    def write():
        with open("note.txt", "w") as f:
            f.write("allowed")
        return open("note.txt").read()
    return _try("scratch", write)
'''
