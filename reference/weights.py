"""Token weights w_j in [0, 1] and their schedules (spec chapter W, 01-weights.md).

The same weights define the corrupted training input (corruption.py), the loss
mask (loss.py), the prior blend of the training-time RTC sampler (sampler.py)
and, with end = H - s, the guidance weights of inference-time RTC (guidance.py).

Worked example ([W-4], default "rtc" parametrization), d=2, e=6, H=10::

    >>> prefix_weights(10, 2, 6, "linear").round(3).tolist()
    [1.0, 1.0, 0.8, 0.6, 0.4, 0.2, 0.0, 0.0, 0.0, 0.0]

The paper's closed form ("paper" parametrization) starts the window at 1::

    >>> prefix_weights(10, 2, 6, "linear", "paper").round(3).tolist()
    [1.0, 1.0, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0, 0.0, 0.0]
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ._validate import MAX_HORIZON, check_array, check_choice, check_horizon, check_int
from .endpoints import EndpointRule, delay_scaled, endpoint

SCHEDULES = ("zeros", "ones", "linear", "exp")
PARAMETRIZATIONS = ("rtc", "paper")
OVERFLOWS = ("clip", "zeros")


def schedule_value(schedule: str, x) -> np.ndarray:
    """Window schedule g(x) on relative positions x in [0, 1] ([W-3]).

    zeros: 0; ones: 1; linear: 1 - x; exp: u * expm1(u) / expm1(1) with u = 1 - x.
    All are non-increasing in x, take values in [0, 1], and (except zeros) g(0) = 1.
    """
    check_choice("schedule", schedule, SCHEDULES)
    x = check_array("x", x, lo=0.0, hi=1.0)
    if schedule == "zeros":
        return np.zeros_like(x)
    if schedule == "ones":
        return np.ones_like(x)
    u = 1.0 - x
    if schedule == "linear":
        return u
    # Dividing by expm1(1) rather than e - 1 makes g(0) exactly 1 in IEEE arithmetic.
    return u * np.expm1(u) / np.expm1(1.0)


def window_positions(d: int, e: int, parametrization: str = "rtc") -> np.ndarray:
    """Relative positions x_j of the window tokens j = d .. e-1 ([W-4], [W-5]).

    rtc:   x_j = (j - d + 1) / (e - d + 1), strictly inside (0, 1)
    paper: x_j = (j - d) / (e - d), so the first window token has x = 0
    """
    check_choice("parametrization", parametrization, PARAMETRIZATIONS)
    d = check_int("d", d, 0, MAX_HORIZON)
    e = check_int("e", e, d, MAX_HORIZON)
    j = np.arange(d, e, dtype=np.float64)
    if parametrization == "rtc":
        return (j - d + 1.0) / (e - d + 1.0)
    return (j - d) / float(e - d) if e > d else j


def prefix_weights(H: int, d: int, e: int, schedule: str = "linear",
                   parametrization: str = "rtc") -> np.ndarray:
    """Weights with committed prefix [0, d), window [d, e), free tail [e, H) ([W-1], [W-4], [W-5]).

    w_j = 1 for j < d; g(x_j) for d <= j < e; 0 for j >= e. Requires 0 <= d <= e <= H.
    """
    H = check_horizon(H)
    d = check_int("d", d, 0, H)
    e = check_int("e", e, d, H)
    check_choice("schedule", schedule, SCHEDULES)
    w = np.zeros(H, dtype=np.float64)
    w[:d] = 1.0
    if e > d:  # an empty window has no positions to evaluate
        w[d:e] = schedule_value(schedule, window_positions(d, e, parametrization))
    return w


def effective_endpoint(H: int, d: int, e: int, s: int | None = None, overflow: str = "clip") -> int:
    """Effective endpoint e* of the soft window ([W-2], [W-6]).

    [W-2] e* = max(e, d): the committed prefix is always clamped, even when the
    rule's endpoint lies below d (d > h_max).
    [W-6] overflow="clip" (default) also caps the window at the overlap o = H - s,
    where the previous chunk still has actions: e* = max(d, min(e, o)).
    overflow="zeros" keeps e and the prior is zero-padded past o ([X-3]).
    """
    H = check_horizon(H)
    d = check_int("d", d, 0, H)
    e = check_int("e", e, 0, H)
    check_choice("overflow", overflow, OVERFLOWS)
    e_star = max(e, d)
    if s is not None:
        s = check_int("s", s, 1, H)  # checked when given, even where overflow="zeros" leaves it unused
    if overflow == "clip":
        if s is None:
            raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
        e_star = max(d, min(e_star, H - s))
    return e_star


@dataclass(frozen=True)
class SoftWindow:
    """Soft RTC window configuration ([W-7]).

    Default ([W-7]): the paper's main rule and schedule, e(d) = min(ceil(2 d), 5), linear,
    "rtc" parametrization, window clipped at the overlap.
    """

    rule: EndpointRule = field(default_factory=lambda: delay_scaled(2.0, 5))
    schedule: str = "linear"
    parametrization: str = "rtc"
    overflow: str = "clip"

    def __post_init__(self):
        if not isinstance(self.rule, EndpointRule):
            raise ValueError(f"rule must be an EndpointRule, got {type(self.rule).__name__}")
        check_choice("schedule", self.schedule, SCHEDULES)
        check_choice("parametrization", self.parametrization, PARAMETRIZATIONS)
        check_choice("overflow", self.overflow, OVERFLOWS)

    def to_dict(self) -> dict:
        return {"rule": self.rule.to_dict(), "schedule": self.schedule,
                "parametrization": self.parametrization, "overflow": self.overflow}


def check_window(H: int, window) -> SoftWindow:
    """A SoftWindow whose endpoint bound (h_max, or h of "fixed") is at most H ([E-1]).

    >>> check_window(4, SoftWindow())
    Traceback (most recent call last):
    ...
    ValueError: window endpoint bound (h_max or h) must be <= H=4, got 5
    """
    H = check_horizon(H)
    if not isinstance(window, SoftWindow):
        raise ValueError(f"window must be a SoftWindow, got {type(window).__name__}")
    if window.rule.kind != "hard" and window.rule.bound() > H:
        raise ValueError(f"window endpoint bound (h_max or h) must be <= H={H}, got {window.rule.bound()}")
    return window


def soft_weights(H: int, d: int, window: SoftWindow, s: int | None = None) -> np.ndarray:
    """Soft RTC token weights for delay d ([W-7]).

    >>> soft_weights(8, 3, SoftWindow(), s=4).round(3).tolist()
    [1.0, 1.0, 1.0, 0.5, 0.0, 0.0, 0.0, 0.0]
    """
    H = check_horizon(H)
    d = check_int("d", d, 0, H)
    window = check_window(H, window)
    e = min(endpoint(window.rule, d), H) if window.rule.kind == "hard" else endpoint(window.rule, d)
    e_star = effective_endpoint(H, d, e, s, window.overflow)
    return prefix_weights(H, d, e_star, window.schedule, window.parametrization)


def hard_weights(H: int, d: int) -> np.ndarray:
    """Hard RTC weights 1[j < d] ([W-8])."""
    H = check_horizon(H)
    d = check_int("d", d, 0, H)
    return (np.arange(H) < d).astype(np.float64)


def check_weights(name: str, w, H: int) -> np.ndarray:
    """Validate a weight vector: shape [H], finite, values in [0, 1] ([W-1])."""
    return check_array(name, w, shape=(check_horizon(H),), lo=0.0, hi=1.0)
