"""Training delay distributions (spec chapter D): a probability table over d_min .. d_max and its inverse-CDF draw."""

from __future__ import annotations

import torch

from .checks import DTYPE, choice, integer, real, tensor

MAX_DELAY = 4096  # [N-12]: every delay a table can draw lies in [0, 4096]
SUM_TOL = 1e-6  # [D-3]: the rounding a float32 table may carry


def delay_probs(dist: str, d_min: int, d_max: int, decay: float = 1.0) -> torch.Tensor:
    """p[k] = P(d = d_min + k): uniform ([D-1]) or proportional to exp(-decay k) ([D-2])."""
    choice("dist", dist, ("uniform", "exponential"))
    d_min = integer("d_min", d_min, 0, MAX_DELAY)
    d_max = integer("d_max", d_max, d_min, MAX_DELAY)
    decay = real("decay", decay, 0.0, 64.0)  # checked for uniform too, where it is unused
    n = d_max - d_min + 1
    if dist == "uniform":
        return torch.full((n,), 1.0 / n, dtype=DTYPE)
    # softmax of the logits -decay k: the largest logit is 0, so exp never overflows.
    return torch.softmax(-decay * torch.arange(n, dtype=DTYPE), dim=0)


def delay_cdf(probs) -> torch.Tensor:
    """Cumulative sums of a table, the last entry set to exactly 1 ([D-3])."""
    p = tensor("probs", probs, ndim=1, lo=0.0, hi=1.0)
    if p.numel() == 0:
        raise ValueError("probs must be a non-empty table summing to 1, got an empty table")
    if p.numel() > MAX_DELAY + 1:
        raise ValueError(f"probs must have at most {MAX_DELAY + 1} entries (delays 0 .. {MAX_DELAY}), "
                         f"got {p.numel()}")
    total = float(p.sum(dtype=torch.float64))
    if abs(total - 1.0) > SUM_TOL:
        raise ValueError(f"probs must sum to 1 within {SUM_TOL}, got sum {total}")
    cdf = torch.cumsum(p, dim=0)
    cdf[-1] = 1.0
    return cdf


def sample_delay(probs, d_min: int, u: float) -> int:
    """d = d_min + #{k : cdf_k <= u} for one uniform u in [0, 1) ([D-3])."""
    cdf = delay_cdf(probs)
    d_min = integer("d_min", d_min, 0, MAX_DELAY - cdf.numel() + 1)  # d_min + n - 1 <= 4096 ([N-12])
    u = real("u", u, 0.0, 1.0, hi_open=True)
    return d_min + int((cdf <= u).sum())
