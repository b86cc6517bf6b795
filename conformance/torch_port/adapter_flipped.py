"""Conformance adapter of the PyTorch port in the flipped convention (noise at t' = 1) ([CF-10], [V-1]).

The runner hands this adapter flipped times (t' = 1 - t) and negated
velocities (u = -v) and maps its outputs back before comparing. Functions
without a flow time or a velocity (delays, executor, metrics, weights) are the
spec-time adapter's.

    softrtc conformance run --impl torch-flipped
"""

from __future__ import annotations

from . import flipped
from .adapter import TorchAdapter
from .field import VelocityField


class FlippedTorchAdapter(TorchAdapter):
    name = "torch-flipped"
    time_convention = "noise_at_1"

    corrupt = staticmethod(flipped.corrupt)
    token_times = staticmethod(flipped.token_times)
    loss = staticmethod(flipped.loss)
    batch_loss = staticmethod(flipped.batch_loss)
    guidance_weight = staticmethod(flipped.guidance_weight)
    samplers = flipped

    def make_field(self, params):
        # The field u = -v of the flipped convention: velocity_vjp returns (du/dx)^T g = -(dv/dx)^T g,
        # which the runner negates back ([CF-10]).
        return flipped.FlippedField(VelocityField(params))


ADAPTER = FlippedTorchAdapter()
