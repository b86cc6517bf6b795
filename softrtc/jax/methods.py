"""The five chunk-generation methods in JAX (spec chapter S, [S-6]); twin of ``softrtc.reference.methods``.

| method          | sampler          | weights                                     |
|-----------------|------------------|---------------------------------------------|
| naive           | naive_sample     | none (the prior is ignored)                  |
| inference_hard  | guided_sample    | prefix_weights(H, d, H - s, "zeros")         |
| inference_soft  | guided_sample    | prefix_weights(H, d, H - s, "exp")           |
| train_hard      | rtc_sample       | hard_weights(H, d)                           |
| train_soft      | rtc_sample       | soft_weights(H, d, window, s)                |

``method``, ``H``, ``s`` and ``num_steps`` are static; the delay ``d`` (a
scalar, or one delay per example ``[B]``) and the window's rule parameters
may be traced, so one compiled ``generate_chunk`` serves every delay.
Traced delays must satisfy [X-1] ``0 <= d <= min(s, H - s)``; concrete ones
are checked. For the first chunk (``prior=None``) every method is the naive
sampler with d = 0 ([X-2]). ``step`` ([S-10]) selects the training-time
sampler's solver step; naive accepts either, the guided methods only
"algorithm1" ([S-14]).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from softrtc.reference import methods as _ref

from . import _validate as v
from .guidance import _BETA, _check_guided_tokens, _guidance_prefix, _guided_conditioned, _guided_plain
from .sampler import (MAX_STEPS, _check_fn, _check_model, _cond_table, _naive, _naive_cond, _naive_conditioned, _rtc,
                      _rtc_conditioned, _select, check_batch, check_leading, check_tree, check_unroll, model_horizon,
                      select_conditioning)
from .weights import SoftWindow, _hard, _soft_weights, check_window

METHODS = _ref.METHODS


def _delay(H, s, d, B=None):
    """A delay scalar or vector [B]; concrete entries must satisfy [X-1]."""
    hi = min(s, H - s)
    if d is None or isinstance(d, str):
        raise ValueError(f"d must be an integer in [0, {hi}] or a non-empty vector [B] of them, got {d!r}")
    if jnp.ndim(d) == 0:
        return v.int_value("d", d, 0, hi)
    d = v.int_array("d", d, shape=(B,), lo=0, hi=hi)
    if 0 in d.shape:  # [N-12] arrays have no empty axis
        raise ValueError(f"d must be an integer in [0, {hi}] or a non-empty vector [B] of them, got an empty vector")
    return d


def _check_request(method, noise, prior, s, d, window):
    """Checks shared by the generate_chunk functions; returns (H, s, d checked against [X-1] or None,
    the window: a given one checked, train_soft's default for a later chunk, else None).

    Arguments a method ignores are checked all the same ([S-8]): the delay for
    every method, naive included (a delay the executor cannot run is an error,
    [X-1]); the prior naive ignores (the other samplers check theirs); a given
    window for every method and for the first chunk.
    """
    v.check_choice("method", method, METHODS)
    H = jnp.shape(noise)[1] if jnp.ndim(noise) == 3 else 0
    H = v.check_int("noise.shape[1] (H)", H, 1)
    s = v.check_int("s", s, 1, H)
    _check_first(prior, d)
    dd = None
    if prior is not None:
        dd = _delay(H, s, d, jnp.shape(noise)[0])
        if method == "naive":
            v.array("prior", prior, shape=jnp.shape(noise))
    if window is not None:
        window = check_window(H, window)
    elif method == "train_soft" and prior is not None:
        window = check_window(H, SoftWindow())
    return H, s, dd, window


def _one(method, H, s, d, window):
    """[S-6] The weights of ``method`` for one delay; arguments checked by the caller (``d`` int32)."""
    s = jnp.asarray(s, jnp.int32)
    if method == "naive":
        return jnp.zeros((H,), jnp.float32)  # naive: no weights
    if method.startswith("inference_"):
        return _guidance_prefix(H, s, d, method.split("_", 1)[1])  # [G-1]
    if method == "train_hard":
        return _hard(H, d)  # [W-8]
    return _soft_weights(H, d, window, s)  # [W-7]


def method_weights(method: str, H: int, s: int, d, window=None) -> jax.Array:
    """Token weights of ``method`` for delay d ([S-6], [G-1], [W-7], [W-8]).

    ``d`` scalar gives [H]; ``d [B]`` gives [B, H]. ``window`` (used by
    train_soft only) is a JAX or reference :class:`SoftWindow`, default
    ``SoftWindow()``; a given window is checked for every method, the default
    is resolved for train_soft only ([S-8]).
    """
    H, s, window = _check_method(method, H, s, window)
    return _weights(method, H, s, _delay(H, s, d), window)


def _check_method(method, H, s, window):
    """``method``, ``H``, ``s`` and ``window`` of :func:`method_weights` checked; returns (H, s, window), the
    window resolved for train_soft ([S-8])."""
    v.check_choice("method", method, METHODS)
    H = v.check_horizon(H)
    s = v.check_int("s", s, 1, H)
    if window is not None or method == "train_soft":
        window = check_window(H, SoftWindow() if window is None else window)
    return H, s, window


def _weights(method, H, s, d, window):
    """:func:`method_weights` of checked arguments: ``d`` a checked int32 scalar or vector, ``window``
    checked (resolved for train_soft)."""
    if d.ndim == 0:
        return _one(method, H, s, d, window)
    return jax.vmap(lambda di: _one(method, H, s, di, window))(d)


def method_weight_table(method: str, H: int, s: int, window=None) -> jax.Array:
    """Weights for every executable delay d = 0 .. min(s, H - s) ([X-1]): [min(s, H - s) + 1, H].

    ``table[d]`` equals ``method_weights(method, H, s, d, window)``. (For
    training delays up to H use :func:`softrtc.jax.weights.weight_table`.)
    """
    H, s, window = _check_method(method, H, s, window)
    return _weight_table(method, H, s, window)


def _weight_table(method, H, s, window):
    """:func:`method_weight_table` of checked arguments: rows d = 0 .. min(s, H - s) ([X-1])."""
    return _weights(method, H, s, jnp.arange(min(s, H - s) + 1, dtype=jnp.int32), window)


def _check_first(prior, d):
    """[X-2] The first chunk (prior None) has d = 0; a traced d cannot be checked and is ignored."""
    if prior is None and not v.is_traced(d):
        if jnp.ndim(d) != 0:
            raise ValueError("d must be an integer in [0, 0] for the first chunk (prior=None, [X-2])")
        v.int_value("d", d, 0, 0)


def generate_chunk(method: str, velocity_fn, obs, noise, prior, s: int, d, num_steps: int,
                   window=None, *, unroll: bool = True, step: str = "algorithm1") -> jax.Array:
    """One batch of chunks by ``method`` ([S-6]) on the straightforward path.

    Batch conventions of :mod:`softrtc.jax.sampler` (obs [B, O], noise and
    prior [B, H, A], ``velocity_fn(obs, x, t [B, H])``). ``prior=None`` is the
    first chunk: naive sampler, d must be 0 ([X-2]).
    """
    H, s, dd, window = _check_request(method, noise, prior, s, d, window)
    step = _ref.check_method_step(method, step)
    unroll = check_unroll(unroll)
    _check_fn("velocity_fn", velocity_fn)
    naive = prior is None or method == "naive"
    obs, x, y, _, T = check_batch(obs, noise, None if naive else prior, num_steps=num_steps, model=velocity_fn)
    # Checked once, above: the samplers' cores take the checked values.
    if naive:
        return _naive(velocity_fn, obs, x, T, unroll)
    w = _weights(method, H, s, dd, window)
    if method.startswith("inference_"):
        return _guided_plain(velocity_fn, obs, x, y, w, T, _BETA, unroll)
    return _rtc(velocity_fn, obs, x, y, w, T, unroll, step)


def method_tables(method: str, model, H: int, s: int, num_steps: int, window=None) -> dict:
    """Precomputed per-method tables for :func:`generate_chunk_conditioned` ([S-3], [G-2]).

    ``{"weights": [D, H], "cond": ...}`` with D = min(s, H - s) + 1. For the
    training-time methods ``cond`` is the per-delay conditioning table
    (``sampler.conditioning_table``); for naive and guided methods, which
    evaluate the model at the scalar time t_k, it is the naive conditioning.
    Depends on the model's parameters and the window only: build it once per
    parameter update, outside the rollout loop.
    """
    H, s, window = _check_method(method, H, s, window)
    _check_model(model)
    _check_model_horizon(model, H, "method_tables")
    T = v.check_int("num_steps", num_steps, 1, MAX_STEPS)
    w = _weight_table(method, H, s, window)
    if method.startswith("train_"):
        return {"weights": w, "cond": _cond_table(model, w, T)}
    return {"weights": w, "cond": _naive_cond(model, T)}


def _check_model_horizon(model, H: int, where: str) -> None:
    """A model that declares its chunk length (``horizon``, ``action_chunk_size``) must have this H ([N-7])."""
    mH = model_horizon(model)
    if mH is not None and mH != H:
        raise ValueError(f"model must have the horizon H={H} given to {where}, got a model with H={mH}")


def _check_tables(method: str, tables, H: int, s: int, T) -> None:
    """``tables`` is :func:`method_tables` of this method, H, s and T ([N-7]); JAX would clamp a mismatch."""
    if not isinstance(tables, dict) or set(tables) != {"weights", "cond"}:
        raise ValueError("tables must be the dict returned by method_tables (keys 'weights', 'cond')")
    D = min(s, H - s) + 1
    w = tables["weights"]
    if tuple(jnp.shape(w)) != (D, H):
        raise ValueError(f"tables['weights'] must have shape [{D}, {H}] (method_tables with H={H}, s={s}), "
                         f"got {list(jnp.shape(w))}")
    T = v.check_int("num_steps", T, 1)
    check_leading("tables['cond']", tables["cond"], (D, T) if method.startswith("train_") else (T,))


def delay_rows(method: str, tables: dict) -> tuple:
    """Split :func:`method_tables` into one row per delay: ``rows[d] = {"weights": [H], "cond": ...}`` ([S-6]).

    A caller that knows the delay on the host (a real-time runtime measures it)
    picks ``rows[d]`` with a Python index and passes it to a jitted
    :func:`generate_chunk_from_row`; every row has the same shapes, so one
    compilation serves every delay. This avoids gathering the conditioning of
    delay ``d`` from the ``[D, T, ...]`` table inside the compiled call, which
    XLA on CPU does as a copy that costs more than the blend itself at batch 1.
    """
    v.check_choice("method", method, METHODS)
    if not isinstance(tables, dict) or set(tables) != {"weights", "cond"}:
        raise ValueError("tables must be the dict returned by method_tables (keys 'weights', 'cond')")
    w = v.array("tables['weights']", tables["weights"], ndim=2, lo=0.0, hi=1.0)
    # Only training-time tables carry a delay axis; naive and guided samplers share one conditioning.
    per_delay = method.startswith("train_")
    if per_delay:
        # One conditioning per weight row: a table with fewer (or more) rows than weights would be
        # truncated (or leave rows without weights) silently.
        check_leading("tables['cond']", tables["cond"], (int(w.shape[0]),))
    else:
        check_tree("tables['cond']", tables["cond"])
    return tuple({"weights": w[d],
                  "cond": select_conditioning(tables["cond"], jnp.int32(d)) if per_delay else tables["cond"]}
                 for d in range(int(w.shape[0])))


def generate_chunk_from_row(method: str, model, obs, noise, prior, num_steps: int, row: dict, *,
                            guided_tokens: int | None = None, unroll: bool = True,
                            step: str = "algorithm1") -> jax.Array:
    """One chunk by ``method`` from a per-delay row of :func:`delay_rows` ([S-6]).

    ``prior`` None means the first chunk: naive sampling, for which the row's
    weights are not used (pass ``rows[0]``, the row of d = 0 [X-2]).
    ``guided_tokens`` (guided methods only, e.g. H - s) restricts
    the guided pull-back to tokens j < guided_tokens ([G-7]); see
    :func:`softrtc.jax.guidance.guided_sample_conditioned`.

    The request is checked whole ([S-8]), also where the chunk does not use
    it: the row's weights ([H], in [0, 1]) and conditioning (leading axis T)
    for the first chunk and for naive; a given ``guided_tokens`` in
    [1, H - 1] for every method (for the guided methods also against the
    row's weights, [G-7]); ``unroll``. Which delay a row belongs to cannot
    be read from its weights (a window with the "ones" schedule, or the
    "paper" parametrization, has w_0 = 1 at d = 0 too), so it is not checked.
    """
    v.check_choice("method", method, METHODS)
    step = _ref.check_method_step(method, step)
    if not isinstance(row, dict) or set(row) != {"weights", "cond"}:
        raise ValueError("row must be an entry of delay_rows(...) (keys 'weights', 'cond')")
    _check_model(model)
    _, x, _, _, T = check_batch(obs, noise, num_steps=num_steps, model=model)
    H = x.shape[1]
    unroll = check_unroll(unroll)
    w = v.array("row['weights']", row["weights"], shape=(H,), lo=0.0, hi=1.0)
    check_leading("row['cond']", row["cond"], (T,))
    head = None
    if guided_tokens is not None:
        if method.startswith("inference_"):
            head = _check_guided_tokens(model, guided_tokens, w, H)
        else:
            v.check_int("guided_tokens", guided_tokens, 1, H - 1)
    # A prior is a chunk batch for every method; naive ignores it ([S-8]).
    y = None if prior is None else v.array("prior", prior, shape=x.shape)
    if prior is None or method == "naive":
        cond = None if method.startswith("train_") else row["cond"]
        return _naive_conditioned(model, obs, x, T, cond, unroll)
    if method.startswith("inference_"):
        return _guided_conditioned(model, obs, x, y, w, T, _BETA, row["cond"], head, unroll)
    return _rtc_conditioned(model, obs, x, y, w, T, row["cond"], unroll, step)


def generate_chunk_conditioned(method: str, model, obs, noise, prior, s: int, d, num_steps: int,
                               window=None, *, tables: dict | None = None, restrict_guidance: bool = False,
                               unroll: bool = True, step: str = "algorithm1") -> jax.Array:
    """:func:`generate_chunk` on the fast path of ``model.apply_conditioned`` ([S-6]).

    ``model`` provides ``time_conditioning`` / ``apply_conditioned`` (the flow
    policy or the JAX reference field). ``tables`` (optional) comes from
    :func:`method_tables` with the same method, H, s, T and window; with it
    the weights and the conditioning of delay ``d`` (scalar or [B]) are
    gathered from the tables instead of computed. ``restrict_guidance``
    (guided methods) takes the pull-back through tokens j < H - s only, where
    the weights of [G-1] can be nonzero ([G-7], needs
    ``model.apply_conditioned_split``); chunks agree within float32 rounding.
    """
    H, s, dd, window = _check_request(method, noise, prior, s, d, window)
    step = _ref.check_method_step(method, step)
    if not isinstance(restrict_guidance, bool):
        raise ValueError(f"restrict_guidance must be a bool, got {restrict_guidance!r}")
    unroll = check_unroll(unroll)
    if tables is not None:
        _check_tables(method, tables, H, s, num_steps)
    _check_model(model)
    naive = prior is None or method == "naive"
    obs, x, y, _, T = check_batch(obs, noise, None if naive else prior, num_steps=num_steps, model=model)
    # Checked once, above: the samplers' cores take the checked values.
    naive_cond = None if tables is None or method.startswith("train_") else tables["cond"]
    if naive:
        return _naive_conditioned(model, obs, x, T, naive_cond, unroll)
    if tables is None:
        w = _weights(method, H, s, dd, window)
        cond = None
    else:
        # The tables' weights are the caller's: their values are checked here ([N-7]).
        w = v.array("weights", tables["weights"][dd], lo=0.0, hi=1.0)
        cond = _select(tables["cond"], dd) if method.startswith("train_") else naive_cond
    if method.startswith("inference_"):
        head = None
        if restrict_guidance and s < H:
            # [G-1] weights vanish from H - s on; given tables' weights are checked for it.
            head = _check_guided_tokens(model, H - s, None if tables is None else w, H)
        return _guided_conditioned(model, obs, x, y, w, T, _BETA, cond, head, unroll)
    return _rtc_conditioned(model, obs, x, y, w, T, cond, unroll, step)
