"""A small flow policy in PyTorch with per-token flow time, in two architectures ([PT-7]).

``"adaln"`` (the default) is the network of spec chapter P, the JAX ``FlowPolicy``
([P-2]..[P-6]): each token ``[x_j, obs]`` projected by ``in_proj``, MLP-Mixer
blocks whose two halves are modulated by (scale, shift, gate) from the time
features ``c_j = time_mlp(emb(t_j))`` of the token's own time (adaLN-zero: the
modulation layers start at zero), a final modulated LayerNorm and ``out_proj``.
Same layers, sizes, names and initialisation rules, so a JAX parameter tree
loads (:meth:`FlowPolicy.load_chapter_p_state`).

``"token_input"`` takes the time the way LeRobot's pi0 / SmolVLA action experts
fuse it: ``z_j = x_j W_x + obs W_o + emb(t_j) W_t + b``, a swish fusion layer,
pre-LayerNorm mixer blocks and a linear read-out; per-token time costs one
small projection per token, where adaLN pays every block's modulation per token.

Precomputed conditioning ([PT-6]): ``time_conditioning(t)`` holds everything
that depends on time (``t.shape + (F,)``, any leading shape), ``encode_obs(obs)``
the observation's share of the input projection, and
``apply_conditioned(obs_enc, x, cond)`` the rest, so
``policy(obs, x, t) == apply_conditioned(encode_obs(obs), x, time_conditioning(t))``.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F

from . import _validate as v

__all__ = ["ARCHITECTURES", "PolicyConfig", "FlowPolicy", "time_embedding", "sincos_time_embedding"]


ARCHITECTURES = ("adaln", "token_input")


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Sizes and architecture of :class:`FlowPolicy`; every field checked ([N-7], [PT-7]).

    ``architecture``: ``"adaln"`` (the default) is the network of spec chapter P, every block modulated by
    the per-token time (adaLN-zero); ``"token_input"`` takes the time at the token input. ``time_dim`` is
    the size of the sinusoidal time embedding: chapter P embeds with ``width`` features ([P-3]), so for
    ``"adaln"`` it is ``width`` (None reads as ``width``, another value is an error); for ``"token_input"``
    None reads as 64.
    """

    horizon: int = 10
    width: int = 128
    channel_hidden: int = 256
    token_hidden: int = 32
    num_layers: int = 2
    time_dim: int | None = None
    architecture: str = "adaln"

    def __post_init__(self):
        v.choice("architecture", self.architecture, ARCHITECTURES)
        v.integer("horizon", self.horizon, 1, v.MAX_HORIZON)
        v.integer("width", self.width, 1, 65536)
        v.integer("channel_hidden", self.channel_hidden, 1, 65536)
        v.integer("token_hidden", self.token_hidden, 1, 65536)
        v.integer("num_layers", self.num_layers, 0 if self.architecture == "token_input" else 1, 1024)
        if self.architecture == "adaln":
            if self.width % 2:
                raise ValueError(f"width must be even for architecture 'adaln' (sin-cos embedding of width "
                                 f"features, [P-3]), got {self.width}")
            if self.time_dim is not None and self.time_dim != self.width:
                raise ValueError(f"time_dim must be None or width={self.width} for architecture 'adaln' "
                                 f"(the time embedding has width features, [P-3]), got {self.time_dim!r}")
            object.__setattr__(self, "time_dim", int(self.width))
        else:
            tdim = v.integer("time_dim", 64 if self.time_dim is None else self.time_dim, 2, 65536)
            if tdim % 2:
                raise ValueError(f"time_dim must be even (sines and cosines), got {tdim}")
            object.__setattr__(self, "time_dim", tdim)


def time_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """[sin, cos] of t * 2 pi / period, dim / 2 periods geometric from 4e-3 to 4 (as [P-3]); shape t.shape + (dim,)."""
    half = dim // 2
    frac = torch.linspace(0.0, 1.0, half, dtype=t.dtype, device=t.device)
    angular = 2.0 * math.pi / (4e-3 * (4.0 / 4e-3) ** frac)
    angle = t[..., None] * angular
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=-1)


def sincos_time_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """The time embedding of chapter P ([P-3]), in its operation order: ``fraction = linspace(0, 1, dim / 2)``,
    ``period = 4e-3 * (4 / 4e-3) ** fraction``, ``angular = 1 / period * 2 * pi``, ``[sin, cos](t * angular)``;
    shape ``t.shape + (dim,)``, in ``t``'s dtype."""
    frac = torch.linspace(0.0, 1.0, dim // 2, dtype=t.dtype, device=t.device)
    angular = 1.0 / (4e-3 * (4.0 / 4e-3) ** frac) * 2 * math.pi
    angle = t[..., None] * angular
    return torch.cat([torch.sin(angle), torch.cos(angle)], dim=-1)


def _norm(h):
    # [P-4], [P-17]: LayerNorm without scale or bias, epsilon 1e-6 (flax's default)
    return F.layer_norm(h, h.shape[-1:], eps=1e-6)


class _Block(nn.Module):
    """Token-input architecture: pre-LayerNorm mixer block, residual, no time."""

    def __init__(self, H: int, C: int, Ch: int, Th: int):
        super().__init__()
        self.token_in, self.token_out = nn.Linear(H, Th, bias=False), nn.Linear(Th, H, bias=False)
        self.channel_in, self.channel_out = nn.Linear(C, Ch), nn.Linear(Ch, C)

    def forward(self, h):
        y = F.layer_norm(h, h.shape[-1:]).transpose(-1, -2)  # mix along the token axis
        h = h + self.token_out(F.gelu(self.token_in(y), approximate="tanh")).transpose(-1, -2)
        y = F.layer_norm(h, h.shape[-1:])
        return h + self.channel_out(F.gelu(self.channel_in(y), approximate="tanh"))


class _AdaLNBlock(nn.Module):
    """Chapter-P mixer block ([P-4]): each half modulated by (scale, shift, gate) of the token's time features;
    mixing layers without bias; ``adaln_1`` / ``adaln_2`` are read by :meth:`FlowPolicy.time_conditioning`."""

    def __init__(self, H: int, C: int, Ch: int, Th: int):
        super().__init__()
        self.token_mix_in, self.token_mix_out = nn.Linear(H, Th, bias=False), nn.Linear(Th, H, bias=False)
        self.channel_mix_in, self.channel_mix_out = nn.Linear(C, Ch, bias=False), nn.Linear(Ch, C, bias=False)
        self.adaln_1, self.adaln_2 = nn.Linear(C, 3 * C), nn.Linear(C, 3 * C)

    def forward(self, h, m1, m2):
        scale, shift, gate = m1.chunk(3, dim=-1)  # split order of [P-4]
        y = (_norm(h) * (1 + scale) + shift).transpose(-1, -2)  # modulate per token, then mix along H
        h = h + gate * self.token_mix_out(F.gelu(self.token_mix_in(y), approximate="tanh")).transpose(-1, -2)
        scale, shift, gate = m2.chunk(3, dim=-1)
        y = _norm(h) * (1 + scale) + shift
        return h + gate * self.channel_mix_out(F.gelu(self.channel_mix_in(y), approximate="tanh"))


def _lecun_normal(w: torch.Tensor, generator: torch.Generator) -> None:
    """flax's default kernel initialiser (variance scaling 1, fan-in, truncated normal at two standard
    deviations, rescaled so that the variance is 1 / fan_in) on a torch weight [out, in]."""
    std = math.sqrt(1.0 / w.shape[1]) / 0.87962566103423978
    nn.init.trunc_normal_(w, 0.0, std, -2.0 * std, 2.0 * std, generator=generator)


class FlowPolicy(nn.Module):
    """v(obs [B, O], x [B, H, A], t [B, H] or [B]) -> [B, H, A] ([PT-7]); parameters drawn from ``generator``.

    ``config.architecture`` selects the network: ``"adaln"`` is chapter P's (adaLN-zero modulation of every
    block by the token's own time), ``"token_input"`` the time at the token input.
    """

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
        if c.architecture == "adaln":
            self._build_adaln(c, generator)
        else:
            self._build_token_input(c, generator)
        self.to(kw["dtype"])

    def _build_token_input(self, c: PolicyConfig, generator) -> None:
        self.in_action = nn.Linear(self.action_dim, c.width, bias=False)
        self.in_obs = nn.Linear(self.obs_dim, c.width, bias=False)
        self.in_time = nn.Linear(c.time_dim, c.width)
        self.fuse = nn.Linear(c.width, c.width)
        self.blocks = nn.ModuleList(_Block(c.horizon, c.width, c.channel_hidden, c.token_hidden)
                                    for _ in range(c.num_layers))
        self.out = nn.Linear(c.width, self.action_dim)
        with torch.no_grad():  # LeCun-normal kernels, zero biases, all from the caller's generator
            for m in self.modules():
                if isinstance(m, nn.Linear):
                    m.weight.copy_(torch.randn(m.weight.shape, generator=generator) / math.sqrt(m.in_features))
                    if m.bias is not None:
                        m.bias.zero_()

    def _build_adaln(self, c: PolicyConfig, generator) -> None:
        C = c.width
        # Chapter P's layers and names ([P-2] .. [P-5]); creation order as the JAX FlowPolicy.
        self.in_proj = nn.Linear(self.action_dim + self.obs_dim, C)
        self.mlp_stack = nn.ModuleList(_AdaLNBlock(c.horizon, C, c.channel_hidden, c.token_hidden)
                                       for _ in range(c.num_layers))
        self.time_mlp = nn.Sequential(nn.Linear(C, C), nn.SiLU(), nn.Linear(C, C), nn.SiLU())
        self.final_adaln = nn.Linear(C, 2 * C)
        self.out_proj = nn.Linear(C, self.action_dim)
        zero = {id(b.adaln_1) for b in self.mlp_stack} | {id(b.adaln_2) for b in self.mlp_stack} \
            | {id(self.final_adaln)}
        with torch.no_grad():  # [P-6]: adaLN-zero; other kernels LeCun normal from the caller's generator
            for m in self.modules():
                if isinstance(m, nn.Linear):
                    if id(m) in zero:
                        m.weight.zero_()
                    else:
                        _lecun_normal(m.weight, generator)
                    if m.bias is not None:
                        m.bias.zero_()

    @property
    def cond_features(self) -> int:
        """Size F of the last axis of :meth:`time_conditioning`: C (token input), or the adaLN modulations
        of every block and the final norm, ``num_layers * 6C + 2C`` (adaln)."""
        C = self.config.width
        return C if self.config.architecture == "token_input" else self.config.num_layers * 6 * C + 2 * C

    def encode_obs(self, obs) -> torch.Tensor:
        """The observation's share of every token's input projection, [B, C] (obs W_o, or obs W_o + b of
        ``in_proj`` for adaln)."""
        if self.config.architecture == "token_input":
            return self.in_obs(obs)
        return F.linear(obs, self.in_proj.weight[:, self.action_dim:], self.in_proj.bias)

    def time_conditioning(self, t) -> torch.Tensor:
        """Every time-dependent input of the network for times of any shape [..., h]: [..., h, F]
        (h = H per token, 1 shared). Token input: emb(t) W_t + b. adaln: the time features
        c = time_mlp(emb(t)) ([P-3]) projected by every block's adaln_1 and adaln_2 and by final_adaln,
        concatenated in that order ([P-11]); each token's entries depend on its own time only."""
        if self.config.architecture == "token_input":
            return self.in_time(time_embedding(t, self.config.time_dim))
        feats = self.time_mlp(sincos_time_embedding(t, self.config.width))
        mods = [m for b in self.mlp_stack for m in (b.adaln_1, b.adaln_2)] + [self.final_adaln]
        # one product for all modulations: they are linear in the same features
        return F.linear(feats, torch.cat([m.weight for m in mods]), torch.cat([m.bias for m in mods]))

    def apply_conditioned(self, obs_enc, x, cond) -> torch.Tensor:
        """The velocity from encode_obs(obs) [B, C], x [B, H, A] and a conditioning [b, h, F] or [h, F]
        (b in {1, B}, h in {1, H}; size-1 axes broadcast)."""
        if not isinstance(cond, torch.Tensor) or cond.dim() not in (2, 3) or cond.shape[-1] != self.cond_features \
                or cond.shape[-2] not in (1, self.H):
            raise ValueError(f"cond must have shape [b, h, {self.cond_features}] or [h, {self.cond_features}] "
                             f"(h in {{1, {self.H}}}) as returned by time_conditioning, got "
                             f"{list(cond.shape) if isinstance(cond, torch.Tensor) else type(cond).__name__}")
        if self.config.architecture == "token_input":
            z = self.in_action(x) + obs_enc[:, None, :] + cond
            h = self.fuse(F.silu(z))
            for blk in self.blocks:
                h = blk(h)
            return self.out(F.layer_norm(h, h.shape[-1:]))
        C = self.config.width
        h = F.linear(x, self.in_proj.weight[:, :self.action_dim]) + obs_enc[:, None, :]  # [P-2], split by rows
        for i, blk in enumerate(self.mlp_stack):
            h = blk(h, cond[..., 6 * i * C:(6 * i + 3) * C], cond[..., (6 * i + 3) * C:(6 * i + 6) * C])
        scale, shift = cond[..., -2 * C:].chunk(2, dim=-1)
        return self.out_proj(_norm(h) * (1 + scale) + shift)  # [P-5]

    def load_chapter_p_state(self, state) -> None:
        """Copy the parameters of a JAX chapter-P ``FlowPolicy`` of the same sizes into this adaln network.

        ``state`` is its pure parameter dict ([P-7]: ``nnx.state(policy).to_pure_dict()``, NumPy or JAX
        arrays, kernels [in, out]); each kernel is stored transposed (torch's [out, in]).
        """
        if self.config.architecture != "adaln":
            raise ValueError("load_chapter_p_state needs architecture 'adaln', got "
                             f"{self.config.architecture!r}")
        if not hasattr(state, "keys") or set(state.keys()) != {"in_proj", "mlp_stack", "time_mlp", "final_adaln",
                                                                "out_proj"}:
            raise ValueError("state must be the pure dict of a JAX FlowPolicy with keys in_proj, mlp_stack, "
                             "time_mlp, final_adaln, out_proj ([P-7])")
        layers = state["mlp_stack"]
        if not hasattr(layers, "keys") or sorted(int(k) for k in layers.keys()) != list(range(len(self.mlp_stack))):
            raise ValueError(f"state['mlp_stack'] must hold layers 0 .. {len(self.mlp_stack) - 1}")
        pairs = [(self.in_proj, state["in_proj"]), (self.final_adaln, state["final_adaln"]),
                 (self.out_proj, state["out_proj"]),
                 (self.time_mlp[0], state["time_mlp"]["layers"][0]), (self.time_mlp[2], state["time_mlp"]["layers"][2])]
        for i, blk in enumerate(self.mlp_stack):
            src = layers[i] if i in layers else layers[str(i)]
            pairs += [(getattr(blk, n), src[n]) for n in ("token_mix_in", "token_mix_out", "channel_mix_in",
                                                          "channel_mix_out", "adaln_1", "adaln_2")]
        with torch.no_grad():
            for mod, leaf in pairs:
                kernel = torch.as_tensor(np.array(leaf["kernel"]), dtype=mod.weight.dtype).T
                if tuple(kernel.shape) != tuple(mod.weight.shape):
                    raise ValueError(f"state kernel of shape {list(kernel.shape)[::-1]} does not fit a layer of "
                                     f"shape [in, out] = {list(mod.weight.shape)[::-1]}")
                mod.weight.copy_(kernel)
                if mod.bias is not None:
                    if "bias" not in leaf:
                        raise ValueError("state layer without the bias this network's layer has")
                    mod.bias.copy_(torch.as_tensor(np.array(leaf["bias"]), dtype=mod.bias.dtype))

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
