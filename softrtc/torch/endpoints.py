"""Endpoint rules in PyTorch (spec chapter E, 01-weights.md); twin of ``softrtc.reference.endpoints``.

Rules are the reference's :class:`EndpointRule` objects (validated when built,
[E-1]), or their dict form ``{"kind", "lam", "h_max", "length"}``
(:func:`rule_from_dict`). A Python delay gives a Python int, computed exactly
as the reference does ([E-2]); an integer tensor of delays (any shape, e.g.
``[B]``, one per example) gives an int64 tensor of the same shape and device,
with the delay-scaled ceiling evaluated in float64, which agrees with the
exact value for every ``lam`` with at most 12 significant digits while
``lam * d <= 4096`` (the float64 rounding error of the product stays below
``1e-12``, far from the ``1e-4`` of ``delta``).
"""

from __future__ import annotations

import math
from fractions import Fraction

import torch

from softrtc.reference.endpoints import (DELAY_SCALED_DELTA, MAX_WINDOW, RULES, EndpointRule, delay_scaled, fixed,
                                         hard, offset)

from . import _validate as v

__all__ = ["EndpointRule", "RULES", "delay_scaled", "offset", "fixed", "hard", "rule_from_dict", "check_rule",
           "endpoint"]


def rule_from_dict(rule) -> EndpointRule:
    """An EndpointRule from its dict form {kind, lam, h_max, length} ([E-1]); unknown keys are errors."""
    if not isinstance(rule, dict):
        raise ValueError(f"rule must be a dict with key 'kind' in {RULES}, got {type(rule).__name__}")
    extra = set(rule) - {"kind", "lam", "h_max", "length"}
    if extra:
        raise ValueError(f"rule has unknown keys {sorted(extra)}; allowed: kind, lam, h_max, length")
    return EndpointRule(rule.get("kind"), rule.get("lam"), rule.get("h_max"), rule.get("length"))


def check_rule(rule) -> EndpointRule:
    """An EndpointRule, or its dict form converted ([E-1])."""
    if isinstance(rule, dict):
        return rule_from_dict(rule)
    if not isinstance(rule, EndpointRule):
        raise ValueError(f"rule must be an EndpointRule or its dict form, got {type(rule).__name__}")
    return rule


def endpoint(rule, d):
    """Raw endpoint e(d) ([E-1]..[E-6]); ``d`` a Python int or an integer tensor of delays.

    >>> endpoint(delay_scaled(1.6, 10), 5), endpoint(delay_scaled(2.0, 5), torch.tensor([0, 1, 2, 3])).tolist()
    (8, [0, 2, 4, 5])
    """
    rule = check_rule(rule)
    d = v.delays("d", d, 0, MAX_WINDOW)
    if not isinstance(d, torch.Tensor):
        if d == 0:
            return 0  # [E-6]
        if rule.kind == "delay_scaled":
            # The float's exact value times d, less delta, then the ceiling ([E-2]).
            return min(math.ceil(Fraction(rule.lam) * d - DELAY_SCALED_DELTA), rule.h_max)
        if rule.kind == "offset":
            return min(d + rule.length, rule.h_max)
        return rule.length if rule.kind == "fixed" else d
    if rule.kind == "hard":
        return d.clone()
    if rule.kind == "delay_scaled":
        raw = torch.ceil(d.to(torch.float64) * rule.lam - float(DELAY_SCALED_DELTA)).to(torch.int64)
        e = torch.clamp(raw, max=rule.h_max)
    elif rule.kind == "offset":
        e = torch.clamp(d + rule.length, max=rule.h_max)
    else:
        e = torch.full_like(d, rule.length)
    return torch.where(d == 0, torch.zeros_like(e), e)  # [E-6]
