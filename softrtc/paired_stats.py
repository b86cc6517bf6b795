"""Statistics of the experiment reports: intervals over seeds and episodes, paired tests ([AX-7], [KR-3]).

Values of one method and delay form a matrix ``V[seed, episode]`` (NaN where
a metric is undefined for an episode, [A-24]). Every method of a task runs
the same environment seeds and sampler keys, so two methods' matrices are
paired entry by entry: fine-tuning seed ``k`` of one method is paired with
fine-tuning seed ``k`` of the other (same seed, same data order), and a
method without fine-tuning (the base) has one row, paired with every row.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["cluster_bootstrap", "paired_difference", "mcnemar_exact", "sign_flip_test", "holm", "as_matrix",
           "nested_bootstrap"]


def as_matrix(name: str, values) -> np.ndarray:
    """``values`` as a float matrix ``[seeds >= 1, episodes >= 1]`` (NaN allowed, infinities not)."""
    try:
        v = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a real matrix [seeds, episodes], got {type(values).__name__}") from None
    if np.asarray(values).dtype.kind == "b":
        v = v.astype(np.float64)
    if v.ndim != 2 or v.shape[0] < 1 or v.shape[1] < 1:
        raise ValueError(f"{name} must be a real matrix [seeds >= 1, episodes >= 1], got shape {list(v.shape)}")
    if np.any(np.isinf(v)):
        raise ValueError(f"{name} must not hold infinities")
    return v


def _check_resamples(num_resamples, seed):
    if isinstance(num_resamples, bool) or not isinstance(num_resamples, (int, np.integer)) \
            or not 1 <= num_resamples <= 10**6:
        raise ValueError(f"num_resamples must be an integer in [1, 1000000], got {num_resamples!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**63:
        raise ValueError(f"seed must be an integer in [0, 2**63 - 1], got {seed!r}")


def _resampled_means(v: np.ndarray, num_resamples: int, seed: int) -> np.ndarray:
    """Means of ``v`` over resampled seeds (rows) and resampled episodes (columns), both with replacement.

    Episodes are resampled as one set of columns for every row: they are the
    same environment seeds in every row, so they are resampled as units.
    """
    rng = np.random.default_rng(seed)
    S, E = v.shape
    rows = rng.integers(0, S, size=(num_resamples, S))
    cols = rng.integers(0, E, size=(num_resamples, E))
    out = np.empty(num_resamples)
    # In blocks, so memory stays bounded for large matrices.
    step = max(1, 2_000_000 // max(S * E, 1))
    for b0 in range(0, num_resamples, step):
        sub = v[rows[b0:b0 + step, :, None], cols[b0:b0 + step, None, :]]
        ok = np.isfinite(sub)
        cnt = ok.sum(axis=(1, 2))
        tot = np.where(ok, sub, 0.0).sum(axis=(1, 2))
        with np.errstate(invalid="ignore", divide="ignore"):
            out[b0:b0 + step] = np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan)
    return out


def cluster_bootstrap(values, num_resamples: int = 2000, seed: int = 0) -> dict:
    """Mean of ``V[seed, episode]`` and its bootstrap 95% interval over seeds and episodes.

    Returns ``{"mean", "lo", "hi", "n"}`` with ``n`` the number of defined
    entries; the interval is the 2.5 / 97.5 percentiles of the resampled means
    (NaN when no entry is defined, or a single one).
    """
    v = as_matrix("values", values)
    _check_resamples(num_resamples, seed)
    ok = np.isfinite(v)
    n = int(ok.sum())
    if n == 0:
        return {"mean": float("nan"), "lo": float("nan"), "hi": float("nan"), "n": 0}
    mean = float(v[ok].mean())
    if n == 1:
        return {"mean": mean, "lo": float("nan"), "hi": float("nan"), "n": 1}
    means = _resampled_means(v, num_resamples, seed)
    means = means[np.isfinite(means)]
    return {"mean": mean, "lo": float(np.percentile(means, 2.5)), "hi": float(np.percentile(means, 97.5)), "n": n}


def _paired_differences(a, b) -> np.ndarray:
    """``a - b`` of two paired ``[seeds, episodes]`` matrices, a one-row matrix paired with every row."""
    a, b = as_matrix("a", a), as_matrix("b", b)
    if a.shape[1] != b.shape[1]:
        raise ValueError(f"a and b must have the same number of episodes, got {a.shape[1]} and {b.shape[1]}")
    if a.shape[0] != b.shape[0] and 1 not in (a.shape[0], b.shape[0]):
        raise ValueError(f"a and b must have the same number of seeds or one of them one, got {a.shape[0]} and "
                         f"{b.shape[0]}")
    S = max(a.shape[0], b.shape[0])
    return np.broadcast_to(a, (S, a.shape[1])) - np.broadcast_to(b, (S, b.shape[1]))


def paired_difference(a, b, num_resamples: int = 2000, seed: int = 0) -> dict:
    """Paired bootstrap of ``mean(a - b)`` over seeds and episodes.

    ``a`` and ``b`` are ``[seeds, episodes]`` with the same number of episodes;
    a one-row matrix is paired with every row of the other. Pairs where either
    value is undefined are left out. Returns ``{"diff", "lo", "hi", "p",
    "n"}``: ``p`` is the two-sided bootstrap p-value (twice the smaller share
    of resampled differences on either side of 0, at most 1).
    """
    d = _paired_differences(a, b)
    _check_resamples(num_resamples, seed)
    r = cluster_bootstrap(d, num_resamples, seed)
    if r["n"] < 2:
        return {"diff": r["mean"], "lo": r["lo"], "hi": r["hi"], "p": float("nan"), "n": r["n"]}
    means = _resampled_means(d, num_resamples, seed)
    means = means[np.isfinite(means)]
    p = min(1.0, 2.0 * min(np.mean(means <= 0.0), np.mean(means >= 0.0)))
    return {"diff": r["mean"], "lo": r["lo"], "hi": r["hi"], "p": float(p), "n": r["n"]}


def mcnemar_exact(a, b) -> dict:
    """Exact McNemar test of paired successes ``a`` vs ``b`` (same shapes, or one a single row).

    ``b10`` counts pairs where only ``a`` succeeded, ``b01`` where only ``b``
    did; ``p = min(1, 2 P[X <= min(b10, b01)])`` for ``X ~ Binomial(b10 + b01,
    1/2)`` (1 when there is no discordant pair). Returns ``{"b10", "b01", "p"}``.
    """
    a, b = as_matrix("a", a), as_matrix("b", b)
    for name, m in (("a", a), ("b", b)):
        if not np.all(np.isin(m, (0.0, 1.0))):
            raise ValueError(f"{name} must hold successes as 0/1 (or booleans) only")
    if a.shape[1] != b.shape[1] or (a.shape[0] != b.shape[0] and 1 not in (a.shape[0], b.shape[0])):
        raise ValueError(f"a and b must be paired: shapes {list(a.shape)} and {list(b.shape)}")
    S = max(a.shape[0], b.shape[0])
    a = np.broadcast_to(a, (S, a.shape[1]))
    b = np.broadcast_to(b, (S, b.shape[1]))
    b10 = int(np.sum((a == 1) & (b == 0)))
    b01 = int(np.sum((a == 0) & (b == 1)))
    n = b10 + b01
    if n == 0:
        return {"b10": 0, "b01": 0, "p": 1.0}
    k = min(b10, b01)
    tail = sum(math.comb(n, i) for i in range(k + 1)) / 2.0**n
    return {"b10": b10, "b01": b01, "p": float(min(1.0, 2.0 * tail))}


# Exact enumeration of the 2^E sign patterns up to this many env seeds; Monte Carlo above.
EXACT_SIGN_FLIP = 16


def sign_flip_test(a, b, num_resamples: int = 10_000, seed: int = 0) -> dict:
    """Paired sign-flip permutation test of ``a`` vs ``b`` with the environment seed as the unit ([AX-7]).

    ``a`` and ``b`` are ``[seeds, episodes]`` as in :func:`paired_difference`
    (a one-row matrix pairs with every row). Episodes of one column share an
    environment seed, so they are not independent across fine-tuning seeds:
    each column is reduced to one difference ``delta_e``, the mean of ``a - b``
    over its defined pairs, and only columns are exchanged. Under the null
    hypothesis (the two methods are exchangeable on every environment seed)
    each ``delta_e`` is as likely to have either sign, so the statistic
    ``mean_e delta_e`` is compared with its values under every sign pattern
    (exactly when at most 16 columns, else ``num_resamples`` random patterns
    with the ``(1 + hits) / (1 + resamples)`` estimate). Returns ``{"diff",
    "p", "n_env"}``; ``p`` is two-sided and 1 when every ``delta_e`` is 0.

    >>> sign_flip_test([[1, 1, 1]], [[0, 0, 0]])["p"]   # 3 env seeds: 2 of 8 patterns are as extreme
    0.25
    """
    d = _paired_differences(a, b)
    _check_resamples(num_resamples, seed)
    ok = np.isfinite(d)
    keep = ok.any(axis=0)
    if not keep.any():
        return {"diff": float("nan"), "p": float("nan"), "n_env": 0}
    delta = np.where(ok, d, 0.0).sum(axis=0)[keep] / ok.sum(axis=0)[keep]
    E = delta.size
    stat = abs(float(delta.mean()))
    if not np.any(delta != 0):
        return {"diff": 0.0, "p": 1.0, "n_env": E}
    # Compare with a tolerance so that patterns equal to the observed one in exact arithmetic count as hits.
    tol = 1e-12 * max(1.0, float(np.abs(delta).sum()))
    if E <= EXACT_SIGN_FLIP:
        signs = 1.0 - 2.0 * ((np.arange(2 ** E)[:, None] >> np.arange(E)[None, :]) & 1)
        p = float(np.mean(np.abs(signs @ delta) / E >= stat - tol))
    else:
        rng = np.random.default_rng(seed)
        hits = 0
        for b0 in range(0, num_resamples, 1000):
            n = min(1000, num_resamples - b0)
            signs = rng.choice((-1.0, 1.0), size=(n, E))
            hits += int(np.sum(np.abs(signs @ delta) / E >= stat - tol))
        p = (1 + hits) / (1 + num_resamples)
    return {"diff": float(delta.mean()), "p": float(min(1.0, p)), "n_env": int(E)}


def holm(pvalues) -> list:
    """Holm's step-down adjustment of a family of p-values (NaN entries are left out of the family).

    The i-th smallest of m p-values becomes ``max_{k <= i} min(1, (m - k + 1) p_(k))``;
    rejecting where the adjusted value is below alpha keeps the family-wise
    error at most alpha ([AX-7]).

    >>> holm([0.01, 0.04, 0.03])
    [0.03, 0.06, 0.06]
    """
    try:
        p = np.asarray(pvalues, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError("pvalues must be a list of reals in [0, 1] (NaN allowed)") from None
    if p.ndim != 1 or np.any(np.isinf(p)) or np.any((p[np.isfinite(p)] < 0) | (p[np.isfinite(p)] > 1)):
        raise ValueError("pvalues must be a list of reals in [0, 1] (NaN allowed)")
    out = np.full(p.shape, np.nan)
    idx = np.flatnonzero(np.isfinite(p))
    m = idx.size
    order = idx[np.argsort(p[idx], kind="stable")]
    running = 0.0
    for k, i in enumerate(order):
        running = max(running, min(1.0, (m - k) * p[i]))
        out[i] = running
    return [float(round(x, 15)) if np.isfinite(x) else float("nan") for x in out]


def _check_blocks(blocks) -> list:
    if isinstance(blocks, (str, bytes, np.ndarray)) or not isinstance(blocks, (list, tuple)) or not blocks:
        raise ValueError("blocks must be a non-empty list of real arrays [seeds, delays, episodes], one per cluster")
    out = []
    for i, b in enumerate(blocks):
        try:
            v = np.asarray(b, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"blocks[{i}] must be a real array [seeds, delays, episodes]") from None
        if v.ndim != 3 or 0 in v.shape:
            raise ValueError(f"blocks[{i}] must be a real array [seeds >= 1, delays >= 1, episodes >= 1], "
                             f"got shape {list(v.shape)}")
        if np.any(np.isinf(v)):
            raise ValueError(f"blocks[{i}] must not hold infinities")
        out.append(v)
    return out


def _counts(draws: np.ndarray, n: int) -> np.ndarray:
    """How often each of ``0..n-1`` was drawn, per leading index: ``[..., k] -> [..., n]``."""
    lead = draws.shape[:-1]
    flat = (np.arange(int(np.prod(lead)))[:, None] * n + draws.reshape(-1, draws.shape[-1])).ravel()
    return np.bincount(flat, minlength=int(np.prod(lead)) * n).reshape(*lead, n).astype(np.float64)


def _cluster_means(v: np.ndarray, cs: np.ndarray, ce: np.ndarray) -> np.ndarray:
    """Mean over delays of the mean over defined entries, with seeds and episodes weighted by counts.

    ``v`` is ``[S, D, E]``, ``cs`` ``[..., S]`` and ``ce`` ``[..., E]``; returns
    ``[...]`` (NaN where no delay has a defined entry).
    """
    ok = np.isfinite(v)
    v0 = np.where(ok, v, 0.0)
    tot = np.einsum("...s,sde,...e->...d", cs, v0, ce, optimize=True)
    if ok.all():  # every entry defined: each delay counts every drawn (seed, episode) pair
        cnt = np.broadcast_to((cs.sum(-1) * ce.sum(-1))[..., None], tot.shape)
    else:
        cnt = np.einsum("...s,sde,...e->...d", cs, ok.astype(np.float64), ce, optimize=True)
    has = cnt > 0
    per_d = np.where(has, tot / np.where(has, cnt, 1.0), 0.0)
    nd = has.sum(-1)
    return np.where(nd > 0, per_d.sum(-1) / np.maximum(nd, 1), np.nan)


def nested_bootstrap(blocks, num_resamples: int = 2000, seed: int = 0) -> dict:
    """Mean over clusters of ``V[seed, delay, episode]`` blocks and its two-stage bootstrap 95% interval ([KR-3]).

    Each block is one cluster (a Kinetix level): its value is the mean over
    delays of the mean over its defined entries (NaN where a metric is
    undefined), and the statistic is the mean of the clusters' values. A
    resample draws the clusters with replacement, then, within each drawn
    cluster, its seeds and its episodes with replacement; an episode index is
    one unit for every seed and delay of its cluster (the same environment
    key). Returns ``{"mean", "lo", "hi", "n"}`` as :func:`cluster_bootstrap`
    (``n`` the number of defined entries).

    >>> r = nested_bootstrap([[[[1.0, 1.0]]], [[[3.0, 3.0]]]], 200, 0)
    >>> r["mean"], r["lo"], r["hi"]
    (2.0, 1.0, 3.0)
    """
    vs = _check_blocks(blocks)
    _check_resamples(num_resamples, seed)
    n = int(sum(np.isfinite(v).sum() for v in vs))
    point = np.array([_cluster_means(v, np.ones(v.shape[0]), np.ones(v.shape[2])) for v in vs])
    point = point[np.isfinite(point)]
    if n == 0 or point.size == 0:
        return {"mean": float("nan"), "lo": float("nan"), "hi": float("nan"), "n": n}
    mean = float(point.mean())
    if n == 1:
        return {"mean": mean, "lo": float("nan"), "hi": float("nan"), "n": 1}
    rng = np.random.default_rng(seed)
    L, B = len(vs), num_resamples
    which = rng.integers(0, L, size=(B, L))
    stats = np.full((B, L), np.nan)
    for c, v in enumerate(vs):
        S, _, E = v.shape
        # Every (resample, position) gets its own within-cluster draw, so a cluster drawn twice is resampled twice.
        cs = _counts(rng.integers(0, S, size=(B, L, S)), S)
        ce = _counts(rng.integers(0, E, size=(B, L, E)), E)
        stats = np.where(which == c, _cluster_means(v, cs, ce), stats)
    ok = np.isfinite(stats)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(ok, stats, 0.0).sum(1) / ok.sum(1)
    means = means[np.isfinite(means)]
    return {"mean": mean, "lo": float(np.percentile(means, 2.5)), "hi": float(np.percentile(means, 97.5)), "n": n}
