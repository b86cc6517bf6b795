"""Method strings of the Kinetix evaluation and their rollout weight tables ([KE-2], [KE-3]).

A method string names a method of chapter S ([S-6]) and, for ``train_soft``,
its soft window; :func:`method_family` says which compiled rollout serves it.

>>> parse_method("train_soft:offset:1").label
'train_soft:offset:1'
"""

from __future__ import annotations

import dataclasses
import re
from typing import Any

import numpy as np

from softrtc.jax import methods as jmethods
from softrtc.reference import endpoints as ref_endpoints
from softrtc.reference import weights as ref_weights
from softrtc.reference._validate import check_int
from softrtc.reference.methods import METHODS

__all__ = ["MethodSpec", "parse_method", "PAPER_METHODS", "method_family", "FAMILY_SAMPLERS", "rollout_weight_table"]

_DISPLAY = {
    "naive": "Base Naive",
    "inference_hard": "Inference Hard RTC",
    "inference_soft": "Inference Soft RTC",
    "train_hard": "Train Hard RTC",
    "train_soft": "Train Soft RTC",
}


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """One evaluated method ([S-6], [KE-2]): a method name of chapter S and, for
    ``train_soft``, its soft window (reference :class:`~softrtc.reference.weights.SoftWindow`)."""

    method: str
    window: ref_weights.SoftWindow | None = None
    label: str = ""

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.window is not None:
            if not isinstance(self.window, ref_weights.SoftWindow):
                raise ValueError(f"window must be a softrtc.reference.weights.SoftWindow, got {type(self.window).__name__}")
            if self.method != "train_soft":
                raise ValueError(f"window is only used by method 'train_soft', got method {self.method!r}")
        if self.method == "train_soft" and self.window is None:
            object.__setattr__(self, "window", ref_weights.SoftWindow())
        if not isinstance(self.label, str):
            raise ValueError(f"label must be a string, got {type(self.label).__name__}")
        if not self.label:
            object.__setattr__(self, "label", self.method)
        # [KE-2], [KE-8]: a label that reads as a method string must name this method and window,
        # so a table row is never shown under another method's name; other labels are free text.
        try:
            name, window = _parse_method_parts(self.label)
        except ValueError:
            return
        if (name, window) != (self.method, self.window):
            raise ValueError(f"label {self.label!r} parses as method {name!r} with window {window}, "
                             f"but this MethodSpec is method {self.method!r} with window {self.window}; "
                             f"label must be a free-form name or a method string of this method and window")

    @property
    def display(self) -> str:
        """Row name in the style of the paper's main table."""
        base = _DISPLAY[self.method]
        return base if self.label == self.method else f"{base} ({self.label.split(':', 1)[1]})" \
            if self.label.startswith(self.method + ":") else self.label


def parse_method(text: str) -> MethodSpec:
    """Parse a method string ([KE-2]).

    ``naive``, ``inference_hard``, ``inference_soft``, ``train_hard``,
    ``train_soft`` (the paper's main window, delay-scaled lam=2, h_max=5,
    linear), or ``train_soft:<rule>:<params>`` with rule
    ``delay_scaled:LAM[:H_MAX]`` (default h_max 5), ``offset:L[:H_MAX]``
    (default 8), ``fixed:H``, ``hard``; optionally followed by
    ``:zeros`` to select ``overflow="zeros"`` ([W-6]); ``train_soft:zeros`` is the main window zero-padded.
    """
    name, window = _parse_method_parts(text)
    if window is None or text.strip() == name:
        return MethodSpec(name)
    return MethodSpec(name, window, label=text.strip())


def _parse_method_parts(text: Any) -> tuple:
    """``(method, window)`` of a method string ([KE-2]); ``window`` is None for methods other than train_soft."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"method must be a non-empty string such as 'train_soft:delay_scaled:2', got {text!r}")
    parts = [p.strip() for p in text.strip().split(":")]
    name = parts[0]
    if name not in METHODS:
        raise ValueError(f"method must start with one of {', '.join(METHODS)}, got {text!r}")
    if len(parts) == 1:
        return name, (ref_weights.SoftWindow() if name == "train_soft" else None)
    if name != "train_soft":
        raise ValueError(f"method {name!r} takes no window parameters, got {text!r}")
    overflow = "clip"
    if parts[-1] == "zeros":
        overflow, parts = "zeros", parts[:-1]
    if len(parts) == 1:  # train_soft:zeros, the main window with zero padding
        return "train_soft", ref_weights.SoftWindow(overflow=overflow)
    rule_name, args = (parts[1], parts[2:]) if len(parts) > 1 else ("delay_scaled", [])
    # Plain ASCII decimals only: Python's int/float would also take "1_0" (10) or other scripts' digits.
    if not all(re.fullmatch(r"[0-9]+(\.[0-9]+)?", a) for a in args):
        raise ValueError(f"method {text!r} is not a valid soft window: parameters must be plain decimal numbers")
    try:
        if rule_name == "delay_scaled" and 1 <= len(args) <= 2:
            rule = ref_endpoints.delay_scaled(float(args[0]), int(args[1]) if len(args) > 1 else 5)
        elif rule_name == "offset" and 1 <= len(args) <= 2:
            rule = ref_endpoints.offset(int(args[0]), int(args[1]) if len(args) > 1 else 8)
        elif rule_name == "fixed" and len(args) == 1:
            rule = ref_endpoints.fixed(int(args[0]))
        elif rule_name == "hard" and not args:
            rule = ref_endpoints.hard()
        else:
            raise ValueError("unknown rule or wrong number of parameters")
    except ValueError as exc:
        raise ValueError(
            f"method {text!r} is not a valid soft window: use train_soft:delay_scaled:LAM[:H_MAX], "
            f"train_soft:offset:L[:H_MAX], train_soft:fixed:H or train_soft:hard, optionally ':zeros' ({exc})"
        ) from None
    return "train_soft", ref_weights.SoftWindow(rule, overflow=overflow)


# The rows of the paper's main table whose method differs ([KE-2]); N=1 and N=2 are lam = 1, 2.
PAPER_METHODS = ("naive", "inference_hard", "inference_soft", "train_hard",
                 "train_soft:delay_scaled:1", "train_soft:delay_scaled:2")


def method_family(method: str) -> str:
    """``"rtc"`` for naive / train_hard / train_soft, ``"guided"`` for inference_* ([KE-3])."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    return "guided" if method.startswith("inference_") else "rtc"


# The sampler each family's compiled rollout runs ([KE-3]): the method's own weight table replaces the
# sampler's, so one program serves every method and window of the family.
FAMILY_SAMPLERS = {"rtc": "train_hard", "guided": "inference_hard"}


def rollout_weight_table(spec: MethodSpec, H: int, s: int) -> np.ndarray:
    """Weights per delay for the rollout ([KE-3]): ``[D, H]`` float32, D = min(s, H - s) + 1.

    Row ``d`` is the method's weights for delay ``d`` ([S-6], [G-1], [W-7],
    [W-8]; all zeros for ``naive``, [W-9]). The first chunk of every episode
    uses no row: it is the naive sampler ([X-2]).
    """
    if not isinstance(spec, MethodSpec):
        raise ValueError(f"spec must be a MethodSpec, got {type(spec).__name__}")
    H = check_int("H", H, 1)
    s = check_int("s", s, 1, H)
    return np.asarray(jmethods.method_weight_table(spec.method, H, s, spec.window), np.float32)
