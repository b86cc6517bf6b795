"""Per-token flow times, weighted corruption and loss (spec chapters C and L), data at t = 1."""

from __future__ import annotations

import torch

from .checks import real, tensor

ETA = 1e-8


def token_times(weights, t: float) -> torch.Tensor:
    """t_j = w_j + (1 - w_j) t: a clamped token (w_j = 1) is clean ([C-1], [S-3])."""
    w = tensor("weights", weights, ndim=1, lo=0.0, hi=1.0)
    return w + (1.0 - w) * real("t", t, 0.0, 1.0)


def corrupt(actions, noise, weights, tau: float):
    """tau_j = w_j + (1 - w_j) tau; x_j = tau_j A_j + (1 - tau_j) eps_j ([C-1], [C-2])."""
    a = tensor("actions", actions, ndim=2)
    n = tensor("noise", noise, shape=tuple(a.shape))
    w = tensor("weights", weights, shape=(a.shape[0],), lo=0.0, hi=1.0)
    tau = real("tau", tau, 0.0, 1.0)
    tj = w + (1.0 - w) * tau
    return tj[:, None] * a + (1.0 - tj[:, None]) * n, tj


def loss(pred, actions, noise, weights) -> torch.Tensor:
    """sum_j (1 - w_j) ||v_j - (A_j - eps_j)||^2 / (sum_j (1 - w_j) + eta) ([L-1], [L-2])."""
    p = tensor("pred", pred, ndim=2)
    a = tensor("actions", actions, shape=tuple(p.shape))
    n = tensor("noise", noise, shape=tuple(p.shape))
    w = tensor("weights", weights, shape=(p.shape[0],), lo=0.0, hi=1.0)
    per_token = ((p - (a - n)) ** 2).sum(dim=-1)  # squared L2 over the action dimension
    m = 1.0 - w
    return (m * per_token).sum() / (m.sum() + ETA)  # eta keeps an all-clamped chunk at 0, not 0/0


def batch_loss(preds, actions, noise, weights, example_loss=loss) -> torch.Tensor:
    """Unweighted mean of per-example losses ([L-3]); weights [B, H], one vector per example."""
    p = tensor("preds", preds, ndim=3)
    if p.shape[0] == 0:
        raise ValueError("preds must have batch size >= 1")
    a = tensor("actions", actions, shape=tuple(p.shape))
    n = tensor("noise", noise, shape=tuple(p.shape))
    w = tensor("weights", weights, shape=tuple(p.shape[:2]), lo=0.0, hi=1.0)
    return torch.stack([example_loss(p[i], a[i], n[i], w[i]) for i in range(p.shape[0])]).mean()
