"""Conformance adapter of the PyTorch port, spec time convention (data at t = 1) ([CF-7]).

    softrtc conformance run --impl torch
    softrtc conformance run --impl conformance/torch_port/adapter.py:ADAPTER
"""

from __future__ import annotations

import numpy as np
import torch

from . import delays, executor, field, metrics, sampling, training
from . import weights as weight_fns  # the name `weights` is an adapter function
from .field import VelocityField


def to_numpy(x):
    """Tensors (and lists or tuples of them) to NumPy; used by the runner on every output."""
    if isinstance(x, torch.Tensor):
        return x.detach().cpu().numpy()
    return np.asarray(x)


class TorchAdapter:
    """Every interface function of [CF-7]. Functions whose arguments the port takes as they are bind its
    module functions directly; those of chapters F, S and G first build the field from its parameters."""

    name = "torch"
    time_convention = "data_at_1"
    to_numpy = staticmethod(to_numpy)

    # chapters E and W
    endpoint = staticmethod(weight_fns.endpoint)
    prefix_weights = staticmethod(weight_fns.prefix_weights)
    weights = staticmethod(weight_fns.soft_weights)
    hard_weights = staticmethod(weight_fns.hard_weights)
    method_weights = staticmethod(weight_fns.method_weights)
    guidance_weights = staticmethod(weight_fns.guidance_weights)

    # chapters D, C and L
    delay_probs = staticmethod(delays.delay_probs)
    sample_delay = staticmethod(delays.sample_delay)
    corrupt = staticmethod(training.corrupt)
    token_times = staticmethod(training.token_times)
    loss = staticmethod(training.loss)
    batch_loss = staticmethod(training.batch_loss)

    # chapters F, S and G: the field is built from the case's parameters; the flipped adapter
    # swaps in its own field and samplers ([V-1])
    guidance_weight = staticmethod(sampling.guidance_weight)
    samplers = sampling

    def make_field(self, params):
        return VelocityField(params)

    def velocity(self, params, obs, x, t):
        return field.velocity(self.make_field(params), obs, x, t)

    def velocity_vjp(self, params, obs, x, t, cotangent):
        return field.velocity_vjp(self.make_field(params), obs, x, t, cotangent)

    def naive_sample(self, params, obs, noise, T):
        return self.samplers.naive_sample(self.make_field(params), obs, noise, T)

    def rtc_sample(self, params, obs, noise, prior, w, T):
        return self.samplers.rtc_sample(self.make_field(params), obs, noise, prior, w, T)

    def guided_sample(self, params, obs, noise, prior, w, T, max_guidance):
        return self.samplers.guided_sample(self.make_field(params), obs, noise, prior, w, T, max_guidance)

    # chapters X and M
    shift_prior = staticmethod(executor.shift_prior)
    execute_chunks = staticmethod(executor.execute_chunks)
    difference_norm = staticmethod(metrics.difference_norm)
    action_delta = staticmethod(metrics.action_delta)
    action_jerk = staticmethod(metrics.action_jerk)
    boundary_jump = staticmethod(metrics.boundary_jump)
    bootstrap_interval = staticmethod(metrics.bootstrap_interval)
    standard_error = staticmethod(metrics.standard_error)


ADAPTER = TorchAdapter()
