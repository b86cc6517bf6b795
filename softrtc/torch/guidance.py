"""Inference-time RTC (guided inpainting) in PyTorch (spec chapter G, 03-inference.md); batched.

Per step, with the base policy's shared time ([G-2]..[G-5]): ``x1 = x + (1 - t) v``,
``err = W (Y - x1)``, ``g = (d x1 / d x)^T err`` by one autograd VJP, ``x <- x + (v + lam(t) g) / T``.
In the flipped convention ([V-1]): ``x1 = x - t' u``, ``u_g = u - lam g``, ``x <- x - u_g / T``.
"""

from __future__ import annotations

import math

import torch

from . import _validate as v
from .sampler import check_batch
from .weights import prefix_weights

MAX_GUIDANCE = 5.0
GUIDANCE_SCHEDULES = {"hard": "zeros", "soft": "exp"}

__all__ = ["MAX_GUIDANCE", "guidance_weights", "guidance_weight", "guided_sample"]


def guidance_weights(H: int, s: int, d, variant: str, *, dtype=None, device=None) -> torch.Tensor:
    """W = prefix_weights(H, d, H - s, zeros | exp, "rtc") ([G-1]); d an int or an integer tensor, d <= H - s."""
    H = v.integer("H", H, 1, v.MAX_HORIZON)
    s = v.integer("s", s, 1, H)
    d = v.delays("d", d, 0, H - s, device=device)
    v.choice("variant", variant, tuple(GUIDANCE_SCHEDULES))
    e = H - s if not isinstance(d, torch.Tensor) else torch.full_like(d, H - s)
    return prefix_weights(H, d, e, GUIDANCE_SCHEDULES[variant], "rtc", dtype=dtype, device=device)


def guidance_weight(t: float, max_guidance: float = MAX_GUIDANCE, convention: str = "data_at_1") -> float:
    """lam(t) = min(c (t^2 + (1 - t)^2) / (1 - t)^2, beta), c = (1 - t) / t, c(0) = inf, t in [0, 1) ([G-4]).

    Flipped ([V-1]): the same value written in t' = 1 - t in (0, 1]: c = t' / (1 - t'),
    r^-2 = ((1 - t')^2 + t'^2) / t'^2, c = inf at t' = 1.
    """
    beta = v.real("max_guidance", max_guidance, 0.0, math.inf, lo_open=True)
    if v.convention(convention) == "data_at_1":
        t = v.real("t", t, 0.0, 1.0, hi_open=True)
        c = math.inf if t == 0.0 else (1.0 - t) / t
        return min(c * (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2, beta)
    tf = v.real("t", t, 0.0, 1.0, lo_open=True)
    c = math.inf if tf == 1.0 else tf / (1.0 - tf)
    return min(c * ((1.0 - tf) ** 2 + tf * tf) / (tf * tf), beta)


def guided_sample(velocity_fn, obs, noise, prior, weights, T: int, max_guidance: float = MAX_GUIDANCE, *,
                  convention: str = "data_at_1", return_trace: bool = False):
    """Guided inpainting with one VJP of ``velocity_fn`` per step ([G-2]..[G-5]); with W = 0 it is the
    naive sampler ([G-6]). The examples of a batch must not interact inside ``velocity_fn`` (no batch
    statistics), since one VJP serves the whole batch. The result carries no gradient."""
    if not callable(velocity_fn):
        raise ValueError("velocity_fn must be callable as velocity_fn(obs, x [B, H, A], t [B, H]) -> [B, H, A]")
    x, y, w, T = check_batch(obs, noise, prior, weights, T)
    if y is None or w is None:
        raise ValueError("guided_sample needs a prior [B, H, A] and weights [H] or [B, H], got None")
    flip = v.convention(convention) == "noise_at_1"
    beta = v.real("max_guidance", max_guidance, 0.0, math.inf, lo_open=True)
    wc = w[..., None]
    x = x.detach()
    trace = []
    for k in range(T):
        t = 1.0 - k / T if flip else k / T
        tv = torch.full(x.shape[:2], t, dtype=x.dtype, device=x.device)
        with torch.enable_grad():
            xg = x.detach().requires_grad_(True)
            vel = v.output("velocity_fn", velocity_fn(obs, xg, tv), x)
            x1g = xg - t * vel if flip else xg + (1.0 - t) * vel
            err = wc * (y - x1g.detach())
            (g,) = torch.autograd.grad(x1g, xg, grad_outputs=err)
        vel, x1 = vel.detach(), x1g.detach()
        lam = guidance_weight(t, beta, convention)
        vg = vel - lam * g if flip else vel + lam * g  # guidance pulls toward the prior, against u when flipped
        nxt = x - vg / T if flip else x + vg / T
        if return_trace:
            trace.append({"state": x, "time": tv, "velocity": vel, "denoised": x1, "error": err, "vjp": g,
                          "guidance_weight": lam, "guided_velocity": vg, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x
