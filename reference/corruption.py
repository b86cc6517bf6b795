"""Weighted corruption of a training chunk (spec chapter C, 02-training.md).

tau_j = w_j + (1 - w_j) tau and x[j] = tau_j A[j] + (1 - tau_j) eps[j]:
a token with w_j = 1 is the clean action, w_j = 0 is ordinary flow matching.

>>> import numpy as np
>>> x, tj = corrupt(np.ones((3, 1)), np.zeros((3, 1)), np.array([1.0, 0.5, 0.0]), 0.2)
>>> tj.tolist(), x[:, 0].tolist()
([1.0, 0.6, 0.2], [1.0, 0.6, 0.2])
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_real
from .weights import check_weights


def token_times(weights, tau: float) -> np.ndarray:
    """Per-token flow time tau_j = w_j + (1 - w_j) tau ([C-1])."""
    w = check_array("weights", weights, ndim=1, lo=0.0, hi=1.0)
    return _token_times(w, check_real("tau", tau, 0.0, 1.0))


def _token_times(w: np.ndarray, tau: float) -> np.ndarray:
    return w + (1.0 - w) * tau  # [C-1] tau_j = w_j + (1 - w_j) tau


def corrupt(actions, noise, weights, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Corrupted chunk x and per-token times ([C-1], [C-2]).

    actions, noise: [H, A]; weights: [H] in [0, 1]; tau in [0, 1].
    """
    a = check_array("actions", actions, ndim=2)
    n = check_array("noise", noise, shape=a.shape)
    w = check_weights("weights", weights, a.shape[0])
    tj = _token_times(w, check_real("tau", tau, 0.0, 1.0))
    return tj[:, None] * a + (1.0 - tj[:, None]) * n, tj  # [C-2] x_j = tau_j A_j + (1 - tau_j) eps_j
