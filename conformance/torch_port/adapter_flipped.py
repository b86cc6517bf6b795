"""Conformance adapter of the PyTorch port in the flipped convention (noise at t' = 1) ([CF-10], [V-1]).

The runner hands this adapter flipped times (t' = 1 - t) and negated
velocities (u = -v) and maps its outputs back before comparing.

    softrtc conformance run --impl torch-flipped
"""

from __future__ import annotations

import torch

from . import flipped
from .adapter import TorchAdapter
from .field import VelocityField


class FlippedTorchAdapter(TorchAdapter):
    name = "torch-flipped"
    time_convention = "noise_at_1"

    def corrupt(self, actions, noise, w, tau_flipped):
        return flipped.corrupt(actions, noise, w, tau_flipped)

    def token_times(self, w, t_flipped):
        return flipped.token_times(w, t_flipped)

    def loss(self, pred_u, actions, noise, w):
        return flipped.loss(pred_u, actions, noise, w)

    batch_loss = None  # not ported in this convention: its cases are reported as unsupported

    def velocity(self, field, obs, x, t_flipped):
        u = flipped.FlippedField(VelocityField(field))
        return u(torch.as_tensor(obs, dtype=torch.float32), torch.as_tensor(x, dtype=torch.float32),
                 torch.as_tensor(t_flipped, dtype=torch.float32))

    def naive_sample(self, field, obs, noise, T):
        return flipped.naive_sample(flipped.FlippedField(VelocityField(field)), obs, noise, T)

    def rtc_sample(self, field, obs, noise, prior, w, T):
        return flipped.rtc_sample(flipped.FlippedField(VelocityField(field)), obs, noise, prior, w, T)

    def guided_sample(self, field, obs, noise, prior, w, T, max_guidance):
        return flipped.guided_sample(flipped.FlippedField(VelocityField(field)), obs, noise, prior, w, T,
                                     max_guidance)

    def guidance_weight(self, t_flipped, max_guidance):
        return flipped.guidance_weight(t_flipped, max_guidance)


ADAPTER = FlippedTorchAdapter()
