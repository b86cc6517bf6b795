"""Mapping other conventions onto this spec (chapter V, 06-conventions.md).

Many PyTorch stacks (LeRobot, openpi's PyTorch code) run flow time the other
way: t' = 1 at noise, t' = 0 at data, x_t' = t' eps + (1 - t') A, and the network
predicts u = eps - A. Then t' = 1 - t and u = -v ([V-1]), the Euler step is
x <- x - u / T from t' = 1 down ([V-2]), and the blended per-token time is
t~'_j = (1 - w_j) t' ([V-3]):

    >>> flipped_token_times([1.0, 0.5, 0.0], 0.75).tolist()
    [0.0, 0.375, 0.75]
    >>> from_flipped_time([0.0, 0.375, 0.75]).tolist()  # the spec's w + (1 - w) t at t = 1 - 0.75
    [1.0, 0.625, 0.25]
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array


def to_flipped_time(t) -> np.ndarray:
    """t' = 1 - t ([V-1])."""
    return 1.0 - check_array("t", t, lo=0.0, hi=1.0)


def from_flipped_time(t_flipped) -> np.ndarray:
    """t = 1 - t' ([V-1])."""
    return 1.0 - check_array("t_flipped", t_flipped, lo=0.0, hi=1.0)


def from_flipped_velocity(u) -> np.ndarray:
    """v = -u: a velocity toward noise becomes one toward data ([V-1])."""
    return -check_array("u", u)


def flipped_token_times(weights, t_flipped: float) -> np.ndarray:
    """t~'_j = (1 - w_j) t' ([V-3]); equals 1 - (w_j + (1 - w_j) t)."""
    w = check_array("weights", weights, ndim=1, lo=0.0, hi=1.0)
    tf = check_array("t_flipped", t_flipped, lo=0.0, hi=1.0)
    if tf.ndim != 0 and tf.shape != w.shape:
        raise ValueError(f"t_flipped must be a scalar or have the shape of weights {list(w.shape)}, "
                         f"got {list(tf.shape)}")
    return (1.0 - w) * tf
