"""Metrics on an executed action sequence a_0 .. a_{N-1} in PyTorch (spec chapter M, 05-metrics.md)."""

from __future__ import annotations

import math

import torch

from ._validate import finite_result, int_tensor, integer, real
from ._validate import real_tensor as tensor

MAX_ORDER = 16  # [N-12]
MAX_RESAMPLES = 10**7
MAX_VALUES = 10**7


def difference_norm(actions, order: int) -> torch.Tensor:
    """D_k = mean_t || Δ^k a_t ||_2, the k-th forward difference along time, N > k ([M-1]).

    A D_k that overflows the dtype raises, naming ``actions`` ([N-15]).
    """
    a = tensor("actions", actions, ndim=2)
    k = integer("order", order, 1, MAX_ORDER)
    if a.shape[0] <= k:
        raise ValueError(f"actions must have more than order={k} steps, got {a.shape[0]}")
    diff = finite_result("actions", torch.diff(a, n=k, dim=0), f"the order-{k} finite difference")
    return finite_result("actions", torch.linalg.vector_norm(diff, dim=-1).mean(),
                         f"D_{k}, the mean norm of the finite differences")


def action_delta(actions) -> torch.Tensor:
    """Action delta D_1 ([M-2])."""
    return difference_norm(actions, 1)


def action_jerk(actions) -> torch.Tensor:
    """Action jerk D_2; a linear ramp has jerk 0 ([M-2])."""
    return difference_norm(actions, 2)


def boundary_jump(actions, chunk_index) -> torch.Tensor:
    """Mean || a_t - a_{t-1} ||_2 over the steps t >= 1 whose chunk differs from step t - 1's ([M-3]).

    A jump that overflows the dtype raises, naming ``actions`` ([N-15]).
    """
    a = tensor("actions", actions, ndim=2)
    ci = int_tensor("chunk_index", chunk_index, expected=(a.shape[0],))
    switch = ci[1:] != ci[:-1]
    if not switch.any():
        raise ValueError("chunk_index has no chunk switch; the boundary jump needs at least one")
    return finite_result("actions", torch.linalg.vector_norm(torch.diff(a, dim=0)[switch], dim=-1).mean(),
                         "the boundary jump")


def bootstrap_interval(values, indices, confidence: float = 0.95) -> tuple[float, float]:
    """The (1 - c) / 2 and (1 + c) / 2 linear quantiles of the resampled means ([M-5]).

    indices [B, n] is the resample matrix (the vectors carry NumPy's draw). An interval that overflows the
    dtype raises, naming ``values`` ([N-15]).
    """
    v = tensor("values", values, ndim=1)
    n = v.shape[0]
    if not 1 <= n <= MAX_VALUES:
        raise ValueError(f"values must hold between 1 and {MAX_VALUES} entries, got {n}")
    idx = int_tensor("indices", indices, expected=(None, n), lo=0, hi=n - 1)
    if not 1 <= idx.shape[0] <= MAX_RESAMPLES:
        raise ValueError(f"indices must hold between 1 and {MAX_RESAMPLES} resamples (rows), got {idx.shape[0]}")
    c = real("confidence", confidence, 0.0, 1.0, lo_open=True, hi_open=True)
    means = v[idx].mean(dim=1)
    q = torch.tensor([(1.0 - c) / 2.0, (1.0 + c) / 2.0], dtype=means.dtype)
    bounds = finite_result("values", torch.quantile(means, q, interpolation="linear"),
                           "a resampled mean or its quantile")
    lo, hi = bounds.tolist()
    return lo, hi


def standard_error(values) -> torch.Tensor:
    """std(ddof=1) / sqrt(n), defined for n >= 2 ([M-6]); an overflow of the dtype raises ([N-15])."""
    v = tensor("values", values, ndim=1)
    if v.shape[0] < 2:
        raise ValueError(f"values must hold at least 2 entries, got {v.shape[0]}")
    return finite_result("values", torch.std(v, correction=1) / math.sqrt(v.shape[0]), "the standard error")
