"""Inference-time RTC (guided inpainting, Black et al. 2025) in JAX (spec chapter G, 03-inference.md).

Twin of ``softrtc.reference.guidance``. The pull-back of the weighted error
through the denoiser x -> x1 = x + (1 - t) v(obs, x, t) is one ``jax.vjp``
per step ([G-3]), so any differentiable ``velocity_fn`` works (the flow
policy, the JAX reference field). Batch conventions are those of
:mod:`softrtc.jax.sampler`: obs [B, O], noise / prior [B, H, A], weights [H]
or [B, H], ``velocity_fn(obs, x [B, H, A], t [B, H])``. Examples of a batch
are independent, so the VJP of the batched denoiser with a per-example
cotangent is the per-example VJP.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference import guidance as _ref

from . import _validate as v
from .sampler import (_at, _runtime, _check_fn, _check_model, _loop, _naive_cond, _times, check_batch, check_leading,
                      check_unroll, field_output, require)
from .weights import PARAMETRIZATIONS, SCHEDULES, _prefix_jit

MAX_GUIDANCE = _ref.MAX_GUIDANCE
GUIDANCE_SCHEDULES = _ref.GUIDANCE_SCHEDULES


def guidance_prefix_weights(H: int, s, d, variant: str) -> jax.Array:
    """W = prefix_weights(H, d, H - s, zeros | exp, "rtc") ([G-1]).

    ``H`` and ``variant`` ("hard" | "soft") are static; ``s`` in [1, H] and
    ``d`` in [0, H - s] may be traced (checked when concrete; traced values
    outside give undefined results).
    """
    H = v.check_horizon(H)
    v.check_choice("variant", variant, tuple(GUIDANCE_SCHEDULES))
    s = v.int_value("s", s, 1, H)
    d = v.int_value("d", d, 0, H - int(s) if not v.is_traced(s) else H)
    return _guidance_prefix(H, s, d, variant)


def _guidance_prefix(H: int, s, d, variant: str) -> jax.Array:
    """:func:`guidance_prefix_weights` of checked arguments (``s``, ``d`` int32)."""
    return _prefix_jit(H, d, H - s, np.int32(SCHEDULES.index(GUIDANCE_SCHEDULES[variant])),
                       np.int32(PARAMETRIZATIONS.index("rtc")))  # [G-1] W: start d, end H - s


def guidance_weight(t, max_guidance=MAX_GUIDANCE) -> jax.Array:
    """lam(t) = min(c (t^2 + (1-t)^2) / (1-t)^2, beta), c = (1-t)/t, lam(0) = beta ([G-4]).

    ``t`` in [0, 1) and ``beta > 0`` may be traced. At t = 0 the where-select
    gives c = +inf without evaluating 1/0 in the selected lane, so no NaN appears.
    """
    t = v.array("t", t, lo=0.0)
    if not v.is_traced(t) and t.size and float(np.max(np.asarray(t))) >= 1.0:
        raise ValueError(f"t must lie in [0, 1), got max {float(np.max(np.asarray(t)))}")
    beta = v.real_value("max_guidance", max_guidance, 0.0, lo_open=True)
    return _guidance_weight(t, beta)


def _guidance_weight(t, beta) -> jax.Array:
    """[G-4] lam(t) for checked t in [0, 1) and beta > 0."""
    safe_t = jnp.where(t == 0.0, 1.0, t)
    c = jnp.where(t == 0.0, jnp.inf, (1.0 - t) / safe_t)
    inv_r2 = (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2
    return jnp.minimum(c * inv_r2, beta)


def _guided(apply_fn, obs, x, y, w, T, beta, unroll, head=None):
    """Shared loop: ``apply_fn(k, x)`` is the velocity at step k ([G-2]..[G-5]).

    With ``head`` (an integer), ``apply_fn(k, x)`` returns the velocity as two
    token groups ``(v[:, :head], v[:, head:])`` and the pull-back runs through
    the first group only ([G-7]); the caller guarantees ``w[..., head:] == 0``.
    """
    times = _times(T)
    (wx,) = _runtime(jnp.broadcast_to(w, x.shape[:2])[..., None])

    def step(k, x):
        t = times[k]

        if head is None:
            def denoise(x):
                vel = apply_fn(k, x)
                return x + (1.0 - t) * vel, vel

            x1, pullback, vel = jax.vjp(denoise, x, has_aux=True)
            err = wx * (y - x1)
        else:
            def denoise(x):
                v_head, v_tail = apply_fn(k, x)
                return x[:, :head] + (1.0 - t) * v_head, jnp.concatenate([v_head, v_tail], axis=1)

            # Tokens j >= head have W_j = 0, so their error is zero and is left out of the pull-back.
            x1, pullback, vel = jax.vjp(denoise, x, has_aux=True)
            err = wx[:, :head] * (y[:, :head] - x1)
        (g,) = pullback(err)
        return x + (vel + _guidance_weight(t, beta) * g) / T

    return _loop(step, x, T, unroll)


def guided_sample(velocity_fn, obs, noise, prior, weights, num_steps: int,
                  max_guidance=MAX_GUIDANCE, *, unroll: bool = True) -> jax.Array:
    """Guided sampler of inference-time RTC ([G-2]..[G-5]); returns x^T [B, H, A].

    g = (d x1 / d x)^T err by ``jax.vjp``; with W = 0 the result is bitwise
    :func:`softrtc.jax.sampler.naive_sample` ([G-6]).
    """
    _check_fn("velocity_fn", velocity_fn)
    _require_prior_weights(prior, weights)
    obs, x, y, w, T = check_batch(obs, noise, prior, weights, num_steps, model=velocity_fn)
    unroll = check_unroll(unroll)
    beta = v.real_value("max_guidance", max_guidance, 0.0, lo_open=True)
    return _guided_plain(velocity_fn, obs, x, y, w, T, beta, unroll)


def _guided_plain(velocity_fn, obs, x, y, w, T: int, beta, unroll: bool) -> jax.Array:
    """[G-2]..[G-5] the guided sampler on checked arguments (``x`` the noise, ``y`` the prior)."""
    # Same runtime time vector as sampler.naive_sample, so that W = 0 is bitwise naive ([G-6]).
    times, w0 = _runtime(_times(T), jnp.zeros(x.shape[:2], jnp.float32))

    def apply_fn(k, x):
        return field_output("velocity_fn", velocity_fn(obs, x, w0 + (1.0 - w0) * times[k]), x)

    return _guided(apply_fn, obs, x, y, w, T, beta, unroll)


def guided_sample_conditioned(model, obs, noise, prior, weights, num_steps: int,
                              max_guidance=MAX_GUIDANCE, *, cond=None, guided_tokens: int | None = None,
                              unroll: bool = True) -> jax.Array:
    """:func:`guided_sample` through ``model.apply_conditioned`` ([G-2]..[G-5]).

    Guidance evaluates the model at the scalar time t_k ([G-2]), so the
    conditioning is that of the naive sampler (``sampler.naive_conditioning``),
    computed here if ``cond`` is omitted.

    ``guided_tokens`` (optional, a static integer n in [1, H - 1]) declares
    that ``weights[..., n:]`` is zero, as it is for the weights of [G-1] with
    n = H - s: the pull-back then runs through the velocity of tokens j < n
    only ([G-7]), which needs ``model.apply_conditioned_split`` ([P-18]).
    Concrete weights are checked; traced ones are the caller's promise. The
    chunks equal those without it within float32 rounding (not bitwise, so
    [G-6] holds only without it).
    """
    _check_model(model)
    _require_prior_weights(prior, weights)
    obs, x, y, w, T = check_batch(obs, noise, prior, weights, num_steps, model=model)
    unroll = check_unroll(unroll)
    beta = v.real_value("max_guidance", max_guidance, 0.0, lo_open=True)
    if cond is not None:
        check_leading("cond", cond, (T,))
    head = None if guided_tokens is None else _check_guided_tokens(model, guided_tokens, w, x.shape[1])
    return _guided_conditioned(model, obs, x, y, w, T, beta, cond, head, unroll)


# max_guidance's default as the checked value v.real_value gives (float32 on the host).
_BETA = np.asarray(np.float32(MAX_GUIDANCE))


def _guided_conditioned(model, obs, x, y, w, T: int, beta, cond, head, unroll: bool) -> jax.Array:
    """[G-2]..[G-5], [G-7] the guided sampler through ``model.apply_conditioned`` on checked arguments;
    ``cond`` a checked naive conditioning or None (computed here), ``head`` a checked token count or None."""
    cond = _naive_cond(model, T) if cond is None else cond

    if head is None:
        def apply_fn(k, x):
            return field_output("model.apply_conditioned", model.apply_conditioned(obs, x, _at(cond, k)), x)
    else:
        def apply_fn(k, x):
            return _split_output(model.apply_conditioned_split(obs, x, _at(cond, k), head), x, head)

    return _guided(apply_fn, obs, x, y, w, T, beta, unroll, head)


def _require_prior_weights(prior, weights) -> None:
    require("prior", prior, "an array [B, H, A] (the previous chunk in this chunk's frame, [X-3])")
    require("weights", weights, "an array [H] or [B, H] in [0, 1] (the guidance weights of [G-1])")


def _split_output(out, x, head: int) -> tuple:
    """``apply_conditioned_split`` must return two real arrays [B, head, A] and [B, H - head, A] ([N-7], [P-18])."""
    name = "model.apply_conditioned_split"
    if not isinstance(out, (tuple, list)) or len(out) != 2:
        raise ValueError(f"{name} must return a pair (v[:, :{head}], v[:, {head}:]), got {type(out).__name__}")
    B, H, A = x.shape
    return (field_output(f"{name} (first group)", out[0], jax.ShapeDtypeStruct((B, head, A), x.dtype)),
            field_output(f"{name} (second group)", out[1], jax.ShapeDtypeStruct((B, H - head, A), x.dtype)))


def _check_guided_tokens(model, guided_tokens, weights, H: int) -> int:
    """Validates ``guided_tokens`` of :func:`guided_sample_conditioned` ([G-7]); returns it as an int."""
    n = v.check_int("guided_tokens", guided_tokens, 1, H - 1)
    if not callable(getattr(model, "apply_conditioned_split", None)):
        raise ValueError("guided_tokens needs a model with apply_conditioned_split(obs, x, cond, head) ([P-18]), "
                         f"which {type(model).__name__} does not provide")
    if weights is not None and not v.is_traced(weights) and bool(jnp.any(weights[..., n:] != 0)):
        raise ValueError(f"guided_tokens = {n} requires weights[..., {n}:] to be zero (the guidance weights of "
                         "tokens j >= guided_tokens), got nonzero entries")
    return n
