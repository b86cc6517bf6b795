"""Inference-time RTC of Black et al. 2025: guided inpainting (spec chapter G, 03-inference.md).

Per Euler step k with t = t_k and the base policy's scalar time:

    v       = v(obs, x, t)
    x1      = x + (1 - t) v                       denoised estimate      [G-2]
    err     = W (Y - x1)                          weighted error         [G-3]
    g       = (d x1 / d x)^T err = err + (1 - t) (dv/dx)^T err           [G-3]
    lam     = min(c (t^2 + (1-t)^2) / (1-t)^2, beta), c = (1-t)/t         [G-4]
    x       = x + (v + lam g) / T                                        [G-5]

with c = +inf at t = 0, so lam = beta there. Guidance weights W come from
weights.prefix_weights(H, d, H - s, schedule): "hard" uses zeros, "soft" exp ([G-1]).
At t = 1/2, c = 1 and (t^2 + (1-t)^2) / (1-t)^2 = 2; at t = 0 the cap beta:

    >>> guidance_weight(0.5), guidance_weight(0.0), guidance_weight(0.9, max_guidance=2.0)
    (2.0, 5.0, 2.0)
"""

from __future__ import annotations

import math

import numpy as np

from ._validate import check_array, check_bool, check_choice, check_horizon, check_int, check_real
from .sampler import MAX_STEPS, _euler_times, field_dims, field_output
from .weights import _prefix, check_weights

MAX_GUIDANCE = 5.0
GUIDANCE_SCHEDULES = {"hard": "zeros", "soft": "exp"}


def guidance_prefix_weights(H: int, s: int, d: int, variant: str) -> np.ndarray:
    """Guidance weights W: start = d, end = H - s, zeros (hard) or exp (soft) schedule ([G-1])."""
    H = check_horizon(H)
    s = check_int("s", s, 1, H)
    d = check_int("d", d, 0, H - s)
    check_choice("variant", variant, tuple(GUIDANCE_SCHEDULES))
    return _prefix(H, d, H - s, GUIDANCE_SCHEDULES[variant], "rtc")  # [G-1] W: start d, end H - s


def guidance_weight(t: float, max_guidance: float = MAX_GUIDANCE) -> float:
    """lam(t) = min(c (t^2 + (1-t)^2) / (1-t)^2, beta), c = (1-t)/t, c(0) = inf ([G-4])."""
    t = check_real("t", t, 0.0, 1.0, hi_open=True)
    return _guidance_weight(t, check_real("max_guidance", max_guidance, 0.0, lo_open=True))


def _guidance_weight(t: float, beta: float) -> float:
    c = math.inf if t == 0.0 else (1.0 - t) / t  # [G-4] c = (1 - t) / t, c(0) = inf
    inv_r2 = (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2  # [G-4] 1 / r^2 = (t^2 + (1 - t)^2) / (1 - t)^2
    return min(c * inv_r2, beta)  # [G-4] lam = min(c / r^2, beta)


def guided_sample(field, obs, noise, prior, weights, num_steps: int,
                  max_guidance: float = MAX_GUIDANCE, return_trace: bool = False):
    """Guided (inpainting) sampler of inference-time RTC ([G-2]..[G-5]).

    ``field`` must be callable as field(obs, x, t) and provide
    field.vjp(obs, x, t, cotangent) (the VJP of v in x).
    """
    check_guided_field(field)
    x = check_array("noise", noise, ndim=2)
    obs = check_array("obs", obs, ndim=1)
    field_dims(field, obs, x)
    return_trace = check_bool("return_trace", return_trace)
    y = check_array("prior", prior, shape=x.shape)
    w = check_weights("weights", weights, x.shape[0])
    T = check_int("num_steps", num_steps, 1, MAX_STEPS)
    beta = check_real("max_guidance", max_guidance, 0.0, lo_open=True)
    return _guided_sample(field, obs, x, y, w, T, beta, return_trace)


def check_guided_field(field) -> None:
    """The guided sampler's field: callable, with ``field.vjp(obs, x, t, cotangent)`` ([G-3])."""
    if not callable(field) or not callable(getattr(field, "vjp", None)):
        raise ValueError("field must be callable and provide field.vjp(obs, x, t, cotangent)")


def _guided_sample(field, obs, x, y, w, T: int, beta: float, return_trace: bool):
    w = w[:, None]
    trace = []
    for t in _euler_times(T):
        tv = np.full(x.shape[0], t)
        v = field_output("field", field(obs, x, tv), x.shape)  # [G-2] scalar time t_k
        x1 = x + (1.0 - t) * v  # [G-2] x1 = x + (1 - t) v
        err = w * (y - x1)  # [G-3] err = W (Y - x1)
        g = err + (1.0 - t) * field_output("field.vjp", field.vjp(obs, x, tv, err), x.shape)  # [G-3] its pull-back
        lam = _guidance_weight(t, beta)  # [G-4]
        vg = v + lam * g
        nxt = x + vg / T  # [G-5] x <- x + (v + lam g) / T
        if return_trace:
            trace.append({"state": x, "time": tv, "velocity": v, "denoised": x1, "error": err,
                          "vjp": g, "guidance_weight": lam, "guided_velocity": vg, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x
