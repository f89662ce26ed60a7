"""Progress bars: when they are drawn (services.common.progress), and that a command's stdout stays
clean while they are (the CLI test drives `zetta evolve export` with stderr on a pseudo-terminal)."""

from __future__ import annotations

import argparse
import fcntl
import io
import os
import pty
import re
import select
import struct
import subprocess
import sys
import termios
from pathlib import Path

import pytest

from services.common import progress as prog
from services.evolver.store import EpisodeKey, Outcome, RolloutStore
from tests.unit.test_evolver_fixtures import make_trace

ROOT = Path(__file__).resolve().parents[2]


class _Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


class _Closed(io.StringIO):
    def isatty(self) -> bool:
        raise ValueError("I/O operation on closed file")


@pytest.mark.parametrize(("no_progress", "env", "stream", "on"), [
    (False, {}, _Terminal(), True),
    (False, {}, io.StringIO(), False),  # a pipe or a file: no bars
    (False, {}, _Closed(), False),
    (True, {}, _Terminal(), False),  # --no-progress
    (False, {"ZETTA_NO_PROGRESS": "1"}, _Terminal(), False),
    (False, {"ZETTA_NO_PROGRESS": "yes"}, _Terminal(), False),
    (False, {"ZETTA_NO_PROGRESS": "0"}, _Terminal(), True),
    (False, {"ZETTA_NO_PROGRESS": "false"}, _Terminal(), True),
    (False, {"ZETTA_NO_PROGRESS": ""}, _Terminal(), True),
])
def test_on_off_rules(no_progress: bool, env: dict[str, str], stream: io.StringIO, on: bool) -> None:
    assert prog.progress_enabled(no_progress, stream, env) is on


def test_no_progress_flag_turns_bars_off_for_the_process(monkeypatch: pytest.MonkeyPatch) -> None:
    """--no-progress sets ZETTA_NO_PROGRESS, so library code and child processes see it too."""
    monkeypatch.delenv(prog.ENV_VAR, raising=False)
    p = argparse.ArgumentParser()
    prog.add_progress_option(p)
    assert p.parse_args([]).no_progress is False and prog.ENV_VAR not in os.environ
    assert p.parse_args(["--no-progress"]).no_progress is True
    assert os.environ[prog.ENV_VAR] == "1"
    monkeypatch.setattr(sys, "stderr", _Terminal())
    assert prog.progress_enabled() is False


def test_bars_write_to_stderr_only(monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.delenv(prog.ENV_VAR, raising=False)
    err = _Terminal()
    monkeypatch.setattr(sys, "stderr", err)
    assert list(prog.progress(range(3), desc="work")) == [0, 1, 2]
    bars = prog.PhaseBars()
    bars("profile", 1, 2)
    bars("repair", 0, 1)
    bars.close()
    assert "work" in err.getvalue() and "3/3" in err.getvalue() and "profile" in err.getvalue()
    assert capsys.readouterr().out == ""
    monkeypatch.setenv(prog.ENV_VAR, "1")
    err.truncate(0)
    err.seek(0)
    assert list(prog.progress(range(3), desc="work")) == [0, 1, 2]
    assert err.getvalue() == ""


def _store(root: Path) -> RolloutStore:
    s = RolloutStore(root)
    s.assign_splits("g", "6", dev=2, heldout=1)
    for seed, kind in ((2, "success"), (3, "drop")):
        tr = make_trace(kind, seed)
        s.add(EpisodeKey("g", "6", seed, "", "profile"), Outcome(kind == "success", int(tr.frame_step[-1]), "", [], tr,
                                                                 "", 1.0))
    return s


def _run_with_terminal_stderr(args: list[str], env: dict[str, str]) -> tuple[int, str, str]:
    """Run the `zetta` CLI with stdout on a pipe and stderr on a pseudo-terminal."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # a terminal's size: tqdm draws to it
    proc = subprocess.Popen([sys.executable, "-m", "services.ops.cli", *args], cwd=ROOT, stdout=subprocess.PIPE,
                            stderr=slave, stdin=subprocess.DEVNULL, env=env)
    os.close(slave)
    err = b""
    while True:
        ready, _, _ = select.select([master], [], [], 120)
        if not ready:
            proc.kill()
            raise AssertionError("the command wrote nothing to stderr for 120 s")
        try:
            chunk = os.read(master, 4096)
        except OSError:  # the child closed its side
            break
        if not chunk:
            break
        err += chunk
    out = proc.stdout.read() if proc.stdout is not None else b""
    rc = proc.wait(timeout=120)
    os.close(master)
    return rc, out.decode(), err.decode(errors="replace")


@pytest.mark.timeout(300)
def test_cli_stdout_stays_parseable_with_a_bar_on_stderr(tmp_path: Path) -> None:
    _store(tmp_path / "store")
    env = {k: v for k, v in os.environ.items() if k != prog.ENV_VAR}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "clients" / "python"), env.get("PYTHONPATH", "")])
    line = re.compile(r"exported (\d+) episodes, (\d+) frames to (.+)")
    for extra, bar in (([], True), (["--no-progress"], False)):
        out_dir = tmp_path / f"ds{len(extra)}"
        rc, out, err = _run_with_terminal_stderr(
            ["evolve", "export", "--store", str(tmp_path / "store"), "--out", str(out_dir), *extra], env)
        assert rc == 0, err
        m = line.fullmatch(out.strip())
        assert m is not None, f"stdout is not the one summary line: {out!r}"
        assert (m.group(1), m.group(3)) == ("2", str(out_dir))
        assert ("export: 100%" in err) is bar, err
