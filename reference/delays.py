"""Distributions of the simulated delay during training (spec chapter D, 02-training.md).

A distribution is a probability table over d = d_min .. d_max. Sampling is the
inverse CDF of one uniform number u in [0, 1), so any framework that draws the
same u draws the same d ([D-3]).

>>> delay_probs("uniform", 0, 3).tolist()
[0.25, 0.25, 0.25, 0.25]
>>> sample_delay(delay_probs("uniform", 0, 3), 0, 0.6)
2
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_choice, check_int, check_real

DISTRIBUTIONS = ("uniform", "exponential")
MAX_DELAY = 4096


def delay_probs(dist: str, d_min: int, d_max: int, decay: float = 1.0) -> np.ndarray:
    """Probability table p[k] = P(d = d_min + k) ([D-1], [D-2]).

    [D-1] uniform: p = 1 / (d_max - d_min + 1).
    [D-2] exponential: p ∝ exp(-decay * (d - d_min)), decay >= 0; decay = 0 is uniform.
    """
    check_choice("dist", dist, DISTRIBUTIONS)
    d_min = check_int("d_min", d_min, 0, MAX_DELAY)
    d_max = check_int("d_max", d_max, d_min, MAX_DELAY)
    # decay is checked for both distributions: a bad value is a mistake even where it is unused.
    decay = check_real("decay", decay, 0.0, 64.0)
    n = d_max - d_min + 1
    if dist == "uniform":
        return np.full(n, 1.0 / n)
    logits = -decay * np.arange(n, dtype=np.float64)
    p = np.exp(logits - logits.max())
    return p / p.sum()


def delay_cdf(probs) -> np.ndarray:
    """Cumulative sums of a probability table, last entry forced to exactly 1 ([D-3])."""
    p = check_array("probs", probs, ndim=1, lo=0.0, hi=1.0)
    if p.size == 0 or abs(p.sum() - 1.0) > 1e-6:  # [D-3]: the tolerance a float32 table needs
        raise ValueError(f"probs must be a non-empty table summing to 1, got sum {p.sum() if p.size else 0}")
    c = np.cumsum(p)
    c[-1] = 1.0
    return c


def sample_delay(probs, d_min: int, u: float) -> int:
    """Inverse-CDF draw ([D-3]): d = d_min + #{k : cdf[k] <= u}, for u in [0, 1)."""
    c = delay_cdf(probs)
    # The table spans d_min .. d_min + n - 1, which must stay within [D-1]'s range.
    if c.size > MAX_DELAY + 1:
        raise ValueError(f"probs must have at most {MAX_DELAY + 1} entries (delays 0 .. {MAX_DELAY}), "
                         f"got {c.size}")
    d_min = check_int("d_min", d_min, 0, MAX_DELAY - c.size + 1)
    u = check_real("u", u, 0.0, 1.0, hi_open=True)
    return d_min + int(np.sum(c <= u))
