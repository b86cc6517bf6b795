"""Mapping the flipped flow-time convention in JAX (spec chapter V, 06-conventions.md).

Twin of ``softrtc.reference.conventions``: t' = 1 - t, u = -v ([V-1]) and the
blended flipped time t~'_j = (1 - w_j) t' ([V-3]). Element-wise, any shape.
"""

from __future__ import annotations

import jax

from . import _validate as v


def to_flipped_time(t) -> jax.Array:
    """t' = 1 - t ([V-1])."""
    return 1.0 - v.array("t", t, lo=0.0, hi=1.0)


def from_flipped_time(t_flipped) -> jax.Array:
    """t = 1 - t' ([V-1])."""
    return 1.0 - v.array("t_flipped", t_flipped, lo=0.0, hi=1.0)


def from_flipped_velocity(u) -> jax.Array:
    """v = -u ([V-1])."""
    return -v.array("u", u)


def to_flipped_velocity(vel) -> jax.Array:
    """u = -v ([V-1])."""
    return -v.array("v", vel)


def flipped_token_times(weights, t_flipped) -> jax.Array:
    """t~'_j = (1 - w_j) t' ([V-3]); weights [..., H], t_flipped a scalar, [...] (per example) or [..., H].

    Other shapes are rejected rather than broadcast ([N-7]).
    """
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.ndim < 1:
        raise ValueError(f"weights must have shape [..., H], got {list(w.shape)}")
    tf = v.array("t_flipped", t_flipped, lo=0.0, hi=1.0)
    if tf.ndim and tf.shape not in (w.shape, w.shape[:-1]):
        raise ValueError(f"t_flipped must be a scalar or have shape {list(w.shape[:-1])} or {list(w.shape)}, "
                         f"got {list(tf.shape)}")
    return (1.0 - w) * (tf[..., None] if tf.ndim and tf.shape != w.shape else tf)


def flipped_velocity_fn(flipped_fn):
    """Wrap a network in the flipped convention, ``u = flipped_fn(obs, x, t')``, as
    ``velocity_fn(obs, x, t) = -flipped_fn(obs, x, 1 - t)`` for the samplers ([V-1], [V-2])."""
    if not callable(flipped_fn):
        raise ValueError("flipped_fn must be callable as flipped_fn(obs, x, t_flipped) -> u")
    return lambda obs, x, t: -flipped_fn(obs, x, 1.0 - t)
