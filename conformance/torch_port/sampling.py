"""Euler samplers in the spec's time convention: noise at t = 0, data at t = 1 ([S-1]..[S-5], [G-2]..[G-5])."""

from __future__ import annotations

import math

import torch

from .checks import integer, real, tensor


def _inputs(field, obs, noise, prior=None, weights=None, T=1):
    x = tensor("noise", noise, shape=(field.H, field.A))
    obs = tensor("obs", obs, ndim=1)
    y = None if prior is None else tensor("prior", prior, shape=(field.H, field.A))
    w = None if weights is None else tensor("weights", weights, shape=(field.H,), lo=0.0, hi=1.0)
    return obs, x, y, w, integer("T", T, 1, 1 << 16)


def naive_sample(field, obs, noise, T: int):
    """x += v(obs, x, t_k) / T with one time for every token ([S-2]). Returns (chunk, trace)."""
    obs, x, _, _, T = _inputs(field, obs, noise, T=T)
    trace = []
    for k in range(T):
        t = torch.full((field.H,), k / T)
        v = field(obs, x, t)
        nxt = x + v / T
        trace.append({"state": x, "time": t, "velocity": v, "next_state": nxt})
        x = nxt
    return x, trace


def rtc_sample(field, obs, noise, prior, weights, T: int):
    """Training-time RTC: blend toward the prior, per-token time, Euler step, no final blend ([S-3]..[S-5])."""
    obs, x, y, w, T = _inputs(field, obs, noise, prior, weights, T)
    wc = w[:, None]
    trace = []
    for k in range(T):
        xb = wc * y + (1.0 - wc) * x
        tb = w + (1.0 - w) * (k / T)
        v = field(obs, xb, tb)
        nxt = xb + v / T
        trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": v, "next_state": nxt})
        x = nxt
    return x, trace


def guidance_weight(t: float, beta: float = 5.0) -> float:
    """min(c (t^2 + (1-t)^2) / (1-t)^2, beta), c = (1-t)/t, c(0) = inf ([G-4])."""
    t = real("t", t, 0.0, 1.0, hi_open=True)
    beta = real("max_guidance", beta, 1e-300, math.inf)
    c = math.inf if t == 0.0 else (1.0 - t) / t
    return min(c * (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2, beta)


def guided_sample(field, obs, noise, prior, weights, T: int, beta: float = 5.0):
    """Inference-time RTC (guided inpainting) with one autograd VJP per step ([G-2]..[G-5])."""
    obs, x, y, w, T = _inputs(field, obs, noise, prior, weights, T)
    wc = w[:, None]
    trace = []
    for k in range(T):
        t = k / T
        tv = torch.full((field.H,), t)

        def denoise(xx):
            return xx + (1.0 - t) * field(obs, xx, tv)  # x1 = x + (1 - t) v

        v = field(obs, x, tv)
        x1 = x + (1.0 - t) * v
        err = wc * (y - x1)
        _, g = torch.autograd.functional.vjp(denoise, x, err)  # g = (dx1/dx)^T err
        lam = guidance_weight(t, beta)
        vg = v + lam * g
        nxt = x + vg / T
        trace.append({"state": x, "time": tv, "velocity": v, "denoised": x1, "error": err, "vjp": g,
                      "guidance_weight": lam, "guided_velocity": vg, "next_state": nxt})
        x = nxt
    return x, trace
