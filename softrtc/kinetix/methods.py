"""Method strings of the Kinetix evaluation and their rollout weight tables ([KE-2], [KE-3]).

A method string names a method of chapter S ([S-6]), for ``train_soft`` its
soft window, and optionally the training-time sampler's solver step ([S-10],
suffix ``:consistent``, [KE-13]); :func:`method_family` says which compiled
rollout serves it.

>>> parse_method("train_soft:offset:1").label
'train_soft:offset:1'
>>> parse_method("train_soft:delay_scaled:2:consistent").display
'Train Soft RTC (delay_scaled:2, consistent step)'
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
from softrtc.reference.methods import METHODS, check_method_step

__all__ = ["MethodSpec", "parse_method", "PAPER_METHODS", "method_family", "FAMILY_SAMPLERS", "rollout_weight_table",
           "CONSISTENT_SUFFIX"]

# [KE-13] The last part of a method string that selects the time-consistent solver step ([S-10]).
CONSISTENT_SUFFIX = "consistent"

_DISPLAY = {
    "naive": "Base Naive",
    "inference_hard": "Inference Hard RTC",
    "inference_soft": "Inference Soft RTC",
    "train_hard": "Train Hard RTC",
    "train_soft": "Train Soft RTC",
}


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """One evaluated method ([S-6], [KE-2]): a method name of chapter S, for ``train_soft`` its soft window
    (reference :class:`~softrtc.reference.weights.SoftWindow`), and the training-time sampler's solver
    step ([S-10], [KE-13]): ``"algorithm1"`` (default) or ``"consistent"``, which the guided methods
    refuse ([S-14])."""

    method: str
    window: ref_weights.SoftWindow | None = None
    label: str = ""
    step: str = "algorithm1"

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
        check_method_step(self.method, self.step)  # [S-14]: the guided methods take "algorithm1" only
        if not isinstance(self.label, str):
            raise ValueError(f"label must be a string, got {type(self.label).__name__}")
        if not self.label:
            object.__setattr__(self, "label", self.method + (":" + CONSISTENT_SUFFIX
                                                             if self.step == "consistent" else ""))
        # [KE-2], [KE-8], [KE-13]: a label that reads as a method string must name this method, window and
        # step, so a table row is never shown under another method's name; other labels are free text.
        try:
            name, window, step = _parse_method_parts(self.label)
        except ValueError:
            return
        if (name, window, step) != (self.method, self.window, self.step):
            raise ValueError(f"label {self.label!r} parses as method {name!r} with window {window} and step "
                             f"{step!r}, but this MethodSpec is method {self.method!r} with window {self.window} "
                             f"and step {self.step!r}; label must be a free-form name or a method string of this "
                             f"method, window and step")

    @property
    def display(self) -> str:
        """Row name in the style of the paper's main table; the consistent step is named last ([KE-13])."""
        base = _DISPLAY[self.method]
        if self.label == self.method:
            return base
        if not self.label.startswith(self.method + ":"):
            return self.label  # free text
        rest = self.label.split(":", 1)[1]
        if self.step == "consistent" and rest.endswith(CONSISTENT_SUFFIX):
            rest = rest[: -len(CONSISTENT_SUFFIX)].rstrip().rstrip(":").rstrip()
            rest = f"{rest}, consistent step" if rest else "consistent step"
        return f"{base} ({rest})"


def parse_method(text: str) -> MethodSpec:
    """Parse a method string ([KE-2], [KE-13]).

    ``naive``, ``inference_hard``, ``inference_soft``, ``train_hard``,
    ``train_soft`` (the paper's main window, delay-scaled lam=2, h_max=5,
    linear), or ``train_soft:<rule>:<params>`` with rule
    ``delay_scaled:LAM[:H_MAX]`` (default h_max 5), ``offset:L[:H_MAX]``
    (default 8), ``fixed:H``, ``hard``; optionally followed by
    ``:zeros`` to select ``overflow="zeros"`` ([W-6]); ``train_soft:zeros`` is the main window zero-padded.
    Last, ``:consistent`` selects the time-consistent solver step ([S-10]) for
    ``naive``, ``train_hard`` and ``train_soft`` (``train_soft:zeros:consistent``);
    the guided methods refuse it ([S-14]).
    """
    name, window, step = _parse_method_parts(text)
    if text.strip() == name:
        return MethodSpec(name)
    return MethodSpec(name, window if name == "train_soft" else None, label=text.strip(), step=step)


def _parse_method_parts(text: Any) -> tuple:
    """``(method, window, step)`` of a method string ([KE-2], [KE-13]); ``window`` is None for methods other
    than train_soft."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"method must be a non-empty string such as 'train_soft:delay_scaled:2', got {text!r}")
    parts = [p.strip() for p in text.strip().split(":")]
    name = parts[0]
    if name not in METHODS:
        raise ValueError(f"method must start with one of {', '.join(METHODS)}, got {text!r}")
    step = "algorithm1"
    if len(parts) > 1 and parts[-1] == CONSISTENT_SUFFIX:
        step, parts = "consistent", parts[:-1]
        if name.startswith("inference_"):
            raise ValueError(f"method {text!r} is not valid: the suffix ':consistent' selects the training-time "
                             f"sampler's solver step ([S-10]) and the guided method {name!r} has no blended step "
                             f"to change ([S-14]); use it with naive, train_hard or train_soft")
    if len(parts) == 1:
        return name, (ref_weights.SoftWindow() if name == "train_soft" else None), step
    if name != "train_soft":
        raise ValueError(f"method {name!r} takes no window parameters (only a last ':consistent' for the "
                         f"training-time sampler), got {text!r}")
    overflow = "clip"
    if parts[-1] == "zeros":
        overflow, parts = "zeros", parts[:-1]
    if len(parts) == 1:  # train_soft:zeros, the main window with zero padding
        return "train_soft", ref_weights.SoftWindow(overflow=overflow), step
    rule_name, args = (parts[1], parts[2:]) if len(parts) > 1 else ("delay_scaled", [])
    # Plain ASCII decimals only: Python's int/float would also take "1_0" (10) or other scripts' digits.
    if not all(re.fullmatch(r"[0-9]+(\.[0-9]+)?", a) for a in args):
        raise ValueError(f"method {text!r} is not a valid soft window: parameters must be plain decimal numbers"
                         f" (':zeros' and then ':consistent' come last, in that order)")
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
            f"train_soft:offset:L[:H_MAX], train_soft:fixed:H or train_soft:hard, optionally ':zeros', "
            f"then optionally ':consistent' ({exc})"
        ) from None
    return "train_soft", ref_weights.SoftWindow(rule, overflow=overflow), step


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
