"""Training of the Zetta VLA by flow matching on teacher demonstrations (`zetta train`).

``zetta train`` = collect demonstrations (``data.py``, unless ``--data`` names existing ones)
+ this training loop + a checkpoint directory with the training config and the data recipe.
"""

from __future__ import annotations

import json
import random
import time
from dataclasses import asdict, dataclass, field
from dataclasses import replace as dataclasses_replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from services.common.progress import add_progress_option, progress
from services.policy_worker.vla.features import CAMERA_INPUTS, IMAGE_INPUTS, parse_cameras
from services.policy_worker.vla.model import VLAConfig, ZettaVLA
from services.policy_worker.vla.policy import save_checkpoint
from services.policy_worker.vla.text import TextEncoder

if TYPE_CHECKING:  # data.py is imported where it is used, as the functions below do
    from services.policy_worker.vla.data import DataRecipe


@dataclass
class TrainConfig:
    steps: int = 20000
    batch_size: int = 128
    lr: float = 3e-4
    weight_decay: float = 1e-4
    warmup: int = 500
    #: Gaussian noise (in normalized units) added to the state inputs: cheap robustness to the
    #: small state drift a learned policy sees that the teacher never did.
    state_noise: float = 0.05
    seed: int = 0
    #: 1 by default: with env processes on the same cores, more intra-op threads spin and slow down.
    threads: int = 1
    time_budget_s: float = 0.0
    #: Image variant: frames are shifted by up to this many pixels (replicate padding), the usual
    #: augmentation of image behaviour cloning: small camera and layout shifts stop mattering.
    image_shift: int = 4
    #: Training state (weights, optimizer, schedule, RNG) is saved this often; a cut-off run resumes.
    checkpoint_every: int = 1000


#: Knobs that change how fast a run goes, not what it learns: a stage or a resume point made with
#: other values is still the same training.
RUNTIME_KNOBS = ("threads",)


def learning_config(cfg: TrainConfig) -> dict:
    """The training configuration that decides the weights (``RUNTIME_KNOBS`` left out)."""
    return {k: v for k, v in asdict(cfg).items() if k not in RUNTIME_KNOBS}


def load_demos(paths: list[str]) -> dict:
    parts = [np.load(p, allow_pickle=False) for p in paths]
    out = {k: np.concatenate([p[k] for p in parts]) for k in ("states", "actions", "episode_lengths", "instructions")}
    if all("images" in p for p in parts):
        out["images"] = np.concatenate([p["images"] for p in parts])
        offsets = np.cumsum([0] + [len(p["states"]) for p in parts[:-1]])
        out["image_steps"] = np.concatenate([
            (p["image_steps"] if "image_steps" in p else np.arange(len(p["states"]))) + o
            for p, o in zip(parts, offsets)])
    recipes = []
    for p in paths:
        meta = Path(p + ".json")
        if meta.exists():
            recipes.append(json.loads(meta.read_text()))
    out["recipes"] = recipes
    return out


def random_shift(images: torch.Tensor, pad: int) -> torch.Tensor:
    """uint8 [B, H, W, C] frames (or [B, cameras, H, W, C]), each shifted by up to ``pad`` pixels
    in x and y, every camera's frame on its own draw."""
    if pad <= 0:
        return images
    if images.dim() == 5:
        return random_shift(images.flatten(0, 1), pad).view(images.shape)
    b, h, w, _ = images.shape
    padded = torch.nn.functional.pad(images.permute(0, 3, 1, 2).float(), (pad, pad, pad, pad), mode="replicate")
    dx = torch.randint(0, 2 * pad + 1, (b,))
    dy = torch.randint(0, 2 * pad + 1, (b,))
    rows = (dy[:, None] + torch.arange(h)[None])[:, None, :, None].expand(b, padded.shape[1], h, w + 2 * pad)
    out = padded.gather(2, rows)
    cols = (dx[:, None] + torch.arange(w)[None])[:, None, None, :].expand(b, padded.shape[1], h, w)
    out = out.gather(3, cols)
    return out.permute(0, 2, 3, 1).to(torch.uint8)


class Resume:
    """The training state of a run in progress, next to its output (``<out_dir>.resume.pt``).

    A run restarted with the same output, configs and init continues from the last saved step
    with the same optimizer, schedule and RNG state; anything else starts afresh."""

    def __init__(self, out_dir: str, cfg: TrainConfig, model_cfg: VLAConfig, init: str) -> None:
        self.path = Path(str(out_dir).rstrip("/") + ".resume.pt")
        self.key = json.dumps({"train": learning_config(cfg), "model": model_cfg.to_dict(), "init": init}, sort_keys=True)
        self.seconds = 0.0
        self.losses: list[float] = []

    def restore(self, model, opt, sched, log=print) -> int:
        if not self.path.exists():
            return 0
        state = torch.load(self.path, weights_only=False)
        if state.get("key") != self.key:
            log(f"{self.path} belongs to another configuration: starting afresh")
            return 0
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["opt"])
        sched.load_state_dict(state["sched"])
        torch.set_rng_state(state["rng"])
        self.seconds, self.losses = state["seconds"], state["losses"]
        log(f"resuming training at step {state['step']} from {self.path}")
        return int(state["step"])

    def save(self, step: int, model, opt, sched, losses: list[float], seconds: float) -> None:
        tmp = self.path.with_suffix(".tmp")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        torch.save({"key": self.key, "step": step, "model": model.state_dict(), "opt": opt.state_dict(),
                    "sched": sched.state_dict(), "rng": torch.get_rng_state(), "losses": losses[-500:],
                    "seconds": seconds}, tmp)
        tmp.replace(self.path)

    def clear(self) -> None:
        self.path.unlink(missing_ok=True)


def chunk_targets(actions: np.ndarray, lengths: np.ndarray, chunk: int) -> np.ndarray:
    """[N, chunk, 7]: the next ``chunk`` teacher actions, the episode's last one repeated at its end."""
    out = np.empty((len(actions), chunk, actions.shape[1]), np.float32)
    start = 0
    for n in lengths:
        ep = actions[start:start + n]
        idx = np.minimum(np.arange(n)[:, None] + np.arange(chunk)[None], n - 1)
        out[start:start + n] = ep[idx]
        start += n
    return out


def train(demo_paths: list[str], out_dir: str, model_cfg: VLAConfig | None = None, cfg: TrainConfig | None = None,
          log=print, text_cache: dict | None = None, init: str = "", extra_meta: dict | None = None) -> dict:
    """Train (or, with ``init``, fine-tune) on the demo files and save a checkpoint to ``out_dir``.

    A fine-tune keeps the architecture of the checkpoint it starts from (its image size and
    cameras): ``model_cfg`` then only names what a new model would be."""
    cfg = cfg or TrainConfig()
    model_cfg = model_cfg or VLAConfig()
    if init:
        model_cfg = VLAConfig.from_dict(json.loads((Path(init) / "config.json").read_text())["model"])
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    torch.set_num_threads(cfg.threads)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    demos = load_demos(demo_paths)
    lengths = demos["episode_lengths"]
    ep_instr = demos["instructions"]
    step_instr = np.repeat(np.arange(len(lengths)), lengths)
    texts = TextEncoder(text_cache)
    uniq = sorted(set(ep_instr.tolist()))
    emb = texts.encode(uniq)
    index = {s: i for i, s in enumerate(uniq)}
    text_idx = np.array([index[ep_instr[e]] for e in step_instr])
    if model_cfg.image_size:
        from services.policy_worker.vla.features import PROPRIO_DIM

        states = demos["states"][:, :PROPRIO_DIM]
        images = torch.from_numpy(demos["images"])
        if images.dim() == 4:  # sets recorded before recipes named their cameras: agentview alone
            images = images[:, None]
        if images.shape[1] != len(model_cfg.cameras):
            raise ValueError(f"the demos hold {images.shape[1]} camera image(s) per frame, the model"
                             f"{' of ' + init if init else ''} reads {list(model_cfg.cameras)}: collect them "
                             f"with the same cameras (--cameras {','.join(model_cfg.cameras)})")
        #: Samples are the transitions that have a frame (every ``image_every`` steps).
        sample_steps = torch.from_numpy(demos["image_steps"])
    else:
        states = demos["states"]
        images = None
        sample_steps = None
    actions = demos["actions"]
    targets = chunk_targets(actions, lengths, model_cfg.chunk)
    model = ZettaVLA(model_cfg)
    s_mean, s_std = states.mean(0), states.std(0)
    if init:  # fine-tune (e.g. a DAgger round): weights and normalization from the checkpoint
        from services.policy_worker.vla.policy import load_checkpoint

        model, _, cache = load_checkpoint(init)
        model.train()
        texts = TextEncoder({**cache, **texts.cache})
        s_mean, s_std = model.state_mean.numpy(), model.state_std.numpy()
    s_std = np.where(s_std < 1e-4, 1.0, s_std)
    a_mean, a_std = actions.mean(0), actions.std(0)
    a_std = np.where(a_std < 1e-4, 1.0, a_std)
    if init:
        a_mean, a_std = model.action_mean.numpy().copy(), model.action_std.numpy().copy()
        s_mean, s_std = s_mean.copy(), s_std.copy()
    model.state_mean.copy_(torch.from_numpy(s_mean))
    model.state_std.copy_(torch.from_numpy(s_std))
    model.action_mean.copy_(torch.from_numpy(a_mean))
    model.action_std.copy_(torch.from_numpy(a_std))
    model.to(device).train()
    S = torch.from_numpy(states).to(device)
    A = torch.from_numpy((targets - a_mean) / a_std).float().to(device)
    E = torch.from_numpy(emb).to(device)
    TI = torch.from_numpy(text_idx).to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(
        opt, lambda s: min(1.0, (s + 1) / cfg.warmup) * 0.5 * (1 + np.cos(np.pi * min(1.0, s / cfg.steps))))
    n = len(S) if sample_steps is None else len(sample_steps)
    log(f"training on {len(lengths)} demos, {n} transitions, {len(uniq)} instructions, "
        f"{sum(p.numel() for p in model.parameters()) / 1e6:.2f}M params, device {device}")
    resume = Resume(out_dir, cfg, model_cfg, init)
    first = resume.restore(model, opt, sched, log)
    start = time.monotonic() - resume.seconds
    losses = resume.losses
    step = first - 1
    bar = progress(total=cfg.steps, desc="train", unit="step", initial=first)
    for step in range(first, cfg.steps):
        pick = torch.randint(0, n, (cfg.batch_size,), device=device)
        idx = pick if sample_steps is None else sample_steps[pick.cpu()].to(device)
        state = S[idx]
        if cfg.state_noise:
            state = state + cfg.state_noise * torch.randn_like(state) * model.state_std
        img = random_shift(images[pick.cpu()], cfg.image_shift).to(device) if images is not None else None
        loss = model.loss(state, E[TI[idx]], A[idx], img)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        losses.append(loss.item())
        bar.update()
        if (step + 1) % 500 == 0:
            log(f"step {step + 1}/{cfg.steps} loss {np.mean(losses[-500:]):.4f} {time.monotonic() - start:.0f}s")
        if (step + 1) % cfg.checkpoint_every == 0 and step + 1 < cfg.steps:
            resume.save(step + 1, model, opt, sched, losses, time.monotonic() - start)
        if cfg.time_budget_s and time.monotonic() - start > cfg.time_budget_s:
            log(f"time budget reached at step {step + 1}")
            break
    bar.close()
    seconds = time.monotonic() - start
    model.cpu().eval()
    meta = {
        "training": {**asdict(cfg), "init": init, "steps_done": step + 1, "seconds": round(seconds, 1),
                     "final_loss": float(np.mean(losses[-500:])), "device": str(device)},
        "data": {"files": [str(p) for p in demo_paths], "demos": int(len(lengths)), "transitions": int(n),
                 "instructions": uniq, "recipes": demos["recipes"]},
        **(extra_meta or {}),
    }
    save_checkpoint(out_dir, model, meta, texts.cache)
    resume.clear()
    log(f"saved {out_dir} ({sum(f.stat().st_size for f in Path(out_dir).iterdir()) / 1e6:.1f} MB) after {seconds:.0f}s")
    return meta


@dataclass
class PipelineConfig:
    """What `zetta train` runs end to end, stored in the checkpoint's config.json.

    Behaviour cloning alone compounds small errors into states the teacher never visited; the
    recipe covers them twice: DART-noisy demos (the teacher's correction recorded at perturbed
    states) and DAgger rounds (the policy drives, the teacher labels every visited state, the
    aggregate fine-tunes the policy from its previous weights). Episode counts are cuts of the
    task-interleaved episode list (``DataRecipe.max_episodes``), so every task gets its share.
    """

    clean_episodes: int = 400
    noisy_episodes: int = 250
    #: Where the clean and DART episodes start: "benchmark" (init state seed % 50) or "sampled"
    #: (a layout sampled from each seed, none of the benchmark's 50: as many layouts as episodes).
    teacher_layouts: str = "benchmark"
    action_noise: float = 0.15
    steps: int = 20000
    lr: float = 1e-3
    dagger_rounds: int = 3
    #: DAgger episodes of each round (a list shorter than the rounds repeats its last entry) on the
    #: benchmark's layouts (init state seed % 50, seeds from 3000 + 1000 r for round r + 1) ...
    dagger_episodes: list[int] = field(default_factory=lambda: [150])
    #: ... and on layouts sampled from each seed (none of the benchmark's 50; seeds from 4000 + 1000 r,
    #: which may repeat a benchmark set's seeds: the layouts differ).
    dagger_sampled_episodes: list[int] = field(default_factory=lambda: [0])
    #: From this round on (1-based), a round fine-tunes on the clean teacher set and the DAgger sets
    #: of the rounds since it only: the DART set and earlier rounds cover states the policy no
    #: longer visits, the clean demonstrations keep it on the teacher's path (without them a round
    #: forgot whole tasks). 0: every round fine-tunes on the aggregate of every set.
    fresh_from_round: int = 0
    beta: float = 0.2
    execute_steps: int = 2
    finetune_steps: int = 8000
    finetune_lr: float = 5e-4

    def round_episodes(self, r: int) -> tuple[int, int]:
        """(benchmark-layout, sampled-layout) DAgger episodes of round ``r`` (0-based)."""
        def pick(v: list[int] | int) -> int:
            v = [v] if isinstance(v, int) else v
            return int(v[min(r, len(v) - 1)]) if v else 0

        return pick(self.dagger_episodes), pick(self.dagger_sampled_episodes)

    def round_data(self, r: int, base: list[str], dagger: list[tuple[int, str]]) -> list[str]:
        """The sets round ``r`` (0-based) fine-tunes on, given the teacher sets (clean first) and the
        (round, path) DAgger sets."""
        if self.fresh_from_round and r + 1 >= self.fresh_from_round:
            return base[:1] + [path for k, path in dagger if k + 1 >= self.fresh_from_round]
        return base + [path for _, path in dagger]


def reuse_demos(recipe: DataRecipe, path: str) -> bool:
    """True when ``path`` holds a teacher-only set (no DAgger student) collected with this exact recipe.

    Clean and DART sets depend on nothing but their recipe (per-episode seeded noise, the same
    teacher code), so an interrupted pipeline need not collect them again. DAgger sets are never
    reused: they depend on the checkpoint that drove them, not only on its path.
    """
    from services.policy_worker.vla.data import default_teacher

    meta = Path(path + ".json")
    if recipe.dagger_checkpoint or not Path(path).exists() or not meta.exists():
        return False
    want = asdict(recipe)
    want["teacher"] = want["teacher"] or default_teacher()
    return json.loads(meta.read_text()).get("recipe") == want


def run_pipeline(out: str, pipe: PipelineConfig, teacher: str, tasks: list[int], processes: int,
                 train_cfg: TrainConfig, model_cfg: VLAConfig, demo_dir: str = "out/demos", log=print) -> dict:
    """Demos (clean + DART-noisy) -> training -> DAgger rounds; the last checkpoint lands in ``out``.

    A stage already trained on its data with its configuration is reused, and the sets only it
    needed are then not collected again (a resumed or extended pipeline starts where it stopped)."""
    from services.common.policies import SAMPLED_LAYOUTS
    from services.policy_worker.vla.data import DataRecipe, collect

    def gather(name: str, episodes: int, **kw) -> str:
        path = f"{demo_dir}/{name}.npz"
        recipe = DataRecipe(tasks=tasks, teacher=teacher, processes=processes, image_size=model_cfg.image_size,
                            cameras=list(model_cfg.cameras),
                            image_every=pipe.execute_steps, seeds_per_task=-(-episodes // len(tasks)),
                            max_episodes=episodes, **kw)
        if reuse_demos(recipe, path):
            log(f"reusing {path}: its recipe is this one")
            return path
        log(json.dumps(collect(recipe, path, log=log)))
        return path

    meta = {"pipeline": asdict(pipe)}
    if pipe.teacher_layouts not in ("benchmark", "sampled"):
        raise ValueError(f"teacher_layouts {pipe.teacher_layouts!r}: use 'benchmark' or 'sampled'")
    layouts = {"init_states": SAMPLED_LAYOUTS} if pipe.teacher_layouts == "sampled" else {}
    teacher_sets = [("clean", pipe.clean_episodes, {"seed_offset": 1000, **layouts})]
    if pipe.noisy_episodes:
        teacher_sets.append(("noisy", pipe.noisy_episodes,
                             {"seed_offset": 2000, "action_noise": pipe.action_noise, **layouts}))
    base = [f"{demo_dir}/{name}.npz" for name, _, _ in teacher_sets]
    stages = [f"{out}-round{r}" for r in range(pipe.dagger_rounds)] + [out]

    def stage(out_dir: str, data: list[str], cfg: TrainConfig, init: str = "") -> dict:
        done = finished_stage(out_dir, data, cfg, init)
        if done is not None:
            log(f"reusing {out_dir}: trained on these files with this configuration")
            return done
        for name, episodes, kw in teacher_sets:
            if f"{demo_dir}/{name}.npz" in data:
                gather(name, episodes, **kw)
        return train(list(data), out_dir, model_cfg, cfg, log=log, init=init, extra_meta=meta)

    result = stage(stages[0], base, dataclasses_replace(train_cfg, steps=pipe.steps, lr=pipe.lr))
    dagger: list[tuple[int, str]] = []
    finetune = dataclasses_replace(train_cfg, steps=pipe.finetune_steps, lr=pipe.finetune_lr)
    for r in range(pipe.dagger_rounds):
        on_benchmark, on_sampled = pipe.round_episodes(r)
        sets = [(f"dagger{r + 1}", on_benchmark, {"seed_offset": 3000 + 1000 * r}),
                (f"dagger{r + 1}s", on_sampled, {"seed_offset": 4000 + 1000 * r, "init_states": SAMPLED_LAYOUTS})]
        dagger += [(r, f"{demo_dir}/{name}.npz") for name, n, _ in sets if n]
        data = pipe.round_data(r, base, dagger)
        if finished_stage(stages[r + 1], data, finetune, stages[r]) is None:
            for name, n, kw in sets:
                if n:
                    gather(name, n, dagger_checkpoint=stages[r], beta=pipe.beta, execute_steps=pipe.execute_steps,
                           **kw)
        result = stage(stages[r + 1], data, finetune, init=stages[r])
    return result


def finished_stage(out_dir: str, data: list[str], cfg: TrainConfig, init: str) -> dict | None:
    """The stored meta of ``out_dir`` when it was trained to the end on exactly ``data`` with ``cfg``
    (a resumed pipeline skips it), else None."""
    path = Path(out_dir) / "config.json"
    if not path.exists():
        return None
    meta = json.loads(path.read_text())
    training = meta.get("training", {})
    want = {**learning_config(cfg), "init": init}
    if meta.get("data", {}).get("files") != [str(p) for p in data] or any(training.get(k) != v for k, v in want.items()):
        return None
    return meta if training.get("steps_done") == cfg.steps else None


def _int_list(text: str) -> list[int]:
    """``150`` or ``150,300`` (a stored pipeline's ``[150, 300]`` too)."""
    return [int(x) for x in text.strip("[]").replace(" ", "").split(",") if x]


def main(argv=None) -> int:
    import argparse

    from services.policy_worker.vla.data import PICK_PLACE_TASKS, default_teacher

    p = argparse.ArgumentParser(prog="zetta train", description="collect demos and train the Zetta VLA")
    p.add_argument("--variant", choices=("state", "image"), default="state")
    p.add_argument("--data", nargs="*", default=[], help="existing demo .npz files (skip collection and DAgger)")
    p.add_argument("--out", default="", help="checkpoint directory (default out/checkpoints/zetta-vla-<variant>)")
    p.add_argument("--teacher", default="")
    p.add_argument("--processes", type=int, default=2)
    p.add_argument("--clean-episodes", type=int, default=PipelineConfig.clean_episodes)
    p.add_argument("--noisy-episodes", type=int, default=PipelineConfig.noisy_episodes)
    p.add_argument("--action-noise", type=float, default=PipelineConfig.action_noise)
    p.add_argument("--teacher-layouts", choices=("benchmark", "sampled"), default=PipelineConfig.teacher_layouts,
                   help="clean and DART episodes on benchmark init states or on layouts sampled from each seed")
    p.add_argument("--dagger-rounds", type=int, default=PipelineConfig.dagger_rounds)
    p.add_argument("--dagger-episodes", type=_int_list, default=[150],
                   help="DAgger episodes per round on the benchmark's layouts, e.g. 150,300 (the last repeats)")
    p.add_argument("--dagger-sampled-episodes", type=_int_list, default=[0],
                   help="DAgger episodes per round on layouts sampled from the seed (none of the benchmark's)")
    p.add_argument("--fresh-from-round", type=int, default=PipelineConfig.fresh_from_round,
                   help="from this round on, fine-tune on the clean set and the DAgger sets since it only "
                        "(0: the aggregate)")
    p.add_argument("--beta", type=float, default=PipelineConfig.beta)
    p.add_argument("--execute-steps", type=int, default=PipelineConfig.execute_steps)
    p.add_argument("--finetune-steps", type=int, default=PipelineConfig.finetune_steps)
    p.add_argument("--finetune-lr", type=float, default=PipelineConfig.finetune_lr)
    p.add_argument("--demo-dir", default="out/demos")
    p.add_argument("--steps", type=int, default=PipelineConfig.steps)
    p.add_argument("--batch-size", type=int, default=TrainConfig.batch_size)
    p.add_argument("--time-budget", type=float, default=0.0, help="seconds of training at most (each run)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--image-size", type=int, default=64)
    p.add_argument("--cameras", type=parse_cameras, default=",".join(IMAGE_INPUTS),
                   help=f"image variant: the camera tensors it reads, comma-separated ({', '.join(CAMERA_INPUTS)})")
    p.add_argument("--init", default="", help="checkpoint to fine-tune from (with --data); its image size and "
                   "cameras are kept, whatever --image-size and --cameras say")
    p.add_argument("--lr", type=float, default=PipelineConfig.lr)
    p.add_argument("--threads", type=int, default=TrainConfig.threads,
                   help="torch intra-op threads for training (1 leaves cores to the env processes)")
    add_progress_option(p)
    a = p.parse_args(argv)
    image_size = a.image_size if a.variant == "image" else 0
    out = a.out or f"out/checkpoints/zetta-vla-{a.variant}"
    model_cfg = VLAConfig(image_size=image_size, cameras=a.cameras)
    train_cfg = TrainConfig(steps=a.steps, batch_size=a.batch_size, seed=a.seed, time_budget_s=a.time_budget, lr=a.lr,
                            threads=a.threads)
    if a.data:
        train(list(a.data), out, model_cfg, train_cfg, init=a.init)
        return 0
    teacher = a.teacher or default_teacher()
    tasks = list(range(10)) if teacher != "scripted-pick-place" else list(PICK_PLACE_TASKS)
    pipe = PipelineConfig(
        clean_episodes=a.clean_episodes, noisy_episodes=a.noisy_episodes, action_noise=a.action_noise,
        teacher_layouts=a.teacher_layouts,
        steps=a.steps, lr=a.lr, dagger_rounds=a.dagger_rounds, dagger_episodes=a.dagger_episodes,
        dagger_sampled_episodes=a.dagger_sampled_episodes, fresh_from_round=a.fresh_from_round, beta=a.beta,
        execute_steps=a.execute_steps, finetune_steps=a.finetune_steps, finetune_lr=a.finetune_lr)
    run_pipeline(out, pipe, teacher, tasks, a.processes, train_cfg, model_cfg, demo_dir=a.demo_dir)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
