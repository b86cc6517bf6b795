"""Conformance adapter of the PyTorch port, spec time convention (data at t = 1) ([CF-7]).

    softrtc conformance run --impl torch
    softrtc conformance run --impl conformance/torch_port/adapter.py:ADAPTER
"""

from __future__ import annotations

import numpy as np
import torch

from . import delays, executor, field, metrics, sampling, training, weights
from .field import VelocityField


def to_numpy(x):
    """Tensors (and lists or tuples of them) to NumPy; used by the runner on every output."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


class TorchAdapter:
    name = "torch"
    time_convention = "data_at_1"
    to_numpy = staticmethod(to_numpy)

    # chapters E and W
    def endpoint(self, rule, d):
        return weights.endpoint(rule, d)

    def prefix_weights(self, H, d, e, schedule, parametrization):
        return weights.prefix_weights(H, d, e, schedule, parametrization)

    def weights(self, H, d, window, s):
        return weights.soft_weights(H, d, window, s)

    def hard_weights(self, H, d):
        return weights.hard_weights(H, d)

    # chapters D, C and L
    def delay_probs(self, dist, d_min, d_max, decay):
        return delays.delay_probs(dist, d_min, d_max, decay)

    def sample_delay(self, probs, d_min, u):
        return delays.sample_delay(probs, d_min, u)

    def corrupt(self, actions, noise, w, tau):
        return training.corrupt(actions, noise, w, tau)

    def token_times(self, w, t):
        return training.token_times(w, t)

    def loss(self, pred, actions, noise, w):
        return training.loss(pred, actions, noise, w)

    def batch_loss(self, preds, actions, noise, w):
        return training.batch_loss(preds, actions, noise, w)

    # chapters F, S and G
    def velocity(self, params, obs, x, t):
        return field.velocity(VelocityField(params), obs, x, t)

    def velocity_vjp(self, params, obs, x, t, cotangent):
        return field.velocity_vjp(VelocityField(params), obs, x, t, cotangent)

    def naive_sample(self, params, obs, noise, T):
        return sampling.naive_sample(VelocityField(params), obs, noise, T)

    def rtc_sample(self, params, obs, noise, prior, w, T):
        return sampling.rtc_sample(VelocityField(params), obs, noise, prior, w, T)

    def guided_sample(self, params, obs, noise, prior, w, T, max_guidance):
        return sampling.guided_sample(VelocityField(params), obs, noise, prior, w, T, max_guidance)

    def method_weights(self, method, H, s, d, window):
        return weights.method_weights(method, H, s, d, window)

    def guidance_weights(self, H, s, d, variant):
        return weights.guidance_weights(H, s, d, variant)

    def guidance_weight(self, t, max_guidance):
        return sampling.guidance_weight(t, max_guidance)

    # chapters X and M
    def shift_prior(self, prev, s):
        return executor.shift_prior(prev, s)

    def execute_chunks(self, chunks, delays_, s):
        return executor.execute_chunks(chunks, delays_, s)

    def difference_norm(self, actions, order):
        return metrics.difference_norm(actions, order)

    def action_delta(self, actions):
        return metrics.action_delta(actions)

    def action_jerk(self, actions):
        return metrics.action_jerk(actions)

    def boundary_jump(self, actions, chunk_index):
        return metrics.boundary_jump(actions, chunk_index)

    def bootstrap_interval(self, values, indices, confidence):
        return metrics.bootstrap_interval(values, indices, confidence)

    def standard_error(self, values):
        return metrics.standard_error(values)


ADAPTER = TorchAdapter()
