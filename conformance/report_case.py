"""One case of a compatibility report in detail ([TP-2]): the adapter called in this process on a case's
arguments, and its expected and actual values rounded as a report shows them.

The report (:mod:`softrtc.conformance.report`) shows, for every failing
requirement id and function, the smallest failing case: its arguments, and
what the implementation returned or raised; for a sampler, the first step
whose values differ. Numbers are rounded to DIGITS significant digits, and
arrays with more than SHOWN_NUMBERS numbers are shown by their shape.
"""

from __future__ import annotations

import math
import re

import numpy as np

from .adapter import ALTERNATES, INTERFACE, TRACE_TIME_KEYS, TRACE_VEL_KEYS

__all__ = ["inspect_case", "case_size", "DIGITS", "SHOWN_NUMBERS"]

# Numbers in a report are rounded to this many significant digits ([TP-4]).
DIGITS = 4
SHOWN_NUMBERS = 24  # arrays with more numbers are shown by shape only


# ---------------------------------------------------------------- numbers

def _round(x: float, digits: int = DIGITS):
    """A float rounded to ``digits`` significant digits; inf as the string "inf" (JSON has no inf)."""
    x = float(x)
    if not math.isfinite(x):
        return "inf" if x > 0 else ("-inf" if x < 0 else "nan")
    return float(f"{x:.{digits}g}")


_NUMBER = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+)(?:[eE][-+]?\d+)?(?![\w.])")
_FLOAT = re.compile(r"(?<![\w.])[-+]?(?:\d+\.\d*|\.\d+|\d+(?=[eE]))(?:[eE][-+]?\d+)?(?![\w.])")


def _round_text(text: str) -> str:
    """Every float written in ``text`` rounded to DIGITS significant digits (integers kept)."""
    return _FLOAT.sub(lambda m: repr(_round(float(m.group(0)))), text)


def _shown(a, digits: int = DIGITS):
    """An array as nested lists of rounded numbers (integers kept), or its shape when it has more than
    SHOWN_NUMBERS numbers."""
    arr = np.asarray(a)
    if arr.size > SHOWN_NUMBERS:
        return f"array of shape {list(arr.shape)}"
    if arr.dtype.kind in "iub":
        return arr.astype(np.int64).tolist()
    arr = arr.astype(np.float64)
    return np.vectorize(lambda v: _round(v, digits), otypes=[object])(arr).tolist() if arr.ndim else _round(arr)


# ---------------------------------------------------------------- one case, in detail

def _arg_size(value) -> int:
    if isinstance(value, list):
        return sum(_arg_size(v) for v in value)
    return 1


def case_size(case: dict) -> int:
    """How many numbers a case's arguments hold (the field's weights, stored apart, not counted)."""
    return sum(_arg_size(v) for k, v in case["args"].items() if k != "field")


def _shown_args(case: dict) -> dict:
    out = {}
    for k, v in sorted(case["args"].items()):
        if k == "field":
            out[k] = f"reference field {v!r} of the vector file"
        elif isinstance(v, list):
            out[k] = _shown(v) if np.asarray(v).dtype != object else v
        elif isinstance(v, float):
            out[k] = _round(v, 12)
        else:
            out[k] = v
    return out


def _to_np(adapter, value) -> np.ndarray:
    conv = getattr(adapter, "to_numpy", None) or np.asarray
    return np.asarray(conv(value))


def _outputs(adapter, fn, out, flipped: bool) -> dict:
    """The adapter's return value as {output: array} in the spec's convention ([CF-10])."""
    if fn.kind == "value":
        got = {fn.outputs[0]: out}
    elif fn.kind in ("tuple", "sample"):
        got = dict(zip(fn.outputs, out))
    else:
        got = {k: out[k] for k in fn.outputs}
    res = {}
    for k, v in got.items():
        if k == "trace":
            res[k] = None if v is None else [_step(adapter, st, flipped) for st in v]
            continue
        a = _to_np(adapter, v)
        if flipped and k in fn.time_out:
            a = 1.0 - a
        if flipped and k in fn.vel_out:
            a = -a
        res[k] = a
    return res


def _step(adapter, step: dict, flipped: bool) -> dict:
    st = {}
    for k in step:
        a = _to_np(adapter, step[k])
        if flipped and k in TRACE_TIME_KEYS:
            a = 1.0 - a
        if flipped and k in TRACE_VEL_KEYS:
            a = -a
        st[k] = a
    return st


def _within(got: np.ndarray, want, tol: dict) -> bool:
    w = np.asarray(want, dtype=np.float64)
    g = np.asarray(got, dtype=np.float64).reshape(w.shape) if np.size(got) == w.size else None
    return g is not None and bool(np.all(np.abs(g - w) <= tol["abs"] + tol["rel"] * np.abs(w)))


# Arguments passed as arrays ([CF-7]): the report calls the adapter itself for the cases it shows.
_FLOAT_ARRAYS = {"actions", "noise", "weights", "pred", "preds", "obs", "x", "cotangent", "prior", "prev", "chunks",
                 "probs", "values"}
_INT_ARRAYS = {"indices", "chunk_index", "delays"}


def _all_ints(value) -> bool:
    if isinstance(value, list):
        return all(_all_ints(v) for v in value)
    return isinstance(value, int) and not isinstance(value, bool)


def _argument(key: str, value, data: dict, fn, flipped: bool):
    """One argument as [CF-7] and [CF-10] give it to an adapter."""
    if key == "field":
        return {k: np.asarray(v, dtype=np.float64) for k, v in data["fields"][value]["params"].items()}
    if key in _FLOAT_ARRAYS or (key == "t" and isinstance(value, list)):
        value = np.asarray(value, dtype=np.float64)
    elif key in _INT_ARRAYS:
        value = np.asarray(value, dtype=np.int64 if _all_ints(value) else np.float64)
    if flipped and key in fn.time_args:
        value = 1.0 - value if isinstance(value, np.ndarray) else 1.0 - float(value)
    if flipped and key in fn.vel_args:
        value = -value
    return value


def _form(adapter, fname: str, case: dict):
    """The adapter's function that runs ``case``: ``fname`` itself, else its alternative form ([CF-27])."""
    if callable(getattr(adapter, fname, None)):
        return fname, INTERFACE[fname]
    alt = ALTERNATES.get(fname)
    if alt is not None and callable(getattr(adapter, alt.name, None)) and alt.needs in case["args"]:
        return alt.name, alt.fn
    return None, None


def inspect_case(adapter, fname: str, case: dict, data: dict) -> dict:
    """Expected and actual values of one case, called in this process: whole outputs when small, and for
    a sampler the first step whose values differ, with every key of that step marked agreeing or not."""
    flipped = getattr(adapter, "time_convention", "data_at_1") == "noise_at_1"
    attr, form_fn = _form(adapter, fname, case)
    if attr is None:
        return {"actual": "no form of the function takes this case"}
    args = [_argument(k, case["args"][k], data, form_fn, flipped) for k in form_fn.args]
    expected = case["expected"]
    try:
        out = getattr(adapter, attr)(*args)
    except Exception as exc:  # the report states what the implementation did
        text = str(exc).splitlines()[0] if str(exc) else ""
        return {"called": attr, "actual": _round_text(f"raised {type(exc).__name__}" + (f": {text}" if text else ""))}
    got = _outputs(adapter, INTERFACE[fname], out, flipped)
    if "error" in expected:
        return {"called": attr, "expected": "ValueError",
                "actual": {k: _shown(v) for k, v in got.items() if k != "trace"}}
    detail = {"called": attr, "expected": {}, "actual": {}}
    for k in INTERFACE[fname].outputs:
        if k != "trace":
            detail["expected"][k] = _shown(expected[k])
            detail["actual"][k] = _shown(got[k])
    if got.get("trace") is not None and "trace" in expected:
        tol = case["tolerance"]
        for i, (st, ws) in enumerate(zip(got["trace"], expected["trace"])):
            agree = {k: k in st and _within(st[k], ws[k], tol) for k in sorted(ws)}
            if not all(agree.values()):
                differ = {}
                for k, ok in agree.items():
                    if not ok and k in st:
                        w = np.asarray(ws[k], dtype=np.float64)
                        differ[k] = _round(float(np.max(np.abs(np.asarray(st[k], dtype=np.float64).reshape(w.shape)
                                                               - w))))
                detail["first_differing_step"] = {"step": i, "agree": sorted(k for k, ok in agree.items() if ok),
                                                  "differ": differ}
                break
    return detail
