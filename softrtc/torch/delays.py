"""Training delay distributions in PyTorch (spec chapter D, 02-training.md); twin of ``softrtc.reference.delays``.

:func:`sample_delays` draws one delay per example ([D-4]) from an explicit
``torch.Generator`` ([N-9]); :func:`sample_delay` is the inverse-CDF rule of
[D-3] for given uniforms (a float or a tensor of any shape).
"""

from __future__ import annotations

import torch

from . import _validate as v

MAX_DELAY = 4096  # [N-12]
SUM_TOL = 1e-6  # [D-3]: the rounding a float32 table may carry

__all__ = ["delay_probs", "delay_cdf", "sample_delay", "sample_delays", "check_generator"]


def delay_probs(dist: str, d_min: int, d_max: int, decay: float = 1.0, *, dtype=None, device=None) -> torch.Tensor:
    """p[k] = P(d = d_min + k): uniform ([D-1]) or proportional to exp(-decay k) ([D-2])."""
    v.choice("dist", dist, ("uniform", "exponential"))
    d_min = v.integer("d_min", d_min, 0, MAX_DELAY)
    d_max = v.integer("d_max", d_max, d_min, MAX_DELAY)
    decay = v.real("decay", decay, 0.0, 64.0)  # checked for uniform too, where it is unused
    kw = v.float_kw(dtype, device)
    n = d_max - d_min + 1
    if dist == "uniform":
        return torch.full((n,), 1.0 / n, **kw)
    # softmax of the logits -decay k: the largest logit is 0, so exp never overflows.
    return torch.softmax(-decay * torch.arange(n, **kw), dim=0)


def delay_cdf(probs) -> torch.Tensor:
    """Cumulative sums of a table, the last entry set to exactly 1 ([D-3])."""
    p = v.real_tensor("probs", probs, ndim=1, lo=0.0, hi=1.0)
    if p.numel() == 0:
        raise ValueError("probs must be a non-empty table summing to 1, got an empty table")
    if p.numel() > MAX_DELAY + 1:
        raise ValueError(f"probs must have at most {MAX_DELAY + 1} entries (delays 0 .. {MAX_DELAY}), got {p.numel()}")
    if not v.compiling():
        total = float(p.sum(dtype=torch.float64))
        if abs(total - 1.0) > SUM_TOL:
            raise ValueError(f"probs must sum to 1 within {SUM_TOL}, got sum {total}")
    cdf = torch.cumsum(p, dim=0)
    return torch.cat([cdf[:-1], torch.ones_like(cdf[-1:])])


def sample_delay(probs, d_min: int, u):
    """d = d_min + #{k : cdf_k <= u} ([D-3]); ``u`` a float in [0, 1) (returns an int) or a tensor of them
    (returns int64 of u's shape)."""
    cdf = delay_cdf(probs)
    d_min = v.integer("d_min", d_min, 0, MAX_DELAY - cdf.numel() + 1)  # d_min + n - 1 <= 4096 ([N-12])
    if isinstance(u, torch.Tensor):
        u = v.real_tensor("u", u, lo=0.0, hi=1.0)
        if not v.compiling() and bool((u >= 1.0).any()):
            raise ValueError("u must lie in [0, 1), got an entry equal to 1")
        return d_min + (cdf[:-1].to(u.dtype) <= u[..., None]).sum(-1)
    u = v.real("u", u, 0.0, 1.0, hi_open=True)
    # [D-3] The last entry is 1 and u < 1, so only the first n - 1 count: a u that rounds up to 1 in float32
    # (1 - 1e-12) draws the last delay, never one past the table.
    return d_min + int((cdf[:-1] <= u).sum())


def check_generator(generator) -> torch.Generator:
    """An explicit torch.Generator ([N-9]): no draw of this package falls back on the global seed."""
    if not isinstance(generator, torch.Generator):
        raise ValueError(f"generator must be a torch.Generator (torch.Generator().manual_seed(seed)), "
                         f"got {type(generator).__name__}")
    return generator


def sample_delays(probs, d_min: int, batch: int, generator: torch.Generator) -> torch.Tensor:
    """One delay per example, int64 ``[batch]`` on the generator's device: u ~ U[0, 1) then [D-3] ([D-4])."""
    batch = v.integer("batch", batch, 1, 1 << 24)
    g = check_generator(generator)
    p = v.real_tensor("probs", probs, ndim=1)
    u = torch.rand(batch, generator=g, dtype=p.dtype, device=g.device)
    return sample_delay(p.to(g.device), d_min, u)
