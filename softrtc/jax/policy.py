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

import contextlib
import dataclasses
import os
import pickle
from typing import Any, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

__all__ = [
    "MIN_PERIOD",
    "MAX_PERIOD",
    "PolicyConfig",
    "MLPMixerBlock",
    "FlowPolicy",
    "sincos_time_embedding",
    "state_pure_dict",
    "load_pure_dict",
    "load_checkpoint",
]

# [P-3] Periods of the sin-cos time embedding, as in the public benchmark.
MIN_PERIOD = 4e-3
MAX_PERIOD = 4.0

_COND_LAYERS = "mlp_stack"
_COND_FINAL = "final_adaln"
_PB_LAYERS = "mlp_stack"


# --------------------------------------------------------------------------- validation


def _is_tracer(a: Any) -> bool:
    return isinstance(a, jax.core.Tracer)


def _check_pos_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    return int(value)


def _as_float_array(name: str, value: Any, *, allow_int: bool = False) -> jax.Array:
    """Converts ``value`` to a JAX array, rejecting bool (and int unless allowed) dtypes [P-15]."""
    if _is_tracer(value):
        arr = value
    else:
        try:
            arr = jnp.asarray(value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a real array, got {type(value).__name__}") from exc
    dt = arr.dtype
    ok = jnp.issubdtype(dt, jnp.floating) or (allow_int and jnp.issubdtype(dt, jnp.integer))
    if dt == jnp.bool_ or not ok:
        allowed = "a real (integer or floating)" if allow_int else "a floating"
        raise ValueError(f"{name} must have {allowed} dtype, got {dt}")
    if jnp.issubdtype(dt, jnp.integer):
        arr = arr.astype(jnp.float32)
    return arr


def _check_finite(name: str, arr: jax.Array) -> None:
    # Values can only be inspected outside tracing; under jit only shapes are checked [P-15].
    # NumPy, not jnp: inside a jit trace even a concrete array would turn into a tracer.
    if not _is_tracer(arr) and not np.all(np.isfinite(np.asarray(arr))):
        raise ValueError(f"{name} must contain only finite values (no NaN or inf)")


def _check_nonempty(name: str, arr: jax.Array) -> None:
    # [N-12] arrays have no empty axis; a shape check, free under jit.
    if 0 in tuple(arr.shape):
        raise ValueError(f"{name} must have at least one entry along every axis, got shape {tuple(arr.shape)}")


# [P-3] Upper bound of the embedding size: far beyond any network, small enough for linspace.
_MAX_EMBEDDING_DIM = 1 << 24


def _check_unit_interval(name: str, arr: jax.Array) -> None:
    if _is_tracer(arr):
        return
    _check_finite(name, arr)
    a = np.asarray(arr)
    if a.size and (np.any(a < 0.0) or np.any(a > 1.0)):
        raise ValueError(f"{name} must lie in [0, 1] (flow time, 0 = noise, 1 = data)")


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
            value = _check_pos_int(f.name, getattr(self, f.name))
            hi = CONFIG_MAX[f.name]
            if value > hi:  # [P-1] [N-12]: bounded, so a typo fails here rather than exhausting memory
                raise ValueError(f"{f.name} must be an integer in [1, {hi}], got {value}")
            object.__setattr__(self, f.name, value)
        if self.channel_dim % 2:
            raise ValueError(f"channel_dim must be even (sin-cos embedding), got {self.channel_dim}")


# --------------------------------------------------------------------------- time embedding


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
    t = _as_float_array("t", t, allow_int=True)
    _check_nonempty("t", t)
    _check_unit_interval("t", t)
    fraction = jnp.linspace(0.0, 1.0, embedding_dim // 2)
    period = MIN_PERIOD * (MAX_PERIOD / MIN_PERIOD) ** fraction
    # Same operation order as the public release (1/period, then *2, then *pi) so that
    # released checkpoints see bit-identical embeddings.
    angular = 1.0 / period * 2 * jnp.pi
    arg = t[..., None] * angular
    return jnp.concatenate([jnp.sin(arg), jnp.cos(arg)], axis=-1)


# --------------------------------------------------------------------------- modules


def layer_norm(norm: nnx.LayerNorm, x: jax.Array) -> jax.Array:
    """``norm(x)`` (a scale- and bias-free LayerNorm) with a hand-written VJP [P-17].

    The forward is the flax module itself, so values are bitwise those of
    ``norm(x)``. The backward uses the closed form
    ``dx = r (g - mean(g) - y mean(g y))`` with ``y = norm(x)`` and
    ``r = 1 / sqrt(var + eps)``: two means, taken as one matrix product,
    where autodiff of the module's statistics emits several reduction kernels
    (each guided sampler step runs nine of these backwards).

    ``norm`` must be an ``nnx.LayerNorm`` and ``x`` a floating array whose last
    axis has its ``num_features`` entries, with no empty axis ([P-15]). Only
    shapes and dtypes are checked (free under ``jit``), not values.
    """
    if not isinstance(norm, nnx.LayerNorm):
        raise ValueError(f"norm must be an nnx.LayerNorm, got {type(norm).__name__}")
    x = _as_float_array("x", x)
    if x.ndim < 1 or x.shape[-1] != norm.num_features:
        raise ValueError(f"x must have shape [..., {norm.num_features}] (the norm's num_features), "
                         f"got {tuple(x.shape)}")
    _check_nonempty("x", x)
    return _layer_norm(norm, x)


def _layer_norm(norm: nnx.LayerNorm, x: jax.Array) -> jax.Array:
    """:func:`layer_norm` without the argument checks (for the network's own, already valid, activations)."""

    @jax.custom_vjp
    def ln(x):
        return norm(x)

    def fwd(x):
        y = norm(x)
        # Same statistics as flax's fast variance (E[x^2] - E[x]^2, clipped at 0); XLA shares them.
        mu = jnp.mean(x, axis=-1, keepdims=True)
        mu2 = jnp.mean(x * x, axis=-1, keepdims=True)
        r = jax.lax.rsqrt(jnp.maximum(0.0, mu2 - mu * mu) + norm.epsilon)
        return y, (y, r)

    def bwd(res, g):
        y, r = res
        # Both means as one product with a column of 1/C: XLA:CPU splits each wide
        # reduction into two kernels (a tree reduction), the product is one.
        C = g.shape[-1]
        m = jnp.stack([g, g * y], axis=-2) @ jnp.full((C, 1), 1.0 / C, g.dtype)
        return (r * (g - m[..., 0, :] - y * m[..., 1, :]),)

    ln.defvjp(fwd, bwd)
    return ln(x)


_SQRT_2_OVER_PI = float(np.sqrt(2.0 / np.pi))
_GELU_CUBIC = 0.044715


def gelu(x: jax.Array) -> jax.Array:
    """``nnx.gelu(x)`` (tanh approximation) whose VJP recomputes ``tanh`` from ``x`` [P-20].

    The forward is ``nnx.gelu`` itself, so values are bitwise those of the
    module. The backward keeps only ``x`` and evaluates
    ``gelu'(x) = (1 + th) / 2 + x (1 - th^2) c (1 + 3 a x^2) / 2`` with
    ``th = tanh(c (x + a x^3))``, ``c = sqrt(2 / pi)``, ``a = 0.044715``.
    The policy's blocks differentiate ``nnx.gelu`` by autodiff as shipped
    ([P-20]); this VJP is the measured alternative, selected inside
    ``autodiff_vjps(gelu=False)`` ([B-12]).

    ``x`` is a floating array of any shape with no empty axis ([P-15]); only
    its shape and dtype are checked (free under ``jit``), not its values.

    >>> round(float(gelu(jnp.float32(1.0))), 4)
    0.8412
    """
    x = _as_float_array("x", x)
    _check_nonempty("x", x)
    return _gelu(x)


@jax.custom_vjp
def _gelu(x: jax.Array) -> jax.Array:
    return nnx.gelu(x)


def _gelu_fwd(x):
    return nnx.gelu(x), x


def _gelu_bwd(x, g):
    x2 = x * x
    # The forward's tanh argument c (x + a x^3), written as (c x)(1 + a x^2): an identical expression
    # would be merged with the forward's by XLA, which then stores th again.
    th = jnp.tanh((_SQRT_2_OVER_PI * x) * (1.0 + _GELU_CUBIC * x2))
    d = 0.5 * (1.0 + th) + 0.5 * x * (1.0 - th * th) * _SQRT_2_OVER_PI * (1.0 + 3.0 * _GELU_CUBIC * x2)
    return (g * d,)


_gelu.defvjp(_gelu_fwd, _gelu_bwd)


# How the blocks are differentiated, read while a policy function is traced and set only by
# `autodiff_vjps`. As shipped: LayerNorm by its closed-form VJP ([P-17]), GELU by autodiff ([P-20]).
_AUTODIFF = {"layer_norm": False, "gelu": True}


@contextlib.contextmanager
def autodiff_vjps(*, layer_norm: bool = False, gelu: bool = True):
    """Trace policy functions with the chosen VJP of each block, for ablations ([B-12]).

    Inside the ``with`` block, policy functions traced (jitted, lowered) use
    ``norm(x)`` (plain autodiff) instead of :func:`layer_norm`'s closed-form
    VJP ([P-17]) when ``layer_norm`` is True, and :func:`gelu`'s recomputing
    VJP instead of autodiff of ``nnx.gelu`` ([P-20]) when ``gelu`` is False.
    The defaults are the shipped choices, so ``autodiff_vjps()`` changes
    nothing. Forward values are the same; functions compiled before or after
    the block are unaffected. Not thread-safe: it sets module state for the
    duration of the block.

    >>> with autodiff_vjps(gelu=False):  # the recomputing GELU VJP of [P-20]
    ...     pass  # e.g. jax.jit(f).lower(...).compile()
    """
    for name, value in (("layer_norm", layer_norm), ("gelu", gelu)):
        if not isinstance(value, bool):
            raise ValueError(f"{name} must be a bool, got {value!r}")
    saved = dict(_AUTODIFF)
    _AUTODIFF.update(layer_norm=layer_norm, gelu=gelu)
    try:
        yield
    finally:
        _AUTODIFF.update(saved)


def _block_norm(norm: nnx.LayerNorm, x: jax.Array) -> jax.Array:
    return norm(x) if _AUTODIFF["layer_norm"] else _layer_norm(norm, x)


def _block_gelu(x: jax.Array) -> jax.Array:
    return nnx.gelu(x) if _AUTODIFF["gelu"] else _gelu(x)


_BLOCK_LINEARS = ("token_mix_in", "token_mix_out", "channel_mix_in", "channel_mix_out")


def _contract(x: jax.Array, kernel: jax.Array) -> jax.Array:
    # nnx.Linear's own contraction: last axis of x with the kernel's first.
    return jax.lax.dot_general(x, kernel, (((x.ndim - 1,), (0,)), ((), ())))


@jax.custom_vjp
def _dot_pullback(x: jax.Array, kernel: jax.Array, kernel_t: jax.Array) -> jax.Array:
    """``x @ kernel`` whose VJP w.r.t. ``x`` multiplies by the stored transpose ``kernel_t`` [P-19]."""
    return _contract(x, kernel)


def _dot_pullback_fwd(x, kernel, kernel_t):
    return _contract(x, kernel), (x, kernel_t)


def _dot_pullback_bwd(res, g):
    x, kernel_t = res
    lead = tuple(range(x.ndim - 1))
    # The kernel's cotangent is the usual x^T g; kernel_t does not enter the value, so its cotangent is zero.
    return _contract(g, kernel_t), jax.lax.dot_general(x, g, ((lead, lead), ((), ()))), jnp.zeros_like(kernel_t)


_dot_pullback.defvjp(_dot_pullback_fwd, _dot_pullback_bwd)


def _linear(module: nnx.Linear, x: jax.Array, kernel_t: jax.Array | None) -> jax.Array:
    """``module(x)``; with ``kernel_t`` its pull-back uses that stored transpose ([P-19]), same forward values."""
    if kernel_t is None:
        return module(x)
    y = _dot_pullback(x, module.kernel[...], kernel_t)
    if module.bias is not None:
        y = y + jnp.reshape(module.bias[...], (1,) * (y.ndim - 1) + (-1,))
    return y


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
            _check_pos_int(name, value)
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
        x = _as_float_array("x", x)
        H, C = self.token_mix_in.in_features, self.channel_mix_in.in_features
        if x.ndim != 3 or x.shape[2] != C or (tokens is not None and x.shape[1] != tokens):
            want = f"[B, {H}, {C}]" if tokens is not None else f"[B, h, {C}]"
            raise ValueError(f"x must have shape {want}, got {list(x.shape)}")
        _check_nonempty("x", x)
        _check_finite("x", x)
        return x

    def _check_modulation(self, name: str, m: Any, x: jax.Array, *, rank3: bool = False) -> jax.Array:
        """A modulation ``[b, h, 3C]`` (or ``[h, 3C]`` unless ``rank3``), b in {1, B}, h in {1, x's h}."""
        m = _as_float_array(name, m)
        B, h, C = x.shape[0], x.shape[1], self.channel_mix_in.in_features
        ok = m.ndim == 3 or (m.ndim == 2 and not rank3)
        ok = ok and m.shape[-1] == 3 * C and m.shape[-2] in (1, h) and (m.ndim == 2 or m.shape[0] in (1, B))
        if not ok:
            form = "" if rank3 else f" (or [h, {3 * C}])"
            raise ValueError(f"{name} must have shape [b, h, {3 * C}]{form} with b in {{1, {B}}} and "
                             f"h in {{1, {h}}}, got {list(m.shape)}")
        _check_finite(name, m)
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
        f = _as_float_array("time_features", time_features)
        C = self.channel_mix_in.in_features
        if f.ndim < 1 or f.shape[-1] != C:
            raise ValueError(f"time_features must have shape [..., {C}], got {list(f.shape)}")
        _check_nonempty("time_features", f)
        _check_finite("time_features", f)
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
        obs_dim = _check_pos_int("obs_dim", obs_dim)
        action_dim = _check_pos_int("action_dim", action_dim)
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
        obs = _as_float_array("obs", obs)
        x = _as_float_array("x", x)
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim or obs.shape[0] < 1:
            raise ValueError(f"obs must have shape [B, {self.obs_dim}] with B >= 1, got {tuple(obs.shape)}")
        want = (obs.shape[0], self.action_chunk_size, self.action_dim)
        if tuple(x.shape) != want:
            raise ValueError(f"x must have shape [B, H, A] = {list(want)}, got {tuple(x.shape)}")
        _check_finite("obs", obs)
        _check_finite("x", x)
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
            _check_finite(f"cond{path}", a)

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
        t = _as_float_array("t", t, allow_int=True)
        h = self.action_chunk_size
        if t.ndim < 1 or t.shape[-1] not in (1, h):
            raise ValueError(f"t must have shape [..., {h}] or [..., 1], got {tuple(t.shape)}")
        _check_nonempty("t", t)
        _check_unit_interval("t", t)
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
        enc = _as_float_array("obs_encoding", obs_encoding)
        if tuple(enc.shape) != (batch, 1, self.channel_dim):
            raise ValueError(f"obs_encoding must have shape [B, 1, C] = [{batch}, 1, {self.channel_dim}] "
                             f"(encode_obs(obs)), got {tuple(enc.shape)}")
        _check_finite("obs_encoding", enc)
        if not (_is_tracer(enc) or _is_tracer(obs) or _is_tracer(self.in_proj.kernel[...])):
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
        obs = _as_float_array("obs", obs)
        if obs.ndim != 2 or obs.shape[1] != self.obs_dim or obs.shape[0] < 1:
            raise ValueError(f"obs must have shape [B, {self.obs_dim}] with B >= 1, got {tuple(obs.shape)}")
        _check_finite("obs", obs)
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
        t = _as_float_array("t", t, allow_int=True)
        b, h = obs.shape[0], self.action_chunk_size
        if t.shape == (b,):
            t = t[:, None]
        elif t.shape != (b, h):
            raise ValueError(f"t must have shape [B] or [B, {h}] with B = obs.shape[0] = {b}, got {tuple(t.shape)}")
        return self._forward(obs, x, self.time_conditioning(t))


# --------------------------------------------------------------------------- checkpoints


def _to_pure_dict(state: Any) -> dict:
    # flax >= 0.12 deprecates the State method in favour of the module-level function.
    fn = getattr(nnx, "to_pure_dict", None)
    return fn(state) if fn is not None else state.to_pure_dict()


def _replace_by_pure_dict(state: Any, pure: dict) -> None:
    fn = getattr(nnx, "replace_by_pure_dict", None)
    if fn is not None:
        fn(state, pure)
    else:
        state.replace_by_pure_dict(pure)


def state_pure_dict(model: FlowPolicy) -> dict:
    """``nnx.state(model).to_pure_dict()``: the dict the public release pickles per policy [P-8]."""
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    return _to_pure_dict(nnx.state(model))


def _flatten(tree: Any, prefix: tuple = ()) -> dict[tuple, Any]:
    out: dict[tuple, Any] = {}
    for k, v in tree.items():
        path = prefix + (k,)
        if isinstance(v, Mapping):
            out.update(_flatten(v, path))
        else:
            out[path] = v
    return out


def _path_str(path: tuple) -> str:
    return "/".join(str(p) for p in path)


def load_pure_dict(model: FlowPolicy, pure_dict: Mapping) -> FlowPolicy:
    """Validates ``pure_dict`` against ``model``'s parameter tree and loads it in place [P-8].

    ``pure_dict`` is a nested dict as written by ``nnx.state(model).to_pure_dict()``
    (layer indices as ints; digit strings are accepted too). Every key path must
    match, with the exact shape and a floating dtype and finite values; leaves are
    cast to the model's dtype and must still be finite after the cast (a float64
    ``1e39`` is rejected, as it would become ``inf`` in float32). Raises ``ValueError`` naming the key path (e.g.
    ``mlp_stack/0/adaln_1/kernel``) and the expected shape. Returns ``model``.
    """
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    if not isinstance(pure_dict, Mapping):
        raise ValueError(f"pure_dict must be a nested mapping of arrays, got {type(pure_dict).__name__}")
    state = nnx.state(model)
    expected = _flatten(_to_pure_dict(state))
    by_name = {tuple(str(p) for p in path): path for path in expected}

    given: dict[tuple, Any] = {}
    for path, leaf in _flatten(pure_dict).items():
        key = tuple(str(p) for p in path)
        if key not in by_name:
            # A leaf where the model has a subtree is also "unexpected" at this path.
            raise ValueError(f"pure_dict has unexpected key '{_path_str(key)}' (not a parameter of this FlowPolicy)")
        if key in given:  # e.g. layer 0 given both as 0 and as "0"
            raise ValueError(f"pure_dict gives key '{_path_str(key)}' twice (as {path!r} and another spelling)")
        given[key] = leaf
    for key, path in by_name.items():
        if key not in given:
            shape = tuple(expected[path].shape)
            raise ValueError(f"pure_dict is missing key '{_path_str(key)}' (expected shape {shape})")

    loaded: dict[tuple, jax.Array] = {}
    for key, path in by_name.items():
        ref = expected[path]
        name = f"pure_dict['{_path_str(key)}']"
        try:
            arr = np.asarray(given[key])
        except Exception as exc:  # noqa: BLE001 - any non-array leaf is a format error
            raise ValueError(f"{name} must be an array of shape {tuple(ref.shape)}") from exc
        if tuple(arr.shape) != tuple(ref.shape):
            raise ValueError(f"{name} has shape {tuple(arr.shape)}, expected shape {tuple(ref.shape)}")
        if not np.issubdtype(arr.dtype, np.floating):
            raise ValueError(f"{name} must have a floating dtype, got {arr.dtype}")
        if not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} must contain only finite values")
        # Finite in float64 may still overflow the parameter dtype (1e39 -> inf in float32): check after the cast.
        with np.errstate(over="ignore"):
            cast = arr.astype(ref.dtype)
        if not np.all(np.isfinite(cast)):
            raise ValueError(f"{name} must contain only finite values within the range of {np.dtype(ref.dtype)} "
                             f"(the parameter dtype)")
        loaded[path] = jnp.asarray(cast)

    nested: dict = {}
    for path, arr in loaded.items():
        node = nested
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = arr
    _replace_by_pure_dict(state, nested)
    nnx.update(model, state)
    return model


def load_checkpoint(model: FlowPolicy, path: str | os.PathLike) -> FlowPolicy:
    """Loads a public-format ``bc`` checkpoint (a pickled pure dict) into ``model`` [P-8].

    The file is unpickled, so only load files you trust. Public layout:
    ``<run>/<epoch>/policies/<level_name>.pkl``, e.g. ``worlds_l_grasp_easy.pkl``.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint file, got {path!r}")
    try:
        with open(path, "rb") as f:
            pure = pickle.load(f)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError) as exc:
        raise ValueError(f"{os.fspath(path)}: not a readable pickled checkpoint ({type(exc).__name__}: {exc})") from exc
    return load_pure_dict(model, pure)

