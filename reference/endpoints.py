"""Endpoint rules e(d) of the soft-conditioning window (spec chapter E, 01-weights.md).

The endpoint bounds the soft window ``d <= j < e``. Three rules are defined:

>>> [endpoint(delay_scaled(lam=2, h_max=5), d) for d in range(6)]
[0, 2, 4, 5, 5, 5]
>>> [endpoint(offset(length=2, h_max=8), d) for d in range(6)]
[0, 3, 4, 5, 6, 7]
>>> [endpoint(fixed(h=5), d) for d in range(6)]
[0, 5, 5, 5, 5, 5]

A rule's raw endpoint may lie below ``d`` (e.g. ``fixed(h=3)`` at ``d=4``);
[W-2] in weights.py turns it into the effective endpoint.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction

from ._validate import check_choice, check_int, check_real

RULES = ("delay_scaled", "fixed", "offset", "hard")
# [E-1] The parameters each rule has; the others must be absent.
RULE_PARAMETERS = {"delay_scaled": ("lam", "h_max"), "offset": ("length", "h_max"), "fixed": ("length",),
                   "hard": ()}

# Upper bound on h_max, L and h; far above any chunk horizon used in practice,
# it keeps vector files and JAX tables finite.
MAX_WINDOW = 4096

# [E-2] delta of the delay-scaled ceiling: ceil(lam * d - delta) is the endpoint the decimal lam means.
DELAY_SCALED_DELTA = Fraction(1, 10000)


@dataclass(frozen=True)
class EndpointRule:
    """An endpoint rule ([E-1]). Build one with :func:`delay_scaled`,
    :func:`fixed`, :func:`offset` or :func:`hard`; fields not used by a rule are None."""

    kind: str
    lam: float | None = None
    h_max: int | None = None
    length: int | None = None

    def __post_init__(self):
        check_choice("kind", self.kind, RULES)
        for name in ("lam", "h_max", "length"):
            if name not in RULE_PARAMETERS[self.kind] and getattr(self, name) is not None:
                raise ValueError(f"{name} is not a parameter of the {self.kind!r} rule and must be None, "
                                 f"got {getattr(self, name)!r}")
        # Parameters are stored as Python float / int, so a NumPy scalar given here (np.float32(1.6),
        # np.int64(5)) is read by its value, as delay_scaled() reads it.
        for name in RULE_PARAMETERS[self.kind]:
            value = getattr(self, name)
            if name == "lam":
                value = check_real("lam", value, lo=0.0, hi=float(MAX_WINDOW))
            else:
                value = check_int(name, value, 0, MAX_WINDOW)
            object.__setattr__(self, name, value)

    def bound(self) -> int:
        """Largest endpoint the rule can return for any d (used to check e <= H)."""
        if self.kind in ("delay_scaled", "offset"):
            return self.h_max
        if self.kind == "fixed":
            return self.length
        return MAX_WINDOW  # hard: e(d) = d, bounded by d itself

    def to_dict(self) -> dict:
        return {k: v for k, v in self.__dict__.items() if v is not None}


def delay_scaled(lam: float, h_max: int) -> EndpointRule:
    """[E-2] e(d) = min(ceil(lam * d - 1e-4), h_max), exact on the value of lam.

    >>> [endpoint(delay_scaled(1.6, 16), d) for d in range(6)]
    [0, 2, 4, 5, 7, 8]
    """
    return EndpointRule("delay_scaled", lam=float(check_real("lam", lam, 0.0, float(MAX_WINDOW))),
                        h_max=check_int("h_max", h_max, 0, MAX_WINDOW))


def offset(length: int, h_max: int) -> EndpointRule:
    """[E-3] e(d) = min(d + L, h_max) for d > 0."""
    return EndpointRule("offset", length=check_int("length", length, 0, MAX_WINDOW),
                        h_max=check_int("h_max", h_max, 0, MAX_WINDOW))


def fixed(h: int) -> EndpointRule:
    """[E-4] e(d) = h for d > 0 (a constant endpoint)."""
    return EndpointRule("fixed", length=check_int("h", h, 0, MAX_WINDOW))


def hard() -> EndpointRule:
    """[E-5] e(d) = d: no soft window, i.e. Hard training-time RTC."""
    return EndpointRule("hard")


def endpoint(rule: EndpointRule, d: int) -> int:
    """Raw endpoint e(d) of ``rule`` for delay ``d`` ([E-1]..[E-6]).

    [E-6] Every rule gives e(0) = 0, so the window vanishes at zero delay.
    """
    if not isinstance(rule, EndpointRule):
        raise ValueError(f"rule must be an EndpointRule, got {type(rule).__name__}")
    return _endpoint(rule, check_int("d", d, 0, MAX_WINDOW))


def _endpoint(rule: EndpointRule, d: int) -> int:
    if d == 0:
        return 0  # [E-6] e(0) = 0
    if rule.kind == "delay_scaled":
        # [E-2] e(d) = min(ceil(lam d - delta), h_max). Fraction(float) is the float's exact value, so the
        # product is exact; DELAY_SCALED_DELTA snaps a product the decimal lam makes an integer (1.6 * 5) back.
        return min(math.ceil(Fraction(rule.lam) * d - DELAY_SCALED_DELTA), rule.h_max)
    if rule.kind == "offset":
        return min(d + rule.length, rule.h_max)  # [E-3] e(d) = min(d + L, h_max)
    if rule.kind == "fixed":
        return rule.length  # [E-4] e(d) = h
    return d  # [E-5] e(d) = d
