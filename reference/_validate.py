"""Input validation shared by every public reference function ([N-7]).

Each checker raises ``ValueError`` whose message names the argument and its
allowed range or shape. Nothing is clamped or coerced silently: an integer
argument given as ``2.0`` or ``True`` is rejected, not converted.
"""

from __future__ import annotations

import math
import numbers

import numpy as np

# [N-12] Chunk length H (and so every token index and delay d <= H) lies in [1, MAX_HORIZON].
MAX_HORIZON = 4096


def check_int(name: str, value, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` as ``int`` if it is an integer in ``[lo, hi]`` ([N-7])."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Integral, np.integer)):
        raise ValueError(f"{name} must be an integer{_range(lo, hi)}, got {value!r}")
    v = int(value)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"{name} must be an integer{_range(lo, hi)}, got {v}")
    return v


def check_horizon(H) -> int:
    """The chunk length ``H``: an integer in [1, MAX_HORIZON] ([N-1], [N-12])."""
    return check_int("H", H, 1, MAX_HORIZON)


def check_real(name: str, value, lo: float | None = None, hi: float | None = None,
               lo_open: bool = False, hi_open: bool = False) -> float:
    """Return ``value`` as ``float`` if finite and within the given bounds ([N-7])."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (numbers.Real, np.floating, np.integer)):
        raise ValueError(f"{name} must be a finite real number{_rrange(lo, hi, lo_open, hi_open)}, got {value!r}")
    try:
        v = float(value)
    except OverflowError:  # an int or Fraction beyond the float range
        raise ValueError(f"{name} must be a finite real number{_rrange(lo, hi, lo_open, hi_open)}, "
                         f"got a value too large for a float") from None
    bad = not math.isfinite(v)
    if lo is not None:
        bad |= v <= lo if lo_open else v < lo
    if hi is not None:
        bad |= v >= hi if hi_open else v > hi
    if bad:
        raise ValueError(f"{name} must be a finite real number{_rrange(lo, hi, lo_open, hi_open)}, got {v!r}")
    return v


def check_bool(name: str, value) -> bool:
    """Return ``value`` if it is a bool (Python or NumPy) ([N-7]); truthy stand-ins are rejected."""
    if not isinstance(value, (bool, np.bool_)):
        raise ValueError(f"{name} must be True or False, got {value!r}")
    return bool(value)


def check_choice(name: str, value, choices) -> str:
    """Return ``value`` if it is one of ``choices`` ([N-7])."""
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def real_array(name: str, value, kinds: str = "iuf") -> np.ndarray:
    """``value`` as a NumPy array whose dtype kind is one of ``kinds`` (default integer or float) ([N-7]).

    Not cast, and shape, range and finiteness are left to the caller. None,
    strings, ragged lists, and booleans, complex numbers or strings in an
    array (which NumPy would convert, or drop an imaginary part of) raise
    ValueError naming ``name``.
    """
    want = {"iuf": "a real numeric array (integer or float)", "iu": "an integer array",
            "b": "a boolean array"}.get(kinds, f"an array of dtype kind {kinds!r}")
    if value is None or isinstance(value, (str, bytes)):
        raise ValueError(f"{name} must be {want}, got {type(value).__name__}")
    try:
        raw = np.asarray(value)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ValueError(f"{name} must be {want}, got a ragged or non-numeric {type(value).__name__}") from exc
    if raw.dtype.kind not in kinds:
        raise ValueError(f"{name} must be {want}, got dtype {raw.dtype}")
    return raw


def check_array(name: str, value, shape: tuple | None = None, ndim: int | None = None,
                lo: float | None = None, hi: float | None = None, allow_empty: bool = False) -> np.ndarray:
    """Return ``value`` as a finite float64 array of the given shape ([N-7], [N-8]).

    ``shape`` may contain ``None`` for a free dimension. An axis of length 0 is
    rejected unless ``allow_empty`` ([N-1]: H >= 1, A >= 1).
    """
    arr = real_array(name, value).astype(np.float64)
    if ndim is not None and arr.ndim != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {arr.shape}")
    if shape is not None:
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = "[" + ", ".join("*" if s is None else str(s) for s in shape) + "]"
            raise ValueError(f"{name} must have shape {want}, got {list(arr.shape)}")
    if not allow_empty and 0 in arr.shape:
        raise ValueError(f"{name} must have at least one entry along every axis, got shape {list(arr.shape)}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must contain only finite values (no NaN or inf)")
    if lo is not None and arr.size and arr.min() < lo:
        raise ValueError(f"{name} values must lie in [{lo}, {hi}], got min {arr.min()}")
    if hi is not None and arr.size and arr.max() > hi:
        raise ValueError(f"{name} values must lie in [{lo}, {hi}], got max {arr.max()}")
    return arr


def finite_result(name: str, result, what: str):
    """``result`` unchanged when every entry is finite; else ValueError naming the input ``name`` ([N-15]).

    Called on what a function computed from inputs that were already checked finite, so a non-finite
    entry can only come from float64 overflow (or inf - inf after one); ``what`` names the quantity.
    """
    if not np.all(np.isfinite(result)):
        raise ValueError(f"{name} is too large in magnitude: {what} overflows float64 ({np.max(np.abs(result))}); "
                         f"a finite result needs smaller values ([N-15])")
    return result


def _range(lo, hi) -> str:
    if lo is not None and hi is not None:
        return f" in [{lo}, {hi}]"
    if lo is not None:
        return f" >= {lo}"
    if hi is not None:
        return f" <= {hi}"
    return ""


def _rrange(lo, hi, lo_open, hi_open) -> str:
    if lo is None and hi is None:
        return ""
    left = "(" if lo_open else "["
    right = ")" if hi_open else "]"
    return f" in {left}{'-inf' if lo is None else lo}, {'inf' if hi is None else hi}{right}"
