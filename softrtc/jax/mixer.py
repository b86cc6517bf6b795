"""One MLP-Mixer block with adaLN-zero modulation and the sin-cos flow-time embedding ([P-3], [P-4], [P-11], [P-18]).

Attribute names match the public release so that its parameter tree loads ([P-7]).
"""

from __future__ import annotations

from typing import Any, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from . import _validate as v
from .vjp import _block_gelu, _block_norm, _linear

__all__ = ["MIN_PERIOD", "MAX_PERIOD", "sincos_time_embedding", "MLPMixerBlock"]

# [P-3] Periods of the sin-cos time embedding, as in the public benchmark.
MIN_PERIOD = 4e-3
MAX_PERIOD = 4.0


# [P-3] Upper bound of the embedding size: far beyond any network, small enough for linspace.
_MAX_EMBEDDING_DIM = 1 << 24


def sincos_time_embedding(t: Any, embedding_dim: int) -> jax.Array:
    """Sin-cos embedding of flow time [P-3]: ``t[..., None] * 2*pi/period`` → ``[sin, cos]``.

    ``t`` may have any shape; the result has shape ``t.shape + (embedding_dim,)``.
    Periods are geometric from ``MIN_PERIOD`` to ``MAX_PERIOD`` over
    ``embedding_dim / 2`` frequencies; sines come first.

    >>> sincos_time_embedding(jnp.zeros((2, 3)), 4).tolist()[0][0]
    [0.0, 0.0, 1.0, 1.0]
    """
    if isinstance(embedding_dim, bool) or not isinstance(embedding_dim, (int, np.integer)) \
            or not 2 <= embedding_dim <= _MAX_EMBEDDING_DIM or embedding_dim % 2:
        raise ValueError(f"embedding_dim must be an even integer in [2, {_MAX_EMBEDDING_DIM}], got {embedding_dim!r}")
    embedding_dim = int(embedding_dim)
    t = v.float_input("t", t, allow_int=True)
    v.check_nonempty("t", t)
    v.check_unit_interval("t", t)
    fraction = jnp.linspace(0.0, 1.0, embedding_dim // 2)
    period = MIN_PERIOD * (MAX_PERIOD / MIN_PERIOD) ** fraction
    # Same operation order as the public release (1/period, then *2, then *pi) so that
    # released checkpoints see bit-identical embeddings.
    angular = 1.0 / period * 2 * jnp.pi
    arg = t[..., None] * angular
    return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)



_BLOCK_LINEARS = ("token_mix_in", "token_mix_out", "channel_mix_in", "channel_mix_out")



class MLPMixerBlock(nnx.Module):
    """One mixer layer with adaLN-zero modulation [P-4].

    Attribute names match the public release so that its parameter tree loads [P-7].
    The block does not see time directly: it consumes the two precomputed
    modulation tensors ``m1 = adaln_1(c)`` and ``m2 = adaln_2(c)`` (each ``[b, h, 3C]``,
    ``b`` in {1, B}, ``h`` in {1, H}) produced by :meth:`FlowPolicy.time_conditioning`.
    """

    def __init__(
        self, token_dim: int, token_hidden_dim: int, channel_dim: int, channel_hidden_dim: int, *, rngs: nnx.Rngs
    ):
        for name, value in (("token_dim", token_dim), ("token_hidden_dim", token_hidden_dim),
                            ("channel_dim", channel_dim), ("channel_hidden_dim", channel_hidden_dim)):
            v.check_int(name, value, 1)
        if not isinstance(rngs, nnx.Rngs):
            raise ValueError(f"rngs must be an nnx.Rngs (e.g. nnx.Rngs(0)), got {type(rngs).__name__}")
        self.token_mix_in = nnx.Linear(token_dim, token_hidden_dim, use_bias=False, rngs=rngs)
        self.token_mix_out = nnx.Linear(token_hidden_dim, token_dim, use_bias=False, rngs=rngs)
        self.channel_mix_in = nnx.Linear(channel_dim, channel_hidden_dim, use_bias=False, rngs=rngs)
        self.channel_mix_out = nnx.Linear(channel_hidden_dim, channel_dim, use_bias=False, rngs=rngs)
        self.norm_1 = nnx.LayerNorm(channel_dim, use_scale=False, use_bias=False, rngs=rngs)
        self.norm_2 = nnx.LayerNorm(channel_dim, use_scale=False, use_bias=False, rngs=rngs)
        # adaLN-zero: zero kernels make every block the identity at initialisation [P-6].
        zeros = nnx.initializers.zeros_init()
        self.adaln_1 = nnx.Linear(channel_dim, 3 * channel_dim, kernel_init=zeros, rngs=rngs)
        self.adaln_2 = nnx.Linear(channel_dim, 3 * channel_dim, kernel_init=zeros, rngs=rngs)

    # ------------------------------------------------------------------ input checks
    # Python-level, at trace time: shapes and dtypes always, values only of concrete arrays ([P-15]).
    # The network itself calls the unchecked `_token_mixing`, `_channel_mixing` and `_modulation`.

    def _check_x(self, x: Any, tokens: int | None) -> jax.Array:
        """``x [B, h, C]``: ``h = H`` for token mixing (``tokens``), any ``h >= 1`` for channel mixing."""
        x = v.float_input("x", x)
        H, C = self.token_mix_in.in_features, self.channel_mix_in.in_features
        if x.ndim != 3 or x.shape[2] != C or (tokens is not None and x.shape[1] != tokens):
            want = f"[B, {H}, {C}]" if tokens is not None else f"[B, h, {C}]"
            raise ValueError(f"x must have shape {want}, got {list(x.shape)}")
        v.check_nonempty("x", x)
        v.check_finite("x", x)
        return x

    def _check_modulation(self, name: str, m: Any, x: jax.Array, *, rank3: bool = False) -> jax.Array:
        """A modulation ``[b, h, 3C]`` (or ``[h, 3C]`` unless ``rank3``), b in {1, B}, h in {1, x's h}."""
        m = v.float_input(name, m)
        B, h, C = x.shape[0], x.shape[1], self.channel_mix_in.in_features
        ok = m.ndim == 3 or (m.ndim == 2 and not rank3)
        ok = ok and m.shape[-1] == 3 * C and m.shape[-2] in (1, h) and (m.ndim == 2 or m.shape[0] in (1, B))
        if not ok:
            form = "" if rank3 else f" (or [h, {3 * C}])"
            raise ValueError(f"{name} must have shape [b, h, {3 * C}]{form} with b in {{1, {B}}} and "
                             f"h in {{1, {h}}}, got {list(m.shape)}")
        v.check_finite(name, m)
        return m

    def _check_block_pullback(self, pullback: Any, names: tuple) -> Mapping | None:
        if pullback is None:
            return None
        want = {n: tuple(getattr(self, n).kernel.shape)[::-1] for n in _BLOCK_LINEARS}
        ok = isinstance(pullback, Mapping) and set(pullback) == set(want)
        if ok:
            for n in names:
                leaf = pullback[n]
                dt = getattr(leaf, "dtype", None)
                ok = ok and tuple(getattr(leaf, "shape", ())) == want[n] and dt is not None \
                    and jnp.issubdtype(dt, jnp.floating)
        if not ok:
            raise ValueError("pullback must be this block's entry of FlowPolicy.pullback_kernels() (keys and "
                             f"floating transposed kernels of shapes {want}), or None")
        return pullback

    # ------------------------------------------------------------------ public API

    def modulation(self, time_features: jax.Array) -> dict[str, jax.Array]:
        """``{"adaln_1": [..., 3C], "adaln_2": [..., 3C]}`` from time-MLP features ``[..., C]`` [P-11].

        ``time_features`` is a floating array with last axis ``C`` and no empty axis ([P-15]).
        """
        f = v.float_input("time_features", time_features)
        C = self.channel_mix_in.in_features
        if f.ndim < 1 or f.shape[-1] != C:
            raise ValueError(f"time_features must have shape [..., {C}], got {list(f.shape)}")
        v.check_nonempty("time_features", f)
        v.check_finite("time_features", f)
        return self._modulation(f)

    def _modulation(self, time_features: jax.Array) -> dict[str, jax.Array]:
        return {"adaln_1": self.adaln_1(time_features), "adaln_2": self.adaln_2(time_features)}

    def __call__(self, x: jax.Array, m1: jax.Array, m2: jax.Array) -> jax.Array:
        """One block on ``x [B, H, C]`` with modulations ``m1``, ``m2`` ``[b, h, 3C]`` [P-4], [P-15]."""
        x = self._check_x(x, self.token_mix_in.in_features)
        m1 = self._check_modulation("m1", m1, x, rank3=True)
        m2 = self._check_modulation("m2", m2, x, rank3=True)
        return self._channel_mixing(self._token_mixing(x, m1), m2)

    def token_mixing(self, x: jax.Array, m1: jax.Array, pullback: Mapping | None = None) -> jax.Array:
        """First half of the block: modulated token MLP along H plus the gated residual [P-4].

        ``x`` is ``[B, H, C]``; ``m1`` is ``[b, h, 3C]`` or ``[h, 3C]`` with b in {1, B}
        and h in {1, H}. ``pullback`` (optional) is this block's entry of
        :meth:`FlowPolicy.pullback_kernels` [P-19]. Shapes and dtypes are checked
        while tracing, values only when concrete ([P-15]).
        """
        x = self._check_x(x, self.token_mix_in.in_features)
        m1 = self._check_modulation("m1", m1, x)
        return self._token_mixing(x, m1, self._check_block_pullback(pullback, ("token_mix_in", "token_mix_out")))

    def _token_mixing(self, x: jax.Array, m1: jax.Array, pullback: Mapping | None = None) -> jax.Array:
        pb = pullback or {}
        # Split order (scale, shift, gate) is fixed by the released checkpoints [P-4].
        scale_1, shift_1, gate_1 = jnp.split(m1, 3, axis=-1)
        # Token mixing acts along H, so the per-token modulation is applied before it.
        y = _block_norm(self.norm_1, x) * (1 + scale_1) + shift_1
        y = jnp.swapaxes(y, -1, -2)
        y = _linear(self.token_mix_out, _block_gelu(_linear(self.token_mix_in, y, pb.get("token_mix_in"))),
                    pb.get("token_mix_out"))
        return x + gate_1 * jnp.swapaxes(y, -1, -2)

    def channel_mixing(self, x: jax.Array, m2: jax.Array, pullback: Mapping | None = None) -> jax.Array:
        """Second half of the block: modulated channel MLP, token by token, plus the gated residual [P-4].

        Acts on each token separately, so it may be applied to any subset of tokens [P-18]:
        ``x`` is ``[B, h, C]`` with ``h >= 1``, ``m2`` is ``[b, h', 3C]`` or ``[h', 3C]``
        with b in {1, B} and h' in {1, h}. ``pullback`` as in :meth:`token_mixing`.
        """
        x = self._check_x(x, None)
        m2 = self._check_modulation("m2", m2, x)
        return self._channel_mixing(x, m2,
                                    self._check_block_pullback(pullback, ("channel_mix_in", "channel_mix_out")))

    def _channel_mixing(self, x: jax.Array, m2: jax.Array, pullback: Mapping | None = None) -> jax.Array:
        pb = pullback or {}
        scale_2, shift_2, gate_2 = jnp.split(m2, 3, axis=-1)
        y = _block_norm(self.norm_2, x) * (1 + scale_2) + shift_2
        y = _linear(self.channel_mix_out, _block_gelu(_linear(self.channel_mix_in, y, pb.get("channel_mix_in"))),
                    pb.get("channel_mix_out"))
        return x + gate_2 * y
