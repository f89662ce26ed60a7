"""Session registry, leases and worker heartbeats, all in Redis.

Everything the gateway knows lives here, so a gateway can restart (or several can run side by
side) without losing a session. Each state change that touches more than one key is one Lua
script, so slot accounting stays exact under concurrent gateways: a slot is never handed out
twice, and a LOST session never frees a slot on a dead worker.

Keys (``P`` is the prefix):
  P:workers                  set of worker ids
  P:worker:<id>              hash: address, families, slots, free, alive, last_hb_ms, busy_until_ms
                             (end of the busy lease the last heartbeat asked for; 0: none)
  P:hb:<id>                  string with a TTL; its existence is the heartbeat. The TTL is the
                             heartbeat timeout, or the busy lease when that is longer
  P:worker:<id>:sessions     set of live session ids on the worker
  P:session:<sid>            hash: family, config, worker, owner, state, lease_ms, expires_ms, reason,
                             action_dtype, action_shape, action_bounds ("low,high", either
                             part empty when unbounded), schema (serialized specs)
  P:leases                   sorted set: live session id -> lease expiry (ms)
  P:epoch                    random token written once per Redis data set; a gateway that sees it
                             change or vanish knows Redis lost its state (restart without persistence)
Closed and LOST session hashes stay for ``tombstone_seconds`` so that late calls get a clear
status instead of "unknown session".
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Sequence
from dataclasses import dataclass

import redis.asyncio as aioredis

CREATE, RUNNING, TERMINATED, LOST = "CREATE", "RUNNING", "TERMINATED", "LOST"
LIVE_STATES = (CREATE, RUNNING)

_ALLOCATE = """
-- KEYS: none (keys are derived from the prefix; one Redis, not a cluster)
-- ARGV: prefix, family, count, now_ms, lease_ms, config_json, hold_ms, owner, sid1..sidN
-- (hold_ms: extra time for building the environments; the lease proper starts at activation)
local p = ARGV[1]
local family = ARGV[2]
local count = tonumber(ARGV[3])
local now = tonumber(ARGV[4])
local lease = tonumber(ARGV[5])
local config = ARGV[6]
local hold = tonumber(ARGV[7])
local owner = ARGV[8]
local workers = redis.call('SMEMBERS', p .. ':workers')
local free = {}
local ids = {}
local total = 0
local hosting = 0
for _, w in ipairs(workers) do
  local wk = p .. ':worker:' .. w
  local alive, fams, f = unpack(redis.call('HMGET', wk, 'alive', 'families', 'free'))
  if alive == '1' and redis.call('EXISTS', p .. ':hb:' .. w) == 1 then
    local ok = false
    for fam in string.gmatch(fams or '', '[^,]+') do
      if fam == family then ok = true end
    end
    if ok then
      hosting = hosting + 1
      local n = tonumber(f) or 0
      if n > 0 then
        table.insert(ids, w)
        free[w] = n
        total = total + n
      end
    end
  end
end
if hosting == 0 then
  return {'no_worker', 0}
end
if total < count then
  return {'full', total}
end
local out = {'ok'}
for i = 1, count do
  local best, bestn = nil, 0
  for _, w in ipairs(ids) do
    if free[w] > bestn then best, bestn = w, free[w] end
  end
  free[best] = free[best] - 1
  redis.call('HINCRBY', p .. ':worker:' .. best, 'free', -1)
  local sid = ARGV[8 + i]
  redis.call('HSET', p .. ':session:' .. sid, 'family', family, 'config', config, 'worker', best,
    'state', 'CREATE', 'lease_ms', lease, 'expires_ms', now + lease + hold, 'created_ms', now, 'reason', '',
    'owner', owner)
  redis.call('SADD', p .. ':worker:' .. best .. ':sessions', sid)
  redis.call('ZADD', p .. ':leases', now + lease + hold, sid)
  table.insert(out, sid)
  table.insert(out, best)
end
return out
"""

_RELEASE = """
-- ARGV: prefix, sid, new_state, reason, tombstone_seconds
local p = ARGV[1]
local sk = p .. ':session:' .. ARGV[2]
local state, worker = unpack(redis.call('HMGET', sk, 'state', 'worker'))
if state ~= 'CREATE' and state ~= 'RUNNING' then
  return {0, state or ''}
end
redis.call('HSET', sk, 'state', ARGV[3], 'reason', ARGV[4])
redis.call('EXPIRE', sk, tonumber(ARGV[5]))
redis.call('ZREM', p .. ':leases', ARGV[2])
if redis.call('SREM', p .. ':worker:' .. worker .. ':sessions', ARGV[2]) == 1 then
  if redis.call('HGET', p .. ':worker:' .. worker, 'alive') == '1' then
    redis.call('HINCRBY', p .. ':worker:' .. worker, 'free', 1)
  end
end
return {1, worker}
"""

_MARK_DEAD = """
-- ARGV: prefix, worker, reason, tombstone_seconds
local p = ARGV[1]
local w = ARGV[2]
local wk = p .. ':worker:' .. w
if redis.call('HGET', wk, 'alive') ~= '1' or redis.call('EXISTS', p .. ':hb:' .. w) == 1 then
  return {0}
end
local sids = redis.call('SMEMBERS', wk .. ':sessions')
local out = {1}
for _, sid in ipairs(sids) do
  table.insert(out, sid)
  local sk = p .. ':session:' .. sid
  redis.call('HSET', sk, 'state', 'LOST', 'reason', ARGV[3])
  redis.call('EXPIRE', sk, tonumber(ARGV[4]))
  redis.call('ZREM', p .. ':leases', sid)
end
redis.call('DEL', wk .. ':sessions')
redis.call('HSET', wk, 'alive', '0', 'free', '0')
return out
"""

_REGISTER = """
-- ARGV: prefix, worker, address, families, slots, hb_ttl_ms, now_ms, reason, tombstone, forgotten_reason,
--       held1..heldN
-- A held session the registry has no record of at all was forgotten by Redis (a restart without
-- persistence): it is recorded LOST with forgotten_reason instead of vanishing as "never created".
local p = ARGV[1]
local w = ARGV[2]
local wk = p .. ':worker:' .. w
local slots = tonumber(ARGV[5])
local held = {}
for i = 11, #ARGV do
  held[ARGV[i]] = true
  local sk = p .. ':session:' .. ARGV[i]
  if redis.call('EXISTS', sk) == 0 then
    redis.call('HSET', sk, 'state', 'LOST', 'reason', ARGV[10], 'worker', w)
    redis.call('EXPIRE', sk, tonumber(ARGV[9]))
  end
end
local kept = {}
local lost = {}
if redis.call('HGET', wk, 'alive') == '1' then
  for _, sid in ipairs(redis.call('SMEMBERS', wk .. ':sessions')) do
    if held[sid] then
      table.insert(kept, sid)
    else
      table.insert(lost, sid)
    end
  end
else
  for _, sid in ipairs(redis.call('SMEMBERS', wk .. ':sessions')) do table.insert(lost, sid) end
end
for _, sid in ipairs(lost) do
  local sk = p .. ':session:' .. sid
  redis.call('HSET', sk, 'state', 'LOST', 'reason', ARGV[8])
  redis.call('EXPIRE', sk, tonumber(ARGV[9]))
  redis.call('ZREM', p .. ':leases', sid)
  redis.call('SREM', wk .. ':sessions', sid)
end
redis.call('SADD', p .. ':workers', w)
redis.call('HSET', wk, 'address', ARGV[3], 'families', ARGV[4], 'slots', slots,
  'free', slots - #kept, 'alive', '1', 'last_hb_ms', ARGV[7], 'busy_until_ms', 0)
redis.call('SET', p .. ':hb:' .. w, ARGV[7], 'PX', tonumber(ARGV[6]))
return kept
"""

_HEARTBEAT = """
-- ARGV: prefix, worker, hb_ttl_ms, now_ms, busy_ms
-- The key lives until the later of now + timeout and the end of the busy lease (now + busy_ms);
-- a heartbeat without a lease (busy_ms 0) sets it back to the timeout, ending an earlier lease.
local wk = ARGV[1] .. ':worker:' .. ARGV[2]
if redis.call('HGET', wk, 'alive') ~= '1' then return 0 end
local now = tonumber(ARGV[4])
local busy = tonumber(ARGV[5])
redis.call('SET', ARGV[1] .. ':hb:' .. ARGV[2], ARGV[4], 'PX', math.max(tonumber(ARGV[3]), busy))
local busy_until = 0
if busy > 0 then busy_until = now + busy end
redis.call('HSET', wk, 'last_hb_ms', ARGV[4], 'busy_until_ms', busy_until)
return 1
"""

_RENEW = """
-- ARGV: prefix, sid, now_ms, lease_ms (0 = the session's own)
local sk = ARGV[1] .. ':session:' .. ARGV[2]
local state, own = unpack(redis.call('HMGET', sk, 'state', 'lease_ms'))
if state ~= 'CREATE' and state ~= 'RUNNING' then return {0, state or ''} end
local lease = tonumber(ARGV[4])
if lease == 0 then lease = tonumber(own) else redis.call('HSET', sk, 'lease_ms', lease) end
local expires = tonumber(ARGV[3]) + lease
redis.call('HSET', sk, 'expires_ms', expires)
redis.call('ZADD', ARGV[1] .. ':leases', expires, ARGV[2])
return {1, tostring(expires)}
"""

_ACTIVATE = """
-- ARGV: prefix, action_dtype, action_shape, schema, now_ms, action_bounds, sid1..sidN
-- The lease starts now: a build longer than the lease must not leave a born-expired session.
local n = 0
for i = 7, #ARGV do
  local sk = ARGV[1] .. ':session:' .. ARGV[i]
  if redis.call('HGET', sk, 'state') == 'CREATE' then
    local expires = tonumber(ARGV[5]) + tonumber(redis.call('HGET', sk, 'lease_ms'))
    redis.call('HSET', sk, 'state', 'RUNNING', 'action_dtype', ARGV[2], 'action_shape', ARGV[3],
      'schema', ARGV[4], 'expires_ms', expires, 'action_bounds', ARGV[6])
    redis.call('ZADD', ARGV[1] .. ':leases', expires, ARGV[i])
    n = n + 1
  end
end
return n
"""

_LOOKUP = """
-- ARGV: prefix, number of fields K, field1..fieldK, sid1..sidN
-- One flat reply of N x K values (nil where a session or field is missing): a single command, so
-- a batch of 1,024 ids costs the gateway one reply to parse instead of 1,024 pipelined ones.
local k = tonumber(ARGV[2])
local fields = {}
for j = 1, k do fields[j] = ARGV[2 + j] end
local out = {}
local n = 0
for i = 3 + k, #ARGV do
  local row = redis.call('HMGET', ARGV[1] .. ':session:' .. ARGV[i], unpack(fields))
  for j = 1, k do
    n = n + 1
    out[n] = row[j]
  end
end
return out
"""


def now_ms() -> int:
    """Wall-clock milliseconds; leases are absolute times shared by every gateway."""
    return int(time.time() * 1000)


class PoolFullError(Exception):
    """No worker has enough free slots of the family."""

    def __init__(self, free: int) -> None:
        super().__init__(f"{free} slots free")
        self.free = free


class NoWorkerError(Exception):
    """No live worker hosts the family."""


@dataclass(frozen=True)
class SessionRecord:
    """What a call needs to know about a session to route and validate it."""

    session_id: str
    state: str
    worker_id: str
    family: str
    reason: str
    action_dtype: str
    action_shape: tuple[int, ...]
    expires_ms: int
    #: Lowest and highest value of every action element (from the action spec); None: unbounded.
    action_low: float | None = None
    action_high: float | None = None
    #: Identity that created the session ("" when auth was off).
    owner: str = ""


@dataclass(frozen=True)
class WorkerRecord:
    """A registered env worker."""

    worker_id: str
    address: str
    families: tuple[str, ...]
    slots: int
    free: int
    alive: bool
    last_hb_ms: int
    #: End of the busy lease the last heartbeat asked for (wall-clock ms); 0 when it asked for none.
    busy_until_ms: int = 0


class Registry:
    """Typed access to the registry keys; every multi-key change is one Lua script."""

    _FIELDS = ("state", "worker", "family", "reason", "action_dtype", "action_shape", "expires_ms", "action_bounds", "owner")

    def __init__(self, client: aioredis.Redis, prefix: str, tombstone_seconds: int) -> None:
        self.r = client
        self.p = prefix
        self.tombstone = tombstone_seconds
        self._allocate = client.register_script(_ALLOCATE)
        self._release = client.register_script(_RELEASE)
        self._mark_dead = client.register_script(_MARK_DEAD)
        self._register = client.register_script(_REGISTER)
        self._heartbeat = client.register_script(_HEARTBEAT)
        self._renew = client.register_script(_RENEW)
        self._activate = client.register_script(_ACTIVATE)
        self._lookup = client.register_script(_LOOKUP)
        self._epoch: str | None = None

    async def start_epoch(self) -> None:
        """Remember the data set this gateway starts on (creating its epoch token if new)."""
        key = f"{self.p}:epoch"
        await self.r.set(key, uuid.uuid4().hex, nx=True)
        self._epoch = _s(await self.r.get(key))

    async def lost_state(self) -> str:
        """Why sessions are missing when Redis lost its data since this gateway started; "" when it did not."""
        if self._epoch is None:
            return ""
        key = f"{self.p}:epoch"
        current = await self.r.get(key)
        if current is None:
            await self.r.set(key, uuid.uuid4().hex, nx=True)
        if current is not None and _s(current) == self._epoch:
            return ""
        return ("the session registry (Redis) lost its state after this gateway started (Redis restarted "
                "without persistence, or its data was flushed)")

    async def allocate(
        self, family: str, count: int, lease_ms: int, config: dict, hold_ms: int = 0, owner: str = ""
    ) -> list[tuple[str, str]]:
        """Reserve ``count`` slots, all or none; returns (session id, worker id) pairs.

        Until :meth:`activate`, a session expires after ``lease_ms + hold_ms`` (time to build it).
        """
        sids = [uuid.uuid4().hex for _ in range(count)]
        res = await self._allocate(
            args=[self.p, family, count, now_ms(), lease_ms, json.dumps(config, sort_keys=True), hold_ms, owner, *sids]
        )
        status = _s(res[0])
        if status == "no_worker":
            raise NoWorkerError(family)
        if status == "full":
            raise PoolFullError(int(res[1]))
        return [(_s(res[i]), _s(res[i + 1])) for i in range(1, len(res), 2)]

    async def activate(self, sids: Sequence[str], action_dtype: str, action_shape: Sequence[int], schema: bytes,
                       bounds: tuple[float | None, float | None] = (None, None)) -> int:
        """CREATE -> RUNNING, storing what requests are validated against; the lease starts now."""
        text = ",".join("" if b is None else repr(float(b)) for b in bounds)
        return int(
            await self._activate(
                args=[self.p, action_dtype, ",".join(str(d) for d in action_shape), schema, now_ms(), text, *sids]
            )
        )

    async def release(self, sid: str, state: str, reason: str) -> tuple[bool, str]:
        """Leave the live states; returns (changed, worker id or the state it already had)."""
        changed, detail = await self._release(args=[self.p, sid, state, reason, self.tombstone])
        return bool(int(changed)), _s(detail)

    async def renew(self, sid: str, lease_ms: int) -> tuple[bool, str]:
        """Push the lease out; returns (renewed, new expiry in ms or the session's state)."""
        ok, detail = await self._renew(args=[self.p, sid, now_ms(), lease_ms])
        return bool(int(ok)), _s(detail)

    async def lookup(self, sids: Sequence[str]) -> list[SessionRecord | None]:
        """One round trip (one command) for a whole batch of sessions; None for unknown ids."""
        if not sids:
            return []
        k = len(self._FIELDS)
        flat = await self._lookup(args=[self.p, k, *self._FIELDS, *sids])
        out: list[SessionRecord | None] = []
        for i, sid in enumerate(sids):
            row = flat[i * k:(i + 1) * k]
            if row[0] is None:
                out.append(None)
                continue
            state, worker, family, reason, adtype, ashape, expires, bounds, owner = (
                _s(v) if v is not None else "" for v in row)
            low, _, high = bounds.partition(",")
            out.append(
                SessionRecord(
                    session_id=sid,
                    state=state,
                    worker_id=worker,
                    family=family,
                    reason=reason,
                    action_dtype=adtype,
                    action_shape=tuple(int(d) for d in ashape.split(",") if d),
                    expires_ms=int(expires or 0),
                    action_low=float(low) if low else None,
                    action_high=float(high) if high else None,
                    owner=owner,
                )
            )
        return out

    async def session_hashes(self, sids: Sequence[str]) -> list[dict[str, bytes]]:
        """Every stored field of each session (for listings), in one round trip."""
        pipe = self.r.pipeline(transaction=False)
        for sid in sids:
            pipe.hgetall(f"{self.p}:session:{sid}")
        rows = await pipe.execute()
        return [{_s(k): v for k, v in row.items()} for row in rows]

    async def count_by_family_state(self) -> dict[tuple[str, str], int]:
        """How many sessions of each (family, state) the registry holds, tombstones included."""
        sids = await self.all_session_ids()
        pipe = self.r.pipeline(transaction=False)
        for sid in sids:
            pipe.hmget(f"{self.p}:session:{sid}", "family", "state")
        counts: dict[tuple[str, str], int] = {}
        for family, state in await pipe.execute():
            if family is not None and state is not None:
                key = (_s(family), _s(state))
                counts[key] = counts.get(key, 0) + 1
        return counts

    async def all_session_ids(self) -> list[str]:
        """Ids of every session hash, live or tombstoned."""
        prefix = f"{self.p}:session:"
        return [_s(k)[len(prefix):] async for k in self.r.scan_iter(match=prefix + "*", count=500)]

    async def register_worker(
        self,
        worker_id: str,
        address: str,
        families: Sequence[str],
        slots: int,
        held: Sequence[str],
        hb_ttl_ms: int,
    ) -> list[str]:
        """(Re)register a worker; returns the held sessions it may keep."""
        reason = f"worker {worker_id} re-registered without this session"
        forgotten = (f"the session registry (Redis) lost this session's record (restarted without persistence, "
                     f"or flushed); worker {worker_id} still held it and dropped it")
        kept = await self._register(
            args=[self.p, worker_id, address, ",".join(families), slots, hb_ttl_ms, now_ms(), reason, self.tombstone,
                  forgotten, *held]
        )
        return [_s(k) for k in kept]

    async def heartbeat(self, worker_id: str, hb_ttl_ms: int, busy_ms: int = 0) -> bool:
        """Refresh the heartbeat key; False if the worker was declared dead.

        ``busy_ms`` > 0 is a busy lease: the key lives ``max(hb_ttl_ms, busy_ms)`` from now, so the
        worker is judged alive until the later of its heartbeat timeout and the lease's end. The
        caller bounds it (the servicer caps it at ZETTA_HEARTBEAT_MAX_BUSY_MS).
        """
        if busy_ms < 0:
            raise ValueError(f"busy_ms must be >= 0, got {busy_ms}")
        return bool(int(await self._heartbeat(args=[self.p, worker_id, hb_ttl_ms, now_ms(), busy_ms])))

    async def deregister(self, worker_id: str) -> list[str]:
        """Remove a draining worker now instead of waiting for its heartbeat to expire."""
        await self.r.delete(f"{self.p}:hb:{worker_id}")
        lost = await self.mark_dead(worker_id, f"worker {worker_id} shut down")
        await self.r.srem(f"{self.p}:workers", worker_id)
        return lost or []

    async def mark_dead(self, worker_id: str, reason: str) -> list[str] | None:
        """Declare a worker dead if its heartbeat key is gone.

        Returns the sessions now LOST, or None when the worker was not alive-but-silent (already
        dead, or heartbeating), so that callers count each death once.
        """
        res = await self._mark_dead(args=[self.p, worker_id, reason, self.tombstone])
        if not int(res[0]):
            return None
        return [_s(s) for s in res[1:]]

    async def worker_ids(self) -> list[str]:
        """Every registered worker id."""
        return sorted(_s(w) for w in await self.r.smembers(f"{self.p}:workers"))

    async def workers(self) -> list[WorkerRecord]:
        """Every registered worker with its state."""
        ids = await self.worker_ids()
        pipe = self.r.pipeline(transaction=False)
        for w in ids:
            pipe.hmget(f"{self.p}:worker:{w}", "address", "families", "slots", "free", "alive", "last_hb_ms",
                       "busy_until_ms")
            pipe.exists(f"{self.p}:hb:{w}")
        rows = await pipe.execute()
        out = []
        for i, w in enumerate(ids):
            address, families, slots, free, alive, last, busy = (_s(v) if v is not None else "" for v in rows[2 * i])
            out.append(
                WorkerRecord(
                    worker_id=w,
                    address=address,
                    families=tuple(f for f in families.split(",") if f),
                    slots=int(slots or 0),
                    free=int(free or 0),
                    alive=alive == "1" and bool(rows[2 * i + 1]),
                    last_hb_ms=int(last or 0),
                    busy_until_ms=int(busy or 0),
                )
            )
        return out

    async def expired_leases(self, limit: int = 256) -> list[str]:
        """Live sessions whose lease ran out."""
        sids = await self.r.zrangebyscore(f"{self.p}:leases", "-inf", now_ms(), start=0, num=limit)
        return [_s(s) for s in sids]


def _s(value: bytes | str | int) -> str:
    """Redis replies come as bytes; keys and fields are ASCII."""
    if isinstance(value, bytes):
        return value.decode()
    return str(value)
