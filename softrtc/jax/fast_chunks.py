"""Fast chunks of one method for one policy: what is known ahead is built once, each request is one call
([S-6], [X-2], [B-3], [P-19], [G-7]).

:class:`FastChunks` is built once per policy (its parameters), method, soft
window, execute horizon ``s`` and Euler step count ``T``. It holds the
per-delay token weights and time conditioning ([S-3], [G-2]), the naive
conditioning of the first chunk, and for the guided methods the stored
transposed kernels of the pull-back ([P-19]); every call encodes the
observation once ([B-3]). Then::

    chunks = FastChunks(policy, "train_soft", execute_horizon=4, num_steps=5)
    c0 = chunks.first(obs, jax.random.key(0))              # naive sampler ([X-2])
    prior = softrtc.jax.executor.shift_prior(c0, 4)       # [X-3]
    c1 = chunks.next(obs, prior, 2, jax.random.key(1))     # delay d = 2

A Python or NumPy delay picks its precomputed row on the host, so one
compiled call serves every delay. A traced delay, or one delay per batch
entry ``[B]``, gathers its row from the tables inside the computation; a
:class:`FastChunks` may also be built inside a ``jit`` from a policy whose
parameters are traced (e.g. one compiled rollout for every checkpoint).
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference.methods import check_method_step

from . import _validate as v
from .methods import (METHODS, _check_tables, delay_rows, generate_chunk_conditioned, generate_chunk_from_row,
                      method_tables)
from .policy import FlowPolicy
from .sampler import conditioning_table, naive_conditioning, naive_sample_conditioned

__all__ = ["FastChunks", "guided_tokens_for", "RESTRICT_MIN_ROWS"]

# [B-3] The guided methods restrict their pull-back ([G-7]) when each of the two token groups it
# evaluates has at least this many rows (batch * min(H - s, s)).
RESTRICT_MIN_ROWS = 16
# Upper bound of the Euler step count ([N-12]).
MAX_STEPS = 1 << 16


def guided_tokens_for(method: str, H: int, s: int, batch: int) -> int | None:
    """``guided_tokens`` of the fast path: ``H - s`` or None (the full pull-back) ([B-3], [G-7]).

    Only the guided methods restrict, and only when each token group of the
    split evaluation ([P-18]) has at least :data:`RESTRICT_MIN_ROWS` rows,
    ``batch * min(H - s, s) >= 16``. The split runs the last layers' matrix
    products twice on half the rows; on XLA:CPU a product with few rows costs
    about as much as one with twice as many, so with small batches the split
    costs more forward time than the restricted backward saves.

    >>> guided_tokens_for("inference_soft", 8, 4, 1), guided_tokens_for("inference_soft", 8, 4, 32)
    (None, 4)
    """
    v.check_choice("method", method, METHODS)
    H = v.check_int("H", H, 1)
    s = v.check_int("s", s, 1, H)
    batch = v.check_int("batch", batch, 1)
    return _guided_tokens(method, H, s, batch)


def _guided_tokens(method: str, H: int, s: int, batch: int) -> int | None:
    if not method.startswith("inference_") or s == H or batch * min(H - s, s) < RESTRICT_MIN_ROWS:
        return None
    return H - s


class _Encoded:
    """The policy seen through one observation encoding ([B-3]) and, optionally, its pull-back kernels ([P-19]).

    Exposes the ``time_conditioning`` / ``apply_conditioned`` interface that
    the conditioned samplers use, with ``in_proj``'s observation half computed
    once per sampler call instead of once per Euler step.
    """

    def __init__(self, policy: FlowPolicy, obs_encoding: jax.Array, pullback=None):
        self.policy = policy
        self.obs_encoding = obs_encoding
        self.pullback = pullback

    def time_conditioning(self, t):
        return self.policy.time_conditioning(t)

    def apply_conditioned(self, obs, x, cond):
        return self.policy.apply_conditioned(obs, x, cond, obs_encoding=self.obs_encoding, pullback=self.pullback)

    def apply_conditioned_split(self, obs, x, cond, head):
        return self.policy.apply_conditioned_split(obs, x, cond, head, obs_encoding=self.obs_encoding,
                                                   pullback=self.pullback)


class _Spec(NamedTuple):
    """Everything static of a :class:`FastChunks`: the key under which its calls are compiled."""

    graphdef: Any
    treedef: Any
    method: str
    H: int
    A: int
    s: int
    T: int
    guided: Any  # "rule" (guided_tokens_for at the traced batch size) or a fixed guided_tokens / None
    step: str = "algorithm1"  # the training-time sampler's solver step ([S-10])


def _model(spec: _Spec, leaves, obs, pullback) -> _Encoded:
    policy = nnx.merge(spec.graphdef, jax.tree.unflatten(spec.treedef, leaves))
    return _Encoded(policy, policy.encode_obs(obs), pullback)


def _tokens(spec: _Spec, batch: int) -> int | None:
    return _guided_tokens(spec.method, spec.H, spec.s, batch) if spec.guided == "rule" else spec.guided


def _noise(spec: _Spec, key, batch: int) -> jax.Array:
    """Standard normal noise [B, H, A] from one key, or from one key per batch entry ([N-9])."""
    if key.ndim == 0:
        return jax.random.normal(key, (batch, spec.H, spec.A), jnp.float32)
    return jax.vmap(lambda k: jax.random.normal(k, (spec.H, spec.A), jnp.float32))(key)


def _first(spec: _Spec, leaves, cond, obs, noise):
    # The first chunk of every method is the naive sampler.
    return naive_sample_conditioned(_model(spec, leaves, obs, None), obs, noise, spec.T, cond=cond)


def _from_row(spec: _Spec, leaves, row, pullback, obs, noise, prior):
    return generate_chunk_from_row(spec.method, _model(spec, leaves, obs, pullback), obs, noise, prior, spec.T,
                                   row, guided_tokens=_tokens(spec, obs.shape[0]), step=spec.step)


def _gathered(spec: _Spec, leaves, tables, pullback, obs, noise, prior, d):
    return generate_chunk_conditioned(spec.method, _model(spec, leaves, obs, pullback), obs, noise, prior,
                                      spec.s, d, spec.T, tables=tables,
                                      restrict_guidance=_tokens(spec, obs.shape[0]) is not None, step=spec.step)


def _first_keyed(spec, leaves, cond, obs, key):
    return _first(spec, leaves, cond, obs, _noise(spec, key, obs.shape[0]))


def _row_keyed(spec, leaves, row, pullback, obs, prior, key):
    return _from_row(spec, leaves, row, pullback, obs, _noise(spec, key, obs.shape[0]), prior)


def _gathered_keyed(spec, leaves, tables, pullback, obs, prior, d, key):
    return _gathered(spec, leaves, tables, pullback, obs, _noise(spec, key, obs.shape[0]), prior, d)


# One jitted function per (call, spec), kept for the process: objects of one architecture, method, s and T
# share their compilations (a new FastChunks per checkpoint compiles nothing new), and the cache of one
# function counts the compilations of that call alone ([B-7]).
_JITTED: dict = {}


def _jitted(fn, spec: _Spec):
    if (fn, spec) not in _JITTED:
        _JITTED[(fn, spec)] = jax.jit(partial(fn, spec))
    return _JITTED[(fn, spec)]


class FastChunks:
    """Chunks of ``method`` ([S-6]) from ``policy`` on the fast path, for one window, ``s`` and ``T``.

    Args:
        policy: a :class:`~softrtc.jax.policy.FlowPolicy` (concrete, or merged from traced parameters
            inside a ``jit``).
        method: one of :data:`~softrtc.jax.methods.METHODS`.
        execute_horizon: ``s`` in [1, H].
        num_steps: Euler steps ``T``.
        window: the soft window of ``train_soft`` ([W-7]; default the paper's main one).
        weights: a weight table ``[min(s, H - s) + 1, H]`` (row d for delay d, may be traced) used
            instead of the method's own; the method then selects the sampler only (an evaluation
            that varies the window without compiling again, [KE-3]).
        guided_tokens: the guided methods' pull-back ([G-7]): ``"rule"`` (:func:`guided_tokens_for`
            at each call's batch size), None (all tokens) or a token count in [1, H - 1].
        stored_transposes: the guided methods multiply by stored transposed kernels ([P-19]).
        step: the training-time sampler's solver step, "algorithm1" (default) or "consistent" ([S-10]);
            naive accepts either, the guided methods only "algorithm1" ([S-14]).

    Every argument is checked here; the calls check what they are given
    (shapes, dtypes, the delay's range when concrete). ``key`` is one typed
    PRNG key, from which noise ``[B, H, A]`` is drawn, or one key per batch
    entry ``[B]``, each drawing its own ``[H, A]`` ([N-9]).
    """

    def __init__(self, policy: FlowPolicy, method: str, execute_horizon: int, num_steps: int, window=None, *,
                 weights=None, guided_tokens="rule", stored_transposes: bool = True, step: str = "algorithm1"):
        if not isinstance(policy, FlowPolicy):
            raise ValueError(f"policy must be a softrtc.jax.policy.FlowPolicy, got {type(policy).__name__}")
        method = v.check_choice("method", method, METHODS)
        step = check_method_step(method, step)
        H, A = policy.action_chunk_size, policy.action_dim
        s = v.check_int("execute_horizon", execute_horizon, 1, H)
        T = v.check_int("num_steps", num_steps, 1, MAX_STEPS)
        if not (guided_tokens is None or guided_tokens == "rule"):
            guided_tokens = v.check_int("guided_tokens", guided_tokens, 1, H - 1)
        v.check_bool("stored_transposes", stored_transposes)
        graphdef, state = nnx.split(policy)
        leaves, treedef = jax.tree.flatten(state)
        self.method, self.H, self.A, self.s, self.T, self.step = method, H, A, s, T, step
        self.max_delay = min(s, H - s)
        self._spec = _Spec(graphdef, treedef, method, H, A, s, T, guided_tokens, step)
        self._leaves = tuple(leaves)
        if weights is None:
            tables = method_tables(method, policy, H, s, T, window)
        else:
            w = v.array("weights", weights, shape=(self.max_delay + 1, H), lo=0.0, hi=1.0)
            cond = conditioning_table(policy, w, T) if method.startswith("train_") else naive_conditioning(policy, T)
            tables = {"weights": w, "cond": cond}
            _check_tables(method, tables, H, s, T)
        self._tables = tables
        self._rows = delay_rows(method, tables)
        guided = method.startswith("inference_")
        self._pullback = policy.pullback_kernels() if guided and stored_transposes else None
        self._naive = tables["cond"] if not method.startswith("train_") else naive_conditioning(policy, T)
        # Looked up once: a request then costs one jitted call and no hashing of the spec.
        self._fns = {fn.__name__: _jitted(fn, self._spec)
                     for fn in (_first, _from_row, _gathered, _first_keyed, _row_keyed, _gathered_keyed)}

    # ------------------------------------------------------------------ requests

    def first(self, obs, key) -> jax.Array:
        """The first chunk ``[B, H, A]`` (naive sampler, no prior, d = 0, [X-2]) for observations ``[B, O]``."""
        return self._fns["_first_keyed"](self._leaves, self._naive, obs, self._key(key, obs))

    def next(self, obs, prior, d, key) -> jax.Array:
        """A later chunk ``[B, H, A]`` for the prior ``[B, H, A]`` ([X-3]) and delay ``d`` ([X-1]): one
        integer (picked on the host when concrete) or one per batch entry ``[B]``."""
        key = self._key(key, obs)
        if self._on_host(d):
            row = self._rows[self._delay(d)]
            return self._fns["_row_keyed"](self._leaves, row, self._pullback, obs, prior, key)
        return self._fns["_gathered_keyed"](self._leaves, self._tables, self._pullback, obs, prior, d, key)

    def chunk(self, obs, noise, prior, d=0) -> jax.Array:
        """:meth:`first` (``prior`` None, ``d`` 0) or :meth:`next` with the noise ``[B, H, A]`` given."""
        if prior is None:
            v.int_value("d", d, 0, 0)
            return self._fns["_first"](self._leaves, self._naive, obs, noise)
        if self._on_host(d):
            row = self._rows[self._delay(d)]
            return self._fns["_from_row"](self._leaves, row, self._pullback, obs, noise, prior)
        return self._fns["_gathered"](self._leaves, self._tables, self._pullback, obs, noise, prior, d)

    def compile_chunk(self, obs, noise, prior):
        """``chunk`` compiled now for these shapes (so the VJP rules in force while tracing apply, [B-12]);
        returns ``fn(obs, noise, prior, d)`` for concrete delays."""
        fn = jax.jit(partial(_from_row, self._spec))  # a fresh function: traced now, whatever is cached
        compiled = fn.lower(self._leaves, self._rows[0], self._pullback, obs, noise, prior).compile()
        return lambda obs, noise, prior, d: compiled(self._leaves, self._rows[self._delay(d)], self._pullback,
                                                     obs, noise, prior)

    def block_until_ready(self) -> "FastChunks":
        """Wait until the tables built at construction are computed (to time the construction, [B-3])."""
        jax.block_until_ready((self._tables, self._rows, self._pullback, self._naive))
        return self

    def compilations(self) -> int:
        """Programs compiled so far for :meth:`chunk` with a prior and a host delay, by every object of this
        architecture, method, s and T: one per input shape, whatever the delays ([B-7])."""
        return self._fns["_from_row"]._cache_size()

    # ------------------------------------------------------------------ checks

    def _on_host(self, d) -> bool:
        return not v.is_traced(d) and jnp.ndim(d) == 0

    def _delay(self, d) -> int:
        # A concrete integer array scalar is read once on the host (no device round trip per check).
        if isinstance(d, (jax.Array, np.ndarray)) and d.ndim == 0 and jnp.issubdtype(d.dtype, jnp.integer):
            d = int(d)
        return v.check_int("d", d, 0, self.max_delay)

    def _key(self, key, obs):
        if not isinstance(key, jax.Array) or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed)) or one per batch entry")
        batch = jnp.shape(obs)[0] if jnp.ndim(obs) >= 1 else None
        if key.ndim != 0 and key.shape != (batch,):
            raise ValueError(f"key must be one typed PRNG key or one per batch entry, shape ({batch},), "
                             f"got shape {tuple(key.shape)}")
        return key
