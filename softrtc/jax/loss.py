"""Weighted flow-matching loss in JAX (spec chapter L, 02-training.md); twin of ``softrtc.reference.loss``.

Per-example functions broadcast over leading batch dims; :func:`batch_loss`
is the unweighted batch mean ([L-3]). Float32 note: ``eta = 1e-8`` vanishes
next to ``sum_j (1 - w_j) >= 1`` in float32, it only matters when every token
is clamped (then the loss is exactly 0, [L-2]).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from . import _validate as v
from .corruption import corrupt
from .sampler import field_output

ETA = 1e-8


def _check_triple(pred, actions, noise):
    p = v.array("pred", pred)
    if p.ndim < 2:
        raise ValueError(f"pred must have shape [..., H, A], got {list(p.shape)}")
    a = v.array("actions", actions, shape=p.shape)
    n = v.array("noise", noise, shape=p.shape)
    return p, a, n


def token_errors(pred, actions, noise) -> jax.Array:
    """l_j = sum_a (v - (A - eps))^2 ([L-1]); [..., H, A] -> [..., H]; a concrete overflow raises ([N-15])."""
    return v.finite_result("pred", _token_errors(*_check_triple(pred, actions, noise)),
                           "the squared error || pred - (actions - noise) ||^2")


def _token_errors(p, a, n):
    return jnp.sum((p - (a - n)) ** 2, axis=-1)


def flow_matching_loss(pred, actions, noise, weights, eta=ETA) -> jax.Array:
    """Per-example loss sum_j (1 - w_j) l_j / (sum_j (1 - w_j) + eta) ([L-2], [L-4]); shape [...].

    A concrete loss that overflows the float type raises, naming ``pred`` ([N-15]).
    """
    return _checked_loss(pred, actions, noise, weights, eta, "pred")


def _checked_loss(pred, actions, noise, weights, eta, name):
    p, a, n = _check_triple(pred, actions, noise)
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.shape != p.shape[:-1]:
        raise ValueError(f"weights must have shape {list(p.shape[:-1])}, got {list(w.shape)}")
    eta = v.real_value("eta", eta, 0.0, 1.0, lo_open=True)
    return v.finite_result(name, _weighted(p, a, n, w, eta), "the weighted sum of squared errors")


@jax.jit
def _weighted(pred, actions, noise, w, eta):
    # Checked by the callers; jitted so an eager call is one dispatch, not one per op.
    m = 1.0 - w
    return jnp.sum(m * _token_errors(pred, actions, noise), axis=-1) / (jnp.sum(m, axis=-1) + eta)


def batch_loss(preds, actions, noise, weights, eta=ETA) -> jax.Array:
    """Unweighted mean of per-example losses ([L-3]); arrays [B, H, A], weights [B, H], B >= 1.

    A concrete loss that overflows the float type raises, naming ``preds`` ([N-15]).
    """
    p = v.array("preds", preds, ndim=3)
    if p.shape[0] == 0:
        raise ValueError("preds must have batch size >= 1, got 0")
    per_example = _checked_loss(p, actions, noise, weights, eta, "preds")
    return v.finite_result("preds", _mean(per_example), "the mean of the per-example losses")


@jax.jit
def _mean(x):
    return jnp.mean(x)


def rtc_loss(velocity_fn, obs, actions, noise, weights, tau, eta=ETA) -> jax.Array:
    """Batch training loss of training-time RTC ([C-1], [C-2], [L-1]..[L-3]).

    Corrupts ``actions [B, H, A]`` with ``noise``, per-example ``weights [B, H]``
    and flow times ``tau [B]``, evaluates ``velocity_fn(obs [B, O], x [B, H, A],
    t [B, H]) -> v [B, H, A]`` at the per-token times, and returns the batch mean.
    """
    if not callable(velocity_fn):
        raise ValueError("velocity_fn must be callable as velocity_fn(obs, x, t) -> v [B, H, A]")
    B = jnp.shape(actions)[0] if jnp.ndim(actions) == 3 else None
    if B is None:
        raise ValueError(f"actions must have shape [B, H, A], got {list(jnp.shape(actions))}")
    if tuple(jnp.shape(tau)) != (B,):
        raise ValueError(f"tau must have shape [B={B}] (one flow time per example), got {list(jnp.shape(tau))}")
    if tuple(jnp.shape(weights))[:1] != (B,) or jnp.ndim(weights) != 2:
        raise ValueError(f"weights must have shape [B={B}, H], got {list(jnp.shape(weights))}")
    # obs is checked although only velocity_fn reads it: a mis-shaped or non-finite observation is an
    # error whatever the field does with it ([N-7]).
    obs = v.array("obs", obs, ndim=2)
    if obs.shape[0] != B:
        raise ValueError(f"obs must have shape [B={B}, O], got {list(obs.shape)}")
    x, tj = corrupt(actions, noise, weights, tau)
    pred = field_output("velocity_fn", velocity_fn(obs, x, tj), x)
    return batch_loss(pred, actions, noise, weights, eta)
