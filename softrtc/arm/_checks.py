"""Scalar checks of the arm's public functions ([N-7]) beyond the reference's integer and choice checks."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["is_real", "check_number"]


def is_real(x) -> bool:
    """A finite real scalar (Python or NumPy; no booleans); huge integers that overflow a float are not."""
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, float, np.integer, np.floating)):
        return False
    try:
        return math.isfinite(x)
    except (OverflowError, TypeError, ValueError):
        return False


def check_number(name: str, value, lo: float, hi: float, lo_open: bool = False) -> float:
    """``value`` as a float if it is a finite real number in ``[lo, hi]`` (``(lo, hi]`` with ``lo_open``) ([N-7])."""
    if not is_real(value) or not (lo < value if lo_open else lo <= value) or not value <= hi:
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    return float(value)
