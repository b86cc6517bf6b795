"""Weighted corruption in JAX (spec chapter C, 02-training.md); twin of ``softrtc.reference.corruption``.

Batched by broadcasting: ``weights [..., H]``, ``tau [...]``, ``actions`` and
``noise [..., H, A]`` with the same leading dims (or use ``vmap``). ``tau`` has
exactly the weights' batch shape or is one shared scalar; a ``[1]`` tau is not
broadcast ([N-7]).
"""

from __future__ import annotations

import jax

from . import _validate as v


def token_times(weights, tau) -> jax.Array:
    """tau_j = w_j + (1 - w_j) tau ([C-1]); weights [..., H], tau [...] -> [..., H]."""
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.ndim < 1:
        raise ValueError(f"weights must have shape [..., H], got {list(w.shape)}")
    return _token_times(w, _tau(w, tau))


def _tau(w, tau):
    tau = v.array("tau", tau, lo=0.0, hi=1.0)
    # tau is one flow time per example (the batch shape of the weights) or one shared scalar; a [1] or
    # [B, 1] tau would broadcast, which [N-7] forbids as it would hide a mis-shaped argument.
    if tau.shape not in ((), w.shape[:-1]):
        raise ValueError(f"tau must have the batch shape of the weights {list(w.shape[:-1])} (or be a scalar), "
                         f"got {list(tau.shape)}")
    return tau


@jax.jit
def _token_times(w, tau):
    return w + (1.0 - w) * tau[..., None]


def _corrupt(a, n, w, tau):
    # Not jitted as a whole: [C-3] compares with the interpolant evaluated op by op,
    # and a fused kernel may contract a * b + c into one rounding.
    tj = _token_times(w, tau)
    return tj[..., None] * a + (1.0 - tj[..., None]) * n, tj


def corrupt(actions, noise, weights, tau) -> tuple[jax.Array, jax.Array]:
    """Corrupted chunk x = tau_j A + (1 - tau_j) eps and times tau_j ([C-1], [C-2], [C-3]).

    actions, noise [..., H, A]; weights [..., H] in [0, 1]; tau [...] in [0, 1].
    With w = 0 the result is bitwise ``tau A + (1 - tau) eps`` ([C-3]).
    """
    a = v.array("actions", actions)
    if a.ndim < 2:
        raise ValueError(f"actions must have shape [..., H, A], got {list(a.shape)}")
    n = v.array("noise", noise, shape=a.shape)
    w = v.array("weights", weights, lo=0.0, hi=1.0)
    if w.shape != a.shape[:-1]:
        raise ValueError(f"weights must have shape {list(a.shape[:-1])}, got {list(w.shape)}")
    return _corrupt(a, n, w, _tau(w, tau))
