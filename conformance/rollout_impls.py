"""Implementations of one rollout request, ``rollout_chunk`` ([CR-2]): the reference, the shipped libraries,
LeRobot, and the integration mutants the suite must catch ([CR-11]).

    rollout_chunk(field, obs, prev, noise, method, s, d, arrival, T, window, max_guidance)
        -> {"chunk": [H, A], "executed": [s, A]}

The implementation makes the whole request: it shifts the previous chunk into
the prior ([X-3]), chooses the method's weights for delay ``d`` ([S-6]),
samples with the served ``field`` ([CR-3]) and decides what the ``s`` ticks
from the request execute: ``prev[s .. s + e - 1]`` then ``chunk[e .. s - 1]``
with ``e = max(d, arrival)`` ([X-4], [R-4]). ``prev`` None is the first
request: naive sampler, ``d = arrival = 0``, ``chunk[0 .. s - 1]`` executed
([X-2]). Each library's function composes that library's own pieces; nothing
here re-implements a library.

A user's adapter provides ``rollout_chunk`` (and optionally ``rollout_methods``,
the methods it implements); :func:`load_rollout_impl` takes a built-in name of
:data:`BUILTIN` or anything ``softrtc conformance run --impl`` takes ([CF-12]).
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import executor as rexec
from softrtc.reference import guidance as rguid
from softrtc.reference import methods as rmeth
from softrtc.reference import sampler as rsamp
from softrtc.reference._validate import check_array, check_choice, check_int

from .adapter import AdapterError
from .adapters.reference import window_from_dict

METHODS = rmeth.METHODS


def check_request(obs, prev, noise, method, s, d, arrival, T, window, max_guidance) -> tuple:
    """The request's arguments checked at the door ([CR-2], [N-7]); returns ``(H, e)``, ``e = max(d, arrival)``."""
    check_choice("method", method, METHODS)
    noise = check_array("noise", noise, ndim=2)
    H = noise.shape[0]
    check_array("obs", obs, ndim=1)
    s = check_int("s", s, 1, H - 1)
    dmax = min(s, H - s)
    if prev is None:
        check_int("d", d, 0, 0)
        check_int("arrival", arrival, 0, 0)
    else:
        check_array("prev", prev, shape=noise.shape)
        check_int("d", d, 0, dmax)
        check_int("arrival", arrival, 0, dmax)
    check_int("T", T, 1, rsamp.MAX_STEPS)
    if window is not None and not isinstance(window, dict):
        raise ValueError(f"window must be None or a window dict {{rule, schedule, parametrization, overflow}}, "
                         f"got {type(window).__name__}")
    if isinstance(max_guidance, bool) or not isinstance(max_guidance, (int, float)) or not max_guidance > 0:
        raise ValueError(f"max_guidance must be a number > 0, got {max_guidance!r}")
    return H, (0 if prev is None else max(int(d), int(arrival)))


def _window(window):
    return None if window is None else window_from_dict(window)


def _executed(prev, chunk, s: int, e: int) -> np.ndarray:
    return chunk[:s] if prev is None else rexec.segment(prev, chunk, s, e)


class ReferenceRollout:
    """The NumPy reference ([X-3], [S-6], [G-2]..[G-5], [X-4], [R-4]); ``prior_shift``, ``pullback`` and
    ``execution`` select the deliberate integration bugs of the mutants ([CR-11]); the defaults are the spec."""

    name = "reference"
    time_convention = "data_at_1"
    rollout_methods = METHODS

    def __init__(self, name: str = "reference", prior_shift: int = 0, pullback: str = "full",
                 execution: str = "spec"):
        self.name, self.prior_shift, self.pullback, self.execution = name, prior_shift, pullback, execution

    def chunk(self, field, obs, prev, noise, method, s, d, T, window, max_guidance) -> np.ndarray:
        """The chunk of one request ([X-2], [X-3], [S-6])."""
        noise = np.asarray(noise, np.float64)
        if prev is None or method == "naive":
            return rsamp.naive_sample(field, obs, noise, T)  # first chunk; [S-6] naive
        prior = rexec.shift_prior(prev, s + self.prior_shift)
        w = rmeth.method_weights(method, noise.shape[0], s, d, _window(window))  # [S-6]
        if method.startswith("inference_"):
            if self.pullback == "no_jacobian":
                field = _NoJacobian(field)
            return rguid.guided_sample(field, obs, noise, prior, w, T, max_guidance)
        return rsamp.rtc_sample(field, obs, noise, prior, w, T)

    def rollout_chunk(self, field, obs, prev, noise, method, s, d, arrival, T, window, max_guidance) -> dict:
        H, e = check_request(obs, prev, noise, method, s, d, arrival, T, window, max_guidance)
        chunk = self.chunk(field, obs, prev, noise, method, s, d, T, window, max_guidance)
        if prev is None:
            return {"chunk": chunk, "executed": chunk[:s]}
        prev = np.asarray(prev, np.float64)
        if self.execution == "tokens_from_switch":
            executed = np.concatenate([prev[s:s + e], chunk[:s - e]])
        elif self.execution == "prefix_not_reapplied":
            executed = chunk[:s]
        elif self.execution == "late_dropped" and arrival > d:
            executed = prev[s:2 * s] if 2 * s <= H else np.concatenate([prev[s:], prev[-1:].repeat(2 * s - H, 0)])
        else:
            executed = rexec.segment(prev, chunk, s, e)  # with e = max(d, arrival) ([R-4])
        return {"chunk": chunk, "executed": executed}


class _NoJacobian:
    """A field whose VJP is zero: the guided sampler's pull-back is then ``g = err``, without the
    ``(1 - t) (dv/dx)^T err`` term of [G-3] (the defect the mutant and LeRobot share)."""

    def __init__(self, field):
        self.field = field

    def __call__(self, obs, x, t):
        return self.field(obs, x, t)

    def vjp(self, obs, x, t, cotangent):
        return np.zeros(np.shape(cotangent))


# The integration mutants of [CR-11]: each a plausible mistake in the glue around correct samplers.
MUTANTS = {
    "mutant-prior-shift": dict(prior_shift=-1),
    "mutant-tokens-from-switch": dict(execution="tokens_from_switch"),
    "mutant-prefix-not-reapplied": dict(execution="prefix_not_reapplied"),
    "mutant-late-dropped": dict(execution="late_dropped"),
    "mutant-no-jacobian": dict(pullback="no_jacobian"),
}

MUTANT_NOTES = {
    "mutant-prior-shift": "the prior is the previous chunk shifted by s - 1 instead of s ([X-3])",
    "mutant-tokens-from-switch": "the new chunk's tokens are counted from the switch tick, not from the request: "
                                 "chunk[0 .. s - e - 1] runs after the switch instead of chunk[e .. s - 1] ([X-4])",
    "mutant-prefix-not-reapplied": "the committed prefix is taken from the new chunk (chunk[0 .. e - 1]) instead of "
                                   "the previous chunk's prev[s .. s + e - 1] ([X-4])",
    "mutant-late-dropped": "a chunk that arrives after its planned delay is dropped and the previous chunk runs on "
                           "to its end, instead of waiting for the chunk ([R-4])",
    "mutant-no-jacobian": "the guided pull-back is err alone, without (1 - t) (dv/dx)^T err ([G-3])",
}


def _jax_rollout():
    from .rollout_libs import JaxRollout

    return JaxRollout()


def _torch_rollout(flipped: bool):
    from .rollout_libs import TorchRollout

    return TorchRollout(flipped)


def _lerobot_rollout():
    from .rollout_libs import LeRobotRollout

    return LeRobotRollout()


BUILTIN = {
    "reference": lambda: ReferenceRollout(),
    "jax": _jax_rollout,
    "torch": lambda: _torch_rollout(False),
    "torch-flipped": lambda: _torch_rollout(True),
    "lerobot": _lerobot_rollout,
    **{name: (lambda name=name, kw=kw: ReferenceRollout(name, **kw)) for name, kw in MUTANTS.items()},
}


class NoRolloutChunk(AdapterError):
    """The adapter loaded but has no ``rollout_chunk`` ([CR-2]); ``adapter`` is the loaded object, so a
    `conformance run` can count its rollout cases unsupported ([CR-10], [CF-9])."""

    def __init__(self, message: str, adapter):
        super().__init__(message)
        self.adapter = adapter


def load_rollout_impl(spec: str):
    """A rollout implementation: a name of :data:`BUILTIN`, or an adapter (``module[:ATTR]``,
    ``file.py[:ATTR]``, [CF-12]) with ``name`` and ``rollout_chunk`` ([CR-2]); NoRolloutChunk for an
    adapter without it."""
    from .adapter import load_adapter

    if isinstance(spec, str) and spec in BUILTIN:
        return BUILTIN[spec]()
    if not isinstance(spec, str) or spec in ("reference", "jax", "torch", "torch-flipped", "lerobot"):
        raise AdapterError(f"impl must be a built-in name {tuple(BUILTIN)}, module[:ATTR] or file.py[:ATTR]")
    adapter = load_adapter(spec)
    if not callable(getattr(adapter, "rollout_chunk", None)):
        raise NoRolloutChunk(f"adapter '{spec}' has no rollout_chunk function ([CR-2])", adapter)
    return adapter


def impl_methods(impl) -> tuple:
    """The methods an implementation runs ([CR-2]): its ``rollout_methods``, else all five of [S-6]."""
    ms = getattr(impl, "rollout_methods", None)
    return tuple(METHODS if ms is None else ms)
