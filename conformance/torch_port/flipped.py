"""The same rules in the flipped time convention of LeRobot / openpi's PyTorch code ([V-1]..[V-3]).

Flow time t' runs from 1 (noise) to 0 (data), x = t' eps + (1 - t') A, and the
network predicts u = eps - A, so t' = 1 - t and u = -v. Each function below is
written natively in that convention; adapter_flipped.py declares
time_convention = "noise_at_1" and the runner maps the results onto the spec.
"""

from __future__ import annotations

import math

import torch

from . import training
from .checks import real, tensor
from .sampling import _inputs

ETA = 1e-8


class FlippedField:
    """u(obs, x, t') of a field given in the spec's convention: u = -v(obs, x, 1 - t') ([V-1]).

    A model trained in the flipped convention would predict u directly; the
    conformance vectors define the field in spec time, so the port wraps it.
    """

    def __init__(self, field):
        self.field, self.H, self.A, self.O = field, field.H, field.A, field.O

    def __call__(self, obs, x, t_flipped):
        return -self.field(obs, x, 1.0 - t_flipped)


def token_times(weights, t_flipped: float) -> torch.Tensor:
    """t~'_j = (1 - w_j) t': a clamped token is clean (t' = 0) ([V-3])."""
    w = tensor("weights", weights, ndim=1, lo=0.0, hi=1.0)
    return (1.0 - w) * real("t", t_flipped, 0.0, 1.0)


def corrupt(actions, noise, weights, tau_flipped: float):
    """x_j = t'_j eps_j + (1 - t'_j) A_j with t'_j = (1 - w_j) tau' ([C-1], [C-2], [V-3])."""
    a = tensor("actions", actions, ndim=2)
    n = tensor("noise", noise, shape=tuple(a.shape))
    w = tensor("weights", weights, shape=(a.shape[0],), lo=0.0, hi=1.0)
    tj = (1.0 - w) * real("tau", tau_flipped, 0.0, 1.0)
    return tj[:, None] * n + (1.0 - tj[:, None]) * a, tj


def loss(pred_u, actions, noise, weights) -> torch.Tensor:
    """Same weighted loss with target u = eps - A ([L-1], [L-2])."""
    p = tensor("pred", pred_u, ndim=2)
    a = tensor("actions", actions, shape=tuple(p.shape))
    n = tensor("noise", noise, shape=tuple(p.shape))
    w = tensor("weights", weights, shape=(p.shape[0],), lo=0.0, hi=1.0)
    m = 1.0 - w
    return (m * ((p - (n - a)) ** 2).sum(dim=-1)).sum() / (m.sum() + ETA)


def batch_loss(preds_u, actions, noise, weights) -> torch.Tensor:
    """Unweighted mean over the batch of the flipped per-example losses ([L-3])."""
    return training.batch_loss(preds_u, actions, noise, weights, example_loss=loss)


def _times(T: int):
    # t'_k = 1 - k / T: from pure noise down to 1/T ([V-2]).
    return [1.0 - k / T for k in range(T)]


def naive_sample(ufield, obs, noise, T: int):
    """x <- x - u(obs, x, t') / T from t' = 1 down ([V-2])."""
    obs, x, _, _, T = _inputs(ufield, obs, noise, T=T)
    trace = []
    for tf in _times(T):
        t = torch.full((ufield.H,), tf)
        u = ufield(obs, x, t)
        nxt = x - u / T
        trace.append({"state": x, "time": t, "velocity": u, "next_state": nxt})
        x = nxt
    return x, trace


def rtc_sample(ufield, obs, noise, prior, weights, T: int):
    """Training-time RTC in flipped time: blend, t~' = (1 - w) t', step x~ - u / T ([S-3]..[S-5], [V-3])."""
    obs, x, y, w, T = _inputs(ufield, obs, noise, prior, weights, T)
    wc = w[:, None]
    trace = []
    for tf in _times(T):
        xb = wc * y + (1.0 - wc) * x
        tb = (1.0 - w) * tf
        u = ufield(obs, xb, tb)
        nxt = xb - u / T
        trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": u, "next_state": nxt})
        x = nxt
    return x, trace


def guidance_weight(t_flipped: float, beta: float = 5.0) -> float:
    """lam of [G-4] written in t': c = t' / (1 - t'), r^-2 = ((1 - t')^2 + t'^2) / t'^2; t' in (0, 1]."""
    tf = real("t", t_flipped, 0.0, 1.0)
    if tf == 0.0:
        raise ValueError("t (flipped time) must lie in (0, 1], got 0.0")
    beta = real("max_guidance", beta, 1e-300, math.inf)
    c = math.inf if tf == 1.0 else tf / (1.0 - tf)
    return min(c * ((1.0 - tf) ** 2 + tf * tf) / (tf * tf), beta)


def guided_sample(ufield, obs, noise, prior, weights, T: int, beta: float = 5.0):
    """Guided inpainting in flipped time: x1 = x - t' u, u_g = u - lam g, x <- x - u_g / T ([G-2]..[G-5])."""
    obs, x, y, w, T = _inputs(ufield, obs, noise, prior, weights, T)
    wc = w[:, None]
    trace = []
    for tf in _times(T):
        tv = torch.full((ufield.H,), tf)

        def denoise(xx):
            return xx - tf * ufield(obs, xx, tv)

        u = ufield(obs, x, tv)
        x1 = x - tf * u
        err = wc * (y - x1)
        _, g = torch.autograd.functional.vjp(denoise, x, err)
        lam = guidance_weight(tf, beta)
        ug = u - lam * g  # guidance pulls toward the prior, i.e. against u
        nxt = x - ug / T
        trace.append({"state": x, "time": tv, "velocity": u, "denoised": x1, "error": err, "vjp": g,
                      "guidance_weight": lam, "guided_velocity": ug, "next_state": nxt})
        x = nxt
    return x, trace
