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
from .endpoints import EndpointRule, _endpoint, delay_scaled

SCHEDULES = ("zeros", "ones", "linear", "exp")
PARAMETRIZATIONS = ("rtc", "paper")
OVERFLOWS = ("clip", "zeros")


def schedule_value(schedule: str, x) -> np.ndarray:
    """Window schedule g(x) on relative positions x in [0, 1] ([W-3]).

    zeros: 0; ones: 1; linear: 1 - x; exp: u * expm1(u) / expm1(1) with u = 1 - x.
    All are non-increasing in x, take values in [0, 1], and (except zeros) g(0) = 1.
    """
    check_choice("schedule", schedule, SCHEDULES)
    return _schedule(schedule, check_array("x", x, lo=0.0, hi=1.0))


def _schedule(schedule: str, x: np.ndarray) -> np.ndarray:
    u = 1.0 - x
    return {"zeros": lambda: np.zeros_like(x),  # [W-3] g = 0
            "ones": lambda: np.ones_like(x),  # [W-3] g = 1
            "linear": lambda: u,  # [W-3] g = 1 - x
            # [W-3] g = u (e^u - 1) / (e - 1); expm1(1), not e - 1, makes g(0) exactly 1 in IEEE arithmetic.
            "exp": lambda: u * np.expm1(u) / np.expm1(1.0)}[schedule]()


def window_positions(d: int, e: int, parametrization: str = "rtc") -> np.ndarray:
    """Relative positions x_j of the window tokens j = d .. e-1 ([W-4], [W-5]).

    rtc:   x_j = (j - d + 1) / (e - d + 1), strictly inside (0, 1)
    paper: x_j = (j - d) / (e - d), so the first window token has x = 0
    """
    check_choice("parametrization", parametrization, PARAMETRIZATIONS)
    d = check_int("d", d, 0, MAX_HORIZON)
    return _positions(d, check_int("e", e, d, MAX_HORIZON), parametrization)


def _positions(d: int, e: int, parametrization: str) -> np.ndarray:
    j = np.arange(d, e, dtype=np.float64)
    if parametrization == "rtc":
        return (j - d + 1.0) / (e - d + 1.0)  # [W-4]
    return (j - d) / float(e - d) if e > d else j  # [W-5]


def prefix_weights(H: int, d: int, e: int, schedule: str = "linear",
                   parametrization: str = "rtc") -> np.ndarray:
    """Weights with committed prefix [0, d), window [d, e), free tail [e, H) ([W-1], [W-4], [W-5]).

    w_j = 1 for j < d; g(x_j) for d <= j < e; 0 for j >= e. Requires 0 <= d <= e <= H.
    """
    H = check_horizon(H)
    d = check_int("d", d, 0, H)
    e = check_int("e", e, d, H)
    check_choice("schedule", schedule, SCHEDULES)
    check_choice("parametrization", parametrization, PARAMETRIZATIONS)
    return _prefix(H, d, e, schedule, parametrization)


def _prefix(H: int, d: int, e: int, schedule: str, parametrization: str) -> np.ndarray:
    w = np.zeros(H, dtype=np.float64)  # [W-1] w_j = 0 on the free tail j >= e
    w[:d] = 1.0  # [W-1] w_j = 1 on the committed prefix j < d
    if e > d:  # [W-4] w_j = g(x_j) on the window d <= j < e (an empty window has no positions)
        w[d:e] = _schedule(schedule, _positions(d, e, parametrization))
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
    if s is not None:
        s = check_int("s", s, 1, H)  # checked when given, even where overflow="zeros" leaves it unused
    if overflow == "clip" and s is None:
        raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
    return _effective_endpoint(H, d, e, s, overflow)


def _effective_endpoint(H: int, d: int, e: int, s: int | None, overflow: str) -> int:
    if overflow == "clip":
        return max(d, min(max(e, d), H - s))  # [W-6] e* = max(d, min(e, o)), o = H - s
    return max(e, d)  # [W-2] e* = max(e, d)


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
    if s is not None:
        s = check_int("s", s, 1, H)
    if window.overflow == "clip" and s is None:
        raise ValueError("s (execute horizon, 1 <= s <= H) is required when overflow='clip'")
    return _soft(H, d, window, s)


def _soft(H: int, d: int, window: SoftWindow, s: int | None) -> np.ndarray:
    e = _endpoint(window.rule, d)  # [E-1] the rule's raw endpoint; e(d) = d <= H for "hard"
    e_star = _effective_endpoint(H, d, e, s, window.overflow)  # [W-2], [W-6]
    return _prefix(H, d, e_star, window.schedule, window.parametrization)  # [W-7]


def hard_weights(H: int, d: int) -> np.ndarray:
    """Hard RTC weights 1[j < d] ([W-8])."""
    H = check_horizon(H)
    return _hard(H, check_int("d", d, 0, H))


def _hard(H: int, d: int) -> np.ndarray:
    return (np.arange(H) < d).astype(np.float64)  # [W-8] w_j = 1[j < d]


def check_weights(name: str, w, H: int) -> np.ndarray:
    """Validate a weight vector: shape [H], finite, values in [0, 1] ([W-1])."""
    return check_array(name, w, shape=(check_horizon(H),), lo=0.0, hi=1.0)
