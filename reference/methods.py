"""The five chunk-generation methods compared by the spec (chapter S, [S-6]).

| method          | sampler          | weights                                     |
|-----------------|------------------|---------------------------------------------|
| naive           | naive_sample     | none (the prior is ignored)                  |
| inference_hard  | guided_sample    | prefix_weights(H, d, H - s, "zeros")         |
| inference_soft  | guided_sample    | prefix_weights(H, d, H - s, "exp")           |
| train_hard      | rtc_sample       | hard_weights(H, d)                           |
| train_soft      | rtc_sample       | soft_weights(H, d, window, s)                |

For the first chunk of an episode (no prior, d = 0) every method is the naive
sampler ([X-2]). Arguments a method ignores are still checked ([S-8]).
"""

from __future__ import annotations

import numpy as np

from ._validate import MAX_HORIZON, check_array, check_choice, check_int
from .executor import check_delay
from .guidance import guidance_prefix_weights, guided_sample
from .sampler import naive_sample, rtc_sample
from .weights import SoftWindow, check_window, hard_weights, soft_weights

METHODS = ("naive", "inference_hard", "inference_soft", "train_hard", "train_soft")


def method_weights(method: str, H: int, s: int, d: int, window: SoftWindow | None = None) -> np.ndarray:
    """Token weights a method uses for delay d ([S-6]).

    A given ``window`` is checked for every method; the default window is
    resolved for train_soft only, so the other methods run for any H ([S-8]).

    >>> method_weights("train_hard", 4, 2, 1).tolist()
    [1.0, 0.0, 0.0, 0.0]
    """
    check_choice("method", method, METHODS)
    d = check_delay(H, s, d)
    if window is not None:
        check_window(H, window)
    if method == "naive":
        return np.zeros(H)
    if method.startswith("inference_"):
        return guidance_prefix_weights(H, s, d, method.split("_", 1)[1])
    if method == "train_hard":
        return hard_weights(H, d)
    return soft_weights(H, d, window if window is not None else SoftWindow(), s)


def generate_chunk(method: str, field, obs, noise, prior, s: int, d: int, num_steps: int,
                   window: SoftWindow | None = None) -> np.ndarray:
    """One chunk by ``method`` ([S-6]); ``prior`` None means the first chunk (naive, d must be 0).

    Arguments the method ignores are checked all the same ([S-8]): the
    delay ([X-1]), a prior of naive (shape of ``noise``), a window of any method.
    """
    check_choice("method", method, METHODS)
    noise = check_array("noise", noise, ndim=2)
    H = check_int("noise.shape[0]", noise.shape[0], 1, MAX_HORIZON)
    s = check_int("s", s, 1, H)
    if window is not None:
        check_window(H, window)
    if prior is not None and method == "naive":
        check_array("prior", prior, shape=noise.shape)
    if prior is None:
        check_int("d", d, 0, 0)
        return naive_sample(field, obs, noise, num_steps)
    w = method_weights(method, H, s, d, window)
    if method == "naive":
        return naive_sample(field, obs, noise, num_steps)
    if method.startswith("inference_"):
        return guided_sample(field, obs, noise, prior, w, num_steps)
    return rtc_sample(field, obs, noise, prior, w, num_steps)
