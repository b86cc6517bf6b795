"""The reference velocity field of [F-1] as a batched ``torch.nn.Module`` (spec chapter F).

``field(obs [..., O], x [..., H, A], t [..., H]) -> v [..., H, A]``. Built from
the parameter dict of a conformance vector file or of
``softrtc.reference.velocity.ReferenceVelocityField.to_dict()`` ([F-3]); its VJP
in ``x`` ([F-2]) is taken by autograd (:func:`velocity_vjp`).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from . import _validate as v

NAMES = ("W1", "Wt", "Wo", "b1", "W2", "b2")

__all__ = ["ReferenceVelocityField", "velocity", "velocity_vjp"]


class ReferenceVelocityField(nn.Module):
    """v = reshape(tanh(vec(x) W1 + vec(phi(t)) Wt + obs Wo + b1) W2 + b2, [H, A]), phi(t) = [t, sin pi t, cos pi t]."""

    def __init__(self, params: dict, *, dtype=None, device=None):
        super().__init__()
        if not isinstance(params, dict) or any(k not in params for k in NAMES):
            raise ValueError(f"params must be a dict with keys {NAMES}")
        kw = v.float_kw(dtype, device)
        p = {k: v.real_tensor(f"params[{k!r}]", params[k], **kw) for k in NAMES}
        for k in ("W1", "Wt", "Wo", "W2"):
            v.shape(f"params[{k!r}]", p[k], ndim=2)
        K = p["W1"].shape[1]
        if p["Wt"].shape[0] % 3 or p["Wt"].shape[0] == 0:
            raise ValueError(f"params['Wt'] must have shape [3H, K], got {list(p['Wt'].shape)}")
        self.H = p["Wt"].shape[0] // 3
        if p["W1"].shape[0] % self.H:
            raise ValueError(f"params['W1'] must have shape [H*A, K] with H={self.H}, got {list(p['W1'].shape)}")
        self.A = p["W1"].shape[0] // self.H
        self.O = p["Wo"].shape[0]
        for k, want in (("Wt", [3 * self.H, K]), ("Wo", [self.O, K]), ("b1", [K]), ("W2", [K, self.H * self.A]),
                        ("b2", [self.H * self.A])):
            v.shape(f"params[{k!r}]", p[k], expected=tuple(want))
        for k in NAMES:
            self.register_buffer(k, p[k])

    def forward(self, obs, x, t) -> torch.Tensor:
        phi = torch.stack([t, torch.sin(math.pi * t), torch.cos(math.pi * t)], dim=-1)  # [..., H, 3]
        pre = x.flatten(-2) @ self.W1 + phi.flatten(-2) @ self.Wt + obs @ self.Wo + self.b1
        return (torch.tanh(pre) @ self.W2 + self.b2).unflatten(-1, (self.H, self.A))


def _point(field, obs, x, t):
    if not isinstance(field, ReferenceVelocityField):
        raise ValueError(f"field must be a ReferenceVelocityField, got {type(field).__name__}")
    x = v.real_tensor("x", x, min_ndim=2, **v.like(field.W1))
    v.shape("x", x, expected=(*x.shape[:-2], field.H, field.A))
    batch = tuple(x.shape[:-2])
    obs = v.real_tensor("obs", obs, expected=(*batch, field.O), **v.like(field.W1))
    t = v.real_tensor("t", t, expected=(*batch, field.H), lo=0.0, hi=1.0, **v.like(field.W1))
    return obs, x, t


def velocity(field, obs, x, t) -> torch.Tensor:
    """The field's velocity at checked arguments ([F-1])."""
    return field(*_point(field, obs, x, t))


def velocity_vjp(field, obs, x, t, cotangent) -> torch.Tensor:
    """(dv/dx)^T cotangent by one autograd VJP ([F-2])."""
    obs, x, t = _point(field, obs, x, t)
    g = v.real_tensor("cotangent", cotangent, expected=tuple(x.shape), **v.like(x))
    with torch.enable_grad():
        xg = x.detach().requires_grad_(True)
        (out,) = torch.autograd.grad(field(obs, xg, t), xg, grad_outputs=g)
    return out
