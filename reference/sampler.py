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

The time-consistent step ([S-10]) blends a window token (0 < w < 1) once,
before the first step, and then advances it by (1 - w) v / T, so its state is
always at the flow time t~ the field is told ([S-9]). Worked example ([S-13]):
v = 1, T = 4, x^0 = 0, Y = 5, w = [1, .5, 0]; the window token ends at
.5 * 5 + .5 * (0 + 1) = 3 instead of Algorithm 1's 5.15625:

    >>> w, y = np.array([1.0, 0.5, 0.0]), np.full((3, 1), 5.0)
    >>> rtc_sample(one, np.zeros(1), np.zeros((3, 1)), y, w, 4)[:, 0].tolist()
    [5.25, 5.15625, 1.0]
    >>> rtc_sample(one, np.zeros(1), np.zeros((3, 1)), y, w, 4, step="consistent")[:, 0].tolist()
    [5.25, 3.0, 1.0]
"""

from __future__ import annotations

import numpy as np

from ._validate import check_array, check_bool, check_choice, check_int, check_real, real_array
from .weights import check_weights

# [N-12] Upper bound of the Euler step count T.
MAX_STEPS = 1 << 16

# [S-10] The training-time sampler's solver steps; "algorithm1" (the paper's) is the default.
STEPS = ("algorithm1", "consistent")


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


def check_step(step) -> str:
    """``step`` if it names a solver step of the training-time sampler ([S-10])."""
    return check_choice("step", step, STEPS)


def step_multipliers(weights, step: str = "algorithm1") -> np.ndarray:
    """Per-token step size c_j, the token moving by c_j v_j / T ([S-10]).

    algorithm1: c = 1. consistent: c_j = 1 - w_j for w_j < 1 and c_j = 1 for
    w_j = 1 (a prefix token keeps Algorithm 1's step, [S-11]).

    >>> step_multipliers(np.array([1.0, 0.75, 0.0]), "consistent").tolist()
    [1.0, 0.25, 1.0]
    """
    step = check_step(step)
    return _multipliers(check_array("weights", weights, ndim=1, lo=0.0, hi=1.0), step)


def _multipliers(w: np.ndarray, step: str) -> np.ndarray:
    if step == "algorithm1":
        return np.ones_like(w)  # [S-4] every token moves by v / T
    return np.where(w < 1.0, 1.0 - w, 1.0)  # [S-10] c_j = 1 - w_j; [S-11] c_j = 1 at w_j = 1


def _reblended(w: np.ndarray, step: str) -> np.ndarray:
    """Tokens blended before every step, not only the first ([S-3], [S-10])."""
    if step == "algorithm1":
        return np.ones(w.shape, dtype=bool)  # [S-3] every token, every step
    return (w == 0.0) | (w == 1.0)  # [S-10] window tokens are blended once, at k = 0


def rtc_sample(field, obs, noise, prior, weights, num_steps: int, return_trace: bool = False,
               step: str = "algorithm1"):
    """Training-time RTC sampler, hard or soft ([S-3], [S-4], [S-5]; ``step`` [S-10]).

    prior Y [H, A] is the previous chunk in the new chunk's frame ([X-3]);
    weights [H] come from weights.soft_weights / hard_weights. ``step`` is
    "algorithm1" (the paper's, default) or "consistent" ([S-10]); for weights
    in {0, 1} both give the same chunk bit for bit ([S-11]).
    """
    obs, x = _check_inputs(field, obs, noise)
    return_trace = check_bool("return_trace", return_trace)
    y = check_array("prior", prior, shape=x.shape)
    w = check_weights("weights", weights, x.shape[0])
    T = check_int("num_steps", num_steps, 1, MAX_STEPS)
    return _rtc_sample(field, obs, x, y, w, T, return_trace, check_step(step))


def _rtc_sample(field, obs, x, y, w, T: int, return_trace: bool, step: str = "algorithm1"):
    c = _multipliers(w, step)[:, None]
    again = _reblended(w, step)[:, None]
    trace = []
    for k, t in enumerate(_euler_times(T)):
        xb = _blend(x, y, w)  # [S-3]
        if k > 0:
            xb = np.where(again, xb, x)  # [S-10] a window token carries its blended state
        tb = _blend_time(t, w)  # [S-3]
        v = field_output("field", field(obs, xb, tb), x.shape)
        # [S-4] x <- x~ + v / T; [S-10] x <- x~ + (c v) / T. c = 1 gives v / T bit for bit ([S-11]).
        nxt = xb + (c * v) / T
        if return_trace:
            trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": v, "next_state": nxt})
        x = nxt
    return (x, trace) if return_trace else x  # [S-5] no final blend
