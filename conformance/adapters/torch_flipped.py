"""Conformance adapter of ``softrtc.torch`` in the flipped time convention (noise at t' = 1) ([CF-10], [V-1]).

    softrtc conformance run --impl torch-flipped

The runner hands this adapter flipped times (t' = 1 - t) and negated
velocities (u = -v) and maps its outputs back. Every function with a flow time
or a velocity runs ``softrtc.torch`` with ``convention="noise_at_1"``, natively
in flipped time; the samplers call the field of the vectors as the flipped
field u(obs, x, t') = -v(obs, x, 1 - t').
"""

from __future__ import annotations

from softrtc.torch import _validate, velocity

from .torch import DTYPE, TorchAdapter, _t


def _flipped_time(t):
    """t' checked like any time, [0, 1] ([N-7]), before it is mapped back to spec time."""
    return _validate.real_tensor("t", _t(t), lo=0.0, hi=1.0)


class FlippedField:
    """u(obs, x, t') = -v(obs, x, 1 - t') of a field given in the spec's time ([V-1])."""

    def __init__(self, field):
        self.field = field

    def __call__(self, obs, x, t_flipped):
        return -self.field(obs, x, 1.0 - t_flipped)


class FlippedTorchAdapter(TorchAdapter):
    name = "torch-flipped"
    time_convention = "noise_at_1"
    convention = "noise_at_1"

    def make_field(self, params):
        return FlippedField(velocity.ReferenceVelocityField(params, dtype=DTYPE))

    def velocity(self, params, obs, x, t):
        # the runner passes t' and expects u = -v; the field's own checks run on the spec-time call
        field = velocity.ReferenceVelocityField(params, dtype=DTYPE)
        return -velocity.velocity(field, _t(obs), _t(x), 1.0 - _flipped_time(t))

    def velocity_vjp(self, params, obs, x, t, cotangent):
        # (du/dx)^T g = -(dv/dx)^T g at t = 1 - t'
        field = velocity.ReferenceVelocityField(params, dtype=DTYPE)
        return -velocity.velocity_vjp(field, _t(obs), _t(x), 1.0 - _flipped_time(t), _t(cotangent))


ADAPTER = FlippedTorchAdapter()
