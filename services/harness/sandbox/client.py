"""Host side of the harness sandbox: package code runs in a locked-in child process, not here.

Harness package code (the critics and recoveries in a package's ``tools/*.py``, and their
module-level code) is untrusted. In the env worker, the critic service and the publish-time probe
it runs in a sandbox child, one per harness runtime (one per slot, one per Evaluate stream): a
runaway critic of one slot then delays no other slot, and one session's observations never reach
another session's package code. Children are forked from a zygote (one per host process, started
on first use or by :func:`start_zygote`) that preloaded numpy and the runtime, so a child costs a
fork (milliseconds), not an interpreter start.

What the kernel enforces on every child (services/harness/sandbox/child.py ``jail``, before any
package code is read): as root, a uid and gid of its own (:data:`UID_BASE` plus its pid; no user of
the host, and no other child, has it) with no supplementary groups; no new privileges;
not dumpable; an empty network namespace (no interface is up, so no socket reaches anything);
a private scratch directory as its root (chroot): nothing else of the file system is visible,
let alone writable; RLIMIT_NPROC 0 (no fork, no thread, no exec'd helper), RLIMIT_AS (memory),
RLIMIT_CPU, RLIMIT_NOFILE, RLIMIT_FSIZE; a seccomp filter (services/harness/sandbox/seccomp.py:
no socket, exec, namespace, ptrace, mount, bpf, perf, keyring or io_uring call, signals only to
itself); killed when its zygote dies, the zygote when its host dies. A host that is not root gets
the same through a user namespace (services/harness/sandbox/userns.py: the child is 65534 inside
without capabilities, pivot_root into its scratch dir); only when the kernel refuses that too does
the child run degraded, and says so (:attr:`SandboxClient.isolation`, the
``zetta_harness_sandbox_mode`` and ``zetta_harness_sandbox_isolation`` gauges, a warning in the log).

Per step the host sends the new frame (the observation's arrays as one block of raw bytes, laid
out by a LAYOUT message sent only when names, dtypes or shapes change, over a Unix socket;
services/harness/sandbox/codec.py) and the indices of the critics to run; the child keeps the
window. A call is timed by the host through a shared cell the child writes before and after
each call: a call still running at the platform's hard limit gets the child SIGKILLed; the next
call respawns it and restores the window, the critic that overran stays switched off for the
episode. Waiting on the socket releases the GIL: heartbeats and other slots run meanwhile.

``ZETTA_HARNESS_SANDBOX=off`` runs package code in the host process instead (trusted code and
benchmarks only; docs/security.md).
"""

from __future__ import annotations

import logging
import mmap
import os
import pickle
import select
import shutil
import signal
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from services.harness.sandbox import codec

log = logging.getLogger("zetta.harness.sandbox")

_SPAWN = struct.Struct("<IIIQI")
#: Sandbox children of a root host run as uid = gid = UID_BASE + their pid: a range no user or group of the host
#: may use (UID_BASE up to UID_BASE + /proc/sys/kernel/pid_max, at most 4194304: 200000-4394303).
#: Every live child has its own, so one child cannot signal another, or read what it owns.
UID_BASE = 200_000
_U32 = struct.Struct("<I")
_ZERO = _U32.pack(0)
_CELL = struct.Struct("<iid")
_ROOT = Path(__file__).resolve().parents[3]
#: How often the host looks at the call cell while the child is between calls (the deadline of a
#: call comes from the start time the child wrote, so this bounds only how late a call is noticed).
_SLICE_S = 0.02


def enabled(environ: Mapping[str, str] | None = None) -> bool:
    """Whether package code runs sandboxed (``ZETTA_HARNESS_SANDBOX``, default on; ``off`` opts out)."""
    value = (os.environ if environ is None else environ).get("ZETTA_HARNESS_SANDBOX", "on").strip().lower()
    if value in ("on", "1", "true", "yes", ""):
        return True
    if value in ("off", "0", "false", "no", "inprocess"):
        return False
    from services.common.config import ConfigError

    raise ConfigError(f"ZETTA_HARNESS_SANDBOX={value!r}: use on (default) or off (in-process, trusted code only)")


@dataclass(frozen=True)
class SandboxLimits:
    """Resource limits of one sandbox child (the platform's, from the host's configuration)."""

    memory_mb: int = 512
    cpu_s: int = 600
    nofile: int = 16
    fsize_bytes: int = 1 << 20
    #: How long loading a package's tools (its module-level code) may take in the child.
    load_timeout_s: float = 10.0

    @classmethod
    def from_env(cls, environ: Any = None) -> "SandboxLimits":
        """ZETTA_SANDBOX_MEMORY_MB (512), ZETTA_SANDBOX_CPU_S (600 s of CPU over a child's life),
        ZETTA_SANDBOX_LOAD_TIMEOUT_S (10)."""
        from services.common.config import EnvReader

        env = EnvReader(environ)
        out = cls(memory_mb=env.int("ZETTA_SANDBOX_MEMORY_MB", 512, minimum=64),
                  cpu_s=env.int("ZETTA_SANDBOX_CPU_S", 600, minimum=1),
                  load_timeout_s=env.float("ZETTA_SANDBOX_LOAD_TIMEOUT_S", 10.0, minimum=0.1))
        env.finish("harness sandbox")
        return out


class SandboxError(RuntimeError):
    """The sandbox child failed: ``index`` is the call it was in (-1: none), ``reason`` why."""

    def __init__(self, index: int, reason: str) -> None:
        super().__init__(reason)
        self.index = index
        self.reason = reason


class CallFailed(RuntimeError):
    """The package code raised (the child is fine)."""


# ---- the zygote ------------------------------------------------------------------------------


class Zygote:
    """The process sandbox children are forked from (one per host process)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._proc: subprocess.Popen[bytes] | None = None
        self._ctrl: socket.socket | None = None
        self.network_degraded = ""
        self.scratch_base = ""
        self._ready = False

    def _launch(self) -> None:
        """Start the zygote process (it imports numpy and the runtime meanwhile)."""
        if self._ctrl is not None:
            self._ctrl.close()
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        env = dict(os.environ)
        paths = [str(_ROOT), str(_ROOT / "clients" / "python")]
        env["PYTHONPATH"] = os.pathsep.join(paths + [p for p in env.get("PYTHONPATH", "").split(os.pathsep) if p])
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "services.harness.sandbox.child", str(theirs.fileno())],
            pass_fds=(theirs.fileno(),), env=env, cwd=str(_ROOT), stdin=subprocess.DEVNULL,
        )
        theirs.close()
        ours.settimeout(120.0)
        self._ctrl = ours
        self._ready = False

    def _start(self) -> None:
        """A running, ready zygote: launched if need be, then waited for."""
        if self._proc is None or self._proc.poll() is not None:
            self._launch()
        elif self._ready:
            return
        ours, proc = self._ctrl, self._proc
        assert ours is not None and proc is not None
        try:
            head = _recv_exact(ours, 5)
            length, kind = struct.unpack("<IB", head)
            body = _recv_exact(ours, length - 1)
        except (OSError, ConnectionError) as exc:
            proc.kill()
            proc.wait()
            self._proc = None
            raise SandboxError(-1, f"the sandbox zygote did not start: {exc}") from None
        self._ready = True
        self.network_degraded = body.decode()
        base = Path(tempfile.mkdtemp(prefix="zetta-sandbox-"))
        base.chmod(0o711)  # children (their own uids) must traverse it to their own directory
        self.scratch_base = str(base)
        weakref.finalize(self, shutil.rmtree, str(base), True)
        if self.network_degraded:
            log.warning("harness sandbox: DEGRADED network isolation: %s", self.network_degraded)

    def spawn(self, limits: SandboxLimits) -> tuple[int, socket.socket, mmap.mmap]:
        """A new child: its pid, the host's end of its channel and the shared call cell."""
        with self._lock:
            self._start()
            assert self._ctrl is not None
            ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
            cell_fd = os.memfd_create("zetta-sandbox-cell")
            os.ftruncate(cell_fd, _CELL.size)
            cell = mmap.mmap(cell_fd, _CELL.size)
            _CELL.pack_into(cell, 0, -1, 0, 0.0)
            spec = (_SPAWN.pack(limits.memory_mb, limits.cpu_s, limits.nofile, limits.fsize_bytes, UID_BASE)
                    + self.scratch_base.encode())
            try:
                socket.send_fds(self._ctrl, [spec], [theirs.fileno(), cell_fd])
                (pid,) = struct.unpack("<i", _recv_exact(self._ctrl, 4))
            except OSError as exc:
                ours.close()
                raise SandboxError(-1, f"the sandbox zygote failed: {exc}") from None
            finally:
                theirs.close()
                os.close(cell_fd)
            if pid <= 0:
                ours.close()
                raise SandboxError(-1, "the sandbox zygote refused to fork")
            return pid, ours, cell

    def close(self) -> None:
        with self._lock:
            if self._ctrl is not None:
                self._ctrl.close()
            if self._proc is not None:
                self._proc.kill()
                self._proc.wait()
            self._proc = self._ctrl = None


_ZYGOTE: Zygote | None = None
_ZYGOTE_LOCK = threading.Lock()


def zygote() -> Zygote:
    global _ZYGOTE
    with _ZYGOTE_LOCK:
        if _ZYGOTE is None:
            _ZYGOTE = Zygote()
        return _ZYGOTE


def start_zygote(wait: bool = False) -> None:
    """Start the zygote now (it takes 1-3 s to import numpy and the runtime, in its own process),
    not at the first reset; ``wait`` for it to be ready."""
    z = zygote()
    with z._lock:
        if z._proc is None or z._proc.poll() is not None:
            z._launch()
        if wait:
            z._start()


def _recv_exact(sock: socket.socket, n: int) -> bytes:
    buf = bytearray(n)
    view = memoryview(buf)
    got = 0
    while got < n:
        r = sock.recv_into(view[got:])
        if r == 0:
            raise ConnectionError("the sandbox closed its channel")
        got += r
    return bytes(buf)


def _kill(pid: int, pidfd: int) -> None:
    try:
        signal.pidfd_send_signal(pidfd, signal.SIGKILL)
    except OSError:
        pass
    try:
        os.close(pidfd)
    except OSError:
        pass


def _remove(path: str) -> None:
    shutil.rmtree(path, ignore_errors=True)


# ---- one child ------------------------------------------------------------------------------


class CriticResult(NamedTuple):
    """One critic call in the child: ``kind`` codec.R_NONE / R_PROPOSAL / R_ERROR, its elapsed
    time (thread CPU when the host asked for it, else wall), and the proposal or the error.
    (A tuple: ten of them are built per env step.)"""

    index: int
    kind: int
    elapsed_s: float
    proposal: tuple[str, str, dict[str, float]] | None = None
    error: str = ""


_new_tuple = tuple.__new__


@dataclass(frozen=True)
class Loaded:
    critics: tuple[str, ...]
    callables: frozenset[str]


Perceive = Callable[[int, str], Any]


class SandboxClient:
    """One sandbox child and the calls into it. Not thread-safe: one runtime's thread uses it."""

    def __init__(self, limits: SandboxLimits | None = None) -> None:
        self.limits = limits or SandboxLimits()
        z = zygote()
        self.pid, self._sock, self._cell = z.spawn(self.limits)
        self._pidfd = os.pidfd_open(self.pid)
        self._finalizer = weakref.finalize(self, _kill, self.pid, self._pidfd)
        self._poll = select.poll()
        self._poll.register(self._sock.fileno(), select.POLLIN | select.POLLHUP | select.POLLERR)
        self._wpoll = select.poll()
        self._wpoll.register(self._sock.fileno(), select.POLLOUT | select.POLLHUP | select.POLLERR)
        self._frames = codec.FrameEncoder()
        #: Bit i set: the critics asked perception query i (QUERIES) of the last frame.
        self.asked = 0
        # Non-blocking: a send or receive is one system call (a socket with a timeout polls before
        # each); waits go through the pollers, with deadlines (a child that stops reading or
        # answering never blocks the host).
        self._sock.setblocking(False)
        #: The last step's critic runs, as sent (the same most steps) and as the reply's heads.
        self._runs: tuple[tuple[int, bool], ...] | None = None
        self._runs_msg = b""
        self._runs_index: tuple[int, ...] = ()
        self._heads: struct.Struct = struct.Struct("<")
        self.dead = ""
        kind, r = self._call(b"", lambda i: self.limits.load_timeout_s, cap_s=self.limits.load_timeout_s)
        if kind != codec.READY:
            self.close()
            raise SandboxError(-1, _error_text(kind, r) or f"unexpected first message {kind}")
        import ast

        self.isolation: dict[str, Any] = ast.literal_eval(r.text())
        scratch = str(self.isolation.get("scratch", ""))
        if scratch.startswith(z.scratch_base + os.sep):
            weakref.finalize(self, _remove, scratch)
        _publish_isolation(self.isolation)

    # ---- plumbing ----

    def close(self) -> None:
        """Kill the child (idempotent)."""
        self._finalizer()
        try:
            self._sock.close()
        except OSError:
            pass
        self.dead = self.dead or "closed"

    def _kill(self, index: int, reason: str) -> SandboxError:
        self.dead = reason
        self.close()
        return SandboxError(index, reason)

    def _cell_now(self) -> tuple[int, float]:
        index, _, start = _CELL.unpack_from(self._cell, 0)
        return index, start

    def _call(self, msg: bytes, hard_limit: Callable[[int], float], cap_s: float,
              perceive: Perceive | None = None) -> tuple[int, codec.Reader]:
        """Send ``msg`` (nothing when empty) and wait for the reply, serving perception queries;
        the child is killed when a call in it passes its hard limit or the reply passes ``cap_s``."""
        if self.dead:
            raise SandboxError(-1, f"the sandbox is gone ({self.dead})")
        if msg:
            self._sendall(msg)
        give_up = time.monotonic() + cap_s
        while True:
            now = time.monotonic()
            index, start = self._cell_now()
            # Between calls (index -1) the cell is looked at again soon: a call may start.
            deadline = (min(give_up, start + hard_limit(index)) if index >= 0
                        else min(give_up, now + min(_SLICE_S, hard_limit(-1) / 2)))
            if now >= give_up or (index >= 0 and now >= deadline):
                if index >= 0 and start + hard_limit(index) <= now:
                    raise self._kill(index, f"interrupted after {hard_limit(index) * 1000:.0f} ms (hard limit); "
                                            "the sandbox process was killed")
                raise self._kill(index, f"no answer from the sandbox within {cap_s:.1f} s; it was killed")
            if not self._poll.poll(max(1, int((deadline - now) * 1000 + 0.999))):
                continue
            try:
                got = self._read()
            except (OSError, ConnectionError, codec.WireError) as exc:
                index, _ = self._cell_now()
                raise self._kill(index, f"the sandbox process died or broke the protocol ({exc})") from None
            if got is None:
                continue  # nothing to read after all
            kind, body = got
            if kind == codec.PERCEIVE and perceive is not None:
                r = codec.Reader(body)
                try:
                    step, query = r.i64(), r.text(256)
                    answer = codec.pack_detections(perceive(step, query))
                except Exception as exc:  # noqa: BLE001 - a bad query fails the critic, not the host
                    w = codec.Writer()
                    w.text(str(exc))
                    answer = w.message(codec.ERROR)
                self._sendall(answer, index)
                continue
            return kind, codec.Reader(body)

    def _sendall(self, msg: bytes, index: int = -1) -> None:
        """Send a whole message: one system call in the common case; while the child's socket
        buffer is full, waits for room for at most the load timeout, then kills the child."""
        try:
            sent = self._sock.send(msg)
        except BlockingIOError:
            sent = 0
        except OSError as exc:
            raise self._kill(index, f"sending to the sandbox failed: {exc}") from None
        if sent == len(msg):
            return
        view = memoryview(msg)
        deadline = time.monotonic() + self.limits.load_timeout_s
        while sent < len(view):
            left = deadline - time.monotonic()
            if left <= 0:
                raise self._kill(index, f"sending to the sandbox failed: it read nothing for "
                                        f"{self.limits.load_timeout_s:.1f} s; it was killed")
            self._wpoll.poll(max(1, int(left * 1000 + 0.999)))
            try:
                sent += self._sock.send(view[sent:])
            except BlockingIOError:
                continue
            except OSError as exc:
                raise self._kill(index, f"sending to the sandbox failed: {exc}") from None

    def _recv_rest(self, n: int) -> bytes:
        """The next ``n`` bytes of a reply already begun (it has the load timeout to arrive)."""
        buf = bytearray(n)
        view = memoryview(buf)
        got = 0
        deadline = time.monotonic() + self.limits.load_timeout_s
        while got < n:
            left = deadline - time.monotonic()
            if left <= 0:
                raise ConnectionError(f"a reply stalled for {self.limits.load_timeout_s:.1f} s")
            self._poll.poll(max(1, int(left * 1000 + 0.999)))
            try:
                r = self._sock.recv_into(view[got:])
            except BlockingIOError:
                continue
            if r == 0:
                raise ConnectionError("the sandbox closed its channel")
            got += r
        return bytes(buf)

    def _read(self) -> tuple[int, memoryview] | None:
        """One reply (None: nothing was there after all)."""
        try:
            first = self._sock.recv(1 << 16)  # a whole reply in the common case
        except BlockingIOError:
            return None
        if not first:
            raise ConnectionError("the sandbox closed its channel")
        if len(first) < 5:
            first += self._recv_rest(5 - len(first))
        length, kind = struct.unpack_from("<IB", first)
        if length < 1 or length > codec.MAX_REPLY:
            raise codec.WireError(f"reply of {length} bytes")
        if len(first) > length + 4:
            raise codec.WireError("the sandbox sent more than one reply")
        if len(first) == length + 4:
            return kind, memoryview(first)[5:]
        return kind, memoryview(first[5:] + self._recv_rest(length + 4 - len(first)))

    # ---- the calls ----

    def load(self, window: int, sources: Mapping[str, str], params: Mapping[str, Mapping[str, Any]] | None = None,
             checked: bool = True) -> Loaded:
        """Import the package's tools (``tools/<stem>.py`` text by stem) in the child. ``checked``:
        the loader's static checks and restricted builtins apply there as they do in-process; off
        only for tests of the kernel layer alone (code that never went through the static checks)."""
        spec = {"window": window, "checked": checked, "sources": dict(sources),
                "params": {k: dict(v) for k, v in (params or {}).items()}}
        msg = codec.frame(codec.INIT, pickle.dumps(spec))
        kind, r = self._call(msg, lambda i: self.limits.load_timeout_s, self.limits.load_timeout_s + 1.0)
        if kind != codec.LOADED:
            raise CallFailed(_error_text(kind, r))
        return Loaded(tuple(r.texts()), frozenset(r.texts(1 << 16)))

    def start(self, instruction: str, milestone_names: Sequence[str], policy_instructions: Sequence[str] = ()) -> None:
        self._send(codec.frame(codec.START, pickle.dumps((instruction, tuple(milestone_names),
                                                          tuple(policy_instructions)))))

    def set_policy_instructions(self, instructions: Sequence[str]) -> None:
        """What the policy was trained on, learned during an episode (no reply)."""
        self._send(codec.frame(codec.POLICY, pickle.dumps(tuple(instructions))))

    def push_message(self, step: int, obs: Mapping[str, np.ndarray], action: np.ndarray | None,
                     milestones: frozenset[str], prefetched: Sequence[tuple[str, Any]] = ()) -> bytes:
        """A frame for the child's window without a reply, to send ahead of the next call (frames
        are encoded in the order they are sent: the encoder sends only what changed), with
        perception answers for it as :meth:`step` takes them."""
        w = codec.Writer()
        layout = self._frames.encode(w, step, obs, action, milestones)
        _answers(w, prefetched)
        return layout + w.message(codec.PUSH)

    def _send(self, msg: bytes) -> None:
        if self.dead:
            raise SandboxError(-1, f"the sandbox is gone ({self.dead})")
        self._sendall(msg)

    def step(self, step: int, obs: Mapping[str, np.ndarray], action: np.ndarray | None, milestones: frozenset[str],
             runs: Sequence[tuple[int, bool]], hard_limit: Callable[[int], float], perceive: Perceive | None = None,
             prefetched: Sequence[tuple[str, Any]] = (), cap_s: float | None = None,
             before: bytes = b"") -> list[CriticResult]:
        """Append a frame to the child's window and run the critics ``runs`` ((index, time in CPU)).
        ``prefetched``: perception answers for this frame, sent along (a query the child asks
        that is not among them costs a round trip through ``perceive``). ``cap_s``: how long the
        whole step may take (default: the sum of the critics' hard limits plus 2 s). ``before``:
        messages sent ahead in the same write (:meth:`push_message` frames). Returns a
        :class:`CriticResult` per critic run, in order."""
        self.send_step(step, obs, action, milestones, runs, prefetched, before)
        return self.results(hard_limit, perceive, cap_s)

    def send_step(self, step: int, obs: Mapping[str, np.ndarray], action: np.ndarray | None,
                  milestones: frozenset[str], runs: Sequence[tuple[int, bool]],
                  prefetched: Sequence[tuple[str, Any]] = (), before: bytes = b"") -> None:
        """The first half of :meth:`step`: send the frame and the critics to run, without waiting
        (the child works while the caller steps its env); :meth:`results` collects the answer."""
        w = codec.Writer()
        layout = self._frames.encode(w, step, obs, action, milestones)
        _answers(w, prefetched)
        runs = tuple(runs)
        if runs != self._runs:  # the same critics as last step, most of the time
            self._runs = runs
            self._runs_index = tuple(i for i, _ in runs)
            self._runs_msg = struct.pack(f"<I{2 * len(runs)}I", len(runs),
                                         *(v for i, s in runs for v in (i, 1 if s else 0)))
            self._heads = codec.result_heads(len(runs))
        w.parts.append(self._runs_msg)
        self._send(before + layout + w.message(codec.STEP))

    def results(self, hard_limit: Callable[[int], float], perceive: Perceive | None = None,
                cap_s: float | None = None) -> list[CriticResult]:
        """The second half of :meth:`step`: wait for the answer to the step sent last (serving its
        perception queries; a critic past its hard limit, counted from its start, is killed)."""
        runs = self._runs or ()
        if cap_s is None:
            cap_s = sum(hard_limit(i) for i in self._runs_index) + 2.0
        kind, r = self._call(b"", hard_limit, cap_s, perceive)
        if kind != codec.RESULTS:
            raise self._kill(-1, f"the sandbox broke the protocol: {_error_text(kind, r)}")
        try:
            n = r.u32()
            if n != len(runs):
                raise codec.WireError(f"{n} results for {len(runs)} critics")
            heads = self._heads.unpack_from(r.buf, r.take_at(self._heads.size))
            out: list[CriticResult] = []
            append = out.append
            it = iter(heads)
            for index, rk, elapsed in zip(it, it, it):
                if rk == codec.R_NONE:
                    append(_new_tuple(CriticResult, (index, rk, elapsed, None, "")))
                elif rk == codec.R_PROPOSAL:
                    append(_new_tuple(CriticResult, (index, rk, elapsed, codec.decode_proposal(r), "")))
                elif rk == codec.R_ERROR:
                    append(_new_tuple(CriticResult, (index, rk, elapsed, None, r.text(4000))))
                else:
                    raise codec.WireError(f"result kind {rk}")
            self.asked = r.u32()
            r.done()
        except codec.WireError as exc:
            raise self._kill(-1, f"the sandbox broke the protocol: {exc}") from None
        if heads[::3] != self._runs_index:
            raise self._kill(-1, "the sandbox answered for other critics than it was asked")
        return out

    def recovery_start(self, ref: str, params: Mapping[str, Any], hard_limit_s: float,
                       perceive: Perceive | None = None, before: bytes = b"") -> None:
        msg = before + codec.frame(codec.REC_START, pickle.dumps((ref, dict(params))))
        kind, r = self._call(msg, lambda i: hard_limit_s, hard_limit_s + 2.0, perceive)
        if kind != codec.REC_STARTED:
            raise CallFailed(_error_text(kind, r))

    def recovery_act(self, hard_limit_s: float, perceive: Perceive | None = None, before: bytes = b""
                     ) -> tuple[np.ndarray | str | None, str, str]:
        """(action array, or an instruction to run the policy under, or None), status, reason."""
        kind, r = self._call(before + codec.frame(codec.REC_ACT), lambda i: hard_limit_s, hard_limit_s + 2.0, perceive)
        if kind != codec.REC_ACTION:
            raise CallFailed(_error_text(kind, r))
        try:
            what = r.u32()
            action: np.ndarray | str | None = None
            if what == 1:
                action = r.array(copy=True)
            elif what == 2:
                action = r.text()
            status, reason = r.text(256), r.text(4000)
            r.done()
        except codec.WireError as exc:
            raise self._kill(-1, f"the sandbox broke the protocol: {exc}") from None
        return action, status, reason

    def check(self, files: Mapping[str, bytes], max_bytes: int, timeout_s: float) -> list[tuple[str, int, str]]:
        """Load ``files`` and build a runtime from them inside the child (the publish-time probe)."""
        msg = codec.frame(codec.CHECK, pickle.dumps((dict(files), max_bytes)))
        kind, r = self._call(msg, lambda i: timeout_s, timeout_s)
        if kind != codec.CHECKED:
            raise CallFailed(_error_text(kind, r))
        return [(r.text(), r.u32(), r.text()) for _ in range(r.u32())]


def _answers(w: codec.Writer, prefetched: Sequence[tuple[str, Any]]) -> None:
    """Perception answers for a frame: ``u32 count | (query, detections)*``."""
    if prefetched:
        w.parts.append(_U32.pack(len(prefetched)))
        for query, found in prefetched:
            w.text(query)
            codec.encode_detections(w, found)
    else:
        w.parts.append(_ZERO)


def _error_text(kind: int, r: codec.Reader) -> str:
    if kind == codec.ERROR:
        try:
            return r.text(8000)
        except codec.WireError:
            return "an unreadable error"
    return f"unexpected reply kind {kind}"


_published: set[str] = set()


def _publish_isolation(report: Mapping[str, Any]) -> None:
    """Once per process: the isolation the children get, in the log and as a gauge."""
    from prometheus_client import Gauge

    global _GAUGE, _MODE_GAUGE
    # (uid and gid differ per child in root mode: not part of what is published once)
    key = repr(sorted((k, v) for k, v in report.items() if k not in ("scratch", "uid", "gid", "outer_uid")))
    if key in _published:
        return
    _published.add(key)
    if _GAUGE is None:
        _GAUGE = Gauge("zetta_harness_sandbox_isolation",
                       "Isolation each harness sandbox child gets (1 enforced, 0 degraded), by feature.", ["feature"])
        _MODE_GAUGE = Gauge("zetta_harness_sandbox_mode",
                            "How harness sandbox children are isolated (1: this mode): root (a distinct uid), "
                            "userns (a user namespace of a non-root host) or degraded.", ["mode"])
    uid = report.get("uid")
    own_uid = isinstance(uid, int) and uid >= UID_BASE  # root mode: UID_BASE + the child's pid
    mode = str(report.get("mode", "root" if own_uid else "degraded"))
    no_caps = report.get("capabilities") == 0
    features = {"unprivileged_user": (mode == "root" and own_uid) or (mode == "userns" and uid == 65534 and no_caps),
                "distinct_uid": mode == "root" and own_uid,
                "network": bool(report.get("network_isolated")),
                "filesystem": bool(report.get("chroot")), "no_new_privs": bool(report.get("no_new_privs")),
                "seccomp": bool(report.get("seccomp"))}
    for name, on in features.items():
        _GAUGE.labels(name).set(1.0 if on else 0.0)
    assert _MODE_GAUGE is not None
    for name in ("root", "userns", "degraded"):
        _MODE_GAUGE.labels(name).set(1.0 if name == mode else 0.0)
    if report.get("degraded"):
        log.warning("harness sandbox DEGRADED (mode %s): %s", mode, "; ".join(map(str, report["degraded"])))
    elif mode == "userns":
        log.info("harness sandbox: mode userns (the host is not root): a user namespace where the child is uid %s "
                 "without capabilities (the host's uid %s outside), own empty network namespace, private root "
                 "(%s to its scratch dir), rlimits memory %s MB, CPU %s s, %s files, no processes, seccomp filter",
                 report.get("uid"), report.get("outer_uid"), report.get("filesystem"), report.get("memory_mb"),
                 report.get("cpu_s"), report.get("nofile"))
    else:
        log.info("harness sandbox: mode %s: a uid of its own per child (%d + its pid), own empty network namespace, "
                 "chroot to a private scratch dir, rlimits memory %s MB, CPU %s s, %s files, no processes, seccomp "
                 "filter", mode, UID_BASE, report.get("memory_mb"), report.get("cpu_s"), report.get("nofile"))


_GAUGE: Any = None
_MODE_GAUGE: Any = None
