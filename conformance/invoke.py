"""One call of a Python adapter, from the request's JSON arguments to the reply ([CF-7], [CF-18], [CF-26],
[CF-29]).

Used the same way in the child process (:mod:`.host`) and with ``--in-process``:
arguments arrive by name as parsed from JSON ([CF-23]) and are turned into the
Python values of [CF-7]; the return value is turned into named outputs with the
adapter's ``to_numpy``. The reply is ``{"result": {output: value}}`` or
``{"error": {"kind", "type", "message", "where"}}``; judging it against the
expected values is the runner's business alone.
"""

from __future__ import annotations

import inspect
import traceback
from pathlib import Path

import numpy as np

from .adapter import (ALTERNATES, FLOAT_ARRAYS, INT_ARRAYS, INTERFACE, Fn, _describe, _fatal, _first_line,
                      check_adapter)

# File names of the runner's own frames, left out when pointing at the adapter's code.
_OWN_FILES = ("invoke.py", "host.py", "runner.py")
NONFINITE = {"NaN": float("nan"), "Infinity": float("inf"), "-Infinity": float("-inf")}


def function_of(attr: str) -> Fn:
    """The Fn of an adapter attribute: an interface function or an alternative form ([CF-27])."""
    if attr in INTERFACE:
        return INTERFACE[attr]
    for alt in ALTERNATES.values():
        if alt.name == attr:
            return alt.fn
    raise ValueError(f"attr must be an interface function or an alternative form, got {attr!r}")


def provided(adapter) -> list[str]:
    """Attribute names of the interface functions and alternative forms the adapter has ([CF-9], [CF-27])."""
    names = list(INTERFACE) + [a.name for a in ALTERNATES.values()]
    return [n for n in names if callable(getattr(adapter, n, None))]


def _all_ints(value) -> bool:
    if isinstance(value, list):
        return all(_all_ints(v) for v in value)
    return isinstance(value, int) and not isinstance(value, bool)


def prepare_arg(key: str, value):
    """One argument as the adapter receives it ([CF-7], [CF-23]): float arrays as float64 arrays, integer
    sequences as int64 arrays (float64 when an element is written as a float, so the implementation sees
    the non-integer it must reject), the field as a dict of float64 arrays, the rest as parsed."""
    if key == "field" and isinstance(value, dict):
        return {k: np.asarray(v, dtype=np.float64) for k, v in value.items()}
    if value is None or isinstance(value, (str, dict, bool)):
        return value
    if key in FLOAT_ARRAYS or (key == "t" and isinstance(value, list)):
        return np.asarray(value, dtype=np.float64)
    if key in INT_ARRAYS:
        return np.asarray(value, dtype=np.int64 if _all_ints(value) else np.float64)
    return value


def _where(exc: BaseException) -> str:
    """file:line of the innermost frame outside the runner, to point at the adapter's code."""
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if not f.filename.endswith(_OWN_FILES)]
    return f"{Path(frames[-1].filename).name}:{frames[-1].lineno}" if frames else ""


def _signature_problem(func, attr: str, fn: Fn) -> str | None:
    try:
        sig = inspect.signature(func)
    except (TypeError, ValueError):
        return None  # builtins without a signature are tried as they are
    try:
        sig.bind(*fn.args)
    except TypeError:
        return (f"adapter.{attr}{sig} cannot be called as {attr}({', '.join(fn.args)}); "
                f"see spec/40-conformance.md [CF-7]")
    return None


class BadResult(Exception):
    """The adapter's return value is not what the function returns ([CF-7], [CF-11])."""


class Invoker:
    """Calls one adapter object; ``functions`` lists what it provides."""

    def __init__(self, adapter):
        check_adapter(adapter)
        self.adapter = adapter
        self.name = adapter.name
        self.time_convention = getattr(adapter, "time_convention", "data_at_1")
        self.functions = provided(adapter)
        self.problems = {a: _signature_problem(getattr(adapter, a), a, function_of(a)) for a in self.functions}

    def call(self, attr: str, args: dict) -> dict:
        """The reply to ``{"function": attr, "args": args}`` ([CF-29]); only KeyboardInterrupt escapes."""
        if attr not in self.functions:
            return {"error": {"kind": "bad_call", "message": f"the implementation has no {attr}"}}
        if self.problems[attr]:
            return {"error": {"kind": "bad_call", "message": self.problems[attr]}}
        fn = function_of(attr)
        try:
            pos = [prepare_arg(k, args[k]) for k in fn.args]
        except KeyError as exc:
            return {"error": {"kind": "bad_call", "message": f"request lacks argument {exc}"}}
        try:
            out = getattr(self.adapter, attr)(*pos)
        except BaseException as exc:  # SystemExit and the like are reported too ([CF-18])
            if _fatal(exc):
                raise
            kind = ("invalid_input" if isinstance(exc, ValueError) else
                    "unsupported" if isinstance(exc, NotImplementedError) else "exception")
            return {"error": {"kind": kind, "type": type(exc).__name__, "message": _first_line(exc)[:300],
                              "where": _where(exc)}}
        try:
            return {"result": self._outputs(fn, attr, out)}
        except BadResult as exc:
            return {"error": {"kind": "bad_result", "message": str(exc)}}

    def _to_np(self, value, what: str) -> np.ndarray:
        conv = getattr(self.adapter, "to_numpy", None) or np.asarray
        try:
            arr = np.asarray(conv(value))
        except BaseException as exc:
            if _fatal(exc):
                raise
            raise BadResult(f"{what}: cannot convert {type(value).__name__} to an array ({_describe(exc)})") from None
        if arr.dtype == object:
            raise BadResult(f"{what}: not a numeric array (got {type(value).__name__})")
        return arr

    def _outputs(self, fn: Fn, attr: str, out) -> dict:
        """Return value -> {output name: array, "trace": list of {key: array} or None}."""
        if fn.kind == "value":
            got = {fn.outputs[0]: out}
        elif fn.kind in ("tuple", "sample"):
            if not isinstance(out, (tuple, list)) or len(out) != len(fn.outputs):
                raise BadResult(f"{attr} must return a tuple ({', '.join(fn.outputs)}), got {type(out).__name__}"
                                + (f" of length {len(out)}" if isinstance(out, (tuple, list)) else ""))
            got = dict(zip(fn.outputs, out))
        else:
            if not hasattr(out, "keys"):
                raise BadResult(f"{attr} must return a mapping with keys {list(fn.outputs)}, got {type(out).__name__}")
            missing = [k for k in fn.outputs if k not in out]
            if missing:
                raise BadResult(f"{attr} result lacks keys {missing}")
            got = {k: out[k] for k in fn.outputs}
        res = {}
        for k, v in got.items():
            res[k] = (None if v is None else self._trace(v, attr)) if k == "trace" else \
                self._to_np(v, f"{attr} output {k!r}")
        return res

    def _trace(self, trace, attr: str) -> list:
        if not isinstance(trace, (list, tuple)):
            raise BadResult(f"{attr} trace must be a list of per-step dicts or None, got {type(trace).__name__}")
        steps = []
        for i, step in enumerate(trace):
            if not hasattr(step, "keys"):
                raise BadResult(f"{attr} trace step {i} must be a dict, got {type(step).__name__}")
            steps.append({str(k): self._to_np(step[k], f"{attr} trace step {i} key {k!r}") for k in step.keys()})
        return steps


def to_json(value):
    """An output for the protocol: arrays as nested lists, non-finite numbers as the strings "NaN",
    "Infinity" and "-Infinity" ([CF-29]), traces step by step."""
    if value is None:
        return None
    if isinstance(value, list):
        return [{k: to_json(v) for k, v in step.items()} for step in value]
    a = np.asarray(value)
    if a.dtype.kind not in "biuf":
        raise BadResult(f"expected numbers, got dtype {a.dtype}")
    if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        flat = ["NaN" if np.isnan(x) else ("Infinity" if x > 0 else "-Infinity") if np.isinf(x) else float(x)
                for x in a.ravel().tolist()]
        return np.array(flat, dtype=object).reshape(a.shape).tolist()
    return a.tolist()
