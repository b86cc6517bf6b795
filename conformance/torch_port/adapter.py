"""Conformance adapter of the PyTorch port, spec time convention (data at t = 1) ([CF-7]).

    softrtc conformance run --impl torch
    softrtc conformance run --impl conformance/torch_port/adapter.py:ADAPTER
"""

from __future__ import annotations

import numpy as np
import torch

from . import sampling, training, weights
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

    def endpoint(self, rule, d):
        return weights.endpoint(rule, d)

    def prefix_weights(self, H, d, e, schedule, parametrization):
        return weights.prefix_weights(H, d, e, schedule, parametrization)

    def weights(self, H, d, window, s):
        return weights.soft_weights(H, d, window, s)

    def hard_weights(self, H, d):
        return weights.hard_weights(H, d)

    def guidance_weights(self, H, s, d, variant):
        return weights.guidance_weights(H, s, d, variant)

    def corrupt(self, actions, noise, w, tau):
        return training.corrupt(actions, noise, w, tau)

    def loss(self, pred, actions, noise, w):
        return training.loss(pred, actions, noise, w)

    def batch_loss(self, preds, actions, noise, w):
        return training.batch_loss(preds, actions, noise, w)

    def velocity(self, field, obs, x, t):
        f = VelocityField(field)
        return f(torch.as_tensor(obs, dtype=torch.float32), torch.as_tensor(x, dtype=torch.float32),
                 torch.as_tensor(t, dtype=torch.float32))

    def naive_sample(self, field, obs, noise, T):
        return sampling.naive_sample(VelocityField(field), obs, noise, T)

    def rtc_sample(self, field, obs, noise, prior, w, T):
        return sampling.rtc_sample(VelocityField(field), obs, noise, prior, w, T)

    def guided_sample(self, field, obs, noise, prior, w, T, max_guidance):
        return sampling.guided_sample(VelocityField(field), obs, noise, prior, w, T, max_guidance)

    def guidance_weight(self, t, max_guidance):
        return sampling.guidance_weight(t, max_guidance)


ADAPTER = TorchAdapter()
