"""The masked flow-matching loss in PyTorch (spec chapter L, 02-training.md); batched, differentiable.

``pred``, ``actions``, ``noise`` ``[..., H, A]``; ``weights`` ``[H]`` or ``[..., H]``.
The spec's target is ``A - eps``; the flipped convention's ``eps - A`` ([V-1]).
"""

from __future__ import annotations

import torch

from . import _validate as v

ETA = 1e-8  # [L-2]: guards the all-clamped example only

__all__ = ["ETA", "token_errors", "loss", "batch_loss"]


def _inputs(pred, actions, noise, weights, min_ndim=2):
    p = v.real_tensor("pred", pred, min_ndim=min_ndim)
    a = v.real_tensor("actions", actions, expected=tuple(p.shape))
    n = v.real_tensor("noise", noise, expected=tuple(p.shape))
    w = v.real_tensor("weights", weights, lo=0.0, hi=1.0)
    if tuple(w.shape) not in ((p.shape[-2],), tuple(p.shape[:-1])):
        raise ValueError(f"weights must have shape [{p.shape[-2]}] or {list(p.shape[:-1])}, got {list(w.shape)}")
    return p, a.to(p.dtype), n.to(p.dtype), w.to(p.dtype)


def token_errors(pred, actions, noise, convention: str = "data_at_1") -> torch.Tensor:
    """l_j = sum_a (v_ja - (A_ja - eps_ja))^2, or with the target eps - A when flipped ([L-1], [V-1]).

    An l_j that overflows the dtype raises, naming ``pred`` ([N-15]).
    """
    v.convention(convention)
    p = v.real_tensor("pred", pred, min_ndim=2)
    a = v.real_tensor("actions", actions, expected=tuple(p.shape)).to(p.dtype)
    n = v.real_tensor("noise", noise, expected=tuple(p.shape)).to(p.dtype)
    return _errors(p, a, n, convention, "pred")


def _errors(p, a, n, convention, name):
    target = a - n if convention == "data_at_1" else n - a
    return v.finite_result(name, ((p - target) ** 2).sum(-1), "the squared error || pred - target ||^2")


def loss(pred, actions, noise, weights, convention: str = "data_at_1") -> torch.Tensor:
    """Per-example loss sum_j (1 - w_j) l_j / (sum_j (1 - w_j) + eta), shape ``pred.shape[:-2]`` ([L-2]).

    A scalar for one chunk ``[H, A]``; ``[B]`` for a batch. Clamped tokens (w = 1) get no gradient. A loss
    that overflows the dtype raises, naming ``pred`` ([N-15]).
    """
    return _loss(pred, actions, noise, weights, convention, "pred")


def _loss(pred, actions, noise, weights, convention, name):
    p, a, n, w = _inputs(pred, actions, noise, weights)
    m = 1.0 - w
    per_token = _errors(p, a, n, v.convention(convention), name)
    return v.finite_result(name, (m * per_token).sum(-1) / (m.sum(-1) + ETA), "the weighted sum of squared errors")


def batch_loss(preds, actions, noise, weights, convention: str = "data_at_1") -> torch.Tensor:
    """Unweighted mean over the batch of the per-example losses ([L-3]); ``preds [B, H, A]``, B >= 1.

    A loss that overflows the dtype raises, naming ``preds`` ([N-15]).
    """
    p = v.real_tensor("preds", preds, ndim=3)
    if p.shape[0] == 0:
        raise ValueError("preds must have batch size B >= 1, got 0")
    return v.finite_result("preds", _loss(p, actions, noise, weights, convention, "preds").mean(),
                           "the mean of the per-example losses")
