"""Metrics on the executed action sequence (spec chapter M, 05-metrics.md).

D_k is the mean L2 norm of the k-th finite difference; action delta = D_1 and
action jerk = D_2 ([M-1], [M-2]):

    >>> import numpy as np
    >>> ramp = np.arange(5.0)[:, None] * np.array([[3.0, 4.0]])
    >>> difference_norm(ramp, 1), difference_norm(ramp, 2)
    (5.0, 0.0)
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_int, check_real, finite_result, real_array
from .delays import MAX_DELAY

HIGH_DELAYS = (3, 4)
# [N-12] Bootstrap bounds: resamples B and values n per resample.
MAX_RESAMPLES = 10**7
MAX_VALUES = 10**7
# [N-12] Entries of one resample matrix B * n: 10^8 int64 values are 800 MB (10^7 by 10^7 would be 800 TB).
MAX_ENTRIES = 10**8


def finite_differences(actions, order: int) -> np.ndarray:
    """k-th forward finite difference along time, shape [N - k, A] ([M-1]); overflow is an error ([N-15])."""
    a = check_array("actions", actions, ndim=2)
    k = check_int("order", order, 1, 16)
    if a.shape[0] <= k:
        raise ValueError(f"actions must have more than order={k} steps, got {a.shape[0]}")
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: reported below, not warned about
        diff = np.diff(a, n=k, axis=0)  # [M-1] Δ^k a_t
    return finite_result("actions", diff, f"the order-{k} finite difference")


def difference_norm(actions, order: int) -> float:
    """D_k = mean over t of || Δ^k a_t ||_2 ([M-1]); overflow is an error naming ``actions`` ([N-15])."""
    diff = finite_differences(actions, order)
    with np.errstate(over="ignore", invalid="ignore"):
        d = np.mean(np.linalg.norm(diff, axis=-1))  # [M-1]
    return float(finite_result("actions", d, f"D_{order}, the mean norm of the finite differences"))


def action_delta(actions) -> float:
    """Action delta = D_1 ([M-2])."""
    return difference_norm(actions, 1)


def action_jerk(actions) -> float:
    """Action jerk = D_2, the paper's 'jerk' ([M-2])."""
    return difference_norm(actions, 2)


def switch_steps(chunk_index) -> np.ndarray:
    """Steps t >= 1 whose action comes from another chunk than step t-1 ([M-3])."""
    ci = real_array("chunk_index", chunk_index, "iu")
    if ci.ndim != 1 or ci.size == 0:
        raise ValueError(f"chunk_index must be a non-empty 1-D integer array, got shape {list(ci.shape)}")
    return _switch_steps(ci)


def _switch_steps(ci: np.ndarray) -> np.ndarray:
    return np.nonzero(ci[1:] != ci[:-1])[0] + 1  # [M-3] t >= 1 with c_t != c_{t-1}


def boundary_jump(actions, chunk_index) -> float:
    """Mean || a_t - a_{t-1} || over chunk-switch steps t ([M-3])."""
    a = check_array("actions", actions, ndim=2)
    ci = real_array("chunk_index", chunk_index, "iu")
    if ci.shape != (a.shape[0],):
        raise ValueError(f"chunk_index must have shape [{a.shape[0]}], got {list(ci.shape)}")
    sw = _switch_steps(ci)
    if sw.size == 0:
        raise ValueError("chunk_index has no chunk switch; the boundary jump needs at least one")
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: reported below, not warned about
        jump = np.mean(np.linalg.norm(a[sw] - a[sw - 1], axis=-1))  # [M-3] mean || a_t - a_{t-1} || over switches
    return float(finite_result("actions", jump, "the boundary jump"))


def solve_rate(solved) -> float:
    """Fraction of episodes solved ([M-4])."""
    s = real_array("solved", solved, "b")
    if s.ndim != 1 or s.size == 0 or s.dtype != bool:
        raise ValueError("solved must be a non-empty 1-D boolean array")
    return float(np.mean(s))


def standard_error(values) -> float:
    """Standard error of the mean, std(ddof=1) / sqrt(n), n >= 2 ([M-6]); overflow is an error ([N-15])."""
    v = check_array("values", values, ndim=1)
    if v.size < 2:
        raise ValueError(f"values must hold at least 2 entries, got {v.size}")
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: reported below, not warned about
        se = np.std(v, ddof=1) / np.sqrt(v.size)
    return float(finite_result("values", se, "the standard error"))


def defined_values(values) -> np.ndarray:
    """The defined entries of a 1-D array of per-episode values, as float64 ([M-8]): NaN and inf are left out."""
    v = real_array("values", values).astype(np.float64)
    if v.ndim != 1:
        raise ValueError(f"values must be a 1-D array, got shape {list(v.shape)}")
    return v[np.isfinite(v)]


def defined_mean(values) -> float:
    """Mean of the defined values ([M-8]); NaN when none is defined; a mean that overflows is an error ([N-15]).

        >>> defined_mean([1.0, float("nan"), 3.0])
        2.0
    """
    v = defined_values(values)
    if not v.size:
        return float("nan")
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: reported below, not warned about
        mean = v.mean()
    return float(finite_result("values", mean, "the mean of the defined values"))


def bootstrap_indices(num_values: int, num_resamples: int, seed: int) -> np.ndarray:
    """Resample index matrix [B, n] = default_rng(seed).integers(0, n, (B, n)) ([M-5])."""
    n = check_int("num_values", num_values, 1, MAX_VALUES)
    B = check_int("num_resamples", num_resamples, 1, MAX_RESAMPLES)
    if n * B > MAX_ENTRIES:
        raise ValueError(f"num_resamples * num_values must be at most {MAX_ENTRIES} ([N-12]), got {B} * {n}")
    seed = check_int("seed", seed, 0)
    return np.random.default_rng(seed).integers(0, n, size=(B, n))


def bootstrap_interval_from_indices(values, indices, confidence: float = 0.95) -> tuple[float, float]:
    """Percentile interval of resampled means ([M-5]), numpy's 'linear' quantiles; overflow is an error ([N-15])."""
    v = check_array("values", values, ndim=1)
    idx = real_array("indices", indices, "iu")
    if idx.ndim != 2 or idx.shape[0] < 1 or idx.shape[1] != v.size or not np.issubdtype(idx.dtype, np.integer) \
            or idx.min() < 0 or idx.max() >= v.size:
        raise ValueError(f"indices must be an integer array [B, {v.size}], B >= 1, with entries in [0, {v.size - 1}]")
    c = check_real("confidence", confidence, 0.0, 1.0, lo_open=True, hi_open=True)
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: reported below, not warned about
        means = v[idx].mean(axis=1)
        lo, hi = np.quantile(means, [(1.0 - c) / 2.0, 1.0 - (1.0 - c) / 2.0])
    finite_result("values", np.array([lo, hi]), "a resampled mean or its quantile")
    return float(lo), float(hi)


def bootstrap_interval(values, num_resamples: int = 10000, seed: int = 0,
                       confidence: float = 0.95) -> tuple[float, float]:
    """95% bootstrap interval of the mean over levels ([M-5])."""
    v = check_array("values", values, ndim=1)
    return bootstrap_interval_from_indices(v, bootstrap_indices(v.size, num_resamples, seed), confidence)


def is_high_delay(d: int) -> bool:
    """High delay means d in {3, 4} ([M-7])."""
    return check_int("d", d, 0, MAX_DELAY) in HIGH_DELAYS
