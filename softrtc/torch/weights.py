"""Token weights and schedules in PyTorch (spec chapter W, 01-weights.md); twin of ``softrtc.reference.weights``.

Every function takes its delays as a Python int (weights ``[H]``) or as an
integer tensor of any shape, e.g. ``[B]`` with one delay per example (weights
``[B, H]``); the endpoint ``e`` and the execute horizon ``s`` likewise. All
``H`` tokens are computed and the committed prefix, window and tail selected
with masks, so the functions are batched, run on the delays' device and trace
under ``torch.compile``. ``dtype`` (default torch's default float dtype) and
``device`` choose the result's; a tensor of delays decides the device.

:func:`weight_table` gives the ``[H + 1, H]`` table of every delay ``0 .. H``;
indexing it with a delay tensor is the training step's weights ([T-3] in the JAX
chapter; here [PT-4]).

>>> [round(x, 3) for x in prefix_weights(10, 2, 6, "linear").tolist()]
[1.0, 1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

import torch

from softrtc.reference.weights import OVERFLOWS, PARAMETRIZATIONS, SCHEDULES, SoftWindow

from . import _validate as v
from .endpoints import MAX_WINDOW, check_rule, endpoint

__all__ = ["SCHEDULES", "PARAMETRIZATIONS", "OVERFLOWS", "SoftWindow", "window_from_dict", "check_window",
           "schedule_value", "prefix_weights", "effective_endpoint", "soft_weights", "hard_weights", "weight_table"]


def window_from_dict(window) -> SoftWindow:
    """A SoftWindow from its dict form {rule, schedule, parametrization, overflow} ([W-7])."""
    if not isinstance(window, dict) or "rule" not in window:
        raise ValueError("window must be a dict with keys rule, schedule, parametrization, overflow")
    extra = set(window) - {"rule", "schedule", "parametrization", "overflow"}
    if extra:
        raise ValueError(f"window has unknown keys {sorted(extra)}")
    return SoftWindow(check_rule(window["rule"]), window.get("schedule", "linear"),
                      window.get("parametrization", "rtc"), window.get("overflow", "clip"))


def check_window(H: int, window) -> SoftWindow:
    """A SoftWindow (or its dict form) whose endpoint bound (h_max, or h of "fixed") is at most H ([E-1])."""
    if isinstance(window, dict):
        window = window_from_dict(window)
    if not isinstance(window, SoftWindow):
        raise ValueError(f"window must be a SoftWindow or its dict form, got {type(window).__name__}")
    if window.rule.kind != "hard" and window.rule.bound() > H:
        raise ValueError(f"window endpoint bound (h_max or h) must be <= H={H}, got {window.rule.bound()}")
    return window


def schedule_value(schedule: str, x: torch.Tensor) -> torch.Tensor:
    """g(x) of [W-3] on relative positions x in [0, 1] (any shape, x's dtype)."""
    v.choice("schedule", schedule, SCHEDULES)
    x = v.real_tensor("x", x, lo=0.0, hi=1.0)
    if schedule == "zeros":
        return torch.zeros_like(x)
    if schedule == "ones":
        return torch.ones_like(x)
    u = 1.0 - x
    if schedule == "linear":
        return u
    # expm1(1) in the denominator, the numerator's function, so that g(0) is exactly 1 ([W-3]).
    return u * torch.expm1(u) / torch.expm1(torch.ones((), dtype=u.dtype, device=u.device))


def _device(*items, device=None):
    for it in items:
        if isinstance(it, torch.Tensor):
            return it.device
    return device


def _as_long(x, device):
    return x if isinstance(x, torch.Tensor) else torch.tensor(x, dtype=torch.int64, device=device)


def _prefix(H: int, d, e, schedule: str, parametrization: str, dtype, device) -> torch.Tensor:
    """Masked weights for int64 tensors d, e of one shape (checked by the callers)."""
    j = torch.arange(H, device=device)
    d, e = d[..., None], e[..., None]
    jf, df, ef = j.to(dtype), d.to(dtype), e.to(dtype)
    if parametrization == "rtc":
        x = (jf - df + 1.0) / (ef - df + 1.0)
    else:  # paper: (j - d) / (e - d); the empty window (e = d) has no token to evaluate
        x = (jf - df) / torch.clamp(ef - df, min=1.0)
    inside = (j >= d) & (j < e)
    g = schedule_value(schedule, torch.where(inside, x, torch.zeros_like(x)).clamp(0.0, 1.0))
    one = torch.ones((), dtype=dtype, device=device)
    return torch.where(j < d, one, torch.where(inside, g, torch.zeros_like(g)))


def prefix_weights(H: int, d, e, schedule: str = "linear", parametrization: str = "rtc", *, dtype=None,
                   device=None) -> torch.Tensor:
    """1 on [0, d), g(x_j) on [d, e), 0 on [e, H) ([W-1], [W-3]..[W-5]); requires 0 <= d <= e <= H.

    ``d`` and ``e`` are ints or integer tensors of one shape (broadcast against each other).
    """
    H = v.integer("H", H, 1, MAX_WINDOW)
    v.choice("schedule", schedule, SCHEDULES)
    v.choice("parametrization", parametrization, PARAMETRIZATIONS)
    kw = v.float_kw(dtype, device)
    dev = _device(d, e, device=device)
    d = v.delays("d", d, 0, H, device=dev)
    e = v.delays("e", e, 0, H, device=dev)
    if not isinstance(d, torch.Tensor) and not isinstance(e, torch.Tensor):
        if e < d:
            raise ValueError(f"e must be an integer in [d={d}, {H}], got {e}")
    elif not v.compiling() and bool((_as_long(e, dev) < _as_long(d, dev)).any()):
        raise ValueError(f"e must be an integer in [d, {H}] entrywise, got an entry below d")
    d, e = torch.broadcast_tensors(_as_long(d, dev), _as_long(e, dev))
    return _prefix(H, d, e, schedule, parametrization, kw["dtype"], dev)


def effective_endpoint(H: int, d, e, s=None, overflow: str = "clip"):
    """e* = max(e, d) ([W-2]); under overflow="clip" also max(d, min(e*, H - s)) ([W-6]).

    ``s`` is checked whenever given ([W-7]); it is required by "clip".
    """
    H = v.integer("H", H, 1, MAX_WINDOW)
    v.choice("overflow", overflow, OVERFLOWS)
    if s is not None:
        s = v.integer("s", s, 1, H)
    if overflow == "clip" and s is None:
        raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
    if not isinstance(d, torch.Tensor):
        e_star = max(e, d)
        return max(d, min(e_star, H - s)) if overflow == "clip" else e_star
    e_star = torch.maximum(e, d)
    return torch.maximum(d, torch.clamp(e_star, max=H - s)) if overflow == "clip" else e_star


def soft_weights(H: int, d, window=None, s=None, *, dtype=None, device=None) -> torch.Tensor:
    """Soft RTC weights for delays d ([W-2], [W-6], [W-7]); window default ``SoftWindow()``.

    >>> [[round(x, 4) for x in row] for row in soft_weights(8, torch.tensor([1, 2]), SoftWindow(), 4).tolist()]
    [[1.0, 0.5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 0.6667, 0.3333, 0.0, 0.0, 0.0, 0.0]]
    """
    H = v.integer("H", H, 1, MAX_WINDOW)
    window = check_window(H, SoftWindow() if window is None else window)
    d = v.delays("d", d, 0, H, device=device)
    if s is not None:
        s = v.integer("s", s, 1, H)
    e = endpoint(window.rule, d)
    # the hard rule's e(d) = d never exceeds H; the others are bounded by h_max <= H (check_window)
    e_star = effective_endpoint(H, d, e, s, window.overflow)
    return prefix_weights(H, d, e_star, window.schedule, window.parametrization, dtype=dtype, device=device)


def hard_weights(H: int, d, *, dtype=None, device=None) -> torch.Tensor:
    """1[j < d] ([W-8])."""
    H = v.integer("H", H, 1, MAX_WINDOW)
    kw = v.float_kw(dtype, device)
    d = v.delays("d", d, 0, H, device=device)
    dev = _device(d, device=device)
    j = torch.arange(H, device=dev)
    return (j < _as_long(d, dev)[..., None]).to(kw["dtype"])


def weight_table(H: int, method: str, window=None, s=None, *, dtype=None, device=None) -> torch.Tensor:
    """Weights of every delay 0 .. H, shape [H + 1, H]: row d is the weights of delay d ([PT-4]).

    ``method``: "none" (zeros, [W-9]), "hard" ([W-8]) or "soft" ([W-7], with ``window`` and ``s``).
    Indexing the table with a delay tensor ``[B]`` gives the weights ``[B, H]`` of a batch.
    """
    H = v.integer("H", H, 1, MAX_WINDOW)
    v.choice("method", method, ("none", "hard", "soft"))
    d = torch.arange(H + 1, device=device)
    if method == "none":
        return torch.zeros(H + 1, H, **v.float_kw(dtype, device))
    if method == "hard":
        return hard_weights(H, d, dtype=dtype, device=device)
    return soft_weights(H, d, window, s, dtype=dtype, device=device)
