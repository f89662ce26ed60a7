"""Split serving: stage 1 ("VLM") and stage 2 (action expert) in two processes, each batching.

    caller ──submit──> [VLM process: BatchScheduler -> encode] ──(token, slot)──> [AE process:
    BatchScheduler -> flow-matching decode] ──(token, slot)──> caller reads actions[slot]

The prefix never goes through a pipe or a serializer: both processes map one preallocated ring
of prefix slots ``[slots, prefix_tokens, width]`` and one of action slots ``[slots, chunk, 7]``.
On CPU the rings are torch tensors in POSIX shared memory (``share_memory_()``); on a CUDA device
they are CUDA tensors whose IPC handles ``torch.multiprocessing`` passes to the AE process once
at start-up (CUDA IPC). Per request only a token and a slot index cross the pipe.

The caller's process is the VLM process (the policy worker itself); the AE runs in a spawned
child. :class:`SplitVLA` has the scheduler's ``submit``/``drain`` surface, so a server can use it
where it would use a :class:`BatchScheduler`. :class:`MonolithicVLA` is the comparison: one
scheduler, both stages in one batch.
"""

from __future__ import annotations

import asyncio
import os
import threading

import numpy as np
import torch
import torch.multiprocessing as tmp

from services.policy_worker.scheduler import BatchScheduler, InferItem, SchedulerConfig, SchedulerObserver


class _SlotRing:
    """Free-list of ring slots; thread-safe (the VLM batch thread takes, the reader frees)."""

    def __init__(self, n: int) -> None:
        self._free = list(range(n - 1, -1, -1))
        self._lock = threading.Lock()

    def take(self, k: int) -> list[int]:
        with self._lock:
            if len(self._free) < k:
                raise RuntimeError(f"prefix ring exhausted ({k} slots asked, {len(self._free)} free)")
            return [self._free.pop() for _ in range(k)]

    def free(self, slot: int) -> None:
        with self._lock:
            self._free.append(slot)


def _ae_main(checkpoint: str, quantize: str, device: str, threads: int, prefixes: torch.Tensor,
             seeds: torch.Tensor, actions: torch.Tensor, conn, cfg: SchedulerConfig) -> None:
    """The action-expert process: its own event loop and BatchScheduler over ring slots."""
    torch.set_num_threads(max(1, threads))
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    policy = ZettaVLAPolicy(checkpoint, quantize=quantize, device=device)
    policy.keep_stage(2)

    def run_batch(_model: str, inputs: dict[str, np.ndarray], _instr: list[str]) -> np.ndarray:
        slots = torch.from_numpy(inputs["slot"].astype(np.int64)).to(prefixes.device)
        with torch.inference_mode():
            out = policy.act_tensor(prefixes.index_select(0, slots), seeds.index_select(0, slots.cpu()).numpy())
            actions.index_copy_(0, slots, out.to(actions.dtype))
        if actions.is_cuda:
            torch.cuda.synchronize()
        return inputs["slot"]

    async def serve() -> None:
        loop = asyncio.get_running_loop()
        sched = BatchScheduler(run_batch, cfg)
        stop = loop.create_future()
        send_lock = threading.Lock()

        def reply(msg) -> None:
            with send_lock:
                conn.send(msg)

        async def one(token: str, slot: int, deadline: float | None) -> None:
            try:
                await sched.submit(InferItem(token, "ae", {"slot": np.array(slot, np.int64)}, deadline=deadline))
                reply((token, slot, None))
            except Exception as exc:  # noqa: BLE001 - travels back to the caller
                reply((token, slot, f"{type(exc).__name__}: {exc}"))

        def reader() -> None:
            while True:
                try:
                    msgs = conn.recv()
                except (EOFError, OSError):
                    msgs = None
                if msgs is None:
                    loop.call_soon_threadsafe(lambda: stop.done() or stop.set_result(None))
                    return
                for token, slot, deadline in msgs:
                    loop.call_soon_threadsafe(lambda t=token, s=slot, d=deadline: loop.create_task(one(t, s, d)))

        threading.Thread(target=reader, daemon=True).start()
        reply(("ready", -1, None))
        await stop
        await sched.drain()

    asyncio.run(serve())


class SplitVLA:
    """Two-process serving of one Zetta VLA checkpoint (see the module docstring).

    ``policy``: a loaded :class:`ZettaVLAPolicy` to serve stage 1 from (the policy worker's own,
    so its process holds one copy of the VLM and none of the action expert); without it the
    checkpoint is loaded here. Either way this process keeps stage 1 only.
    """

    def __init__(self, checkpoint: str | None = None, quantize: str = "", device: str = "cpu",
                 vlm: SchedulerConfig | None = None, ae: SchedulerConfig | None = None,
                 slots: int = 4096, threads: int = 1, name: str = "zetta-vla-image",
                 observer: SchedulerObserver | None = None, policy=None) -> None:
        from services.policy_worker.vla.policy import IMAGE_CHECKPOINT, ZettaVLAPolicy

        torch.set_num_threads(max(1, threads))
        self.name = name
        if policy is None:
            policy = ZettaVLAPolicy(str(checkpoint or IMAGE_CHECKPOINT), name=name, quantize=quantize, device=device)
        checkpoint, quantize, device = policy.checkpoint, policy.quantize, str(policy.device)
        self.policy = policy
        self.policy.keep_stage(1)
        cfg = self.policy.cfg
        self.chunk_size = cfg.chunk
        dev = torch.device(device)
        self.prefixes = torch.zeros(slots, cfg.prefix_tokens, cfg.width, device=dev)
        self.actions = torch.zeros(slots, cfg.chunk, cfg.action_dim, device=dev)
        #: Each request's noise seed (ZettaVLAPolicy.request_seeds), in host shared memory.
        self.seeds = torch.zeros(slots, dtype=torch.int64).share_memory_()
        if dev.type == "cpu":
            self.prefixes.share_memory_()
            self.actions.share_memory_()
        self._ring = _SlotRing(slots)
        # The worker's metrics see the stage-1 batches (the request-facing queue); stage 2 batches
        # the same items again in its own process.
        self._vlm = BatchScheduler(self._encode_batch, vlm or SchedulerConfig(), observer)
        ctx = tmp.get_context("spawn")
        self._conn, child = ctx.Pipe()
        self._proc = ctx.Process(
            target=_ae_main,
            args=(checkpoint, quantize, device, threads, self.prefixes, self.seeds, self.actions, child,
                  ae or SchedulerConfig()),
            daemon=True,
        )
        self._proc.start()
        ready = self._conn.recv()
        assert ready[0] == "ready", ready
        self._waiters: dict[str, asyncio.Future] = {}
        self._loop: asyncio.AbstractEventLoop | None = None
        self._send_lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    def input_specs(self):
        return self.policy.input_specs()

    def _encode_batch(self, _model: str, inputs: dict[str, np.ndarray], instructions: list[str]) -> np.ndarray:
        prefix, seeds = self.policy.encode(inputs, instructions)
        slots = self._ring.take(len(prefix))
        idx = torch.tensor(slots, device=self.prefixes.device)
        self.prefixes.index_copy_(0, idx, prefix.to(self.prefixes.dtype))
        self.seeds[slots] = torch.from_numpy(seeds)
        if self.prefixes.is_cuda:
            torch.cuda.synchronize()
        return np.asarray(slots, np.int64)

    def _read(self) -> None:
        while True:
            try:
                token, slot, error = self._conn.recv()
            except (EOFError, OSError):
                return
            loop = self._loop
            if loop is not None:
                loop.call_soon_threadsafe(self._resolve, token, slot, error)

    def _resolve(self, token: str, slot: int, error: str | None) -> None:
        fut = self._waiters.pop(token, None)
        if error is None:
            result = self.actions[slot].cpu().numpy().copy()
        self._ring.free(slot)
        if fut is None or fut.done():
            return
        if error is None:
            fut.set_result(result)
        else:
            from services.policy_worker.scheduler import DeadlineExceededError

            fut.set_exception(DeadlineExceededError(error) if "Deadline" in error else RuntimeError(error))

    async def submit(self, item: InferItem) -> np.ndarray:
        """Same contract as :meth:`BatchScheduler.submit`; returns the item's action chunk."""
        self._loop = asyncio.get_running_loop()
        slot = int(await self._vlm.submit(item))
        fut = self._loop.create_future()
        self._waiters[item.token] = fut
        with self._send_lock:
            self._conn.send([(item.token, slot, item.deadline)])
        return await fut

    async def drain(self) -> None:
        await self._vlm.drain()
        self.close()

    def close(self) -> None:
        if self._proc.is_alive():
            try:
                with self._send_lock:
                    self._conn.send(None)
            except (OSError, BrokenPipeError):
                pass
            self._proc.join(timeout=5)
            if self._proc.is_alive():
                self._proc.terminate()
                self._proc.join(timeout=5)


class MonolithicVLA:
    """Both stages in one process behind one BatchScheduler (the comparison point)."""

    def __init__(self, checkpoint: str | None = None, quantize: str = "", device: str = "cpu",
                 config: SchedulerConfig | None = None, threads: int = 1) -> None:
        from services.policy_worker.vla.policy import IMAGE_CHECKPOINT, ZettaVLAPolicy

        torch.set_num_threads(max(1, threads))
        self.policy = ZettaVLAPolicy(str(checkpoint or IMAGE_CHECKPOINT), quantize=quantize, device=device)
        self.chunk_size = self.policy.chunk_size
        self._sched = BatchScheduler(lambda _m, x, i: self.policy.infer(x, i), config or SchedulerConfig())

    def input_specs(self):
        return self.policy.input_specs()

    async def submit(self, item: InferItem) -> np.ndarray:
        return await self._sched.submit(item)

    async def drain(self) -> None:
        await self._sched.drain()

    def close(self) -> None:
        pass


class SplitRouter:
    """Drop-in for the worker's BatchScheduler: split models go to their SplitVLA, the rest to
    the ordinary scheduler (so the servicer is unchanged)."""

    def __init__(self, default: BatchScheduler, split: dict[str, SplitVLA]) -> None:
        self._default = default
        self._split = split
        self._closing = False

    @property
    def closed(self) -> bool:
        return self._closing or self._default.closed

    def compute_estimate(self, key):
        return self._default.compute_estimate(key)

    async def submit(self, item: InferItem) -> np.ndarray:
        if self._closing:
            from services.policy_worker.scheduler import SchedulerClosedError

            raise SchedulerClosedError("scheduler is draining; not accepting requests")
        target = self._split.get(item.model)
        return await (target.submit(item) if target is not None else self._default.submit(item))

    async def drain(self) -> None:
        self._closing = True
        await asyncio.gather(self._default.drain(), *(s.drain() for s in self._split.values()))


def wrap_for_split(scheduler: BatchScheduler, models: dict, config: SchedulerConfig,
                   observer: SchedulerObserver | None = None):
    """What main.py calls when ZETTA_VLA_SPLIT is set: a SplitRouter when a state VLA is served.

    Each state VLA the worker loaded becomes the stage-1 half of its SplitVLA (its action expert is
    freed here and loaded in the AE process), so the worker holds one copy of each stage in all; the
    router sends that model's requests to the split, never to ``models[name].infer``.
    """
    from services.policy_worker.vla.policy import ZettaVLAPolicy

    split = {}
    for name, model in models.items():
        if isinstance(model, ZettaVLAPolicy):
            split[name] = SplitVLA(vlm=config, ae=config, threads=int(os.environ.get("ZETTA_TORCH_THREADS", "1")),
                                   name=name, observer=observer, policy=model)
    return SplitRouter(scheduler, split) if split else scheduler
