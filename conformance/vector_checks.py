"""Checks of one vector case before any implementation sees it ([CF-6], [CF-24], [CF-27], [CF-28]).

A case is malformed when a field of [CF-6] is missing or of the wrong type, when
it names a function outside the interface, lacks an argument, names a field the
file does not hold, holds a tolerance outside [0, 1], an argument array that is
not a rectangular array of numbers, or an expected output that is missing, not
numeric, of a shape its arguments do not give, or written as a float where the
output is an integer. The rules of ``spec/vectors.schema.json`` are checked too
([CF-38]): no key the schema does not declare, in the file, a field or a case; no
argument the function does not take, no output it does not return. Such a case
is a defect of the vectors, never a failure of the implementation under test:
:class:`~.vectors_io.VectorError`, status 2.
"""

from __future__ import annotations

import math
import re

import numpy as np

from .adapter import ALTERNATES, FLOAT_ARRAYS, GUIDANCE_KEYS, INT_ARRAYS, INTERFACE, TRACE_KEYS
from .vectors_io import MAX_ABS_INT, VectorError

# Tolerances are fractions: a larger abs or rel passes anything of the size of the quantities checked ([CF-5]).
MAX_TOLERANCE = 1.0

# The keys spec/vectors.schema.json declares ([CF-38]): anything else is a defect, never ignored.
TOP_KEYS = ("format_version", "spec_version", "chapter", "title", "generator", "reference", "fields", "cases")
CASE_KEYS = ("id", "function", "requirements", "tolerance", "args", "expected")
FIELD_KEYS = ("params", "horizon", "action_dim", "obs_dim", "hidden")
PARAM_KEYS = ("W1", "Wt", "Wo", "b1", "W2", "b2")
# The schema's patterns: (key, pattern, what it means).
HEADER_PATTERNS = (("format_version", r"1\.[0-9]+", "a string '1.MINOR'"),
                   ("spec_version", r"[0-9]+\.[0-9]+\.[0-9]+", "a string 'MAJOR.MINOR.PATCH'"),
                   ("chapter", r"[A-Z]+", "capital letters"),
                   ("title", r".*", "a string"), ("generator", r".*", "a string"), ("reference", r".*", "a string"))
ID_PATTERN = re.compile(r"[A-Z]+\.[A-Za-z_]+\..+", re.S)
REQUIREMENT_PATTERN = re.compile(r"[A-Z]+-[0-9]+")


def _unknown(where: str, obj: dict, allowed, what: str = "unknown keys") -> None:
    extra = sorted(str(k) for k in obj if k not in allowed)
    if extra:
        raise VectorError(f"{where}: {what} {extra} (spec/vectors.schema.json allows {list(allowed)}, [CF-38])")


def check_header(file: str, data: dict) -> None:
    """The file's top level: only the schema's keys, its header strings on their patterns (all but
    format_version optional: a hand-made file may omit them), a non-empty case list ([CF-2], [CF-38])."""
    _unknown(file, data, TOP_KEYS, "unknown top-level keys")
    for key, pattern, what in HEADER_PATTERNS:
        if key in data and (not isinstance(data[key], str) or not re.fullmatch(pattern, data[key], re.S)):
            raise VectorError(f"{file}: '{key}' must be {what}, got {data[key]!r} ([CF-38])")
    if not isinstance(data.get("cases"), list) or not data["cases"]:
        raise VectorError(f"{file}: 'cases' must be a non-empty list of cases ([CF-38])")


def all_ints(value) -> bool:
    """Whether every number of a (nested) JSON list was written as an integer ([CF-23])."""
    if isinstance(value, list):
        return all(all_ints(v) for v in value)
    return isinstance(value, int) and not isinstance(value, bool)


def as_array(what: str, value, dtype) -> np.ndarray:
    """``value`` as a NumPy array of ``dtype``; VectorError unless it is a rectangular array of numbers
    (NumPy's own type detection: None, strings and objects make no numeric array)."""
    if isinstance(value, bool) or not isinstance(value, (list, int, float)):
        raise VectorError(f"{what} is not a rectangular array of numbers")
    try:
        a = np.asarray(value)
        if a.dtype == object and any(isinstance(x, int) and abs(x) > MAX_ABS_INT for x in a.reshape(-1).tolist()):
            raise ValueError("an integer beyond 2^53 in magnitude, [CF-28]")  # NumPy holds it as an object
        if a.dtype.kind not in "iuf":
            raise ValueError(f"elements of type {a.dtype}")
        if a.dtype.kind != "f" and np.any(np.abs(a) > MAX_ABS_INT):
            raise ValueError("an integer beyond 2^53 in magnitude, [CF-28]")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise ValueError("a number that overflows a double, [CF-28]")
        return a.astype(dtype, copy=False)
    except (TypeError, ValueError, OverflowError) as exc:
        text = str(exc).strip().splitlines()
        raise VectorError(f"{what} is not a rectangular array of numbers ({text[0][:200] if text else ''})") from None


def check_fields(file: str, fields: dict) -> None:
    """Every field of a file's 'fields' holds exactly the schema's keys: 'params' (the six weight arrays of
    [F-3], rectangular and real) and the integer sizes ([F-3], [CF-24], [CF-38])."""
    for name, f in fields.items():
        if not isinstance(f, dict) or not isinstance(f.get("params"), dict):
            raise VectorError(f"{file}: field {name!r} has no 'params' object")
        where = f"{file}: field {name!r}"
        _unknown(where, f, FIELD_KEYS)
        missing = [k for k in FIELD_KEYS if k not in f]
        if missing:
            raise VectorError(f"{where} lacks {missing} (spec/vectors.schema.json, [CF-38])")
        for k in FIELD_KEYS[1:]:
            if isinstance(f[k], bool) or not isinstance(f[k], int) or f[k] < 1:
                raise VectorError(f"{where}: '{k}' must be an integer >= 1, got {f[k]!r} ([CF-38])")
        _unknown(f"{where} params", f["params"], PARAM_KEYS)
        missing = [k for k in PARAM_KEYS if k not in f["params"]]
        if missing:
            raise VectorError(f"{where} params lack {missing} ([F-3], [CF-38])")
        for k, v in f["params"].items():
            a = as_array(f"{file}: field {name!r} {k}", v, np.float64)
            if a.ndim != (1 if k.startswith("b") else 2):
                raise VectorError(f"{where} {k} must be a {'vector' if k.startswith('b') else 'matrix'}, "
                                  f"got {a.ndim} dimensions ([F-3], [CF-38])")


def check_case(file: str, i: int, case, fields: dict) -> None:
    """Raise VectorError unless ``case`` is well formed ([CF-6], [CF-24], spec/vectors.schema.json)."""
    where = f"{file}: case {i}"
    if not isinstance(case, dict):
        raise VectorError(f"{where} must be a JSON object, got {type(case).__name__}")
    for key, kind in (("id", str), ("function", str), ("requirements", list), ("args", dict), ("tolerance", dict),
                      ("expected", dict)):
        if not isinstance(case.get(key), kind):
            raise VectorError(f"{where} ({case.get('id', '?')!r}): '{key}' must be a {kind.__name__}, "
                              f"got {type(case.get(key)).__name__}")
    where = f"{where} ({case['id']!r})"
    _unknown(where, case, CASE_KEYS)
    if not ID_PATTERN.fullmatch(case["id"]):
        raise VectorError(f"{where}: 'id' {case['id']!r} must look like CHAPTER.function.name ([CF-6], [CF-38])")
    reqs = case["requirements"]
    if not reqs or not all(isinstance(r, str) and REQUIREMENT_PATTERN.fullmatch(r) for r in reqs) \
            or len(set(reqs)) != len(reqs):
        raise VectorError(f"{where}: 'requirements' must be a non-empty list of distinct ids like 'W-1', got {reqs!r}")
    fn = INTERFACE.get(case["function"])
    if fn is None:
        raise VectorError(f"{where}: 'function' {case['function']!r} is not an interface function ([CF-7])")
    missing = [a for a in fn.args if a not in case["args"]]
    if missing:
        raise VectorError(f"{where}: 'args' lacks {missing} of {case['function']}({', '.join(fn.args)})")
    alt = ALTERNATES.get(case["function"])
    extra = sorted(a for a in case["args"] if a not in fn.args and (alt is None or a != alt.needs))
    if extra:
        raise VectorError(f"{where}: 'args' holds {extra}, which {case['function']}({', '.join(fn.args)}) does not "
                          "take ([CF-7], [CF-38])")
    if "field" in fn.args:
        name = case["args"]["field"]
        if not isinstance(name, str) or not isinstance(fields.get(name), dict) \
                or not isinstance(fields[name].get("params"), dict):
            raise VectorError(f"{where}: 'field' {name!r} names no field with 'params' in the file's 'fields'")
    tol = case["tolerance"]
    for key in ("abs", "rel"):
        v = tol.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or not \
                0 <= v <= MAX_TOLERANCE:
            raise VectorError(f"{where}: tolerance '{key}' must be a finite number in [0, {MAX_TOLERANCE:g}], "
                              f"got {v!r}")
    _check_guidance(where, case)
    arrays = _check_args(where, case, fn)
    _check_exact(where, case, fn)
    exp = case["expected"]
    if "error" in exp:
        if exp != {"error": "ValueError"}:
            raise VectorError(f"{where}: an error case's 'expected' must be exactly {{'error': 'ValueError'}}")
        return
    missing = [k for k in fn.outputs if k not in exp]
    if missing:
        raise VectorError(f"{where}: 'expected' lacks outputs {missing} of {case['function']}")
    extra = sorted(k for k in exp if k not in fn.outputs)
    if extra:
        raise VectorError(f"{where}: 'expected' holds {extra}, which {case['function']} does not return "
                          f"(its outputs: {list(fn.outputs)}; [CF-7], [CF-38])")
    _check_expected(where, case, fn, arrays)


def _check_exact(where: str, case: dict, fn) -> None:
    """The tolerance's optional 'exact': {output or "trace/KEY": [flat index, ...]} ([CF-32]); the indices
    must lie in the output (checked against the expected shape by _check_expected's arrays)."""
    tol = case["tolerance"]
    extra = sorted(set(tol) - {"abs", "rel", "exact"})
    if extra:
        raise VectorError(f"{where}: tolerance has unknown keys {extra}")
    if "exact" not in tol:
        return
    ex = tol["exact"]
    trace_keys = TRACE_KEYS.get(case["function"], ())
    names = set(fn.outputs) - {"trace"} | {f"trace/{k}" for k in trace_keys}
    if not isinstance(ex, dict) or not set(ex) <= names or not all(
            isinstance(v, list) and v and all(isinstance(i, int) and not isinstance(i, bool) and i >= 0 for i in v)
            for v in ex.values()):
        raise VectorError(f"{where}: tolerance 'exact' must map outputs of {case['function']} "
                          f"({sorted(names)}) to non-empty lists of indices >= 0")
    if "error" in case["expected"]:
        raise VectorError(f"{where}: an error case has no outputs to compare exactly")
    for k, idx in ex.items():
        want = case["expected"]["trace"][0].get(k[6:]) if k.startswith("trace/") and case["expected"].get("trace") \
            else case["expected"].get(k)
        size = int(np.size(np.asarray(want, dtype=object))) if want is not None else 0
        if max(idx) >= size:
            raise VectorError(f"{where}: tolerance 'exact' index {max(idx)} is outside {k!r} ({size} entries)")


def _check_guidance(where: str, case: dict) -> None:
    """A guided case's optional 'guidance' argument: the parameters that define its weights ([CF-27])."""
    alt = ALTERNATES.get(case["function"])
    if alt is None or alt.needs not in case["args"]:
        return
    g = case["args"][alt.needs]
    if not isinstance(g, dict) or sorted(g) != sorted(GUIDANCE_KEYS):
        raise VectorError(f"{where}: 'guidance' must be an object with exactly the keys {list(GUIDANCE_KEYS)}")
    ints = all(isinstance(g[k], int) and not isinstance(g[k], bool) for k in ("H", "s", "d", "end"))
    if not ints or not all(isinstance(g[k], str) for k in ("variant", "schedule")) \
            or isinstance(g["max_guidance"], bool) or not isinstance(g["max_guidance"], (int, float)):
        raise VectorError(f"{where}: 'guidance' holds integers H, s, d, end, strings variant, schedule and a "
                          "number max_guidance")


MAX_DEPTH = 8  # of an argument that is not an array (a window dict holds a rule dict: depth 2)


def _check_plain(where: str, v, depth: int = 0) -> None:
    """A non-array argument: finite floats, integers within 2^53, nesting at most MAX_DEPTH ([CF-28])."""
    if depth > MAX_DEPTH:
        raise VectorError(f"{where} is nested deeper than {MAX_DEPTH} levels ([CF-28])")
    if isinstance(v, dict):
        for x in v.values():
            _check_plain(where, x, depth + 1)
    elif isinstance(v, list):
        for x in v:
            _check_plain(where, x, depth + 1)
    elif isinstance(v, float) and not math.isfinite(v):
        raise VectorError(f"{where} holds a number that overflows a double ([CF-28])")
    elif isinstance(v, int) and not isinstance(v, bool) and abs(v) > MAX_ABS_INT:
        raise VectorError(f"{where} holds an integer beyond 2^53 in magnitude ([CF-28])")


def _check_args(where: str, case: dict, fn) -> dict:
    """The case's array arguments as arrays (numbers and lists only: None, strings, dicts and booleans travel
    as they are, for the implementation to reject); every other argument checked by _check_plain."""
    out = {}
    for key in case["args"]:
        if key not in fn.args:
            _check_plain(f"{where}: argument {key!r}", case["args"][key])
    for key in fn.args:
        v = case["args"][key]
        if not isinstance(v, (list, int, float)) or isinstance(v, bool) or \
                not (key in FLOAT_ARRAYS or key in INT_ARRAYS or (key == "t" and isinstance(v, list))):
            if key != "field":
                _check_plain(f"{where}: argument {key!r}", v)
            continue
        if key in FLOAT_ARRAYS or (key == "t" and isinstance(v, list)):
            out[key] = as_array(f"{where}: argument {key!r}", v, np.float64)
        elif key in INT_ARRAYS:
            out[key] = as_array(f"{where}: argument {key!r}", v, np.int64 if all_ints(v) else np.float64)
    return out


def _int_arg(where: str, case: dict, key: str) -> int:
    v = case["args"][key]
    if isinstance(v, bool) or not isinstance(v, int) or v < 0:
        raise VectorError(f"{where}: a case with expected outputs needs a non-negative integer {key!r}, got {v!r}")
    return v


def _shape_of(where: str, arrays: dict, key: str) -> tuple:
    if key not in arrays:
        raise VectorError(f"{where}: a case with expected outputs needs an array {key!r}")
    return arrays[key].shape


def expected_shapes(where: str, case: dict, arrays: dict) -> dict:
    """{output: shape} that the case's arguments give ([CF-7]); the trace is checked separately."""
    f = case["function"]
    if f in ("prefix_weights", "weights", "hard_weights", "method_weights", "guidance_weights"):
        return {"weights": (_int_arg(where, case, "H"),)}
    if f == "delay_probs":
        n = _int_arg(where, case, "d_max") - _int_arg(where, case, "d_min") + 1
        return {"probs": (n,)}
    if f == "corrupt":
        a = _shape_of(where, arrays, "actions")
        return {"x": a, "times": a[:1]}
    if f == "token_times":
        return {"times": _shape_of(where, arrays, "weights")}
    if f in ("velocity", "velocity_vjp"):
        return {"velocity" if f == "velocity" else "vjp": _shape_of(where, arrays, "x")}
    if f in TRACE_KEYS:
        return {"chunk": _shape_of(where, arrays, "noise")}
    if f == "shift_prior":
        return {"prior": _shape_of(where, arrays, "prev")}
    if f == "execute_chunks":
        c = _shape_of(where, arrays, "chunks")
        n = c[0] * _int_arg(where, case, "s") if len(c) == 3 else -1
        return {"actions": (n, c[-1]), "chunk_index": (n,), "token_index": (n,)}
    if f == "bootstrap_interval":
        return {"interval": (2,)}
    return {k: () for k in INTERFACE[f].outputs}  # scalars: e, d, loss, lam, value


def _check_expected(where: str, case: dict, fn, arrays: dict) -> None:
    exp = case["expected"]
    want = expected_shapes(where, case, arrays)
    for k in fn.outputs:
        if k == "trace":
            _check_trace(where, case, arrays)
            continue
        a = as_array(f"{where}: expected {k!r}", exp[k], np.float64)
        if a.shape != want[k]:
            raise VectorError(f"{where}: expected {k!r} has shape {list(a.shape)}, its arguments give "
                              f"{list(want[k])} ([CF-24])")
        if k in fn.int_out and not all_ints(exp[k]):
            raise VectorError(f"{where}: expected {k!r} is an integer output written as a float ([CF-23])")


def _check_trace(where: str, case: dict, arrays: dict) -> None:
    tr, f = case["expected"]["trace"], case["function"]
    T = _int_arg(where, case, "T")
    if not isinstance(tr, list) or len(tr) != T or not all(isinstance(st, dict) for st in tr):
        raise VectorError(f"{where}: expected 'trace' must be a list of {T} per-step objects ([CF-11])")
    state = _shape_of(where, arrays, "noise")
    shapes = {k: state for k in TRACE_KEYS[f]}
    shapes.update(time=state[:1], guidance_weight=())
    for i, st in enumerate(tr):
        if sorted(st) != sorted(TRACE_KEYS[f]):
            raise VectorError(f"{where}: expected trace step {i} must have exactly the keys {list(TRACE_KEYS[f])} "
                              "([CF-11])")
        for k, v in st.items():
            if as_array(f"{where}: expected trace step {i} {k!r}", v, np.float64).shape != shapes[k]:
                raise VectorError(f"{where}: expected trace step {i} {k!r} has shape {list(np.shape(v))}, "
                                  f"expected {list(shapes[k])} ([CF-24])")
