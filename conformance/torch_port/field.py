"""The reference velocity field of [F-1] as a torch function of (obs, x, t)."""

from __future__ import annotations

import math

import torch

from .checks import tensor

NAMES = ("W1", "Wt", "Wo", "b1", "W2", "b2")


class VelocityField:
    """v(obs, x, t) = reshape(tanh(vec(x) W1 + vec(phi(t)) Wt + obs Wo + b1) W2 + b2, [H, A]).

    Differentiable with autograd, so samplers take VJPs with torch.autograd.
    """

    def __init__(self, params: dict):
        if not isinstance(params, dict) or any(k not in params for k in NAMES):
            raise ValueError(f"params must be a dict with keys {NAMES}")
        self.p = {k: tensor(f"params[{k!r}]", params[k]) for k in NAMES}
        HA, K = self.p["W1"].shape
        self.H = self.p["Wt"].shape[0] // 3
        self.A = HA // self.H
        self.O = self.p["Wo"].shape[0]

    def __call__(self, obs, x, t) -> torch.Tensor:
        p = self.p
        phi = torch.stack([t, torch.sin(math.pi * t), torch.cos(math.pi * t)], dim=-1)  # [H, 3]
        h = torch.tanh(x.reshape(-1) @ p["W1"] + phi.reshape(-1) @ p["Wt"] + obs @ p["Wo"] + p["b1"])
        return (h @ p["W2"] + p["b2"]).reshape(self.H, self.A)


def _point(field, obs, x, t):
    """The checked arguments of the field: obs [O], x [H, A], t [H] in [0, 1] ([N-7])."""
    return (tensor("obs", obs, shape=(field.O,)), tensor("x", x, shape=(field.H, field.A)),
            tensor("t", t, shape=(field.H,), lo=0.0, hi=1.0))


def velocity(field, obs, x, t) -> torch.Tensor:
    """The field's velocity [H, A] at checked arguments ([F-1])."""
    return field(*_point(field, obs, x, t))


def velocity_vjp(field, obs, x, t, cotangent) -> torch.Tensor:
    """(dv/dx)^T cotangent at (obs, x, t) by one torch.autograd VJP ([F-2]).

    Works for any field callable as field(obs, x, t) with attributes H, A and O,
    the flipped field u of [V-1] included (its VJP is the negated one).
    """
    obs, x, t = _point(field, obs, x, t)
    g = tensor("cotangent", cotangent, shape=(field.H, field.A))
    _, vjp = torch.autograd.functional.vjp(lambda xx: field(obs, xx, t), x, g)
    return vjp
