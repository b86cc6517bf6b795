"""Comparing an implementation's outputs with the expected ones, and mapping between the time conventions
([CF-5], [CF-10], [CF-11], [CF-32]).

A number passes when ``|got - want| <= abs + rel * |want|``; an integer output
must be an integer equal to the expected one ([CF-5]). Outputs of a
"noise_at_1" implementation are mapped onto the spec (t = 1 - t', v = -u)
before comparing ([CF-10], [V-1]). Every verdict against the implementation is
a :class:`CaseFailure` with a one-line message.
"""

from __future__ import annotations

import math

import numpy as np

from .adapter import TRACE_TIME_KEYS, TRACE_VEL_KEYS, Fn
from .invoke import NONFINITE
from .results import TRACE_NOT_PROVIDED


class CaseFailure(Exception):
    """A case failed; the message is one line. ``ratio`` is the worst |got - want| / tolerance when a
    number was out of tolerance, inf when none could be compared (exact-match mismatch, wrong shape,
    type or kind of result, exception) ([CF-5], [CF-14])."""

    def __init__(self, message: str, ratio: float = math.inf):
        super().__init__(message)
        self.ratio = float(ratio)


# ---------------------------------------------------------------- comparing

def _decode(what: str, value) -> np.ndarray:
    """A reply's value as an array; the protocol's "NaN", "Infinity" and "-Infinity" strings as numbers
    ([CF-29]), any other string or a ragged list as a failure."""
    try:
        a = np.asarray(value)
    except (TypeError, ValueError):
        raise CaseFailure(f"{what}: not a rectangular array of numbers") from None
    if a.dtype.kind == "U":
        if not np.isin(a, list(NONFINITE)).all():
            raise CaseFailure(f"{what}: expected numbers, got strings")
        a = np.vectorize(NONFINITE.get, otypes=[np.float64])(a)
    elif a.dtype == object:
        raise CaseFailure(f"{what}: not a numeric array")
    return a


def check_integers(what: str, value) -> None:
    """CaseFailure unless ``value`` holds integers only ([CF-5]): JSON integers (never ``4.0``, never
    ``true``/``false``, which Python reads as 1 and 0), Python ints, NumPy integer scalars or arrays of an
    integer dtype. An integer output given as a real or a boolean is the wrong kind of result, whatever its
    value (alternative not chosen: accepting any real equal to an integer, under which an implementation
    computing an endpoint or a delay in floating point would pass until rounding made it 3.9999999)."""
    if isinstance(value, np.ndarray):
        if value.dtype.kind not in "iu":
            raise CaseFailure(f"{what}: expected integers, got an array of {value.dtype}")
        return
    if isinstance(value, (list, tuple)):
        for v in value:
            check_integers(what, v)
        return
    if isinstance(value, (bool, np.bool_)):
        raise CaseFailure(f"{what}: expected an integer, got the boolean {bool(value)!r}")
    if not isinstance(value, (int, np.integer)):
        shown = value if isinstance(value, (float, str)) else type(value).__name__
        raise CaseFailure(f"{what}: expected an integer, got {shown!r}")


def compare(what: str, got, want, tol: dict, integer: bool = False, exact=None) -> float:
    """Worst |got - want| / (abs + rel |want|) ([CF-5]); raise CaseFailure when above 1 (or not a number).
    ``exact``: flat indices of entries that must match exactly ([CF-32])."""
    if not isinstance(tol, dict) or not {"abs", "rel"} <= set(tol):
        raise ValueError(f"tol must be a dict with keys 'abs' and 'rel' ([CF-5]), got {tol!r}")
    w = np.asarray(want, dtype=np.float64)
    if integer:
        check_integers(what, got)
    g = _decode(what, got)
    if g.dtype.kind not in "biuf":
        raise CaseFailure(f"{what}: expected numbers, got dtype {g.dtype}")
    if g.dtype.kind == "b":
        raise CaseFailure(f"{what}: expected real numbers, got booleans")
    g = g.astype(np.float64)
    if g.shape != w.shape:
        if g.size == w.size == 1 and w.ndim == 0:
            g = g.reshape(())
        else:
            raise CaseFailure(f"{what}: shape {list(g.shape)}, expected {list(w.shape)}")
    if not np.all(np.isfinite(g)):
        bad = np.argwhere(~np.isfinite(g))
        where = f" at index {bad[0].tolist()}" if g.ndim else ""
        raise CaseFailure(f"{what}: non-finite value (NaN or inf){where}")
    if not np.all(np.isfinite(w)):  # the reader refuses such files ([CF-28]); a ratio of NaN must never pass
        raise CaseFailure(f"{what}: the expected value is not finite")
    err = np.abs(g - w)
    bound = np.zeros_like(err) if integer else tol["abs"] + tol["rel"] * np.abs(w)
    if exact and not integer:
        bound = np.array(bound, dtype=np.float64)
        bound.reshape(-1)[np.asarray(exact, dtype=np.int64)] = 0.0
    ratio = np.where(err == 0, 0.0, np.divide(err, bound, out=np.full_like(err, np.inf), where=bound > 0))
    worst = float(ratio.max()) if ratio.size else 0.0
    if not worst <= 1.0:  # NaN fails too
        i = np.unravel_index(int(np.nanargmax(np.where(np.isnan(ratio), np.inf, ratio))), ratio.shape) \
            if ratio.ndim else ()
        idx = f"[{', '.join(map(str, i))}]" if i else ""
        times = "exact match required" if integer or not math.isfinite(worst) else f"{worst:.3g} x tolerance"
        raise CaseFailure(f"{what}{idx}: got {_number(g[i], integer)!r}, expected {_number(w[i], integer)!r} "
                          f"({times})", worst if worst == worst else math.inf)
    return worst


def _number(x, integer: bool):
    """A plain Python number for messages: an int for integer outputs, else a float (never np.float64(...))."""
    v = float(x)
    return int(v) if integer and v.is_integer() else v


def check_outputs(fn: Fn, fname: str, got: dict, expected: dict, tol: dict,
                  plain: bool = False) -> tuple[float, str]:
    """Worst ratio over every output ([CF-5], [CF-11]). With ``plain`` (values parsed from JSON without
    booleans) a value equal to the expected one as parsed has ratio 0 without going through NumPy."""
    worst, note, exact = 0.0, "", tol.get("exact", {})
    for k in fn.outputs:
        if k == "trace":
            if got.get("trace") is None:
                note = TRACE_NOT_PROVIDED
                continue
            tr, want = got["trace"], expected["trace"]
            if len(tr) != len(want):
                raise CaseFailure(f"{fname} trace has {len(tr)} steps, expected {len(want)}")
            for i, (st, ws) in enumerate(zip(tr, want)):
                missing = [k2 for k2 in ws if k2 not in st]
                if missing:
                    raise CaseFailure(f"{fname} trace step {i} lacks keys {missing}")
                for k2 in sorted(ws):
                    if not (plain and st[k2] == ws[k2]):
                        worst = max(worst, compare(f"trace step {i} {k2}", st[k2], ws[k2], tol,
                                                   exact=exact.get(f"trace/{k2}")))
            continue
        if k in fn.int_out:  # before the shortcut: 4.0 == 4 and True == 1 in Python
            check_integers(k, got[k])
        if not (plain and got[k] == expected[k]):
            worst = max(worst, compare(k, got[k], expected[k], tol, k in fn.int_out, exact.get(k)))
    return worst, note


# ---------------------------------------------------------------- mapping between conventions

def _flip_args(fn: Fn, args: dict) -> dict:
    """Arguments in the flipped convention ([CF-10]): flow times t' = 1 - t, velocities u = -v."""
    out = dict(args)
    for k in fn.time_args:
        v = np.asarray(args[k], dtype=np.float64)
        out[k] = (1.0 - v).tolist() if v.ndim else 1.0 - float(v)
    for k in fn.vel_args:
        out[k] = (-np.asarray(args[k], dtype=np.float64)).tolist()
    return out


def _outputs(fn: Fn, attr: str, result, flipped: bool) -> dict:
    """A reply's result as {output: array, "trace": [{key: array}] or None} in the spec's convention; in the
    spec's own convention the values stay as received (compare() decodes them)."""
    if not isinstance(result, dict):
        raise CaseFailure(f"{attr} result must be an object with the outputs {list(fn.outputs)}")
    missing = [k for k in fn.outputs if k not in result]
    if missing:
        raise CaseFailure(f"{attr} result lacks keys {missing}")
    got = {}
    for k in fn.outputs:
        v = result[k]
        if k == "trace":
            if v is not None and (not isinstance(v, list) or not all(isinstance(st, dict) for st in v)):
                raise CaseFailure(f"{attr} trace must be a list of per-step dicts or None, got {type(v).__name__}")
            got[k] = None if v is None or not flipped else [
                {sk: _flip_out(_decode(f"{attr} trace step {i} key {sk!r}", sv), sk in TRACE_TIME_KEYS,
                               sk in TRACE_VEL_KEYS, flipped) for sk, sv in st.items()} for i, st in enumerate(v)]
            if v is not None and not flipped:
                got[k] = v
            continue
        got[k] = _flip_out(_decode(f"{attr} output {k!r}", v), k in fn.time_out, k in fn.vel_out, flipped) \
            if flipped and k not in fn.int_out else v  # integers keep their JSON or NumPy kind ([CF-5])
    return got


def _flip_out(a: np.ndarray, is_time: bool, is_vel: bool, flipped: bool) -> np.ndarray:
    if flipped and is_time and a.dtype.kind in "iuf":
        return 1.0 - a
    if flipped and is_vel and a.dtype.kind in "iuf":
        return -a
    return a
