"""Input validation of the port ([N-7]): ValueError naming the argument and its allowed range."""

from __future__ import annotations

import math
import numbers

import torch

DTYPE = torch.float32


def integer(name, value, lo=None, hi=None) -> int:
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value}")
    return int(value)


def real(name, value, lo, hi, hi_open=False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite real number, got {value!r}")
    v = float(value)
    if v < lo or v > hi or (hi_open and v == hi):
        raise ValueError(f"{name} must lie in [{lo}, {hi}{')' if hi_open else ']'}, got {v}")
    return v


def choice(name, value, allowed):
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
    return value


def tensor(name, value, shape=None, ndim=None, lo=None, hi=None) -> torch.Tensor:
    """A finite float32 tensor of the given shape (None entries are free)."""
    try:
        t = torch.as_tensor(value, dtype=DTYPE)
    except (TypeError, ValueError, RuntimeError) as exc:
        raise ValueError(f"{name} must be a numeric array") from exc
    if ndim is not None and t.dim() != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {list(t.shape)}")
    if shape is not None and (t.dim() != len(shape) or any(s is not None and s != n for s, n in zip(shape, t.shape))):
        raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must contain only finite values")
    if t.numel() and ((lo is not None and t.min() < lo) or (hi is not None and t.max() > hi)):
        raise ValueError(f"{name} values must lie in [{lo}, {hi}]")
    return t
