"""Metrics on executed action sequences in JAX (spec chapter M, 05-metrics.md); twin of ``softrtc.reference.metrics``.

All functions act on one episode ``actions [N, A]`` and ``vmap`` over
episodes. Episodes of different lengths in one padded batch use the optional
traced ``length``: only steps ``t < length`` count ([M-4] truncation). The
difference order ``k`` is static.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import metrics as _ref
from softrtc.reference.delays import MAX_DELAY

from . import _validate as v

HIGH_DELAYS = _ref.HIGH_DELAYS

# The resample index matrix comes from NumPy's generator ([M-5]); it is data, not a JAX computation.
bootstrap_indices = _ref.bootstrap_indices


def _actions(actions):
    a = v.array("actions", actions, ndim=2)
    return a


def finite_differences(actions, order: int) -> jax.Array:
    """k-th forward finite difference along time, [N - k, A] ([M-1]); N > k; a concrete overflow raises ([N-15])."""
    a = _actions(actions)
    k = v.check_int("order", order, 1, 16)
    if a.shape[0] <= k:
        raise ValueError(f"actions must have more than order={k} steps, got {a.shape[0]}")
    return v.finite_result("actions", jnp.diff(a, n=k, axis=0), f"the order-{k} finite difference")


def _length(length, N, k):
    if length is None:
        return None
    return v.int_value("length", length, k + 1, N)


def difference_norm(actions, order: int, length=None) -> jax.Array:
    """D_k = mean_t || Δ^k a_t ||_2 ([M-1]); with ``length`` only the first ``length`` steps count.

    ``length`` (traced or concrete) must lie in [k + 1, N]. A concrete D_k that overflows raises ([N-15]).
    """
    a = _actions(actions)
    k = v.check_int("order", order, 1, 16)
    if a.shape[0] <= k:
        raise ValueError(f"actions must have more than order={k} steps, got {a.shape[0]}")
    n = _length(length, a.shape[0], k)
    return v.finite_result("actions", _difference_norm(a, k, a.shape[0] if n is None else n),
                           f"D_{k}, the mean norm of the finite differences")


# The public functions check on the host and call jitted cores: eager JAX would
# compile every primitive separately for each new shape.
@functools.partial(jax.jit, static_argnums=(1,))
def _difference_norm(a, k, n):
    norms = jnp.linalg.norm(jnp.diff(a, n=k, axis=0), axis=-1)
    mask = jnp.arange(norms.shape[0]) < n - k
    return jnp.sum(jnp.where(mask, norms, 0.0)) / (n - k)


def action_delta(actions, length=None) -> jax.Array:
    """Action delta = D_1 ([M-2])."""
    return difference_norm(actions, 1, length)


def action_jerk(actions, length=None) -> jax.Array:
    """Action jerk = D_2 ([M-2])."""
    return difference_norm(actions, 2, length)


def switch_mask(chunk_index) -> jax.Array:
    """[N] booleans: step t >= 1 takes its action from another chunk than t - 1 ([M-3]).

    The static-shape form of the reference's ``switch_steps`` (``jnp.nonzero(mask)``).
    """
    ci = v.int_array("chunk_index", chunk_index, shape=(None,))
    if ci.shape[0] < 1:  # [N-12]: no empty axis (the mask would get an entry of its own)
        raise ValueError("chunk_index must be a non-empty 1-D integer array [N], got shape [0]")
    return jnp.concatenate([jnp.zeros((1,), bool), ci[1:] != ci[:-1]])


def boundary_jump(actions, chunk_index, length=None) -> jax.Array:
    """Mean || a_t - a_{t-1} || over chunk-switch steps t ([M-3]); NaN if there is no switch.

    The reference raises when there is no switch; here that is checked when
    ``chunk_index`` is concrete, and traced inputs without a switch give NaN (0/0). A concrete jump that
    overflows raises ([N-15]).
    """
    a = _actions(actions)
    ci = v.int_array("chunk_index", chunk_index, shape=(a.shape[0],))
    mask = switch_mask(ci)
    if length is not None:
        mask = mask & (jnp.arange(a.shape[0]) < v.int_value("length", length, 1, a.shape[0]))
    if not v.is_traced(mask) and not bool(jnp.any(mask)):
        raise ValueError("chunk_index has no chunk switch; the boundary jump needs at least one")
    return v.finite_result("actions", _boundary_jump(a, mask), "the boundary jump")


@jax.jit
def _boundary_jump(a, mask):
    step = jnp.linalg.norm(a - jnp.roll(a, 1, axis=0), axis=-1)
    return jnp.sum(jnp.where(mask, step, 0.0)) / jnp.sum(mask)


def solve_rate(solved) -> jax.Array:
    """Fraction of episodes solved ([M-4]); solved is a non-empty 1-D boolean array."""
    if v.is_traced(solved):
        s = solved
    else:
        try:
            s = np.asarray(solved)
        except (TypeError, ValueError) as exc:  # e.g. ragged lists
            raise ValueError(f"solved must be a non-empty 1-D boolean array, got {type(solved).__name__}") from exc
    if s.ndim != 1 or s.size == 0 or s.dtype != np.bool_:
        raise ValueError(f"solved must be a non-empty 1-D boolean array, got dtype {s.dtype} and shape "
                         f"{list(s.shape)}")
    return jnp.mean(jnp.asarray(s).astype(jnp.float32))


def standard_error(values) -> jax.Array:
    """std(ddof=1) / sqrt(n), n >= 2 ([M-6]); a concrete overflow raises ([N-15])."""
    x = v.array("values", values, ndim=1)
    if x.shape[0] < 2:
        raise ValueError(f"values must hold at least 2 entries, got {x.shape[0]}")
    return v.finite_result("values", _standard_error(x), "the standard error")


@jax.jit
def _standard_error(x):
    return jnp.std(x, ddof=1) / jnp.sqrt(x.shape[0])


def bootstrap_interval_from_indices(values, indices, confidence: float = 0.95) -> tuple[jax.Array, jax.Array]:
    """Percentile interval of resampled means with linear quantiles ([M-5]).

    ``indices [B, n]`` is the resample matrix (e.g. :data:`bootstrap_indices`);
    ``confidence`` is static. A concrete interval that overflows raises ([N-15]).
    """
    x = v.array("values", values, ndim=1)
    if x.shape[0] > _ref.MAX_VALUES:
        raise ValueError(f"values must hold at most {_ref.MAX_VALUES} entries ([N-12]), got {x.shape[0]}")
    idx = v.int_array("indices", indices, lo=0, hi=max(x.shape[0] - 1, 0))
    if idx.ndim != 2 or not 1 <= idx.shape[0] <= _ref.MAX_RESAMPLES or idx.shape[1] != x.shape[0] \
            or not jnp.issubdtype(idx.dtype, jnp.integer):
        raise ValueError(f"indices must be an integer array [B, {x.shape[0]}], 1 <= B <= {_ref.MAX_RESAMPLES}, "
                         f"with entries in [0, {x.shape[0] - 1}], got shape {list(idx.shape)}")
    if not v.is_traced(idx) and idx.size and (int(idx.min()) < 0 or int(idx.max()) >= x.shape[0]):
        raise ValueError(f"indices must be an integer array [B, {x.shape[0]}] with entries in [0, {x.shape[0] - 1}]")
    c = v.check_real("confidence", confidence, 0.0, 1.0, lo_open=True, hi_open=True)
    return v.finite_result("values", _bootstrap(x, idx, c), "a resampled mean or its quantile")


@functools.partial(jax.jit, static_argnums=(2,))
def _bootstrap(x, idx, c):
    means = jnp.mean(x[idx], axis=1)
    q = jnp.quantile(means, jnp.array([(1.0 - c) / 2.0, 1.0 - (1.0 - c) / 2.0]))
    return q[0], q[1]


def bootstrap_interval(values, num_resamples: int = 10000, seed: int = 0, confidence: float = 0.95):
    """95% bootstrap interval of the mean over levels ([M-5]), NumPy's index matrix."""
    x = v.array("values", values, ndim=1)
    return bootstrap_interval_from_indices(x, bootstrap_indices(x.shape[0], num_resamples, seed), confidence)


def is_high_delay(d) -> jax.Array:
    """d in {3, 4} ([M-7]); ``d`` may be traced or an integer array (no empty axis).

    Concrete delays must lie in [0, 4096] ([N-12]); traced ones are checked for dtype only.
    """
    d = v.int_array("d", d, lo=0, hi=MAX_DELAY)
    if 0 in d.shape:
        raise ValueError(f"d must have at least one entry along every axis, got shape {list(d.shape)}")
    return (d == HIGH_DELAYS[0]) | (d == HIGH_DELAYS[1])
