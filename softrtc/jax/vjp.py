"""The policy's hand-written VJP rules and the switch that turns them off for ablations ([P-17], [P-19], [P-20], [B-12]).

Forward values are always those of the flax modules; only how a VJP with
respect to the network input is taken differs: LayerNorm by its closed form
([P-17]), products by stored transposed kernels ([P-19]), GELU by autodiff as
shipped or by a recomputing VJP ([P-20]). :func:`autodiff_vjps` selects each
choice while a policy function is traced.
"""

from __future__ import annotations

import contextlib

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from . import _validate as v

__all__ = ["layer_norm", "gelu", "autodiff_vjps"]


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
    x = v.float_input("x", x)
    if x.ndim < 1 or x.shape[-1] != norm.num_features:
        raise ValueError(f"x must have shape [..., {norm.num_features}] (the norm's num_features), "
                         f"got {tuple(x.shape)}")
    v.check_nonempty("x", x)
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
    x = v.float_input("x", x)
    v.check_nonempty("x", x)
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
