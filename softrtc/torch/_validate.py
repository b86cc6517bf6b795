"""Input checks of ``softrtc.torch`` ([N-7], [PT-2]): ValueError naming the argument and its range.

Shapes and dtypes are checked always (they are static under ``torch.compile``).
Values (finiteness, ranges) are checked on every eager call; while
``torch.compile`` traces a function they are skipped, because a check that
reads tensor values would split the compiled graph: inside a compiled region
the value ranges are the caller's promise, as they are under ``jax.jit`` for the
JAX twin.
"""

from __future__ import annotations

import math
import numbers

import numpy as np
import torch

MAX_HORIZON = 4096  # [N-12]
MAX_STEPS = 1 << 16
CONVENTIONS = ("data_at_1", "noise_at_1")  # [V-1]: the spec's time and the flipped time


def compiling() -> bool:
    """Whether torch.compile is tracing the caller (value checks are skipped then)."""
    return torch.compiler.is_compiling()


def integer(name: str, value, lo=None, hi=None) -> int:
    """A Python or NumPy integer (not a bool, not a float such as 2.0) in [lo, hi]."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {value}")
    return int(value)


def real(name: str, value, lo, hi, lo_open=False, hi_open=False) -> float:
    """A finite real number (not a bool) in the interval given."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a finite real number, got {value!r}")
    try:
        v = float(value)
    except OverflowError:
        v = math.inf
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo) or (hi_open and v == hi):
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}"
                         f"{')' if hi_open else ']'}, got {value!r}")
    return v


def choice(name: str, value, allowed):
    if not isinstance(value, str) or value not in allowed:
        raise ValueError(f"{name} must be one of {tuple(allowed)}, got {value!r}")
    return value


def convention(value) -> str:
    """The time convention of [V-1]: "data_at_1" (the spec's) or "noise_at_1" (flipped)."""
    return choice("convention", value, CONVENTIONS)


def as_tensor(name: str, value, dtype=None, device=None) -> torch.Tensor:
    """A real numeric tensor. A tensor keeps its dtype and device unless ``dtype``/``device`` are given;
    anything else is converted (float arrays to ``dtype`` or torch's default float dtype). Boolean,
    complex and non-numeric inputs are rejected, not converted ([N-7])."""
    if isinstance(value, torch.Tensor):
        t = value
    else:
        try:
            a = np.asarray(value)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name} must be a real numeric array") from exc
        if a.dtype.kind not in "iuf":
            raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
        t = torch.as_tensor(a)
        if t.is_floating_point() and dtype is None:
            t = t.to(torch.get_default_dtype())
    if t.dtype == torch.bool or t.is_complex():
        raise ValueError(f"{name} must be a real numeric array, got dtype {t.dtype}")
    if dtype is not None or device is not None:
        t = t.to(dtype=dtype if dtype is not None else t.dtype, device=device if device is not None else t.device)
    return t


def shape(name: str, t: torch.Tensor, expected=None, ndim=None, min_ndim=None) -> None:
    """Exact shape (None entries free), exact number of axes, or a minimum number of axes."""
    if ndim is not None and t.dim() != ndim:
        raise ValueError(f"{name} must have {ndim} axes, got shape {list(t.shape)}")
    if min_ndim is not None and t.dim() < min_ndim:
        raise ValueError(f"{name} must have at least {min_ndim} axes, got shape {list(t.shape)}")
    if expected is not None and (t.dim() != len(expected)
                                 or any(e is not None and e != n for e, n in zip(expected, t.shape))):
        raise ValueError(f"{name} must have shape {[('*' if e is None else e) for e in expected]}, "
                         f"got {list(t.shape)}")


def values(name: str, t: torch.Tensor, lo=None, hi=None) -> None:
    """Finite entries within [lo, hi]; skipped while torch.compile traces.

    One reduction and one host read per check on the common path (the comparison with both bounds
    is false for NaN, so it also rejects non-finite values); the message is worked out only on failure.
    """
    if compiling() or t.numel() == 0:
        return
    if lo is not None and hi is not None and math.isfinite(lo) and math.isfinite(hi):
        if bool(((t >= lo) & (t <= hi)).all()):
            return
    elif not t.is_floating_point() or bool(torch.isfinite(t).all()):
        if (lo is None or not bool((t < lo).any())) and (hi is None or not bool((t > hi).any())):
            return
    if t.is_floating_point() and not bool(torch.isfinite(t).all()):
        raise ValueError(f"{name} must contain only finite values")
    raise ValueError(f"{name} values must lie in [{lo}, {hi}], got min {float(t.min())}, max {float(t.max())}")


def real_tensor(name: str, value, expected=None, ndim=None, min_ndim=None, lo=None, hi=None, dtype=None,
                device=None) -> torch.Tensor:
    """A floating tensor (integer input becomes ``dtype`` or the default float dtype) of the given shape
    with finite values in [lo, hi]."""
    t = as_tensor(name, value, dtype, device)
    if not t.is_floating_point():
        t = t.to(torch.get_default_dtype() if dtype is None else dtype)
    shape(name, t, expected, ndim, min_ndim)
    values(name, t, lo, hi)
    return t


def int_tensor(name: str, value, expected=None, ndim=None, lo=None, hi=None, device=None) -> torch.Tensor:
    """An int64 tensor with entries in [lo, hi]; float input is rejected even where its values are
    whole numbers (a delay written 2.0 is an error, [N-7], [CF-23])."""
    t = as_tensor(name, value, device=device)
    if t.is_floating_point():
        raise ValueError(f"{name} must hold integers, got dtype {t.dtype}")
    t = t.to(torch.int64)
    shape(name, t, expected, ndim)
    values(name, t, lo, hi)
    return t


def delays(name: str, d, lo: int, hi: int, device=None):
    """A delay given as a Python integer (returned as int) or an integer tensor of any shape (int64)."""
    if isinstance(d, torch.Tensor) or isinstance(d, np.ndarray):
        return int_tensor(name, d, lo=lo, hi=hi, device=device)
    return integer(name, d, lo, hi)


def like(t: torch.Tensor) -> dict:
    """dtype and device of a floating tensor, for tensors built to match it."""
    return {"dtype": t.dtype, "device": t.device}


def float_kw(dtype, device) -> dict:
    """dtype/device keywords of a new floating tensor: ``dtype`` must be a floating dtype or None."""
    if dtype is not None and (not isinstance(dtype, torch.dtype) or not dtype.is_floating_point):
        raise ValueError(f"dtype must be a floating torch.dtype or None, got {dtype!r}")
    return {"dtype": torch.get_default_dtype() if dtype is None else dtype, "device": device}


def output(name: str, value, x: torch.Tensor) -> torch.Tensor:
    """What a caller's velocity field returned must be a floating tensor of the state's shape ([N-7])."""
    if not isinstance(value, torch.Tensor) or not value.is_floating_point():
        raise ValueError(f"{name} must return a floating tensor of shape {list(x.shape)}, "
                         f"got {type(value).__name__}")
    if value.shape != x.shape:
        raise ValueError(f"{name} must return a tensor of the state's shape {list(x.shape)}, got {list(value.shape)}")
    return value


def finite_result(name: str, result: torch.Tensor, what: str) -> torch.Tensor:
    """``result`` unchanged; with a non-finite entry, a ValueError naming the input ``name`` ([N-15]).

    The inputs were checked finite, so a non-finite result is an overflow of the tensor's dtype. Skipped while
    ``torch.compile`` traces, like every value check of this module.
    """
    if not compiling() and result.is_floating_point() and not bool(torch.isfinite(result.detach()).all()):
        raise ValueError(f"{name} is too large in magnitude: {what} overflows {result.dtype}; a finite result "
                         f"needs smaller values ([N-15])")
    return result
