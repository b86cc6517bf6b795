"""Endpoint rules and token weights (spec chapters E and W), the guidance weights of [G-1] and the
weights of each method ([S-6]).

Rules and windows are plain dicts, the same shape the conformance vectors use:
rule = {"kind": "delay_scaled", "lam": 2.0, "h_max": 5} (or offset with "length" = L,
fixed with "length" = h, hard); window = {"rule", "schedule", "parametrization", "overflow"}.
"""

from __future__ import annotations

import math
from fractions import Fraction

import torch

from .checks import DTYPE, choice, integer, real

MAX_WINDOW = 4096
SCHEDULES = ("zeros", "ones", "linear", "exp")


def endpoint(rule: dict, d: int) -> int:
    """Raw endpoint e(d) ([E-1]..[E-6]); e(0) = 0 for every rule."""
    if not isinstance(rule, dict):
        raise ValueError("rule must be a dict with a 'kind'")
    kind = choice("rule.kind", rule.get("kind"), ("delay_scaled", "offset", "fixed", "hard"))
    used = {"delay_scaled": ("lam", "h_max"), "offset": ("length", "h_max"), "fixed": ("length",), "hard": ()}[kind]
    for name in ("lam", "h_max", "length"):  # [E-1]: a parameter the rule does not have must be absent
        if name not in used and rule.get(name) is not None:
            raise ValueError(f"{name} is not a parameter of the {kind!r} rule")
    d = integer("d", d, 0, MAX_WINDOW)
    if kind == "delay_scaled":
        lam = real("lam", rule.get("lam"), 0.0, MAX_WINDOW)
        h_max = integer("h_max", rule.get("h_max"), 0, MAX_WINDOW)
        # [E-2]: exact product of the float's value (Fraction), less delta = 1e-4, then the ceiling.
        return 0 if d == 0 else min(math.ceil(Fraction(lam) * d - Fraction(1, 10000)), h_max)
    if kind == "offset":
        L = integer("length", rule.get("length"), 0, MAX_WINDOW)
        h_max = integer("h_max", rule.get("h_max"), 0, MAX_WINDOW)
        return 0 if d == 0 else min(d + L, h_max)
    if kind == "fixed":
        h = integer("length", rule.get("length"), 0, MAX_WINDOW)
        return 0 if d == 0 else h
    return d


def _schedule(name: str, x: torch.Tensor) -> torch.Tensor:
    """g(x) of [W-3]."""
    if name == "zeros":
        return torch.zeros_like(x)
    if name == "ones":
        return torch.ones_like(x)
    u = 1.0 - x
    # expm1(1) in the denominator, as in [W-3], so that g(0) is exactly 1.
    return u if name == "linear" else u * torch.expm1(u) / torch.expm1(torch.ones((), dtype=u.dtype))


def prefix_weights(H: int, d: int, e: int, schedule: str = "linear", parametrization: str = "rtc") -> torch.Tensor:
    """1 on [0, d), g(x_j) on [d, e), 0 on [e, H) ([W-1], [W-4], [W-5])."""
    H = integer("H", H, 1, MAX_WINDOW)
    d = integer("d", d, 0, H)
    e = integer("e", e, d, H)
    choice("schedule", schedule, SCHEDULES)
    choice("parametrization", parametrization, ("rtc", "paper"))
    w = torch.zeros(H, dtype=DTYPE)
    w[:d] = 1.0
    if e > d:
        j = torch.arange(d, e, dtype=torch.float64)
        # rtc: x = (j - d + 1) / (e - d + 1) keeps every window token editable; paper starts at x = 0.
        x = (j - d + 1) / (e - d + 1) if parametrization == "rtc" else (j - d) / (e - d)
        w[d:e] = _schedule(schedule, x).to(DTYPE)
    return w


def check_window(H: int, window: dict) -> tuple:
    """A window dict checked whole: its rule ([E-1]), schedule, parametrization, overflow, and an
    endpoint bound (h_max, or h of "fixed") of at most H. Returns (rule, schedule, parametrization, overflow)."""
    if not isinstance(window, dict) or "rule" not in window:
        raise ValueError("window must be a dict with keys rule, schedule, parametrization, overflow")
    rule = window["rule"]
    schedule = choice("schedule", window.get("schedule", "linear"), SCHEDULES)
    par = choice("parametrization", window.get("parametrization", "rtc"), ("rtc", "paper"))
    overflow = choice("overflow", window.get("overflow", "clip"), ("clip", "zeros"))
    endpoint(rule, 0)  # validates the rule's parameters, whatever the delay
    kind = rule["kind"]
    bound = rule["h_max"] if kind in ("delay_scaled", "offset") else rule["length"] if kind == "fixed" else 0
    if bound > H:
        raise ValueError(f"window endpoint bound (h_max or h) must be <= H={H}, got {bound}")
    return rule, schedule, par, overflow


def soft_weights(H: int, d: int, window: dict, s=None) -> torch.Tensor:
    """Soft RTC weights ([W-2], [W-6], [W-7])."""
    H = integer("H", H, 1, MAX_WINDOW)
    d = integer("d", d, 0, H)
    rule, schedule, par, overflow = check_window(H, window)
    e = endpoint(rule, d)
    e_star = max(min(e, H), d)  # [W-2]: the committed prefix stays clamped when e < d
    if s is not None:
        s = integer("s", s, 1, H)  # checked whenever given, also where "zeros" leaves it unused
    if overflow == "clip":
        if s is None:
            raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
        e_star = max(d, min(e_star, H - s))  # [W-6]: no window past the previous chunk's end
    return prefix_weights(H, d, e_star, schedule, par)


def hard_weights(H: int, d: int) -> torch.Tensor:
    """1[j < d] ([W-8])."""
    H = integer("H", H, 1, MAX_WINDOW)
    d = integer("d", d, 0, H)
    return (torch.arange(H) < d).to(DTYPE)


def guidance_weights(H: int, s: int, d: int, variant: str) -> torch.Tensor:
    """Inference-time RTC weights: start d, end H - s, zeros (hard) or exp (soft) ([G-1])."""
    H = integer("H", H, 1, MAX_WINDOW)
    s = integer("s", s, 1, H)
    d = integer("d", d, 0, H - s)
    sched = {"hard": "zeros", "soft": "exp"}[choice("variant", variant, ("hard", "soft"))]
    return prefix_weights(H, d, H - s, sched, "rtc")


METHODS = ("naive", "inference_hard", "inference_soft", "train_hard", "train_soft")
# The default window of [W-7]: the paper's rule and schedule with this spec's rtc and clip.
DEFAULT_WINDOW = {"rule": {"kind": "delay_scaled", "lam": 2.0, "h_max": 5}, "schedule": "linear",
                  "parametrization": "rtc", "overflow": "clip"}


def method_weights(method: str, H: int, s: int, d: int, window=None) -> torch.Tensor:
    """Token weights of a method for delay d ([S-6]); the request is checked whole ([S-8]).

    d must be executable, 0 <= d <= min(s, H - s) ([X-1]), for every method; a
    given window is checked for every method, the default one is resolved by
    train_soft only.
    """
    choice("method", method, METHODS)
    H = integer("H", H, 1, MAX_WINDOW)
    s = integer("s", s, 1, H)
    d = integer("d", d, 0, min(s, H - s))
    if window is not None:
        check_window(H, window)
    if method == "naive":
        return torch.zeros(H, dtype=DTYPE)
    if method in ("inference_hard", "inference_soft"):
        return guidance_weights(H, s, d, method.removeprefix("inference_"))
    if method == "train_hard":
        return hard_weights(H, d)
    return soft_weights(H, d, DEFAULT_WINDOW if window is None else window, s)
