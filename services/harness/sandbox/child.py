"""The sandbox's zygote and child processes (``python -m services.harness.sandbox.child FD``).

The zygote is started once per host process (env worker, critic service) by
services/harness/sandbox/client.py. It imports numpy and the harness runtime, leaves the host's
network (an empty network namespace) and, when the host is not root, enters a user namespace
(services/harness/sandbox/userns.py), and then forks one child per request it reads on its control
socket. Each child locks itself in before it reads any package code (:func:`jail`): private
scratch directory as its root, resource limits, a uid and gid of its own (root host: the host's
uid base plus its pid) or no capabilities in the user namespace (non-root host), no new
privileges, killed with its zygote, and last a seccomp filter (seccomp.py). It then serves one
harness runtime's package code
over the channel socket the host passed with the request (services/harness/sandbox/codec.py).
Nothing here is imported by the host process.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import mmap
import os
import resource
import signal
import socket
import struct
import sys
import time
from collections import deque
from collections.abc import Callable
from typing import Any

# Single-threaded numerical libraries: a child may not start threads (RLIMIT_NPROC), and the
# zygote's own thread pools would not survive the fork anyway.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_var] = "1"

import pickle  # noqa: E402 - after the thread settings, like numpy
import subprocess  # noqa: E402,F401 - preloaded: a child cannot read modules from disk after chroot

import numpy as np  # noqa: E402

from services.harness.sandbox import codec, seccomp, userns  # noqa: E402

PR_SET_PDEATHSIG = 1
PR_SET_DUMPABLE = 4
PR_SET_NO_NEW_PRIVS = 38
#: The spawn request: memory MB, CPU s, open files, file size bytes, uid base, then the scratch
#: base path. A child's uid and gid are the uid base plus its pid: no two live children share one.
SPAWN = struct.Struct("<IIIQI")
#: The shared cell a child writes before and after each call: index of the call (-1: none), start.
CELL = struct.Struct("<iid")

_libc = ctypes.CDLL(ctypes.util.find_library("c") or None, use_errno=True)


def _prctl(option: int, arg: int) -> None:
    if _libc.prctl(option, ctypes.c_ulong(arg), 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"prctl({option}): {os.strerror(err)}")


def _preload() -> None:
    """Everything package code may import, loaded before any child is forked (after chroot
    nothing can be read from disk)."""
    import pkgutil

    import services.common.config  # PlatformLimits reads the configuration through it
    import services.harness.package.loader
    import services.harness.runtime.limits
    import services.harness.runtime.engine  # noqa: F401
    import services.harness.runtime.library as library

    for info in pkgutil.iter_modules(library.__path__, library.__name__ + "."):
        __import__(info.name)
    import collections.abc  # noqa: F401
    import encodings.idna  # noqa: F401 - socket and str.encode look codecs up lazily
    import dataclasses  # noqa: F401
    import functools  # noqa: F401
    import itertools  # noqa: F401
    import math  # noqa: F401
    import typing  # noqa: F401

    np.random.default_rng(0).normal(size=3)  # lazy parts of numpy.random
    np.linalg.norm(np.ones(3))


def leave_network() -> str:
    """Leave the host's network, and when not root enter a user namespace (userns.enter): "" when
    the children get an empty network namespace, else why not."""
    return userns.enter().network_degraded


def jail(scratch_base: str, memory_mb: int, cpu_s: int, nofile: int, fsize: int, keep: tuple[int, ...],
         network_degraded: str, uid_base: int) -> dict[str, Any]:
    """Lock this (freshly forked) child in; returns what is enforced and what is degraded.

    How depends on the zygote's mode (services/harness/sandbox/userns.py): as root, chroot and a
    uid/gid of its own (``uid_base`` plus its pid: pids are unique among live processes, so no two
    live children share one); in a user namespace (a non-root host), a private root (pivot_root)
    and no capabilities; degraded, neither."""
    degraded: list[str] = []
    uid = uid_base + os.getpid()  # root mode: its own
    base_as = _vm_size()  # before the chroot hides /proc
    if network_degraded:
        degraded.append("network: " + network_degraded)
    iso = userns.current()
    root = iso.mode == "root"
    scratch = os.path.join(scratch_base, f"c{os.getpid()}")
    os.mkdir(scratch, 0o700)
    if root:
        os.chown(scratch, uid, uid)
    # stdin, stdout, stderr go nowhere: package output never reaches the host's logs.
    null = os.open(os.devnull, os.O_RDWR)
    for fd in (0, 1, 2):
        os.dup2(null, fd)
    os.close(null)
    for fd in sorted(int(f) for f in os.listdir("/proc/self/fd")):
        if fd > 2 and fd not in keep:
            try:
                os.close(fd)
            except OSError:
                pass
    filesystem = ""
    if root:
        os.chroot(scratch)
        os.chdir("/")
        filesystem = "chroot"
    elif iso.mode == "userns":
        filesystem = userns.private_root(scratch)
    else:
        os.chdir(scratch)
        degraded.append("filesystem: not root and no user namespace, so no private root and no change of user; "
                        f"the child keeps the host's uid (user namespace: {iso.userns_refused})")
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # an oversized write fails with EFBIG instead of killing
    limits = {
        resource.RLIMIT_AS: base_as + memory_mb * (1 << 20),
        resource.RLIMIT_CPU: cpu_s,
        resource.RLIMIT_NOFILE: nofile,
        resource.RLIMIT_FSIZE: fsize,
        resource.RLIMIT_CORE: 0,
    }
    for which, value in limits.items():
        resource.setrlimit(which, (value, value))
    if root:
        os.setgroups([])
        os.setgid(uid)
        os.setuid(uid)
    elif iso.mode == "userns":
        userns.drop_capabilities()  # uid and gid are 65534 already: the only ids mapped
    resource.setrlimit(resource.RLIMIT_NPROC, (0, 0))
    _prctl(PR_SET_NO_NEW_PRIVS, 1)
    _prctl(PR_SET_DUMPABLE, 0)
    _prctl(PR_SET_PDEATHSIG, signal.SIGKILL)  # after setuid, which clears it
    # Last: the system call filter (services/harness/sandbox/seccomp.py); needs no-new-privileges.
    filtered = seccomp.install()
    if filtered:
        degraded.append(filtered)
    return {
        "mode": iso.mode, "uid": os.getuid(), "gid": os.getgid(), "outer_uid": iso.outer_uid if iso.mode == "userns" else os.getuid(),
        "capabilities": userns.capabilities(), "chroot": bool(filesystem), "filesystem": filesystem,
        "network_isolated": not network_degraded, "no_new_privs": True, "seccomp": not filtered,
        "memory_mb": memory_mb, "cpu_s": cpu_s, "nofile": nofile, "fsize": fsize, "degraded": degraded, "scratch": scratch,
    }


def _vm_size() -> int:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmSize:"):
                return int(line.split()[1]) * 1024
    return 0


# ---- the child's service loop ---------------------------------------------------------------


class Channel:
    """Blocking framed messages over the channel socket."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.pending = b""

    def send(self, data: bytes) -> None:
        self.sock.sendall(data)

    def recv(self) -> tuple[int, memoryview]:
        # One read takes a whole step's message in the common case (a few KB); set-up messages
        # (START, PUSH) may arrive several at once.
        buf = self.pending
        while len(buf) < 5:
            more = self.sock.recv(1 << 16)
            if not more:
                raise SystemExit(0)  # the host closed the channel
            buf += more
        length, kind = struct.unpack_from("<IB", buf)
        if length < 1 or length > codec.MAX_MESSAGE:
            raise SystemExit(2)
        total = length + 4
        if len(buf) >= total:
            self.pending = buf[total:]
            return kind, memoryview(buf)[5:total]
        self.pending = b""
        body = bytearray(total - 5)
        have = len(buf) - 5
        body[:have] = buf[5:]
        view = memoryview(body)
        while have < len(body):
            r = self.sock.recv_into(view[have:])
            if r == 0:
                raise SystemExit(0)
            have += r
        return kind, view


def _error(text: str) -> bytes:
    w = codec.Writer()
    w.text(text[:4000])
    return w.message(codec.ERROR)


def _describe(exc: BaseException) -> str:
    return f"raised {type(exc).__name__}: {exc}"[:2000]


class Host:
    """A child's state: the package's critics and recoveries, the window, the episode."""

    def __init__(self, chan: Channel, cell: mmap.mmap) -> None:
        from services.harness.runtime import api
        from services.harness.runtime.library import EpisodeMemory
        from services.harness.runtime.perception import QUERIES

        # Resolved once (an import statement per step costs a dictionary walk each time).
        self._Frame, self._Window, self._Detection, self._Proposal = api.Frame, api.Window, api.Detection, api.Proposal
        self._queries = tuple(enumerate(QUERIES))

        self.chan = chan
        self.cell = cell
        view = memoryview(cell)
        self._cell_index = view[0:4].cast("i")  # the layout of CELL: index, padding, start
        self._cell_start = view[8:16].cast("d")
        self.critics: list[tuple[str, Callable[[Any], Any]]] = []
        self.modules: dict[str, Any] = {}
        self.window: deque[Any] = deque(maxlen=32)
        self.instruction = ""
        self.milestone_names: tuple[str, ...] = ()
        self.policy_instructions: tuple[str, ...] = ()
        self.memory = EpisodeMemory()
        self.recovery: Any = None
        self.frames = codec.FrameDecoder()
        #: (step, query) the critics asked this step: which perception answers the host sends along.
        self.asked: set[tuple[int, str]] = set()

    def mark(self, index: int) -> None:
        self._cell_start[0] = time.monotonic()  # the start first: the host reads the index, then the start
        self._cell_index[0] = index

    def unmark(self) -> None:
        self._cell_index[0] = -1

    def serve(self) -> None:
        handlers: dict[int, Callable[[memoryview], bytes]] = {
            codec.INIT: self.init, codec.START: self.start, codec.STEP: self.step, codec.PUSH: self.push,
            codec.REC_START: self.rec_start, codec.REC_ACT: self.rec_act, codec.CHECK: self.check,
            codec.LAYOUT: self.layout, codec.POLICY: self.policy,
        }
        while True:
            kind, body = self.chan.recv()
            handler = handlers.get(kind)
            reply = handler(body) if handler else _error(f"unknown message kind {kind}")
            if reply:
                self.chan.send(reply)

    # ---- set-up ----

    def init(self, body: memoryview) -> bytes:
        from types import MappingProxyType

        from services.harness.package.loader import _import_tool
        from services.harness.package.model import LoadedPackage
        from services.harness.package.safety import check_source
        from services.harness.runtime.engine import _code_critics

        spec = pickle.loads(body)
        self.window = deque(maxlen=int(spec["window"]))
        self.mark(0)
        try:
            tools = {}
            for stem, source in sorted(spec["sources"].items()):
                path = f"tools/{stem}.py"
                if spec["checked"]:  # the static checks and restricted builtins, as in-process
                    check_source(path, source)
                    tools[stem] = _import_tool(stem, path, source, "_zetta_sandboxed", "sandbox")
                else:  # the kernel layer alone: code that never went through the static checks
                    module = type(sys)(f"_zetta_unchecked_{stem}")
                    exec(compile(source, f"<unchecked>/{path}", "exec"), module.__dict__)
                    tools[stem] = module
            package = LoadedPackage("sandboxed", "", "", {}, "", MappingProxyType(spec["params"]), {},
                                    MappingProxyType(tools))
            self.critics = _code_critics(package)
        except BaseException as exc:  # noqa: BLE001 - package code: reported, the host decides
            self.unmark()
            return _error(_describe(exc))
        self.unmark()
        self.modules = tools
        callables = [f"{stem}:{attr}" for stem, m in sorted(self.modules.items())
                     for attr, v in vars(m).items() if callable(v) and not attr.startswith("_")]
        w = codec.Writer()
        w.texts([name for name, _ in self.critics])
        w.texts(callables)
        return w.message(codec.LOADED)

    def start(self, body: memoryview) -> bytes:
        from services.harness.runtime.library import EpisodeMemory

        instruction, names, policy = pickle.loads(body)
        self.instruction, self.milestone_names, self.policy_instructions = instruction, tuple(names), tuple(policy)
        self.window.clear()
        self.memory = EpisodeMemory()
        self.recovery = None
        return b""

    def check(self, body: memoryview) -> bytes:
        """The publish-time probe: import the tools and build a runtime, report the problems."""
        from services.harness.package.errors import PackageRejected
        from services.harness.package.loader import load_files
        from services.harness.runtime.engine import HarnessError, HarnessRuntime

        files, max_bytes = pickle.loads(body)
        problems: list[tuple[str, int, str]] = []
        try:
            HarnessRuntime(load_files(files, max_bytes))
        except PackageRejected as exc:
            problems = [(p.path, p.line, p.reason) for p in exc.problems]
        except HarnessError as exc:
            problems = [("SKILL.md", 0, f"does not make a runnable harness: {exc}")]
        except BaseException as exc:  # noqa: BLE001 - anything else the package's code did
            problems = [("tools/", 0, f"import check failed: {_describe(exc)}")]
        w = codec.Writer()
        w.u32(len(problems))
        for path, line, reason in problems:
            w.text(path)
            w.u32(max(0, int(line)))
            w.text(reason)
        return w.message(codec.CHECKED)

    # ---- the hot path ----

    def layout(self, body: memoryview) -> bytes:
        self.frames.set_layout(body)
        return b""

    def _frame(self, r: codec.Reader) -> tuple[int, dict[str, Any]]:
        step, obs, action, milestones = self.frames.decode(r)
        cache: dict[str, Any] = {}
        self.window.append(self._Frame(step, obs, action, milestones, self._sensor(step, cache)))
        return step, cache

    def _sensor(self, step: int, cache: dict[str, Any]) -> Callable[[str], Any]:
        chan, asked, Detection = self.chan, self.asked, self._Detection

        def perceive(query: str) -> Any:
            if not isinstance(query, str):
                raise TypeError("perceive takes a query string")
            if query in cache:
                asked.add((step, query))
                return cache[query]
            w = codec.Writer()
            w.i64(step)
            w.text(query)
            chan.send(w.message(codec.PERCEIVE))
            kind, body = chan.recv()
            if kind == codec.ERROR:
                raise ValueError(codec.Reader(body).text())
            found = codec.decode_detections(codec.Reader(body), Detection)
            cache[query] = found
            asked.add((step, query))
            return found

        return perceive

    def push(self, body: memoryview) -> bytes:
        r = codec.Reader(body)
        _, cache = self._frame(r)
        self._answers(r, cache)
        r.done()
        return b""

    def _answers(self, r: codec.Reader, cache: dict[str, Any]) -> None:
        """Perception answers the host sent along with a frame, into its cache."""
        Detection = self._Detection
        for _ in range(r.u32()):
            query = r.text()
            cache[query] = codec.decode_detections(r, Detection)

    def policy(self, body: memoryview) -> bytes:
        """The instructions the policy was trained on, learned during the episode (no reply)."""
        self.policy_instructions = tuple(str(s) for s in pickle.loads(body))
        return b""

    def _window(self) -> Any:
        return self._Window(tuple(self.window), self.instruction, self.milestone_names, self.policy_instructions)

    def step(self, body: memoryview) -> bytes:
        Proposal = self._Proposal
        r = codec.Reader(body)
        now, cache = self._frame(r)
        self._answers(r, cache)
        flat = r.u32s(2 * r.u32())
        window = self._window()
        asked = self.asked
        asked.clear()
        heads: list[Any] = []  # per critic run: index, result kind, elapsed (codec.RESULT)
        w = codec.Writer()  # the bodies of proposals and errors, in order
        thread_time, perf = time.thread_time, time.perf_counter
        cell_index, cell_start, monotonic = self._cell_index, self._cell_start, time.monotonic
        critics = self.critics
        R_NONE, R_PROPOSAL, R_ERROR = codec.R_NONE, codec.R_PROPOSAL, codec.R_ERROR
        for k in range(0, len(flat), 2):
            index = flat[k]
            name, fn = critics[index]
            cell_start[0] = monotonic()  # self.mark(index), inlined: the start first
            cell_index[0] = index
            clock = thread_time if flat[k + 1] else perf
            t0 = clock()
            try:
                result = fn(window)
            except BaseException as exc:  # noqa: BLE001 - package code: that critic is switched off
                elapsed = clock() - t0
                cell_index[0] = -1
                heads += (index, R_ERROR, elapsed)
                w.text(_describe(exc))
                continue
            elapsed = clock() - t0
            cell_index[0] = -1
            if result is None:
                heads += (index, R_NONE, elapsed)
            elif isinstance(result, Proposal):
                heads += (index, R_PROPOSAL, elapsed)
                try:
                    codec.encode_proposal(w, str(result.evidence), str(result.suggested_mode), dict(result.details))
                except Exception as exc:  # noqa: BLE001 - details that are not numbers
                    return _error(f"critic {name}: proposal does not encode: {_describe(exc)}")
            else:
                heads += (index, R_ERROR, elapsed)
                w.text(f"returned {type(result).__name__}, not a Proposal or None")
        n = len(heads) // 3
        out = codec.Writer()
        out.u32(n)
        out.parts.append(codec.result_heads(n).pack(*heads))
        out.parts += w.parts
        # Which queries the critics asked of this frame: the host sends those along next step.
        out.u32(sum(1 << i for i, q in self._queries if (now, q) in asked))
        return out.message(codec.RESULTS)

    def rec_start(self, body: memoryview) -> bytes:
        ref, params = pickle.loads(body)
        stem, attr = ref.split(":", 1)
        self.recovery = None
        self.mark(len(self.critics))
        try:
            factory = getattr(self.modules[stem], attr)
            recovery = factory(dict(params))
            recovery.start(self._window(), self.memory)
        except BaseException as exc:  # noqa: BLE001 - package code: the intervention fails
            self.unmark()
            return _error(_describe(exc))
        self.unmark()
        self.recovery = recovery
        return codec.frame(codec.REC_STARTED)

    def rec_act(self, body: memoryview) -> bytes:
        from services.harness.runtime.library.recoveries import PolicyUnder

        if self.recovery is None:
            return _error("no package recovery is active in this sandbox (it was restarted)")
        self.mark(len(self.critics))
        try:
            action = self.recovery.act(self._window())
            w = codec.Writer()
            if isinstance(action, PolicyUnder):
                w.u32(2)
                w.text(str(action.instruction))
            elif action is None:
                w.u32(0)
            else:
                w.u32(1)
                w.array(np.asarray(action, dtype=np.float64))
            w.text(str(getattr(self.recovery, "status", "")))
            w.text(str(getattr(self.recovery, "reason", "")))
        except BaseException as exc:  # noqa: BLE001 - package code: the intervention fails
            self.unmark()
            return _error(_describe(exc))
        self.unmark()
        return w.message(codec.REC_ACTION)


def child_main(chan_fd: int, cell_fd: int, spec: bytes, network_degraded: str) -> None:
    memory_mb, cpu_s, nofile, fsize, uid_base = SPAWN.unpack_from(spec)
    scratch_base = spec[SPAWN.size:].decode()
    cell = mmap.mmap(cell_fd, CELL.size)
    os.close(cell_fd)
    sock = socket.socket(fileno=chan_fd)
    try:
        report = jail(scratch_base, memory_mb, cpu_s, nofile, fsize, (sock.fileno(),), network_degraded, uid_base)
    except BaseException as exc:  # noqa: BLE001 - a child that cannot lock itself in never runs package code
        sock.sendall(_error(f"the sandbox could not be set up: {_describe(exc)}"))
        os._exit(3)
    chan = Channel(sock)
    w = codec.Writer()
    w.text(repr(report))
    chan.send(w.message(codec.READY))
    try:
        Host(chan, cell).serve()
    except SystemExit:
        pass
    os._exit(0)


def zygote_main(ctrl_fd: int) -> None:
    """Fork a child per request on the control socket; exit when the host closes it."""
    try:
        _zygote_loop(ctrl_fd)
    except (BrokenPipeError, ConnectionResetError):
        os._exit(0)  # the host went away (it stopped, or refused its configuration): nothing to report


def _zygote_loop(ctrl_fd: int) -> None:
    _prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    ctrl = socket.socket(fileno=ctrl_fd)
    _preload()
    network_degraded = leave_network()
    signal.signal(signal.SIGCHLD, signal.SIG_IGN)  # children are reaped by the kernel
    ctrl.sendall(codec.frame(codec.READY, network_degraded.encode()))
    while True:
        msg, fds, _flags, _addr = socket.recv_fds(ctrl, 4096, 2)
        if not msg:
            os._exit(0)
        if len(fds) != 2:
            for fd in fds:
                os.close(fd)
            ctrl.sendall(struct.pack("<i", -1))
            continue
        pid = os.fork()
        if pid == 0:
            ctrl.close()
            signal.signal(signal.SIGCHLD, signal.SIG_DFL)
            try:
                child_main(fds[0], fds[1], msg, network_degraded)
            finally:
                os._exit(4)
        for fd in fds:
            os.close(fd)
        ctrl.sendall(struct.pack("<i", pid))


if __name__ == "__main__":
    zygote_main(int(sys.argv[1]))
