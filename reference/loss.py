"""Weighted flow-matching loss (spec chapter L, 02-training.md).

L = sum_j (1 - w_j) l_j / (sum_j (1 - w_j) + eta), with
l_j = || v_j - (A_j - eps_j) ||^2 summed over the action dimension, eta = 1e-8.
Clamped tokens (w_j = 1) have weight zero: their predictions do not enter L.
With target A - eps = 1 and predictions 0, 1, 3, every l_j is 1, 0 or 4; the
clamped first token drops out and L = (0 + 4) / 2 (up to eta):

    >>> import numpy as np
    >>> pred, acts, noise = np.array([[0.0], [1.0], [3.0]]), np.ones((3, 1)), np.zeros((3, 1))
    >>> round(flow_matching_loss(pred, acts, noise, np.array([1.0, 0.0, 0.0])), 6)
    2.0
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_real, finite_result
from .weights import check_weights

ETA = 1e-8


def token_errors(pred, actions, noise) -> np.ndarray:
    """Per-token squared error l_j against the target A - eps ([L-1]).

    An l_j that overflows float64 is an error naming ``pred`` ([N-15]).
    """
    p = check_array("pred", pred, ndim=2)
    return _token_errors(p, check_array("actions", actions, shape=p.shape), check_array("noise", noise, shape=p.shape))


def _token_errors(p: np.ndarray, a: np.ndarray, n: np.ndarray, name: str = "pred") -> np.ndarray:
    with np.errstate(over="ignore", invalid="ignore"):  # [N-15]: overflow is reported below, not warned about
        l = np.sum((p - (a - n)) ** 2, axis=-1)  # [L-1] l_j = || v_j - (A_j - eps_j) ||^2
    return finite_result(name, l, "the squared error || pred - (actions - noise) ||^2")


def _loss(l: np.ndarray, w: np.ndarray, eta: float, name: str = "pred") -> float:
    m = 1.0 - w
    with np.errstate(over="ignore", invalid="ignore"):
        loss = np.sum(m * l) / (np.sum(m) + eta)  # [L-2] L = sum (1 - w_j) l_j / (sum (1 - w_j) + eta)
    return float(finite_result(name, loss, "the weighted sum of squared errors"))


def flow_matching_loss(pred, actions, noise, weights, eta: float = ETA) -> float:
    """Loss of one chunk ([L-1], [L-2]): weighted mean of l_j with weights 1 - w_j.

    A loss that overflows float64 is an error naming ``pred`` ([N-15]).
    """
    l = token_errors(pred, actions, noise)
    w = check_weights("weights", weights, l.shape[0])
    return _loss(l, w, check_real("eta", eta, 0.0, 1.0, lo_open=True))


def batch_loss(preds, actions, noise, weights, eta: float = ETA) -> float:
    """Mean over the batch of per-chunk losses ([L-3]); arrays [B, H, A], weights [B, H].

    A loss that overflows float64 is an error naming ``preds`` ([N-15]).
    """
    p = check_array("preds", preds, ndim=3)
    a = check_array("actions", actions, shape=p.shape)
    n = check_array("noise", noise, shape=p.shape)
    w = check_array("weights", weights, shape=p.shape[:2], lo=0.0, hi=1.0)
    eta = check_real("eta", eta, 0.0, 1.0, lo_open=True)
    losses = [_loss(_token_errors(p[i], a[i], n[i], "preds"), w[i], eta, "preds") for i in range(p.shape[0])]
    with np.errstate(over="ignore"):
        return float(finite_result("preds", np.mean(losses), "the mean of the per-chunk losses"))  # [L-3]
