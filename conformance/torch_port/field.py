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

    def __call__(self, obs, x, t) -> torch.Tensor:
        p = self.p
        phi = torch.stack([t, torch.sin(math.pi * t), torch.cos(math.pi * t)], dim=-1)  # [H, 3]
        h = torch.tanh(x.reshape(-1) @ p["W1"] + phi.reshape(-1) @ p["Wt"] + obs @ p["Wo"] + p["b1"])
        return (h @ p["W2"] + p["b2"]).reshape(self.H, self.A)
