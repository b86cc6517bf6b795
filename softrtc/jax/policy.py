"""MLP-Mixer flow policy with per-token flow time (spec chapter P, ``spec/30-policy.md``).

The network is the flow-matching velocity field ``v(obs, x, t)`` of the public
RTC Kinetix benchmark, extended so that the flow time ``t`` is given per token
([P-9]) and so that everything that depends on time alone can be computed ahead
of time ([P-11], [P-12]).

Worked example (tiny sizes)::

    >>> import flax.nnx as nnx, jax.numpy as jnp
    >>> cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=16,
    ...                    token_hidden_dim=4, num_layers=2, action_chunk_size=3)
    >>> pol = FlowPolicy(obs_dim=5, action_dim=2, config=cfg, rngs=nnx.Rngs(0))
    >>> obs, x = jnp.zeros((4, 5)), jnp.zeros((4, 3, 2))
    >>> pol(obs, x, jnp.full((4, 3), 0.5)).shape          # per-token time
    (4, 3, 2)
    >>> cond = pol.time_conditioning(jnp.array([[1.0, 0.6, 0.2]]))  # one table row
    >>> pol.apply_conditioned(obs, x, cond).shape        # serves any batch
    (4, 3, 2)
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from . import _validate as v
from .mixer import _BLOCK_LINEARS, MAX_PERIOD, MIN_PERIOD, MLPMixerBlock, sincos_time_embedding
from .vjp import _block_norm, _dot_pullback, _linear

__all__ = [
    "MIN_PERIOD",
    "MAX_PERIOD",
    "PolicyConfig",
    "MLPMixerBlock",
    "FlowPolicy",
    "sincos_time_embedding",
]

_COND_LAYERS = "mlp_stack"
_COND_FINAL = "final_adaln"
_PB_LAYERS = "mlp_stack"

# --------------------------------------------------------------------------- config


# Upper bounds of the PolicyConfig fields ([P-1]); the chunk length is [N-12]'s H <= 4096.
CONFIG_MAX = {"channel_dim": 1 << 16, "channel_hidden_dim": 1 << 16, "token_hidden_dim": 1 << 16,
              "num_layers": 1024, "action_chunk_size": 4096}
# Input sizes of FlowPolicy: the bounds of the reference velocity field ([F-3]).
OBS_DIM_MAX, ACTION_DIM_MAX = 1 << 20, 4096


@dataclasses.dataclass(frozen=True)
class PolicyConfig:
    """Network sizes [P-1]; defaults are the benchmark architecture.

    ``action_chunk_size`` is the horizon ``H``; ``channel_dim`` must be even
    because the sin-cos time embedding has ``channel_dim / 2`` frequencies [P-3].
    """

    channel_dim: int = 256
    channel_hidden_dim: int = 512
    token_hidden_dim: int = 64
    num_layers: int = 4
    action_chunk_size: int = 8

    def __post_init__(self) -> None:
        for f in dataclasses.fields(self):
            # Stored as plain int: a NumPy integer would not survive the JSON checkpoint header.
            value = v.check_int(f.name, getattr(self, f.name), 1)
            hi = CONFIG_MAX[f.name]
            if value > hi:  # [P-1] [N-12]: bounded, so a typo fails here rather than exhausting memory
                raise ValueError(f"{f.name} must be an integer in [1, {hi}], got {value}")
            object.__setattr__(self, f.name, value)
        if self.channel_dim % 2:
            raise ValueError(f"channel_dim must be even (sin-cos embedding), got {self.channel_dim}")



def _tokens(a: jax.Array, lo: int, hi: int | None) -> jax.Array:
    """Tokens ``lo:hi`` of a conditioning leaf ``[..., h, F]``; a shared leaf (h = 1) serves every token."""
    return a if a.shape[-2] == 1 else a[..., lo:hi, :]


_List = getattr(nnx, "List", list)  # nnx.List marks the layer list as data on flax >= 0.12


class FlowPolicy(nnx.Module):
    """Velocity field ``v(obs [B, obs_dim], x [B, H, A], t [B, H] or [B]) -> [B, H, A]`` [P-1].

    Three entry points compute the same function:

    * ``policy(obs, x, t)`` — straightforward path; ``t`` per token ``[B, H]`` or
      per sample ``[B]`` (shared by all tokens) [P-9].
    * ``policy.time_conditioning(t)`` — every time-dependent tensor (all adaLN
      modulations), for ``t`` of shape ``[..., H]`` or ``[..., 1]`` [P-11].
    * ``policy.apply_conditioned(obs, x, cond)`` — the network given such a
      ``cond``; leading dim 1 broadcasts over the batch [P-12].

    Args:
        obs_dim: flat observation size (679 in the Kinetix benchmark).
        action_dim: action size ``A`` (6 in the benchmark).
        config: :class:`PolicyConfig` sizes.
        rngs: explicit ``nnx.Rngs`` (e.g. ``nnx.Rngs(0)``) for initialisation [P-16].
    """

    def __init__(self, *, obs_dim: int, action_dim: int, config: PolicyConfig = PolicyConfig(), rngs: nnx.Rngs):
        obs_dim = v.check_int("obs_dim", obs_dim, 1)
        action_dim = v.check_int("action_dim", action_dim, 1)
        for name, value, hi in (("obs_dim", obs_dim, OBS_DIM_MAX), ("action_dim", action_dim, ACTION_DIM_MAX)):
            if value > hi:  # [P-1] [N-12]
                raise ValueError(f"{name} must be an integer in [1, {hi}], got {value}")
        if not isinstance(config, PolicyConfig):
            raise ValueError(f"config must be a PolicyConfig, got {type(config).__name__}")
        if not isinstance(rngs, nnx.Rngs):
            raise ValueError(f"rngs must be an nnx.Rngs (e.g. nnx.Rngs(0)), got {type(rngs).__name__}")
        c = config.channel_dim
        self.config = config
        self.obs_dim = obs_dim
        self.action_dim = action_dim
        self.channel_dim = c
        self.action_chunk_size = config.action_chunk_size
        self.num_layers = config.num_layers

        # Creation order follows the public release, so equal seeds give equal initial weights.
        self.in_proj = nnx.Linear(action_dim + obs_dim, c, rngs=rngs)
        self.mlp_stack = _List(
            [
                MLPMixerBlock(config.action_chunk_size, config.token_hidden_dim, c, config.channel_hidden_dim, rngs=rngs)
                for _ in range(config.num_layers)
            ]
        )
        self.time_mlp = nnx.Sequential(
            nnx.Linear(c, c, rngs=rngs),
            nnx.swish,
            nnx.Linear(c, c, rngs=rngs),
            nnx.swish,
        )
        # [P-5] v = out_proj(final_norm(h) * (1 + scale) + shift), (scale, shift) = final_adaln(c).
        self.final_norm = nnx.LayerNorm(c, use_scale=False, use_bias=False, rngs=rngs)
        self.final_adaln = nnx.Linear(c, 2 * c, kernel_init=nnx.initializers.zeros_init(), rngs=rngs)
        self.out_proj = nnx.Linear(c, action_dim, rngs=rngs)

    # ------------------------------------------------------------------ input checks

    def _check_obs_x(self, obs: Any, x: Any) -> tuple[jax.Array, jax.Array]:
        obs = v.float_input("obs", obs)
        x = v.float_input("x", x)
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim or obs.shape[0] < 1:
            raise ValueError(f"obs must have shape [B, {self.obs_dim}] with B >= 1, got {tuple(obs.shape)}")
        want = (obs.shape[0], self.action_chunk_size, self.action_dim)
        if tuple(x.shape) != want:
            raise ValueError(f"x must have shape [B, H, A] = {list(want)}, got {tuple(x.shape)}")
        v.check_finite("obs", obs)
        v.check_finite("x", x)
        return obs, x

    def _check_cond(self, cond: Any, batch: int) -> None:
        h, c = self.action_chunk_size, self.channel_dim
        if not isinstance(cond, Mapping) or set(cond) != {_COND_LAYERS, _COND_FINAL}:
            raise ValueError(
                f"cond must be a mapping with keys {{'{_COND_LAYERS}', '{_COND_FINAL}'}} as returned by "
                "time_conditioning"
            )
        layers = cond[_COND_LAYERS]
        if not isinstance(layers, (tuple, list)) or len(layers) != self.num_layers:
            raise ValueError(f"cond['{_COND_LAYERS}'] must be a sequence of {self.num_layers} layer entries")

        def leaf(path: str, a: Any, feat: int) -> None:
            shape = tuple(getattr(a, "shape", ()))
            ok = len(shape) in (2, 3) and shape[-1] == feat and shape[-2] in (1, h)
            if ok and len(shape) == 3:
                ok = shape[0] in (1, batch)
            if not ok:
                raise ValueError(
                    f"cond{path} must have shape [b, h, {feat}] or [h, {feat}] with b in {{1, {batch}}} and "
                    f"h in {{1, {h}}}, got {shape}"
                )
            # [N-7], [P-15]: a real floating dtype (bool, integer and complex leaves are not cast); the
            # dtype is known while tracing, the values only of concrete leaves.
            dt = getattr(a, "dtype", None)
            if dt is None or not jnp.issubdtype(dt, jnp.floating):
                raise ValueError(f"cond{path} must have a real floating dtype (as returned by time_conditioning), "
                                 f"got {dt}")
            v.check_finite(f"cond{path}", a)

        for i, entry in enumerate(layers):
            if not isinstance(entry, Mapping) or set(entry) != {"adaln_1", "adaln_2"}:
                raise ValueError(f"cond['{_COND_LAYERS}'][{i}] must be a mapping with keys 'adaln_1', 'adaln_2'")
            for k in ("adaln_1", "adaln_2"):
                leaf(f"['{_COND_LAYERS}'][{i}]['{k}']", entry[k], 3 * c)
        leaf(f"['{_COND_FINAL}']", cond[_COND_FINAL], 2 * c)

    # ------------------------------------------------------------------ time path

    def time_conditioning(self, t: Any) -> dict[str, Any]:
        """All time-dependent tensors of the network for flow times ``t`` [P-11].

        ``t`` has shape ``[..., H]`` (one time per token) or ``[..., 1]`` (one time
        shared by all tokens, the naive-sampler fast path [P-13]); values in [0, 1].
        Returns ``{"mlp_stack": ({"adaln_1": m, "adaln_2": m}, ...) per layer,
        "final_adaln": f}`` with ``m`` of shape ``t.shape + (3C,)`` and ``f`` of shape
        ``t.shape + (2C,)``. Each token's entries depend on its own time ``t[..., j]``
        only, and equal those of a shared time of that value [P-10]. The result depends on ``t`` and the parameters only, so a
        table over (delay, solver step) can be built once and indexed inside a jitted
        sampler (``jax.tree.map(lambda a: a[k], table)``).

        Example (benchmark sizes, C = 256): ``t`` of shape ``[5, 1, 8]`` (5 solver
        steps, batch 1) gives ``m`` of shape ``[5, 1, 8, 768]``.
        """
        t = v.float_input("t", t, allow_int=True)
        h = self.action_chunk_size
        if t.ndim < 1 or t.shape[-1] not in (1, h):
            raise ValueError(f"t must have shape [..., {h}] or [..., 1], got {tuple(t.shape)}")
        v.check_nonempty("t", t)
        v.check_unit_interval("t", t)
        feats = self.time_mlp(sincos_time_embedding(t, self.channel_dim))
        return {
            _COND_LAYERS: tuple(block._modulation(feats) for block in self.mlp_stack),
            _COND_FINAL: self.final_adaln(feats),
        }

    # ------------------------------------------------------------------ network

    def apply_conditioned(self, obs: Any, x: Any, cond: Mapping[str, Any], *, obs_encoding: Any = None,
                          pullback: Mapping | None = None) -> jax.Array:
        """Velocity ``[B, H, A]`` from precomputed time conditioning ``cond`` [P-12].

        Every leaf of ``cond`` has shape ``[b, h, F]`` (or ``[h, F]``, read as
        ``b = 1``) with ``b`` in {1, B} and ``h`` in {1, H}; size-1 dims broadcast.
        ``apply_conditioned(obs, x, time_conditioning(t[:, :]))`` equals
        ``policy(obs, x, t)``.

        ``obs_encoding`` (optional, ``[B, 1, C]``) is :meth:`encode_obs` of ``obs``;
        with it the observation half of ``in_proj`` is not recomputed (spec/32-runtime-bench.md, [B-3]).
        ``pullback`` (optional) is :meth:`pullback_kernels`: same values, and a
        VJP with respect to ``x`` multiplies by the stored transposed kernels [P-19].
        """
        obs, x = self._check_obs_x(obs, x)
        self._check_cond(cond, obs.shape[0])
        return self._forward(obs, x, cond, self._check_encoding(obs_encoding, obs),
                             pullback=self._check_pullback(pullback))

    def _check_encoding(self, obs_encoding: Any, obs: jax.Array) -> jax.Array | None:
        """``obs_encoding`` must be ``encode_obs(obs)`` [P-12]: its shape always; its values within
        [P-14] when both are concrete (under jit they are the caller's promise)."""
        if obs_encoding is None:
            return None
        batch = obs.shape[0]
        enc = v.float_input("obs_encoding", obs_encoding)
        if tuple(enc.shape) != (batch, 1, self.channel_dim):
            raise ValueError(f"obs_encoding must have shape [B, 1, C] = [{batch}, 1, {self.channel_dim}] "
                             f"(encode_obs(obs)), got {tuple(enc.shape)}")
        v.check_finite("obs_encoding", enc)
        if not (v.is_traced(enc) or v.is_traced(obs) or v.is_traced(self.in_proj.kernel[...])):
            want = np.asarray(self.encode_obs(obs))
            if not np.allclose(np.asarray(enc), want, rtol=1e-4, atol=1e-4):
                raise ValueError("obs_encoding must equal encode_obs(obs) within rtol = atol = 1e-4 [P-14]; "
                                 "it was computed from another observation or other parameters")
        return enc

    def pullback_kernels(self) -> dict:
        """Transposed copies of the kernels a VJP with respect to ``x`` multiplies by [P-19].

        ``{"mlp_stack": ({"token_mix_in": W.T, "token_mix_out": ..., "channel_mix_in": ...,
        "channel_mix_out": ...}, ...) per layer, "out_proj": W.T, "in_proj_x": W[:A].T}``.
        They depend on the parameters only: compute them once per parameter set,
        outside the jitted sampler (inside it XLA folds the transpose back into
        the product), and pass them as ``pullback=`` to :meth:`apply_conditioned`.
        """
        def t(kernel):
            return jnp.asarray(kernel).T.copy()

        return {
            _PB_LAYERS: tuple({name: t(getattr(block, name).kernel[...]) for name in _BLOCK_LINEARS}
                              for block in self.mlp_stack),
            "out_proj": t(self.out_proj.kernel[...]),
            "in_proj_x": t(self.in_proj.kernel[...][: self.action_dim]),
        }

    def _check_pullback(self, pullback: Any) -> Mapping | None:
        if pullback is None:
            return None
        c, a = self.channel_dim, self.action_dim

        def shape(block, name):
            return tuple(getattr(block, name).kernel.shape)[::-1]

        want = {_PB_LAYERS: tuple({n: shape(b, n) for n in _BLOCK_LINEARS} for b in self.mlp_stack),
                "out_proj": shape(self, "out_proj"), "in_proj_x": (c, a)}
        ok = isinstance(pullback, Mapping) and set(pullback) == set(want) \
            and isinstance(pullback[_PB_LAYERS], (tuple, list)) and len(pullback[_PB_LAYERS]) == self.num_layers
        if ok:
            got = {_PB_LAYERS: tuple({n: tuple(jnp.shape(e.get(n, ()))) for n in _BLOCK_LINEARS}
                                     if isinstance(e, Mapping) and set(e) == set(_BLOCK_LINEARS) else None
                                     for e in pullback[_PB_LAYERS]),
                   "out_proj": tuple(jnp.shape(pullback["out_proj"])),
                   "in_proj_x": tuple(jnp.shape(pullback["in_proj_x"]))}
            ok = got == want
        if not ok:
            raise ValueError("pullback must be the mapping returned by pullback_kernels() of this policy "
                             f"(keys and transposed kernel shapes {want})")
        return pullback

    def encode_obs(self, obs: Any) -> jax.Array:
        """Observation part of the input projection, ``obs @ W_obs + b`` of shape ``[B, 1, C]`` ([B-3]).

        ``in_proj`` acts on ``[x_j, obs]``, so its output splits into
        ``x_j @ W_x + (obs @ W_obs + b)``; the second term is the same for every
        token and every solver step of one sampler call and can be computed once.
        """
        obs = v.float_input("obs", obs)
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim or obs.shape[0] < 1:
            raise ValueError(f"obs must have shape [B, {self.obs_dim}] with B >= 1, got {tuple(obs.shape)}")
        v.check_finite("obs", obs)
        kernel = self.in_proj.kernel[...]
        return (obs @ kernel[self.action_dim:] + self.in_proj.bias[...])[:, None, :]

    def _forward(self, obs: jax.Array, x: jax.Array, cond: Mapping[str, Any],
                 obs_encoding: jax.Array | None = None, head: int | None = None, pullback: Mapping | None = None):
        b = obs.shape[0]
        pb = pullback or {_PB_LAYERS: (None,) * self.num_layers}
        if obs_encoding is not None:
            # [B-3] split input projection: only the action rows of the kernel act per token and step.
            wx = self.in_proj.kernel[...][: self.action_dim]
            hdn = (x @ wx if pullback is None else _dot_pullback(x, wx, pullback["in_proj_x"])) + obs_encoding
        else:
            # Action first, then observation: the in_proj kernel rows are laid out this way [P-2].
            # (The stored transpose covers only the action rows, so this full projection keeps autodiff's VJP.)
            obs_tok = jnp.broadcast_to(obs[:, None, :], (b, self.action_chunk_size, self.obs_dim))
            hdn = self.in_proj(jnp.concatenate([x, obs_tok], axis=-1))
        layers = cond[_COND_LAYERS]
        for block, m, kt in zip(self.mlp_stack[:-1], layers[:-1], pb[_PB_LAYERS][:-1]):
            hdn = block._channel_mixing(block._token_mixing(hdn, m["adaln_1"], kt), m["adaln_2"], kt)
        last = pb[_PB_LAYERS][-1]
        hdn = self.mlp_stack[-1]._token_mixing(hdn, layers[-1]["adaln_1"], last)
        m2, fin, out_t = layers[-1]["adaln_2"], cond[_COND_FINAL], pb.get("out_proj")
        if head is None:
            return self._output(hdn, m2, fin, last, out_t)
        # [P-18] Everything after the last token mixing acts token by token.
        return (self._output(hdn[:, :head], _tokens(m2, 0, head), _tokens(fin, 0, head), last, out_t),
                self._output(hdn[:, head:], _tokens(m2, head, None), _tokens(fin, head, None), last, out_t))

    def _output(self, hdn: jax.Array, m2: jax.Array, fin: jax.Array, last: Mapping | None,
                out_t: jax.Array | None) -> jax.Array:
        """The per-token layers: last block's channel mixing, final modulated LayerNorm, output projection."""
        hdn = self.mlp_stack[-1]._channel_mixing(hdn, m2, last)
        scale, shift = jnp.split(fin, 2, axis=-1)
        hdn = _block_norm(self.final_norm, hdn) * (1 + scale) + shift
        return _linear(self.out_proj, hdn, out_t)

    def apply_conditioned_split(self, obs: Any, x: Any, cond: Mapping[str, Any], head: int, *,
                                obs_encoding: Any = None, pullback: Mapping | None = None
                                ) -> tuple[jax.Array, jax.Array]:
        """``apply_conditioned`` as two token groups: ``(v[:, :head], v[:, head:])`` [P-18].

        Everything after the last block's token mixing (its channel MLP, the
        final modulated LayerNorm, the output projection) acts on each token
        alone, so it is evaluated separately for tokens ``j < head`` and
        ``j >= head``. A VJP of the first group then never runs the backward
        of those layers for the second group (the guided samplers' restricted
        pull-back, [G-7]). The two results concatenated along H equal
        ``apply_conditioned`` within [P-14] (not bitwise: the matrix products
        run on fewer rows). ``head`` is a static integer in [1, H - 1];
        ``obs_encoding`` and ``pullback`` as in :meth:`apply_conditioned`.

        >>> # v_head, v_tail = pol.apply_conditioned_split(obs, x, cond, 4)  # [B, 4, A], [B, H - 4, A]
        """
        if isinstance(head, bool) or not isinstance(head, (int, np.integer)) or not 1 <= head < self.action_chunk_size:
            raise ValueError(f"head must be an integer in [1, {self.action_chunk_size - 1}] (H - 1), got {head!r}")
        head = int(head)
        obs, x = self._check_obs_x(obs, x)
        self._check_cond(cond, obs.shape[0])
        return self._forward(obs, x, cond, self._check_encoding(obs_encoding, obs), head=head,
                             pullback=self._check_pullback(pullback))

    def __call__(self, obs: Any, x: Any, t: Any) -> jax.Array:
        """Velocity ``[B, H, A]`` with flow time ``t`` of shape ``[B, H]`` or ``[B]`` [P-9].

        A per-sample time ``[B]`` applies to every token; its modulation is computed
        once per sample (shape ``[B, 1, F]``) as in the public release, and the result
        equals that of the per-token time ``t[:, None]`` repeated over ``H`` [P-9].
        """
        obs, x = self._check_obs_x(obs, x)
        t = v.float_input("t", t, allow_int=True)
        b, h = obs.shape[0], self.action_chunk_size
        if t.shape == (b,):
            t = t[:, None]
        elif t.shape != (b, h):
            raise ValueError(f"t must have shape [B] or [B, {h}] with B = obs.shape[0] = {b}, got {tuple(t.shape)}")
        return self._forward(obs, x, self.time_conditioning(t))
