"""The Zetta VLA: a small policy with pi0's two-stage structure.

Stage 1, the "VLM" (:class:`PrefixEncoder`): the observation (proprioception and object state,
or a camera image plus proprioception) and the instruction's all-MiniLM-L6-v2 embedding become a
prefix of ``prefix_tokens`` vectors. The instruction gates the observation features (FiLM) before
the prefix MLP, so one scene can mean ten different tasks.

Stage 2, the action expert (:class:`ActionExpert`): flow matching. Training regresses the
velocity ``a - x0`` at ``x_t = t a + (1 - t) x0`` (x0 Gaussian); inference integrates the learned
field from t = 0 to 1 in ``flow_steps`` Euler steps, conditioned on the prefix, producing an action
chunk [chunk, 7] in normalized units. :meth:`ActionExpert.forward` starts from the given x0
(zeros when none is given); the served policy samples x0 ~ N(0, I) by default, because the zero
start averages the teacher's modes (see ``ZettaVLAPolicy``).

The two stages share nothing but the prefix tensor, which is what lets the policy worker run them
in two processes (see :mod:`services.policy_worker.vla.split`).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import nn

from services.common.policies import ACTION_DIM
from services.policy_worker.vla.features import IMAGE_INPUTS, PROPRIO_DIM, STATE_DIM, check_cameras
from services.policy_worker.vla.text import TEXT_DIM

#: Gripper outputs below this magnitude mean "hold" (0); the teacher commands -1, -0.5, 0, 0.5, 1.
GRIPPER_DEADZONE = 0.25


@dataclass
class VLAConfig:
    state_dim: int = STATE_DIM
    proprio_dim: int = PROPRIO_DIM
    text_dim: int = TEXT_DIM
    #: 0: state-based variant; > 0: image-based variant on a square RGB image of that size.
    image_size: int = 0
    #: Image variant: the camera tensors it reads, one encoder each (checkpoints that predate the
    #: field read the agentview camera alone).
    cameras: tuple[str, ...] = IMAGE_INPUTS
    width: int = 128
    prefix_tokens: int = 4
    prefix_hidden: int = 256
    chunk: int = 8
    expert_hidden: int = 128
    expert_blocks: int = 3
    flow_steps: int = 10
    action_dim: int = ACTION_DIM

    def __post_init__(self) -> None:
        self.cameras = check_cameras(self.cameras)

    @classmethod
    def from_dict(cls, d: dict) -> "VLAConfig":
        return cls(**{k: v for k, v in d.items() if k in cls.__dataclass_fields__})

    def to_dict(self) -> dict:
        d = asdict(self)
        d["cameras"] = list(self.cameras)
        return d


class ImageEncoder(nn.Module):
    """A small conv net: uint8 [B, H, W, 3] -> [B, width]."""

    def __init__(self, width: int) -> None:
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, 32, 5, stride=2, padding=2), nn.GELU(),
            nn.Conv2d(32, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(64, 64, 3, stride=2, padding=1), nn.GELU(),
            nn.Conv2d(64, 128, 3, stride=2, padding=1), nn.GELU(),
            nn.AdaptiveAvgPool2d(4), nn.Flatten(), nn.Linear(128 * 16, width), nn.GELU(),
        )

    def forward(self, image: torch.Tensor) -> torch.Tensor:
        x = image.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)


class PrefixEncoder(nn.Module):
    """Stage 1: (observation, instruction embedding) -> prefix [B, prefix_tokens, width]."""

    def __init__(self, cfg: VLAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        w = cfg.width
        if cfg.image_size:
            self.image = ImageEncoder(w)  # the first camera's (the name older checkpoints load into)
            #: One encoder per further camera: a wrist view and a scene view share no statistics.
            self.more_images = nn.ModuleList(ImageEncoder(w) for _ in cfg.cameras[1:])
            obs_in = cfg.proprio_dim
        else:
            self.image = None
            self.more_images = nn.ModuleList()
            obs_in = cfg.state_dim
        self.obs = nn.Sequential(nn.Linear(obs_in, w), nn.GELU(), nn.Linear(w, w))
        self.text = nn.Sequential(nn.Linear(cfg.text_dim, w), nn.GELU(), nn.Linear(w, w))
        self.film = nn.Linear(w, 2 * w)
        feat = (2 + len(cfg.cameras)) * w if cfg.image_size else 2 * w
        #: The compute-heavy "prefix MLP": the module the W8A8 plug-in targets by default.
        self.prefix_mlp = nn.Sequential(
            nn.Linear(feat, cfg.prefix_hidden), nn.GELU(),
            nn.Linear(cfg.prefix_hidden, cfg.prefix_hidden), nn.GELU(),
            nn.Linear(cfg.prefix_hidden, cfg.prefix_tokens * w),
        )
        self.norm = nn.LayerNorm(w)

    def forward(self, state: torch.Tensor, text: torch.Tensor, image: torch.Tensor | None = None) -> torch.Tensor:
        """``image``: uint8 [B, cameras, H, W, 3] in ``cfg.cameras`` order ([B, H, W, 3] for one)."""
        t = self.text(text)
        scale, shift = self.film(t).chunk(2, dim=-1)
        o = self.obs(state)
        o = o * (1 + scale) + shift
        parts = [o]
        if self.image is not None:
            assert image is not None, "image variant needs an image"
            views = image[:, None] if image.dim() == 4 else image
            assert views.shape[1] == len(self.cfg.cameras), f"expected {len(self.cfg.cameras)} camera images"
            for k, encoder in enumerate([self.image, *self.more_images]):
                parts.append(encoder(views[:, k]) * (1 + scale) + shift)
        parts.append(t)
        prefix = self.prefix_mlp(torch.cat(parts, dim=-1))
        return self.norm(prefix.view(len(state), self.cfg.prefix_tokens, self.cfg.width))


def time_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device, dtype=torch.float32) / half)
    args = t[:, None].float() * freqs[None] * 100.0
    return torch.cat([torch.sin(args), torch.cos(args)], dim=-1)


class _Block(nn.Module):
    def __init__(self, hidden: int) -> None:
        super().__init__()
        self.norm = nn.LayerNorm(hidden)
        self.film = nn.Linear(hidden, 2 * hidden)
        self.mlp = nn.Sequential(nn.Linear(hidden, 2 * hidden), nn.GELU(), nn.Linear(2 * hidden, hidden))

    def forward(self, x: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        scale, shift = self.film(cond).chunk(2, dim=-1)
        return x + self.mlp(self.norm(x) * (1 + scale) + shift)


class ActionExpert(nn.Module):
    """Stage 2: velocity field v(x_t, t | prefix) over a flattened action chunk."""

    def __init__(self, cfg: VLAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        h = cfg.expert_hidden
        flat = cfg.chunk * cfg.action_dim
        self.prefix_proj = nn.Sequential(nn.Linear(cfg.prefix_tokens * cfg.width, h), nn.GELU())
        self.time_proj = nn.Sequential(nn.Linear(64, h), nn.GELU())
        self.inp = nn.Linear(flat, h)
        self.blocks = nn.ModuleList([_Block(h) for _ in range(cfg.expert_blocks)])
        self.out = nn.Sequential(nn.LayerNorm(h), nn.Linear(h, flat))

    def condition(self, prefix: torch.Tensor) -> torch.Tensor:
        return self.prefix_proj(prefix.flatten(1))

    def velocity(self, x: torch.Tensor, t: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        c = cond + self.time_proj(time_embedding(t, 64))
        h = self.inp(x.flatten(1))
        for block in self.blocks:
            h = block(h, c)
        return self.out(h).view_as(x)

    def forward(self, prefix: torch.Tensor, noise: torch.Tensor | None = None, steps: int | None = None) -> torch.Tensor:
        """Integrate from x0 (zeros unless ``noise`` is given) to an action chunk [B, chunk, 7]."""
        cfg = self.cfg
        steps = steps or cfg.flow_steps
        x = noise if noise is not None else torch.zeros(len(prefix), cfg.chunk, cfg.action_dim, device=prefix.device)
        cond = self.condition(prefix)
        dt = 1.0 / steps
        for k in range(steps):
            # The flow time is built from x's own rows, not a Python batch size, so a trace of this
            # method (policy.py serves one) holds for every batch size.
            t = torch.full_like(x[:, 0, 0], k * dt)
            x = x + dt * self.velocity(x, t, cond)
        return x


class ZettaVLA(nn.Module):
    """Both stages plus the normalization statistics (buffers, saved with the weights)."""

    def __init__(self, cfg: VLAConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.encoder = PrefixEncoder(cfg)
        self.expert = ActionExpert(cfg)
        obs_in = cfg.proprio_dim if cfg.image_size else cfg.state_dim
        self.register_buffer("state_mean", torch.zeros(obs_in))
        self.register_buffer("state_std", torch.ones(obs_in))
        self.register_buffer("action_mean", torch.zeros(cfg.action_dim))
        self.register_buffer("action_std", torch.ones(cfg.action_dim))

    def normalize_state(self, state: torch.Tensor) -> torch.Tensor:
        return (state - self.state_mean) / self.state_std

    def encode(self, state: torch.Tensor, text: torch.Tensor, image: torch.Tensor | None = None) -> torch.Tensor:
        """Stage 1 on raw (unnormalized) state."""
        return self.encoder(self.normalize_state(state), text, image)

    def act(self, prefix: torch.Tensor, noise: torch.Tensor | None = None) -> torch.Tensor:
        """Stage 2; returns actions in environment units, gripper snapped to -1, 0 or +1.

        The Panda gripper integrates the sign of its command (0 holds the current opening, which
        the teacher uses to keep a partial aperture), so three levels lose nothing and remove the
        flicker of a regressed value near a mode boundary.
        """
        return self.to_env_units(self.expert(prefix, noise))

    def to_env_units(self, chunk: torch.Tensor) -> torch.Tensor:
        """Stage 2's normalized chunk in environment units, clamped, gripper snapped (see :meth:`act`)."""
        a = (chunk * self.action_std + self.action_mean).clamp(-1.0, 1.0)
        g = a[..., -1]
        a[..., -1] = torch.where(g.abs() < GRIPPER_DEADZONE, torch.zeros_like(g), torch.sign(g))
        return a

    def loss(self, state, text, actions_norm, image=None) -> torch.Tensor:
        """Flow-matching loss on normalized action chunks [B, chunk, 7]."""
        prefix = self.encoder(self.normalize_state(state), text, image)
        x0 = torch.randn_like(actions_norm)
        t = torch.rand(len(actions_norm), device=actions_norm.device)
        # pi0 samples t skewed towards the noisy end; a Beta(1.5, 1) does the same here.
        t = 1 - torch.distributions.Beta(1.5, 1.0).sample((len(actions_norm),)).to(actions_norm.device)
        xt = t[:, None, None] * actions_norm + (1 - t[:, None, None]) * x0
        v = self.expert.velocity(xt, t, self.expert.condition(prefix))
        return ((v - (actions_norm - x0)) ** 2).mean()
