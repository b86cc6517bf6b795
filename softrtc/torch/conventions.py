"""The flipped time convention of LeRobot and openpi's PyTorch code (spec chapter V, [V-1]..[V-3]).

Every function of this package with a flow time or a velocity takes
``convention="data_at_1"`` (the spec's: noise at t = 0, data at t = 1, target
``A - eps``) or ``convention="noise_at_1"`` (flipped: t' = 1 - t, noise at
t' = 1, target ``u = eps - A``), the names of the conformance adapters'
``time_convention`` ([CF-8]). Each is written natively in its convention, not
by mapping one onto the other at the boundary.
"""

from __future__ import annotations

import torch

from . import _validate as v

__all__ = ["CONVENTIONS", "to_flipped_time", "from_flipped_time", "from_flipped_velocity", "flipped_token_times"]

CONVENTIONS = v.CONVENTIONS


def to_flipped_time(t) -> torch.Tensor:
    """t' = 1 - t ([V-1])."""
    return 1.0 - v.real_tensor("t", t, lo=0.0, hi=1.0)


def from_flipped_time(t_flipped) -> torch.Tensor:
    """t = 1 - t' ([V-1])."""
    return 1.0 - v.real_tensor("t_flipped", t_flipped, lo=0.0, hi=1.0)


def from_flipped_velocity(u) -> torch.Tensor:
    """v = -u ([V-1])."""
    return -v.real_tensor("u", u)


def flipped_token_times(weights, t_flipped) -> torch.Tensor:
    """t~'_j = (1 - w_j) t' ([V-3]): a clamped token has flipped time 0 (clean)."""
    from .corruption import token_times

    return token_times(weights, t_flipped, convention="noise_at_1")
