"""Conformance adapter of the PyTorch port in the flipped convention (noise at t' = 1) ([CF-10], [V-1]).

The runner hands this adapter flipped times (t' = 1 - t) and negated
velocities (u = -v) and maps its outputs back before comparing. Functions
without a flow time or a velocity (delays, executor, metrics, weights) are the
spec-time adapter's.

    softrtc conformance run --impl torch-flipped
"""

from __future__ import annotations

from . import field, flipped
from .adapter import TorchAdapter
from .field import VelocityField


def _ufield(params):
    return flipped.FlippedField(VelocityField(params))


class FlippedTorchAdapter(TorchAdapter):
    name = "torch-flipped"
    time_convention = "noise_at_1"

    def corrupt(self, actions, noise, w, tau_flipped):
        return flipped.corrupt(actions, noise, w, tau_flipped)

    def token_times(self, w, t_flipped):
        return flipped.token_times(w, t_flipped)

    def loss(self, pred_u, actions, noise, w):
        return flipped.loss(pred_u, actions, noise, w)

    def batch_loss(self, preds_u, actions, noise, w):
        return flipped.batch_loss(preds_u, actions, noise, w)

    def velocity(self, params, obs, x, t_flipped):
        return field.velocity(_ufield(params), obs, x, t_flipped)

    def velocity_vjp(self, params, obs, x, t_flipped, cotangent):
        # (du/dx)^T g = -(dv/dx)^T g; the runner negates it back ([CF-10])
        return field.velocity_vjp(_ufield(params), obs, x, t_flipped, cotangent)

    def naive_sample(self, params, obs, noise, T):
        return flipped.naive_sample(_ufield(params), obs, noise, T)

    def rtc_sample(self, params, obs, noise, prior, w, T):
        return flipped.rtc_sample(_ufield(params), obs, noise, prior, w, T)

    def guided_sample(self, params, obs, noise, prior, w, T, max_guidance):
        return flipped.guided_sample(_ufield(params), obs, noise, prior, w, T, max_guidance)

    def guidance_weight(self, t_flipped, max_guidance):
        return flipped.guidance_weight(t_flipped, max_guidance)


ADAPTER = FlippedTorchAdapter()
