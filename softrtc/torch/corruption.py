"""Per-token flow times and corruption in PyTorch (spec chapter C, 02-training.md); batched.

Shapes: ``actions``, ``noise`` ``[..., H, A]``; ``weights`` ``[H]`` (shared) or
the batch shape ``[..., H]`` (one row per example, [D-4]); ``tau`` a float or a
tensor of the batch shape ``[...]`` (one flow time per example, [C-1]). Results
keep the actions' dtype and device and carry gradients.
"""

from __future__ import annotations

import torch

from . import _validate as v

__all__ = ["token_times", "corrupt", "sample_tau"]


def _check_weights(w, H: int, batch: tuple) -> torch.Tensor:
    w = v.real_tensor("weights", w, lo=0.0, hi=1.0)
    if tuple(w.shape) not in ((H,), (*batch, H)):
        raise ValueError(f"weights must have shape [{H}] or {[*batch, H]}, got {list(w.shape)}")
    return w


def _check_time(name: str, t, batch: tuple, like: torch.Tensor):
    """A float in [0, 1] (kept a float) or a tensor of shape ``batch`` (or a scalar tensor)."""
    if isinstance(t, torch.Tensor):
        t = v.real_tensor(name, t, lo=0.0, hi=1.0)
        if t.dim() and tuple(t.shape) != tuple(batch):
            raise ValueError(f"{name} must be a scalar or have the batch shape {list(batch)}, got {list(t.shape)}")
        return t.to(like.dtype)[..., None] if t.dim() else t.to(like.dtype)
    return v.real(name, t, 0.0, 1.0)


def token_times(weights, t, convention: str = "data_at_1") -> torch.Tensor:
    """Per-token times: t_j = w_j + (1 - w_j) t ([C-1], [S-3]); flipped, t'_j = (1 - w_j) t' ([V-3]).

    ``weights [..., H]``; ``t`` a float or a tensor of the batch shape ``[...]``.
    """
    v.convention(convention)
    w = v.real_tensor("weights", weights, min_ndim=1, lo=0.0, hi=1.0)
    tt = _check_time("t", t, tuple(w.shape[:-1]), w)
    return w + (1.0 - w) * tt if convention == "data_at_1" else (1.0 - w) * tt


def corrupt(actions, noise, weights, tau, convention: str = "data_at_1"):
    """(x, times): x_j = tau_j A_j + (1 - tau_j) eps_j with tau_j = w_j + (1 - w_j) tau ([C-1], [C-2]).

    Flipped ([V-1], [V-3]): tau'_j = (1 - w_j) tau', x_j = tau'_j eps_j + (1 - tau'_j) A_j. With w = 0 it
    is the ordinary interpolant bitwise ([C-3]). ``times`` has the weights' batch shape ``[..., H]``.
    """
    v.convention(convention)
    a = v.real_tensor("actions", actions, min_ndim=2)
    n = v.real_tensor("noise", noise, expected=tuple(a.shape))
    batch, H = tuple(a.shape[:-2]), a.shape[-2]
    w = _check_weights(weights, H, batch).to(a.dtype)
    tt = _check_time("tau", tau, batch, a)
    if convention == "data_at_1":
        tj = w + (1.0 - w) * tt
        x = tj[..., None] * a + (1.0 - tj[..., None]) * n
    else:
        tj = (1.0 - w) * tt
        x = tj[..., None] * n + (1.0 - tj[..., None]) * a
    if tj.shape != (*batch, H):
        tj = tj.expand(*batch, H)
    return x, tj


def sample_tau(batch: int, generator: torch.Generator, *, dtype=None, device=None) -> torch.Tensor:
    """One flow time per example, tau ~ U[0, 1) ([C-1]), ``[batch]`` from an explicit generator ([N-9]).

    The flipped convention draws the same uniform: t' ~ U[0, 1) describes the same distribution.
    """
    from .delays import check_generator

    batch = v.integer("batch", batch, 1, 1 << 24)
    g = check_generator(generator)
    kw = v.float_kw(dtype, device)
    return torch.rand(batch, generator=g, dtype=kw["dtype"], device=g.device).to(kw["device"] or g.device)
