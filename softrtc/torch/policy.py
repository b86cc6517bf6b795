"""A small flow policy in PyTorch with per-token flow time ([PT-7]).

The time enters the way LeRobot's pi0 / SmolVLA action experts fuse it: each
action token is projected together with the observation and a sinusoidal
embedding of its own flow time, ``z_j = x_j W_x + obs W_o + emb(t_j) W_t + b``,
then a two-layer fusion MLP (swish), then MLP-Mixer blocks (token mixing and
channel mixing, pre-LayerNorm, residual) and a linear read-out. Per-token time
therefore costs one small projection per token, not a modulation of every
block, so a training-time RTC step costs about what a plain flow-matching step
costs.

Precomputed conditioning ([PT-6]): ``time_conditioning(t)`` is ``emb(t) W_t + b``
(``t.shape + (C,)``, any leading shape), ``encode_obs(obs)`` is ``obs W_o``,
and ``apply_conditioned(obs_enc, x, cond)`` the rest, so
``policy(obs, x, t) == apply_conditioned(encode_obs(obs), x, time_conditioning(t))``.
"""

from __future__ import annotations

import dataclasses
import math

import torch
from torch import nn
from torch.nn import functional as F

from . import _validate as v

__all__ = ["PolicyConfig", "FlowPolicy", "time_embedding"]


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Sizes of :class:`FlowPolicy`; every field an integer in its range ([N-7])."""

    horizon: int = 10
    width: int = 128
    channel_hidden: int = 256
    token_hidden: int = 32
    num_layers: int = 2
    time_dim: int = 64

    def __post_init__(self):
        v.integer("horizon", self.horizon, 1, v.MAX_HORIZON)
        v.integer("width", self.width, 1, 65536)
        v.integer("channel_hidden", self.channel_hidden, 1, 65536)
        v.integer("token_hidden", self.token_hidden, 1, 65536)
        v.integer("num_layers", self.num_layers, 0, 1024)
        v.integer("time_dim", self.time_dim, 2, 65536)
        if self.time_dim % 2:
            raise ValueError(f"time_dim must be even (sines and cosines), got {self.time_dim}")


def time_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """[sin, cos] of t * 2 pi / period, dim / 2 periods geometric from 4e-3 to 4 (as [P-3]); shape t.shape + (dim,)."""
    half = dim // 2
    frac = torch.linspace(0.0, 1.0, half, dtype=t.dtype, device=t.device)
    angular = 2.0 * math.pi / (4e-3 * (4.0 / 4e-3) ** frac)
    angle = t[..., None] * angular
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=-1)


class _Block(nn.Module):
    def __init__(self, H: int, C: int, Ch: int, Th: int):
        super().__init__()
        self.token_in, self.token_out = nn.Linear(H, Th, bias=False), nn.Linear(Th, H, bias=False)
        self.channel_in, self.channel_out = nn.Linear(C, Ch), nn.Linear(Ch, C)

    def forward(self, h):
        y = F.layer_norm(h, h.shape[-1:]).transpose(-1, -2)  # mix along the token axis
        h = h + self.token_out(F.gelu(self.token_in(y), approximate="tanh")).transpose(-1, -2)
        y = F.layer_norm(h, h.shape[-1:])
        return h + self.channel_out(F.gelu(self.channel_in(y), approximate="tanh"))


class FlowPolicy(nn.Module):
    """v(obs [B, O], x [B, H, A], t [B, H] or [B]) -> [B, H, A] ([PT-7]); parameters drawn from ``generator``."""

    def __init__(self, obs_dim: int, action_dim: int, config: PolicyConfig = PolicyConfig(), *,
                 generator: torch.Generator, dtype=None):
        super().__init__()
        if not isinstance(config, PolicyConfig):
            raise ValueError(f"config must be a PolicyConfig, got {type(config).__name__}")
        self.obs_dim = v.integer("obs_dim", obs_dim, 1, 1 << 20)
        self.action_dim = v.integer("action_dim", action_dim, 1, 4096)
        if not isinstance(generator, torch.Generator):
            raise ValueError("generator must be a torch.Generator (explicit seed of the initialisation)")
        self.config = c = config
        self.H = c.horizon
        kw = v.float_kw(dtype, None)
        self.in_action = nn.Linear(action_dim, c.width, bias=False)
        self.in_obs = nn.Linear(obs_dim, c.width, bias=False)
        self.in_time = nn.Linear(c.time_dim, c.width)
        self.fuse = nn.Linear(c.width, c.width)
        self.blocks = nn.ModuleList(_Block(c.horizon, c.width, c.channel_hidden, c.token_hidden)
                                    for _ in range(c.num_layers))
        self.out = nn.Linear(c.width, action_dim)
        with torch.no_grad():  # LeCun-normal kernels, zero biases, all from the caller's generator
            for m in self.modules():
                if isinstance(m, nn.Linear):
                    m.weight.copy_(torch.randn(m.weight.shape, generator=generator) / math.sqrt(m.in_features))
                    if m.bias is not None:
                        m.bias.zero_()
        self.to(kw["dtype"])

    def encode_obs(self, obs) -> torch.Tensor:
        """obs W_o: the observation's share of every token's input projection, [B, C]."""
        return self.in_obs(obs)

    def time_conditioning(self, t) -> torch.Tensor:
        """emb(t) W_t + b for times of any shape [..., h]: [..., h, C] (h = H per token, 1 shared)."""
        return self.in_time(time_embedding(t, self.config.time_dim))

    def apply_conditioned(self, obs_enc, x, cond) -> torch.Tensor:
        """The velocity from encode_obs(obs) [B, C], x [B, H, A] and a conditioning [b, h, C] or [h, C]
        (b in {1, B}, h in {1, H}; size-1 axes broadcast)."""
        z = self.in_action(x) + obs_enc[:, None, :] + cond
        h = self.fuse(F.silu(z))
        for blk in self.blocks:
            h = blk(h)
        return self.out(F.layer_norm(h, h.shape[-1:]))

    def forward(self, obs, x, t) -> torch.Tensor:
        if not isinstance(x, torch.Tensor) or x.dim() != 3 or x.shape[1:] != (self.H, self.action_dim):
            raise ValueError(f"x must have shape [B, {self.H}, {self.action_dim}], got "
                             f"{list(x.shape) if isinstance(x, torch.Tensor) else type(x).__name__}")
        B = x.shape[0]
        if not isinstance(obs, torch.Tensor) or tuple(obs.shape) != (B, self.obs_dim):
            raise ValueError(f"obs must have shape [{B}, {self.obs_dim}]")
        if not isinstance(t, torch.Tensor) or tuple(t.shape) not in ((B,), (B, self.H)):
            raise ValueError(f"t must have shape [{B}] (one time per example) or [{B}, {self.H}] (per token)")
        v.values("t", t, 0.0, 1.0)
        tt = t[:, None] if t.dim() == 1 else t  # a shared time is conditioned once per example
        return self.apply_conditioned(self.encode_obs(obs), x, self.time_conditioning(tt))
