"""Soft RTC fine-tuning with noisy window priors: the project's variant, not the paper's method ([AX-5]).

At inference the soft window's prior is the previous chunk, planned from an
older observation; in training ([C-2]) it is the true action. This variant
trains the window tokens (``0 < w_j < 1``) from a corrupted input built on a
*perturbed* prior ``A_j + delta_j`` with ``delta_j ~ N(0, sigma_j^2)``
(normalized action units, per token and action dimension), while the target
velocity stays ``A - eps`` and the loss mask stays ``1 - w`` ([L-2]). The
committed prefix (``w = 1``) is not perturbed: at inference it is exactly the
executed previous chunk. ``sigma`` is measured on the base policy's rollouts
(:func:`softrtc.arm.experiment.measure_prior_error`): the error of the shifted
previous chunk against the fresh plan at the same observation.

Everything else is chapter T's step ([T-2]..[T-9]): the same optimizer
(:func:`softrtc.jax.training.make_optimizer`), the same minibatch order and
the same per-step draws of delay, flow time and noise from the same key, so a
run differs from the plain soft fine-tune of the same seed only by ``delta``
(drawn from its own key, ``fold_in(step key, 1)``).
"""

from __future__ import annotations

import functools

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from softrtc.jax.delays import delay_cdf
from softrtc.jax.loss import ETA, flow_matching_loss
from softrtc.jax.policy import FlowPolicy
from softrtc.jax.training import TrainConfig, make_train_step

__all__ = ["train_prior_noise"]


def _loss(graphdef, rest, params, obs, actions, key, wt, cdf, d_min, sigma):
    model = nnx.merge(graphdef, params, rest)
    B, H, A = actions.shape
    # The same split and draws as chapter T's step, so delay, tau and eps match the plain run.
    k_d, k_tau, k_eps = jax.random.split(key, 3)
    u = jax.random.uniform(k_d, (B,), jnp.float32)
    d = d_min + jnp.sum(cdf <= u[:, None], axis=-1).astype(jnp.int32)
    tau = jax.random.uniform(k_tau, (B,), jnp.float32)
    eps = jax.random.normal(k_eps, (B, H, A), jnp.float32)
    w = wt[d]
    window = ((w > 0.0) & (w < 1.0)).astype(jnp.float32)
    delta = jax.random.normal(jax.random.fold_in(key, 1), (B, H, A), jnp.float32) * sigma[None]
    prior = actions + window[..., None] * delta
    tj = w + (1.0 - w) * tau[:, None]
    x = tj[..., None] * prior + (1.0 - tj[..., None]) * eps
    pred = model(obs, x, tj)
    return jnp.mean(flow_matching_loss(pred, actions, eps, w, ETA))


@functools.partial(jax.jit, static_argnums=(0, 1))
def _update(graphdef, optimizer, rest, params, opt_state, obs, actions, key, wt, cdf, d_min, sigma):
    loss, grads = jax.value_and_grad(_loss, argnums=2)(graphdef, rest, params, obs, actions, key, wt, cdf, d_min,
                                                       sigma)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss


def train_prior_noise(policy: FlowPolicy, obs, actions, config: TrainConfig, key, num_steps: int,
                      sigma) -> tuple[FlowPolicy, np.ndarray]:
    """Fine-tune ``policy`` with the soft objective of ``config`` and window priors perturbed by ``sigma``.

    ``obs [N, O]`` and ``actions [N, H, A]`` are normalized arrays (as given
    to ``softrtc.jax.training.train``), ``config.method`` must be ``soft``,
    ``sigma`` is ``[H, A]`` (finite, ``>= 0``; all zeros gives the plain soft
    objective). Returns ``(policy, losses [num_steps])``; ``policy`` is not modified.
    """
    if not isinstance(config, TrainConfig) or config.method != "soft":
        raise ValueError("config must be a TrainConfig with method 'soft'")
    if not isinstance(policy, FlowPolicy):
        raise ValueError(f"policy must be a FlowPolicy, got {type(policy).__name__}")
    if isinstance(num_steps, bool) or not isinstance(num_steps, (int, np.integer)) or not 1 <= num_steps <= 10**7:
        raise ValueError(f"num_steps must be an integer in [1, 10000000], got {num_steps!r}")
    if not isinstance(key, jax.Array) or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key) or key.shape != ():
        raise ValueError("key must be a single typed JAX PRNG key (jax.random.key(seed))")
    step = make_train_step(policy, config)
    o, a = step.check_batch((obs, actions))
    H, A = a.shape[1], a.shape[2]
    sg = np.asarray(sigma, np.float64)
    if sg.shape != (H, A) or not np.all(np.isfinite(sg)) or np.any(sg < 0):
        raise ValueError(f"sigma must be a finite array >= 0 of shape [{H}, {A}], got shape {list(sg.shape)}")
    n, bs = o.shape[0], config.batch_size
    if n < bs:
        raise ValueError(f"config.batch_size must be an integer in [1, {n}] (the number of examples), got {bs}")
    graphdef, params, rest = nnx.split(policy, nnx.Param, ...)
    opt_state = step.optimizer.init(params)
    cdf = delay_cdf(step.delay_table)
    cdf = jnp.concatenate([cdf, jnp.ones((H + 1 - cdf.shape[0],), jnp.float32)])
    d_min = jnp.asarray(config.d_min, jnp.int32)
    sg = jnp.asarray(sg, jnp.float32)
    # Key split and batch order of softrtc.jax.training.train ([T-8], [T-9]).
    k_data, k_steps = jax.random.split(key)
    per_epoch = n // bs
    losses, perm, epoch = [], None, -1
    for i in range(num_steps):
        e, b = divmod(i, per_epoch)
        if e != epoch:
            epoch, perm = e, jax.random.permutation(jax.random.fold_in(k_data, e), n)
        idx = perm[b * bs:(b + 1) * bs]
        params, opt_state, loss = _update(graphdef, step.optimizer, rest, params, opt_state, o[idx], a[idx],
                                          jax.random.fold_in(k_steps, i), step.weight_table, cdf, d_min, sg)
        losses.append(loss)
    return nnx.merge(graphdef, params, rest), np.asarray(jax.device_get(jnp.stack(losses)))
