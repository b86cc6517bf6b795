"""Euler samplers: naive and training-time (hard / soft) RTC (spec chapter S, 03-inference.md).

Algorithm 1 of the paper, per solver step k = 0 .. T-1 with t_k = k / T:

    x~[j] = w_j Y[j] + (1 - w_j) x[j]        blended state        [S-3]
    t~_j  = w_j + (1 - w_j) t_k              blended flow time    [S-3]
    x     = x~ + v(obs, x~, t~) / T                               [S-4]

and the result is x after step T-1, without a final blend ([S-5]). A token
with w = 1 is replaced by the prior before every step; with a constant field
v = 1 and T = 4 steps it ends at Y + 1/4, while a free token gains 1:

    >>> import numpy as np
    >>> one = lambda obs, x, t: np.ones_like(x)
    >>> rtc_sample(one, np.zeros(1), np.zeros((2, 1)), np.full((2, 1), 5.0), np.array([1.0, 0.0]), 4)[:, 0].tolist()
    [5.25, 1.0]
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_bool, check_int, check_real, real_array
from .weights import check_weights

# [N-12] Upper bound of the Euler step count T.
MAX_STEPS = 1 << 16


def euler_times(num_steps: int) -> np.ndarray:
    """t_k = k / T for k = 0 .. T-1 ([S-1])."""
    return _euler_times(check_int("num_steps", num_steps, 1, MAX_STEPS))


def _euler_times(T: int) -> np.ndarray:
    return np.arange(T, dtype=np.float64) / T  # [S-1] t_k = k / T


def blend(x, prior, weights) -> np.ndarray:
    """x~ = w Y + (1 - w) x, token-wise ([S-3]). A token with w = 1 equals Y exactly."""
    x = check_array("x", x, ndim=2)
    y = check_array("prior", prior, shape=x.shape)
    return _blend(x, y, check_weights("weights", weights, x.shape[0]))


def _blend(x: np.ndarray, y: np.ndarray, w: np.ndarray) -> np.ndarray:
    return w[:, None] * y + (1.0 - w[:, None]) * x  # [S-3] x~_j = w_j Y_j + (1 - w_j) x_j


def blend_time(t: float, weights) -> np.ndarray:
    """t~_j = w_j + (1 - w_j) t ([S-3]); t a flow time in [0, 1]."""
    w = check_array("weights", weights, ndim=1, lo=0.0, hi=1.0)
    return _blend_time(check_real("t", t, 0.0, 1.0), w)


def _blend_time(t: float, w: np.ndarray) -> np.ndarray:
    return w + (1.0 - w) * t  # [S-3] t~_j = w_j + (1 - w_j) t


def field_output(name: str, value, shape: tuple) -> np.ndarray:
    """A velocity (or VJP) returned by a field: shape of the state, finite ([N-7])."""
    # [N-7] As for inputs: a complex, boolean or string result is an error, not converted.
    v = real_array(f"the result of {name}", value).astype(np.float64)
    if v.shape != tuple(shape):
        raise ValueError(f"{name} must return an array of the state's shape {list(shape)}, got {list(v.shape)}")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"{name} returned non-finite values (NaN or inf)")
    return v


def field_dims(field, obs: np.ndarray, noise: np.ndarray) -> None:
    """``noise`` [H, A] and ``obs`` [O] against the sizes the field declares, if any ([N-7]).

    A field with integer ``horizon``, ``action_dim`` or ``obs_dim`` (as
    :class:`~softrtc.reference.velocity.ReferenceVelocityField`) would reject
    a mis-shaped state under its own argument name ``x``; checked here, the
    error names the sampler's argument instead.
    """
    def size(attr):
        v = getattr(field, attr, None)
        return int(v) if isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_)) else None

    H, A, O = size("horizon"), size("action_dim"), size("obs_dim")
    if (H is not None and noise.shape[0] != H) or (A is not None and noise.shape[1] != A):
        raise ValueError(f"noise must have the field's shape [H={'*' if H is None else H}, "
                         f"A={'*' if A is None else A}], got {list(noise.shape)}")
    if O is not None and obs.shape[0] != O:
        raise ValueError(f"obs must have the field's shape [O={O}], got {list(obs.shape)}")


def _check_inputs(field, obs, noise):
    if not callable(field):
        raise ValueError("field must be callable as field(obs, x, t) -> velocity [H, A]")
    x0 = check_array("noise", noise, ndim=2)
    obs = check_array("obs", obs, ndim=1)
    field_dims(field, obs, x0)
    return obs, x0


def naive_sample(field, obs, noise, num_steps: int, return_trace: bool = False):
    """Naive Euler sampler of the base policy ([S-2]): x += v(obs, x, t_k 1) / T.

    Returns the chunk [H, A]; with ``return_trace`` also a list of per-step dicts
    (state, time, velocity, next_state).
    """
    obs, x = _check_inputs(field, obs, noise)
    return_trace = check_bool("return_trace", return_trace)
    return _naive_sample(field, obs, x, check_int("num_steps", num_steps, 1, MAX_STEPS), return_trace)


def _naive_sample(field, obs, x, T: int, return_trace: bool):
    trace = []
    for t in _euler_times(T):
        tv = np.full(x.shape[0], t)
        v = field_output("field", field(obs, x, tv), x.shape)
        nxt = x + v / T  # [S-2] x <- x + v(obs, x, t_k 1) / T
        if return_trace:
            trace.append({"state": x, "time": tv, "velocity": v, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x


def rtc_sample(field, obs, noise, prior, weights, num_steps: int, return_trace: bool = False):
    """Training-time RTC sampler, hard or soft ([S-3], [S-4], [S-5]).

    prior Y [H, A] is the previous chunk in the new chunk's frame ([X-3]);
    weights [H] come from weights.soft_weights / hard_weights.
    """
    obs, x = _check_inputs(field, obs, noise)
    return_trace = check_bool("return_trace", return_trace)
    y = check_array("prior", prior, shape=x.shape)
    w = check_weights("weights", weights, x.shape[0])
    return _rtc_sample(field, obs, x, y, w, check_int("num_steps", num_steps, 1, MAX_STEPS), return_trace)


def _rtc_sample(field, obs, x, y, w, T: int, return_trace: bool):
    trace = []
    for t in _euler_times(T):
        xb, tb = _blend(x, y, w), _blend_time(t, w)  # [S-3]
        v = field_output("field", field(obs, xb, tb), x.shape)
        nxt = xb + v / T  # [S-4] x <- x~ + v(obs, x~, t~) / T
        if return_trace:
            trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": v, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x  # [S-5] no final blend
