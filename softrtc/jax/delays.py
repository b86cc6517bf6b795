"""Training delay distributions in JAX (spec chapter D, 02-training.md); twin of ``softrtc.reference.delays``.

The table length ``d_max - d_min + 1`` is a shape, so ``d_min`` and ``d_max``
are static Python ints for :func:`delay_probs`; ``decay`` may be traced.
Sampling is the inverse CDF of a uniform ``u`` ([D-3]) and accepts any shape
of ``u`` (one draw per element), a traced ``d_min`` and a traced table.

Float32 note ([N-8]): the CDF is accumulated in float32, so a ``u`` within
float32 rounding (about 1e-7) of a CDF entry may fall on the other side than
in the float64 reference. Tables whose CDF entries are dyadic (e.g. uniform
over 1, 2, 4 or 8 delays) agree for every ``u``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import delays as _ref

from . import _validate as v

DISTRIBUTIONS = _ref.DISTRIBUTIONS
MAX_DELAY = _ref.MAX_DELAY
# [N-12] At most 2^31 - 1 draws per sample_delays call: a finite bound, so a huge shape is a ValueError.
MAX_DRAWS = 2**31 - 1


def delay_probs(dist: str, d_min: int, d_max: int, decay=1.0) -> jax.Array:
    """Probability table p[k] = P(d = d_min + k), shape [d_max - d_min + 1] ([D-1], [D-2]).

    ``dist``, ``d_min``, ``d_max`` are static; ``decay`` in [0, 64] may be traced.
    """
    v.check_choice("dist", dist, DISTRIBUTIONS)
    d_min = v.check_int("d_min", d_min, 0, MAX_DELAY)
    d_max = v.check_int("d_max", d_max, d_min, MAX_DELAY)
    # decay is checked for both distributions: a bad value is a mistake even where it is unused.
    decay = v.real_value("decay", decay, 0.0, 64.0)
    n = d_max - d_min + 1
    if dist == "uniform":
        return jnp.full((n,), 1.0 / n, jnp.float32)
    # logits start at 0 and decrease, so exp never overflows ([D-2]).
    p = jnp.exp(-decay * jnp.arange(n, dtype=jnp.float32))
    return p / jnp.sum(p)


def delay_cdf(probs) -> jax.Array:
    """Cumulative sums of a table [n], last entry exactly 1 ([D-3]).

    A concrete table must be non-empty, in [0, 1] and sum to 1 within 1e-6.
    """
    p = v.array("probs", probs, ndim=1, lo=0.0, hi=1.0)
    if p.shape[0] == 0:
        raise ValueError("probs must be a non-empty table summing to 1, got an empty table")
    if not v.is_traced(p) and abs(float(np.sum(np.asarray(p))) - 1.0) > 1e-6:
        raise ValueError(f"probs must be a non-empty table summing to 1, got sum {float(np.sum(np.asarray(p)))}")
    return _cdf(p)


@jax.jit
def _cdf(p):
    return jnp.cumsum(p).at[-1].set(1.0)


def sample_delay(probs, d_min, u) -> jax.Array:
    """Inverse-CDF draw(s) d = d_min + #{k : cdf[k] <= u} ([D-3]), int32 of u's shape.

    ``u`` in [0, 1) (any shape, checked when concrete); ``d_min`` may be traced.
    """
    c = delay_cdf(probs)
    # The table spans d_min .. d_min + n - 1, which must stay within [D-1]'s range.
    d_min = v.int_value("d_min", d_min, 0, MAX_DELAY - c.shape[0] + 1)
    # Any shape, an empty batch of draws included; the range is checked before rounding to float32.
    u = v.array("u", u, lo=0.0, hi=1.0, hi_open=True, allow_empty=True)
    return _inverse_cdf(c, d_min, u)


@jax.jit
def _inverse_cdf(c, d_min, u):
    # The last CDF entry is exactly 1 > u, so it never counts: leaving it out keeps a valid u that float32
    # rounds up to 1.0 (any u >= 1 - 2^-25) on the table's last delay instead of one past it.
    return d_min + jnp.sum(c[:-1] <= u[..., None], axis=-1).astype(jnp.int32)


def sample_delays(key, probs, d_min, shape=()) -> jax.Array:
    """Delays of the given static ``shape`` from a PRNG key ([D-3], [D-4], [N-9]).

    ``shape`` entries are integers >= 0 holding at most 2^31 - 1 draws in all ([N-12]).
    Draws ``u = jax.random.uniform(key, shape)`` in [0, 1) and applies
    :func:`sample_delay`, so a caller holding the same ``u`` gets the same d.
    """
    if isinstance(shape, (int, np.integer)) and not isinstance(shape, bool):
        shape = (int(shape),)
    if not isinstance(shape, (tuple, list)):
        raise ValueError(f"shape must be an integer or a tuple of integers >= 0, got {shape!r}")
    shape = tuple(v.check_int("shape entry", s, 0, MAX_DRAWS) for s in shape)
    if int(np.prod(shape, dtype=object)) > MAX_DRAWS:  # object: Python ints, no overflow
        raise ValueError(f"shape must hold at most {MAX_DRAWS} draws ([N-12]), got {shape}")
    if not (isinstance(key, jax.Array) and (jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                                            or (key.dtype == jnp.uint32 and key.shape == (2,)))):
        raise ValueError(f"key must be a JAX PRNG key (jax.random.key or jax.random.PRNGKey), got {key!r}")
    return sample_delay(probs, d_min, jax.random.uniform(key, shape, jnp.float32))
