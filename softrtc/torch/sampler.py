"""Euler samplers in PyTorch: naive and training-time RTC (spec chapter S, 03-inference.md); batched.

``velocity_fn(obs, x [B, H, A], t [B, H]) -> [B, H, A]`` is any callable or
``nn.Module`` with per-token time (``obs`` is passed through untouched, so it
may be a tensor ``[B, ...]`` or a dict of them). ``noise`` is ``[B, H, A]``,
``prior`` ``[B, H, A]``, ``weights`` ``[H]`` (shared) or ``[B, H]`` (one delay
per example). ``convention="data_at_1"`` runs the spec's time (t_k = k / T,
``x <- x~ + v / T``); ``"noise_at_1"`` the flipped one natively (t'_k = 1 - k / T,
blended time (1 - w) t', ``x <- x~ - u / T``, [V-2], [V-3]).

The training-time samplers take ``step`` ([S-10]): ``"algorithm1"`` (the
paper's, default) or ``"consistent"`` (window tokens blended once, moved by
``(1 - w) v / T``); for weights in {0, 1} the two are bitwise equal ([S-11]).

Precomputed conditioning ([PT-6]): for a ``model`` with ``time_conditioning(t)``
and ``apply_conditioned(obs_enc, x, cond)`` (and optionally ``encode_obs(obs)``),
the blended times of every step depend on the weights only ([S-3]), so
:func:`step_conditioning` computes all T steps' time conditioning in one call and
the ``*_conditioned`` samplers reuse it; :func:`conditioning_table` does it once
for every delay of a weight table.
"""

from __future__ import annotations

import torch

from softrtc.reference.sampler import STEPS, check_step

from . import _validate as v

__all__ = ["STEPS", "euler_times", "blend", "naive_sample", "rtc_sample", "step_times", "step_conditioning",
           "conditioning_table", "naive_sample_conditioned", "rtc_sample_conditioned"]


def euler_times(T: int, convention: str = "data_at_1", *, dtype=None, device=None) -> torch.Tensor:
    """t_k = k / T ([S-1]), or t'_k = 1 - k / T flipped ([V-2]); shape [T]."""
    T = v.integer("T", T, 1, v.MAX_STEPS)
    v.convention(convention)
    t = torch.arange(T, **v.float_kw(dtype, device)) / T
    return t if convention == "data_at_1" else 1.0 - t


def _check_fn(fn):
    if not callable(fn):
        raise ValueError("velocity_fn must be callable as velocity_fn(obs, x [B, H, A], t [B, H]) -> [B, H, A]")


def check_batch(obs, noise, prior=None, weights=None, T=None):
    """Sampler inputs ([N-7]): noise [B, H, A] (B >= 1), obs with B rows when a tensor, prior of noise's
    shape, weights [H] or [B, H] in [0, 1], T in [1, 2^16]."""
    x = v.real_tensor("noise", noise, ndim=3)
    B, H, _ = x.shape
    if B < 1:
        raise ValueError("noise must have batch size B >= 1, got 0")
    if isinstance(obs, torch.Tensor) and (obs.dim() < 1 or obs.shape[0] != B):
        raise ValueError(f"obs must have B={B} rows (the batch of noise), got shape {list(obs.shape)}")
    y = None if prior is None else v.real_tensor("prior", prior, expected=tuple(x.shape)).to(x.dtype)
    w = None
    if weights is not None:
        w = v.real_tensor("weights", weights, lo=0.0, hi=1.0).to(x.dtype)
        if tuple(w.shape) not in ((H,), (B, H)):
            raise ValueError(f"weights must have shape [{H}] or [{B}, {H}], got {list(w.shape)}")
    T = None if T is None else v.integer("T", T, 1, v.MAX_STEPS)
    return x, y, w, T


def blend(x, prior, weights) -> torch.Tensor:
    """x~ = w Y + (1 - w) x token-wise ([S-3]); weights [H] or x's batch shape [..., H]."""
    x = v.real_tensor("x", x, min_ndim=2)
    y = v.real_tensor("prior", prior, expected=tuple(x.shape))
    w = v.real_tensor("weights", weights, lo=0.0, hi=1.0)
    if tuple(w.shape) not in ((x.shape[-2],), tuple(x.shape[:-1])):
        raise ValueError(f"weights must have shape [{x.shape[-2]}] or {list(x.shape[:-1])}, got {list(w.shape)}")
    w = w[..., None]
    return w * y + (1.0 - w) * x


def naive_sample(velocity_fn, obs, noise, T: int, *, convention: str = "data_at_1", return_trace: bool = False):
    """x <- x + v(obs, x, t_k 1) / T, one time for every token ([S-1], [S-2]); flipped x <- x - u / T ([V-2])."""
    _check_fn(velocity_fn)
    x, _, _, T = check_batch(obs, noise, T=T)
    flip = v.convention(convention) == "noise_at_1"
    sign = -1.0 if flip else 1.0
    trace = []
    for k in range(T):
        t = torch.full(x.shape[:2], 1.0 - k / T if flip else k / T, dtype=x.dtype, device=x.device)
        vel = v.output("velocity_fn", velocity_fn(obs, x, t), x)
        nxt = x + sign * vel / T
        if return_trace:
            trace.append({"state": x, "time": t, "velocity": vel, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x


def _step_parts(wc, step: str):
    """Per-token step size c and the tokens blended before every step ([S-10]); None, None for Algorithm 1."""
    if step == "algorithm1":
        return None, None
    c = torch.where(wc < 1.0, 1.0 - wc, torch.ones_like(wc))  # [S-10] c = 1 - w; [S-11] c = 1 at w = 1
    return c, (wc == 0.0) | (wc == 1.0)  # [S-10] window tokens are blended at k = 0 only


def _carry(xb, x, again, k: int):
    """[S-10] A window token keeps its carried state after the first step."""
    return xb if again is None or k == 0 else torch.where(again, xb, x)


def _scaled(vel, c):
    """[S-4] v, or [S-10] c v; c = 1 gives v bit for bit ([S-11])."""
    return vel if c is None else c * vel


def rtc_sample(velocity_fn, obs, noise, prior, weights, T: int, *, convention: str = "data_at_1",
               return_trace: bool = False, step: str = "algorithm1"):
    """Training-time RTC: blend toward the prior, per-token time, Euler step, no final blend ([S-3]..[S-5]).

    ``step`` "algorithm1" (default) or "consistent" ([S-10]). With w = 0 it is the naive sampler
    bitwise under either step ([S-7], [S-11]).
    """
    _check_fn(velocity_fn)
    step = check_step(step)
    x, y, w, T = check_batch(obs, noise, prior, weights, T)
    if y is None or w is None:
        raise ValueError("rtc_sample needs a prior [B, H, A] and weights [H] or [B, H], got None")
    flip = v.convention(convention) == "noise_at_1"
    wb = w.expand(x.shape[:2])
    wc = wb[..., None]
    c, again = _step_parts(wc, step)
    trace = []
    for k in range(T):
        xb = _carry(wc * y + (1.0 - wc) * x, x, again, k)
        tb = (1.0 - wb) * (1.0 - k / T) if flip else wb + (1.0 - wb) * (k / T)
        vel = v.output("velocity_fn", velocity_fn(obs, xb, tb), x)
        nxt = xb - _scaled(vel, c) / T if flip else xb + _scaled(vel, c) / T
        if return_trace:
            trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": vel, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x


# --------------------------------------------------------------------------- precomputed conditioning


def _check_model(model):
    if not (callable(getattr(model, "time_conditioning", None)) and callable(getattr(model, "apply_conditioned", None))):
        raise ValueError("model must provide time_conditioning(t) and apply_conditioned(obs, x, cond)")


def _at(cond, k):
    return tuple(c[k] for c in cond) if isinstance(cond, (tuple, list)) else cond[k]


def _leading(cond) -> int:
    first = cond[0] if isinstance(cond, (tuple, list)) else cond
    if not isinstance(first, torch.Tensor) or first.dim() < 1:
        raise ValueError("cond must be a tensor or a tuple of tensors with a leading step axis [T, ...]")
    return first.shape[0]


def step_times(weights, T: int, convention: str = "data_at_1") -> torch.Tensor:
    """Blended times of every step, [T, ..., H]: w + (1 - w) t_k, or (1 - w) t'_k flipped ([S-3], [V-3])."""
    w = v.real_tensor("weights", weights, min_ndim=1, lo=0.0, hi=1.0)
    t = euler_times(T, convention, **v.like(w)).reshape(-1, *([1] * w.dim()))
    return w + (1.0 - w) * t if convention == "data_at_1" else (1.0 - w) * t


def step_conditioning(model, weights, T: int, convention: str = "data_at_1"):
    """``model.time_conditioning`` of every step's blended times, one call: leaves [T, b, H, F] for weights
    [b, H]. Weights ``[1, 1]`` of zeros give the naive sampler's shared time, leaves [T, 1, 1, F]."""
    _check_model(model)
    return model.time_conditioning(step_times(weights, T, convention))


def conditioning_table(model, weight_table, T: int, convention: str = "data_at_1"):
    """Conditioning of every delay of a weight table [D, H]: leaves [D, T, 1, H, F]; row d serves
    :func:`rtc_sample_conditioned` for delay d, for any batch ([PT-6])."""
    wt = v.real_tensor("weight_table", weight_table, ndim=2, lo=0.0, hi=1.0)
    cond = step_conditioning(model, wt[:, None, :], T, convention)  # [T, D, 1, H, F]
    return tuple(c.transpose(0, 1) for c in cond) if isinstance(cond, (tuple, list)) else cond.transpose(0, 1)


def _encode(model, obs):
    enc = getattr(model, "encode_obs", None)
    return enc(obs) if callable(enc) else obs


def naive_sample_conditioned(model, obs, noise, T: int, cond=None, *, convention: str = "data_at_1"):
    """The naive sampler with the shared time's conditioning computed once for all steps ([S-2], [PT-6])."""
    _check_model(model)
    x, _, _, T = check_batch(obs, noise, T=T)
    flip = v.convention(convention) == "noise_at_1"
    if cond is None:
        cond = step_conditioning(model, torch.zeros(1, 1, **v.like(x)), T, convention)
    elif _leading(cond) != T:
        raise ValueError(f"cond must have a leading axis of T={T} steps, got {_leading(cond)}")
    o = _encode(model, obs)
    for k in range(T):
        vel = model.apply_conditioned(o, x, _at(cond, k))
        x = x - vel / T if flip else x + vel / T
    return x


def rtc_sample_conditioned(model, obs, noise, prior, weights, T: int, cond=None, *, convention: str = "data_at_1",
                           step: str = "algorithm1"):
    """Training-time RTC with every step's time conditioning computed ahead ([S-3]..[S-5], [PT-6]; ``step``
    [S-10]).

    ``cond`` (optional) is :func:`step_conditioning` of these weights, or a row of :func:`conditioning_table`.
    The blend is one fused multiply-add per step: x~ = (w Y) + (1 - w) x.
    """
    _check_model(model)
    step = check_step(step)
    x, y, w, T = check_batch(obs, noise, prior, weights, T)
    if y is None or w is None:
        raise ValueError("rtc_sample_conditioned needs a prior and weights, got None")
    flip = v.convention(convention) == "noise_at_1"
    if cond is None:
        cond = step_conditioning(model, w if w.dim() == 2 else w[None], T, convention)
    elif _leading(cond) != T:
        raise ValueError(f"cond must have a leading axis of T={T} steps, got {_leading(cond)}")
    o = _encode(model, obs)
    wc = w[..., None]
    wy, keep = wc * y, 1.0 - wc  # the prior's share is the same every step
    c, again = _step_parts(wc.expand(x.shape[:2] + (1,)), step)
    for k in range(T):
        xb = _carry(torch.addcmul(wy, keep, x), x, again, k)
        vel = _scaled(model.apply_conditioned(o, xb, _at(cond, k)), c)
        x = xb - vel / T if flip else xb + vel / T
    return x
