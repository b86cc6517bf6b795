"""The five chunk-generation methods compared by the spec (chapter S, [S-6]).

| method          | sampler          | weights                                     |
|-----------------|------------------|---------------------------------------------|
| naive           | naive_sample     | none (the prior is ignored)                  |
| inference_hard  | guided_sample    | prefix_weights(H, d, H - s, "zeros")         |
| inference_soft  | guided_sample    | prefix_weights(H, d, H - s, "exp")           |
| train_hard      | rtc_sample       | hard_weights(H, d)                           |
| train_soft      | rtc_sample       | soft_weights(H, d, window, s)                |

For the first chunk of an episode (no prior, d = 0) every method is the naive
sampler ([X-2]). Arguments a method ignores are still checked ([S-8]). The
training-time methods take a solver ``step`` ([S-10]); naive accepts either
step, the guided methods only "algorithm1" ([S-14]).
"""

from __future__ import annotations

import numpy as np

from ._validate import MAX_HORIZON, check_array, check_choice, check_int
from .executor import check_delay
from .guidance import GUIDANCE_SCHEDULES, MAX_GUIDANCE, _guided_sample, check_guided_field
from .sampler import MAX_STEPS, _naive_sample, _rtc_sample, check_step, field_dims
from .weights import SoftWindow, _hard, _prefix, _soft, check_window

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
    if window is not None or method == "train_soft":
        window = check_window(H, SoftWindow() if window is None else window)
    return _method_weights(method, H, s, d, window)


def _method_weights(method: str, H: int, s: int, d: int, window: SoftWindow | None) -> np.ndarray:
    if method == "naive":
        return np.zeros(H)  # [S-6] naive: no weights
    if method.startswith("inference_"):  # [S-6], [G-1] W: start d, end H - s
        return _prefix(H, d, H - s, GUIDANCE_SCHEDULES[method.split("_", 1)[1]], "rtc")
    if method == "train_hard":
        return _hard(H, d)  # [S-6], [W-8]
    return _soft(H, d, window, s)  # [S-6], [W-7]


def generate_chunk(method: str, field, obs, noise, prior, s: int, d: int, num_steps: int,
                   window: SoftWindow | None = None, step: str = "algorithm1") -> np.ndarray:
    """One chunk by ``method`` ([S-6]); ``prior`` None means the first chunk (naive, d must be 0).

    Arguments the method ignores are checked all the same ([S-8]): the
    delay ([X-1]), a prior of naive (shape of ``noise``), a window of any method.
    ``step`` ([S-10]) is used by train_hard / train_soft; naive and the first
    chunk run the naive sampler under either step (bitwise the same, [S-11]);
    inference_hard / inference_soft reject "consistent" ([S-14]).
    """
    check_choice("method", method, METHODS)
    step = check_method_step(method, step)
    noise = check_array("noise", noise, ndim=2)
    H = check_int("noise.shape[0]", noise.shape[0], 1, MAX_HORIZON)
    s = check_int("s", s, 1, H)
    if window is not None:
        check_window(H, window)
    if prior is not None and method == "naive":
        check_array("prior", prior, shape=noise.shape)
    if prior is None:
        check_int("d", d, 0, 0)
    else:
        d = check_delay(H, s, d)
    if prior is not None and method.startswith("inference_"):
        check_guided_field(field)
    elif not callable(field):
        raise ValueError("field must be callable as field(obs, x, t) -> velocity [H, A]")
    obs = check_array("obs", obs, ndim=1)
    field_dims(field, obs, noise)
    T = check_int("num_steps", num_steps, 1, MAX_STEPS)
    if prior is None or method == "naive":
        return _naive_sample(field, obs, noise, T, False)  # first chunk; [S-6] naive
    y = check_array("prior", prior, shape=noise.shape)
    if method == "train_soft":
        window = check_window(H, SoftWindow() if window is None else window)
    w = _method_weights(method, H, s, d, window)
    if method.startswith("inference_"):
        return _guided_sample(field, obs, noise, y, w, T, MAX_GUIDANCE, False)  # [S-6] guided sampler
    return _rtc_sample(field, obs, noise, y, w, T, False, step)  # [S-6] training-time sampler, [S-10]


def check_method_step(method: str, step) -> str:
    """``step`` ([S-10]) if ``method`` can run it: any step for naive and train_*, only
    "algorithm1" for the guided methods, whose sampler has no blend to change ([S-14])."""
    step = check_step(step)
    if method.startswith("inference_") and step != "algorithm1":
        raise ValueError(f"step must be 'algorithm1' for method {method!r} (the guided sampler has no "
                         f"blended step, [S-14]), got {step!r}")
    return step
