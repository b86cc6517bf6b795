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


def real(name, value, lo, hi, hi_open=False, lo_open=False) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real) or not math.isfinite(float(value)):
        raise ValueError(f"{name} must be a finite real number, got {value!r}")
    v = float(value)
    if v < lo or v > hi or (hi_open and v == hi) or (lo_open and v == lo):
        raise ValueError(f"{name} must lie in {'(' if lo_open else '['}{lo}, {hi}{')' if hi_open else ']'}, got {v}")
    return v


def choice(name, value, allowed):
    if value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
    return value


def _as_tensor(name, value, dtype=None) -> torch.Tensor:
    """A real numeric tensor; boolean, complex and non-numeric arrays are rejected, not converted ([N-7])."""
    try:
        t = torch.as_tensor(value)
    except (TypeError, ValueError, RuntimeError, OverflowError) as exc:
        raise ValueError(f"{name} must be a numeric array") from exc
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name} must be a real numeric array, got dtype {t.dtype}")
    return t if dtype is None else t.to(dtype)


def _shape(name, t: torch.Tensor, shape=None, ndim=None) -> None:
    if ndim is not None and t.dim() != ndim:
        raise ValueError(f"{name} must have {ndim} dimensions, got shape {list(t.shape)}")
    if shape is not None and (t.dim() != len(shape) or any(s is not None and s != n for s, n in zip(shape, t.shape))):
        raise ValueError(f"{name} must have shape {list(shape)}, got {list(t.shape)}")


def tensor(name, value, shape=None, ndim=None, lo=None, hi=None) -> torch.Tensor:
    """A finite float32 tensor of the given shape (None entries are free)."""
    t = _as_tensor(name, value, DTYPE)
    _shape(name, t, shape, ndim)
    if not torch.isfinite(t).all():
        raise ValueError(f"{name} must contain only finite values")
    if t.numel() and ((lo is not None and t.min() < lo) or (hi is not None and t.max() > hi)):
        raise ValueError(f"{name} values must lie in [{lo}, {hi}]")
    return t


def int_tensor(name, value, shape=None, ndim=None, lo=None, hi=None) -> torch.Tensor:
    """An int64 tensor of the given shape with entries in [lo, hi].

    Only an integer dtype is accepted: a float array is rejected even where its
    values are whole numbers ([N-7], [CF-23]: a delay written 2.0 is an error).
    """
    t = _as_tensor(name, value)
    if t.is_floating_point():
        raise ValueError(f"{name} must hold integers, got dtype {t.dtype}")
    t = t.to(torch.int64)
    _shape(name, t, shape, ndim)
    if t.numel() and ((lo is not None and t.min() < lo) or (hi is not None and t.max() > hi)):
        raise ValueError(f"{name} entries must be integers in [{lo}, {hi}]")
    return t
