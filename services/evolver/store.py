"""The rollout store: append-only traces and videos on disk, an sqlite index, the dev/gate/test splits.

It is the evolution's checkpoint: every finished rollout is on disk before the loop moves on, so a
stopped ``zetta evolve`` resumes by asking :meth:`RolloutStore.get` for each episode key it needs.
Valid rollouts and infrastructure-invalid attempts live in separate tables and never mix; an
invalid attempt is logged and the same episode key is run again. A seed belongs to exactly one
split per (suite, task): dev (repair), held-out (the gate's admission seeds) or test (the reported
number, read by no decision); no two seeds of a task share an initial state. The only way to move
a seed is :meth:`RolloutStore.move_to_dev` (gate -> dev), which is recorded.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sqlite3
import threading
import time
from collections.abc import Collection, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from services.evolver.trace import Trace, in_control_at_success

DEV = "dev"
#: The gate's admission seeds (the paper's held-out set of Phase III).
HELDOUT = "heldout"
#: The reported number's seeds: measured once, after every decision; nothing reads them before.
TEST = "test"
SPLITS = (DEV, HELDOUT, TEST)
#: Purposes of the rollouts a test seed may have: the final measurement, with its do-nothing control.
TEST_PURPOSES = frozenset({"test", "control-test"})
#: LIBERO ships 50 fixed initial states per task; an episode seed s uses init state s % 50.
INIT_STATES = 50

_SCHEMA = """
CREATE TABLE IF NOT EXISTS rollouts (
  key TEXT PRIMARY KEY, suite TEXT NOT NULL, task TEXT NOT NULL, seed INTEGER NOT NULL,
  init_state INTEGER NOT NULL, split TEXT NOT NULL, harness TEXT NOT NULL, purpose TEXT NOT NULL,
  round INTEGER NOT NULL, success INTEGER NOT NULL, steps INTEGER NOT NULL,
  first_missing TEXT NOT NULL, milestones_reached TEXT NOT NULL, policy_steps INTEGER NOT NULL,
  recovery_steps INTEGER NOT NULL, interventions INTEGER NOT NULL, trace_path TEXT NOT NULL,
  video_path TEXT NOT NULL, wall_s REAL NOT NULL, created_at REAL NOT NULL,
  in_control_at_success INTEGER NOT NULL DEFAULT 0);
CREATE INDEX IF NOT EXISTS rollouts_q ON rollouts (suite, task, harness, split, success);
CREATE TABLE IF NOT EXISTS invalid (
  id INTEGER PRIMARY KEY AUTOINCREMENT, key TEXT NOT NULL, reason TEXT NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS seeds (
  suite TEXT NOT NULL, task TEXT NOT NULL, seed INTEGER NOT NULL, split TEXT NOT NULL,
  PRIMARY KEY (suite, task, seed));
CREATE TABLE IF NOT EXISTS split_moves (
  id INTEGER PRIMARY KEY AUTOINCREMENT, suite TEXT NOT NULL, task TEXT NOT NULL, seed INTEGER NOT NULL,
  from_split TEXT NOT NULL, to_split TEXT NOT NULL, reason TEXT NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS rejected (
  fingerprint TEXT PRIMARY KEY, cluster TEXT NOT NULL, reason TEXT NOT NULL, created_at REAL NOT NULL);
CREATE TABLE IF NOT EXISTS events (
  id INTEGER PRIMARY KEY AUTOINCREMENT, kind TEXT NOT NULL, ident TEXT NOT NULL, body TEXT NOT NULL,
  created_at REAL NOT NULL);
"""

#: The columns an insert names, so it never depends on the order a migration left them in.
_ROLLOUT_COLUMNS = ("key, suite, task, seed, init_state, split, harness, purpose, round, success, steps, "
                    "first_missing, milestones_reached, policy_steps, recovery_steps, interventions, trace_path, "
                    "video_path, wall_s, created_at, in_control_at_success")


class StoreError(RuntimeError):
    """A write the store refuses: a duplicate key, a seed in the wrong split, an unknown split."""


@dataclass(frozen=True)
class EpisodeKey:
    """What identifies one rollout: the same key always means the same episode and harness.

    ``purpose`` separates rollouts of the same episode made for different reasons (profiling,
    regression of a candidate, held-out evaluation), so none overwrites another."""

    suite: str
    task: str
    seed: int
    harness: str
    purpose: str

    @property
    def init_state(self) -> int:
        """LIBERO's initial-state index of this episode."""
        return self.seed % INIT_STATES

    def __str__(self) -> str:
        return f"{self.suite}/{self.task}/{self.seed}/{self.harness or 'bare'}/{self.purpose}"


@dataclass(frozen=True)
class Rollout:
    """One row of the index."""

    key: str
    suite: str
    task: str
    seed: int
    init_state: int
    split: str
    harness: str
    purpose: str
    round: int
    success: bool
    steps: int
    first_missing: str
    milestones_reached: list[str]
    policy_steps: int
    recovery_steps: int
    interventions: int
    trace_path: str
    video_path: str
    wall_s: float
    #: An intervention was still in control at the success step (trace.in_control_at_success).
    in_control_at_success: bool = False

    @property
    def credited(self) -> bool:
        """A success the evolver's decisions count: the policy, not an intervention that never
        handed back, was in control when the task was done (the re-entry contract)."""
        return self.success and not self.in_control_at_success


@dataclass(frozen=True)
class Outcome:
    """What a finished valid episode produced, before the store files it."""

    success: bool
    steps: int
    first_missing: str
    milestones_reached: Sequence[str]
    trace: Trace
    video_path: str
    wall_s: float


class RolloutStore:
    """Append-only rollouts under ``root`` (traces/, videos/, index.sqlite)."""

    def __init__(self, root: str | os.PathLike[str]) -> None:
        self.root = Path(root)
        (self.root / "traces").mkdir(parents=True, exist_ok=True)
        (self.root / "videos").mkdir(parents=True, exist_ok=True)
        self._lock = threading.Lock()
        self._db = sqlite3.connect(self.root / "index.sqlite", check_same_thread=False, isolation_level=None)
        self._db.execute("PRAGMA journal_mode=WAL")
        self._db.executescript(_SCHEMA)
        cols = {r[1] for r in self._db.execute("PRAGMA table_info(events)")}
        if "ident" not in cols:  # stores written before events had idents
            self._db.execute("ALTER TABLE events ADD COLUMN ident TEXT NOT NULL DEFAULT ''")
        if "in_control_at_success" not in {r[1] for r in self._db.execute("PRAGMA table_info(rollouts)")}:
            self._add_in_control_column()

    def _add_in_control_column(self) -> None:
        """Stores written before the column: add it, filled from the traces of successes that had
        interventions (a trace that is not there, as in a published index, leaves 0)."""
        self._db.execute("ALTER TABLE rollouts ADD COLUMN in_control_at_success INTEGER NOT NULL DEFAULT 0")
        rows = self._db.execute("SELECT key, trace_path FROM rollouts WHERE success = 1 AND interventions > 0")
        for key, trace_path in rows.fetchall():
            path = self.root / trace_path
            if path.exists() and in_control_at_success(Trace.from_bytes(path.read_bytes()).interventions):
                self._db.execute("UPDATE rollouts SET in_control_at_success = 1 WHERE key = ?", (key,))

    def close(self) -> None:
        """Close the index."""
        self._db.close()

    # ---- splits ----------------------------------------------------------------------------

    def assign_splits(self, suite: str, task: str, dev: int, heldout: int, test: int = 0,
                      trained: Collection[int] = ()) -> tuple[list[int], list[int]]:
        """Fix the splits of a task once: test seeds first, then held-out (gate) seeds, then dev
        seeds, each on an initial state no other seed of the task uses. Test seeds take initial
        states outside ``trained`` (the layouts the policy's demonstrations came from) while there
        are any, so the reported number starts from layouts the policy never saw. Idempotent: a task
        that has splits keeps them and only grows to the asked sizes with fresh initial states.
        Budgets that cannot be disjoint (more seeds than LIBERO's 50 initial states) are refused.
        Returns (dev, held-out); :meth:`seeds` gives the test seeds."""
        want = {TEST: test, HELDOUT: heldout, DEV: dev}
        have = {split: self.seeds(suite, task, split) for split in SPLITS}
        total = sum(max(want[k], len(have[k])) for k in SPLITS)
        if total > INIT_STATES:
            raise StoreError(
                f"{suite}/{task}: dev {max(dev, len(have[DEV]))} + gate {max(heldout, len(have[HELDOUT]))} + test "
                f"{max(test, len(have[TEST]))} = {total} seeds, but a task has {INIT_STATES} initial states and the "
                "splits must not share one: lower --dev-seeds, --heldout-seeds or --test-seeds")
        for split in (TEST, HELDOUT, DEV):
            while len(have[split]) < want[split]:
                seed = (self._fresh_seed(suite, task, avoid=trained) if split == TEST else None) \
                    or self._fresh_seed(suite, task)
                assert seed is not None  # the budget check above leaves an initial state for every seed
                self._insert_seed(suite, task, seed, split)
                have[split].append(seed)
        return sorted(have[DEV]), sorted(have[HELDOUT])

    def assign_seeds(self, suite: str, task: str, split: str, seeds: Sequence[int]) -> list[int]:
        """Fix these exact seeds in ``split`` (idempotent); refuses a seed, or an initial state, that
        another split of the task already holds. Returns the split's seeds."""
        have = self.seeds(suite, task, split)
        taken = {s % INIT_STATES: s for other in SPLITS if other != split for s in self.seeds(suite, task, other)}
        for seed in seeds:
            if seed in have:
                continue
            if seed % INIT_STATES in taken:
                raise StoreError(f"{suite}/{task}: seed {seed} shares initial state {seed % INIT_STATES} with seed "
                                 f"{taken[seed % INIT_STATES]} of another split")
            self._insert_seed(suite, task, seed, split)
            have.append(seed)
        return sorted(have)

    def _fresh_seed(self, suite: str, task: str, avoid: Collection[int] = ()) -> int | None:
        """The smallest seed whose initial state no seed of the task uses and ``avoid`` does not
        name (None when none is left)."""
        states = {s % INIT_STATES for s in self._all_seeds(suite, task)} | {a % INIT_STATES for a in avoid}
        return next((s for s in range(1, INIT_STATES + 1) if s % INIT_STATES not in states), None)

    def _insert_seed(self, suite: str, task: str, seed: int, split: str) -> None:
        if split not in SPLITS:
            raise StoreError(f"unknown split {split!r}; splits: {SPLITS}")
        with self._lock:
            self._db.execute("INSERT INTO seeds VALUES (?,?,?,?)", (suite, task, seed, split))

    def _all_seeds(self, suite: str, task: str) -> list[int]:
        rows = self._db.execute("SELECT seed FROM seeds WHERE suite=? AND task=?", (suite, task)).fetchall()
        return [r[0] for r in rows]

    def seeds(self, suite: str, task: str, split: str) -> list[int]:
        """Seeds of one split, ascending."""
        rows = self._db.execute("SELECT seed FROM seeds WHERE suite=? AND task=? AND split=? ORDER BY seed",
                                (suite, task, split)).fetchall()
        return [r[0] for r in rows]

    def split_of(self, suite: str, task: str, seed: int) -> str | None:
        """The split a seed belongs to, or None for a seed never assigned."""
        row = self._db.execute("SELECT split FROM seeds WHERE suite=? AND task=? AND seed=?",
                               (suite, task, seed)).fetchone()
        return row[0] if row else None

    def move_to_dev(self, suite: str, task: str, seed: int, reason: str) -> int | None:
        """Reclassify a held-out seed that triggered a change as dev, record why, and draw one fresh
        held-out seed on an initial state no seed of the task uses; returns it (None when every
        initial state is taken: the gate split shrinks by one, and the move records that)."""
        if self.split_of(suite, task, seed) != HELDOUT:
            raise StoreError(f"{suite}/{task} seed {seed} is not a held-out seed")
        fresh = self._fresh_seed(suite, task)
        if fresh is None:
            reason += "; no initial state left for a fresh gate seed"
        with self._lock:
            self._db.execute("UPDATE seeds SET split=? WHERE suite=? AND task=? AND seed=?", (DEV, suite, task, seed))
            self._db.execute("INSERT INTO split_moves (suite, task, seed, from_split, to_split, reason, created_at) "
                             "VALUES (?,?,?,?,?,?,?)", (suite, task, seed, HELDOUT, DEV, reason, time.time()))
        if fresh is not None:
            self._insert_seed(suite, task, fresh, HELDOUT)
        return fresh

    def split_moves(self) -> list[dict[str, Any]]:
        """Every recorded split move, oldest first."""
        cur = self._db.execute("SELECT suite, task, seed, from_split, to_split, reason, created_at FROM split_moves "
                               "ORDER BY id")
        cols = [c[0] for c in cur.description]
        return [dict(zip(cols, r)) for r in cur.fetchall()]

    def split_manifest(self, suite: str, task: str) -> dict[str, Any]:
        """The split as a manifest records it: seeds per split and the moves that changed it."""
        return {"dev": self.seeds(suite, task, DEV), "heldout": self.seeds(suite, task, HELDOUT),
                "test": self.seeds(suite, task, TEST),
                "moves": [m for m in self.split_moves() if m["suite"] == suite and m["task"] == task]}

    # ---- rollouts ----------------------------------------------------------------------------

    def get(self, key: EpisodeKey) -> Rollout | None:
        """The valid rollout filed under ``key``, if any (what resuming checks)."""
        rows = self._query("key = ?", (str(key),))
        return rows[0] if rows else None

    def add(self, key: EpisodeKey, outcome: Outcome, round_: int = 0) -> Rollout:
        """File a valid rollout. Refuses a duplicate key and a seed outside the task's splits."""
        split = self.split_of(key.suite, key.task, key.seed)
        if split is None:
            raise StoreError(f"{key}: seed {key.seed} has no split for {key.suite}/{key.task}; assign splits first")
        if (split == TEST) != (key.purpose in TEST_PURPOSES):
            raise StoreError(f"{key}: seed {key.seed} is a {split} seed; test seeds take only the final measurement "
                             f"({', '.join(sorted(TEST_PURPOSES))}) and that measurement only test seeds")
        if self.get(key) is not None:
            raise StoreError(f"{key}: a rollout is already filed under this key (the store is append-only)")
        digest = hashlib.sha256(str(key).encode()).hexdigest()[:24]
        trace_path = self.root / "traces" / f"{digest}.npz"
        _write_once(trace_path, outcome.trace.to_bytes())
        video = ""
        if outcome.video_path and os.path.exists(outcome.video_path):
            dest = self.root / "videos" / f"{digest}.mp4"
            if not dest.exists():
                shutil.copyfile(outcome.video_path, dest)
            video = str(dest.relative_to(self.root))
        row = (str(key), key.suite, key.task, key.seed, key.init_state, split, key.harness, key.purpose, round_,
               int(outcome.success), outcome.steps, outcome.first_missing, json.dumps(list(outcome.milestones_reached)),
               outcome.steps - outcome.trace.recovery_steps, outcome.trace.recovery_steps,
               len(outcome.trace.interventions), str(trace_path.relative_to(self.root)), video, outcome.wall_s,
               time.time(), int(outcome.success and in_control_at_success(outcome.trace.interventions)))
        with self._lock:
            try:
                self._db.execute(f"INSERT INTO rollouts ({_ROLLOUT_COLUMNS}) VALUES ({','.join('?' * len(row))})", row)
            except sqlite3.IntegrityError:
                raise StoreError(f"{key}: a rollout is already filed under this key (the store is append-only)") from None
        rollout = self.get(key)
        assert rollout is not None
        return rollout

    def log_invalid(self, key: EpisodeKey, reason: str) -> None:
        """Record an infrastructure-invalid attempt (lost worker, simulator crash); it is never a rollout."""
        with self._lock:
            self._db.execute("INSERT INTO invalid (key, reason, created_at) VALUES (?,?,?)",
                             (str(key), reason, time.time()))

    def invalid_attempts(self, key: EpisodeKey | None = None) -> list[tuple[str, str]]:
        """(key, reason) of the logged invalid attempts, of one key or all."""
        if key is None:
            return [tuple(r) for r in self._db.execute("SELECT key, reason FROM invalid ORDER BY id")]
        return [tuple(r) for r in self._db.execute("SELECT key, reason FROM invalid WHERE key=? ORDER BY id",
                                                    (str(key),))]

    def query(self, suite: str | None = None, task: str | None = None, harness: str | None = None,
              seed: int | None = None, success: bool | None = None, split: str | None = None,
              purpose: str | None = None) -> list[Rollout]:
        """Valid rollouts matching every given field."""
        clauses, args = [], []
        for col, val in (("suite", suite), ("task", task), ("harness", harness), ("seed", seed), ("split", split),
                         ("purpose", purpose)):
            if val is not None:
                clauses.append(f"{col} = ?")
                args.append(val)
        if success is not None:
            clauses.append("success = ?")
            args.append(int(success))
        return self._query(" AND ".join(clauses) or "1", tuple(args))

    def _query(self, where: str, args: tuple[Any, ...]) -> list[Rollout]:
        cur = self._db.execute(f"SELECT * FROM rollouts WHERE {where} ORDER BY created_at, key", args)
        cols = [c[0] for c in cur.description]
        out = []
        for r in cur.fetchall():
            d = dict(zip(cols, r))
            d.pop("created_at")
            d["success"] = bool(d["success"])
            d["in_control_at_success"] = bool(d["in_control_at_success"])
            d["milestones_reached"] = json.loads(d["milestones_reached"])
            out.append(Rollout(**d))
        return out

    def trace(self, rollout: Rollout) -> Trace:
        """Load a rollout's trace."""
        return Trace.from_bytes((self.root / rollout.trace_path).read_bytes())

    # ---- evolution bookkeeping ----------------------------------------------------------------

    def reject(self, fingerprint: str, cluster: str, reason: str) -> None:
        """Put a candidate in the buffer of rejected candidates; it is never evaluated again."""
        with self._lock:
            self._db.execute("INSERT OR IGNORE INTO rejected VALUES (?,?,?,?)", (fingerprint, cluster, reason, time.time()))

    def is_rejected(self, fingerprint: str) -> bool:
        """Whether a candidate with this fingerprint was rejected before."""
        return self._db.execute("SELECT 1 FROM rejected WHERE fingerprint=?", (fingerprint,)).fetchone() is not None

    def rejected(self) -> list[tuple[str, str, str]]:
        """(fingerprint, cluster, reason) of every rejected candidate."""
        return [tuple(r) for r in self._db.execute("SELECT fingerprint, cluster, reason FROM rejected")]

    def record(self, kind: str, body: dict[str, Any], ident: str = "") -> None:
        """Append an evolution event (round result, admitted version, cluster version curve).

        Events with an ``ident`` describe one thing (a round's profile of a task): when a resumed
        round records it again, readers see only the latest; the earlier row stays on disk."""
        with self._lock:
            self._db.execute("INSERT INTO events (kind, ident, body, created_at) VALUES (?,?,?,?)",
                             (kind, ident, json.dumps(body, sort_keys=True), time.time()))

    def events(self, kind: str | None = None) -> list[dict[str, Any]]:
        """Recorded events, oldest first, optionally of one kind; the latest per ident."""
        where, args = ("", ()) if kind is None else ("WHERE kind=?", (kind,))
        rows = self._db.execute(f"SELECT id, kind, ident, body FROM events {where} ORDER BY id", args).fetchall()
        latest = {(k, i): n for n, k, i, _ in rows if i}
        return [dict(json.loads(b), kind=k) for n, k, i, b in rows if not i or latest[(k, i)] == n]


def _write_once(path: Path, data: bytes) -> None:
    """Write a new file atomically; an existing file is never replaced (append-only)."""
    tmp = path.with_suffix(f".tmp{os.getpid()}.{threading.get_ident()}")
    tmp.write_bytes(data)
    try:
        os.link(tmp, path)
    except FileExistsError:
        raise StoreError(f"{path} exists: the store never overwrites a trace") from None
    finally:
        tmp.unlink()
