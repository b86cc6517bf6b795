"""Run the conformance vectors against an adapter and report per requirement id ([CF-13]..[CF-18]).

    softrtc conformance run --impl NAME_OR_MODULE:ATTR [--report FILE] [--junit FILE] [--vectors DIR]

Every case is one call of one interface function. A case passes when every
expected number agrees within its tolerance: ``|got - want| <= abs + rel * |want|``
elementwise, integers exactly ([CF-5]). Outputs of a "noise_at_1" adapter are
mapped onto the spec (t = 1 - t', v = -u) before comparing ([CF-10], [V-1]).
Vector files are parsed with the number convention of [CF-23] (a fraction or
exponent makes a float) and a malformed case stops the run with status 2 ([CF-24]).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import re
import sys
import time
import traceback
import xml.etree.ElementTree as ET
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from .._cli_util import command_error, comma_list, input_dir, output_file
from .._files import write_atomic
from . import FORMAT_VERSION, vectors_dir
from .adapter import (ALTERNATES, GUIDANCE_KEYS, INTERFACE, TRACE_TIME_KEYS, TRACE_VEL_KEYS, AdapterError, Fn,
                      _describe, _fatal, forms, load_adapter, supported_functions)


# Arguments that are arrays in the interface ([CF-7]); everything else is passed as parsed from JSON ([CF-23]).
FLOAT_ARRAYS = {"actions", "noise", "weights", "pred", "preds", "obs", "x", "cotangent", "prior", "prev", "chunks",
                "probs", "values"}
INT_ARRAYS = {"indices", "chunk_index", "delays"}
MAX_LISTED_FAILURES = 25


@dataclass
class CaseResult:
    """Outcome of one case: status is pass, fail or unsupported."""

    id: str
    file: str
    function: str
    requirements: list
    status: str
    worst: float = 0.0  # largest |got - want| / tolerance over the case's numbers; inf when none could be compared
    message: str = ""
    seconds: float = 0.0


@dataclass
class RunResult:
    impl: str
    adapter_name: str
    time_convention: str
    format_version: str
    spec_versions: list
    cases: list = field(default_factory=list)
    seconds: float = 0.0

    @property
    def counts(self) -> dict:
        out = {"pass": 0, "fail": 0, "unsupported": 0}
        for c in self.cases:
            out[c.status] += 1
        return out

    @property
    def ok(self) -> bool:
        """[CF-16] success: no failure, and at least one supported case."""
        n = self.counts
        return n["fail"] == 0 and n["pass"] > 0

    def by_requirement(self) -> dict:
        reqs: dict[str, dict] = {}
        for c in self.cases:
            for r in c.requirements:
                e = reqs.setdefault(r, {"pass": 0, "fail": 0, "unsupported": 0, "worst": 0.0})
                e[c.status] += 1
                if c.status != "unsupported":
                    e["worst"] = max(e["worst"], c.worst)
        for e in reqs.values():
            e["status"] = "FAIL" if e["fail"] else ("PASS" if e["pass"] else "UNSUPPORTED")
        return dict(sorted(reqs.items(), key=lambda kv: _req_key(kv[0])))


def _req_key(rid: str):
    m = re.match(r"([A-Z]+)-(\d+)$", rid)
    return (m.group(1), int(m.group(2))) if m else (rid, 0)


TRACE_NOT_PROVIDED = "trace not provided; chunk checked only"
UNSUPPORTED_CASE = "unsupported case"


class VectorError(Exception):
    """The vector directory is missing or holds files this runner cannot read."""


def _reject_constant(name: str):
    raise ValueError(f"{name} is not a JSON number (vector files hold finite numbers only, [CF-3])")


def _path(name: str, value) -> Path:
    """A str or os.PathLike argument as a Path ([N-7])."""
    if not isinstance(value, (str, os.PathLike)):
        raise ValueError(f"{name} must be a path (str or os.PathLike), got {type(value).__name__}")
    return Path(value)


def parse_json(text: str):
    """JSON text to Python under the number convention of [CF-23]: a number written with a fraction or an
    exponent is a float, one written without is an int; NaN and Infinity are refused."""
    if not isinstance(text, (str, bytes, bytearray)):
        raise ValueError(f"text must be JSON text (str or bytes), got {type(text).__name__}")
    return json.loads(text, parse_float=float, parse_int=int, parse_constant=_reject_constant)


def load_vectors(directory=None) -> list[dict]:
    """Read every vector file of ``directory`` (index.json excluded), checking format_version ([CF-2])
    and the structure of every case ([CF-24]); raise VectorError naming the first problem."""
    d = _path("directory", directory) if directory is not None else vectors_dir()
    if not d.is_dir():
        raise VectorError(f"vectors directory {d} {'is not a directory' if d.exists() else 'does not exist'}")
    files = sorted(p for p in d.glob("*.json") if p.name != "index.json")
    if not files:
        raise VectorError(f"vectors directory {d} holds no *.json vector files")
    index = _read_index(d, files)
    out, seen = [], {}
    for p in files:
        try:
            raw = p.read_bytes()
        except OSError as exc:
            raise VectorError(f"cannot read vector file {p}: {exc}") from None
        if index is not None:
            _check_digest(p.name, raw, index[p.name])
        try:
            data = parse_json(raw.decode("utf-8"))
        except ValueError as exc:
            raise VectorError(f"cannot read vector file {p}: {exc}") from None
        if not isinstance(data, dict):
            raise VectorError(f"{p.name}: expected a JSON object with 'format_version' and 'cases', "
                              f"got a {type(data).__name__}")
        _check_format(p.name, data.get("format_version"))
        if not isinstance(data.get("cases"), list):
            raise VectorError(f"{p.name}: missing 'cases' list")
        fields = data.get("fields", {})
        if not isinstance(fields, dict):
            raise VectorError(f"{p.name}: 'fields' must be a JSON object, got {type(fields).__name__}")
        for i, case in enumerate(data["cases"]):
            _check_case_shape(p.name, i, case, fields)
            if case["id"] in seen:
                raise VectorError(f"{p.name}: case {i}: id {case['id']!r} already used in {seen[case['id']]} ([CF-6])")
            seen[case["id"]] = p.name
        if index is not None and len(data["cases"]) != index[p.name].get("cases"):
            raise VectorError(f"{p.name}: {len(data['cases'])} cases, index.json lists {index[p.name].get('cases')} "
                              "([CF-25])")
        data["_file"] = p.name
        out.append(data)
    return out


def _check_format(where: str, version) -> None:
    """A format_version this runner reads: the same major version as FORMAT_VERSION ([CF-2])."""
    major = FORMAT_VERSION.split(".")[0]
    if str(version or "").split(".")[0] != major:
        raise VectorError(f"{where}: format_version {version!r} is not readable by this runner (needs {major}.x)")


def _read_index(d: Path, files: list) -> dict | None:
    """``d/index.json``'s ``files`` entry, {name: {sha256, cases, ...}}, once it lists exactly ``files`` in a
    readable format ([CF-25]); None when the directory has no index (a hand-made set of cases)."""
    path = d / "index.json"
    if not path.exists():
        return None
    try:
        index = parse_json(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise VectorError(f"cannot read {path}: {exc}") from None
    listed = index.get("files") if isinstance(index, dict) else None
    if not isinstance(listed, dict) or not all(isinstance(v, dict) for v in listed.values()):
        raise VectorError(f"{path}: expected an object with 'files': {{name: {{sha256, cases, ...}}}} ([CF-2])")
    _check_format(str(path), index.get("format_version"))
    names = {p.name for p in files}
    missing, unlisted = sorted(set(listed) - names), sorted(names - set(listed))
    if missing:
        raise VectorError(f"{missing[0]}: listed in index.json but missing from {d} ([CF-25])")
    if unlisted:
        raise VectorError(f"{unlisted[0]}: not listed in index.json; the vectors in {d} are not one generated set "
                          "([CF-25])")
    return listed


def _check_digest(name: str, raw: bytes, entry: dict) -> None:
    """The file's SHA-256 must be the one index.json lists ([CF-25])."""
    digest = hashlib.sha256(raw).hexdigest()
    if digest != entry.get("sha256"):
        raise VectorError(f"{name}: SHA-256 {digest[:12]}... differs from index.json's {str(entry.get('sha256'))[:12]}"
                          "...: the file was changed after generation (regenerate with `softrtc conformance "
                          "generate`, or run a hand-made set from a folder without index.json) ([CF-25])")


def _check_case_shape(file: str, i: int, case, fields: dict) -> None:
    """Raise VectorError unless ``case`` is well formed ([CF-6], [CF-24], spec/vectors.schema.json): its
    fields and their types, a known interface function, every argument of that function, a named field
    present in the file, a finite non-negative tolerance, and either every output or ``error``."""
    where = f"{file}: case {i}"
    if not isinstance(case, dict):
        raise VectorError(f"{where} must be a JSON object, got {type(case).__name__}")
    for key, kind in (("id", str), ("function", str), ("requirements", list), ("args", dict), ("tolerance", dict),
                      ("expected", dict)):
        if not isinstance(case.get(key), kind):
            raise VectorError(f"{where} ({case.get('id', '?')!r}): '{key}' must be a {kind.__name__}, "
                              f"got {type(case.get(key)).__name__}")
    where = f"{where} ({case['id']!r})"
    if not case["requirements"] or not all(isinstance(r, str) for r in case["requirements"]):
        raise VectorError(f"{where}: 'requirements' must be a non-empty list of strings")
    fn = INTERFACE.get(case["function"])
    if fn is None:
        raise VectorError(f"{where}: 'function' {case['function']!r} is not an interface function ([CF-7])")
    missing = [a for a in fn.args if a not in case["args"]]
    if missing:
        raise VectorError(f"{where}: 'args' lacks {missing} of {case['function']}({', '.join(fn.args)})")
    if "field" in fn.args:
        name = case["args"]["field"]
        if not isinstance(name, str) or not isinstance(fields.get(name), dict) \
                or not isinstance(fields[name].get("params"), dict):
            raise VectorError(f"{where}: 'field' {name!r} names no field with 'params' in the file's 'fields'")
    tol = case["tolerance"]
    for key in ("abs", "rel"):
        v = tol.get(key)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
            raise VectorError(f"{where}: tolerance '{key}' must be a finite number >= 0, got {v!r}")
    exp = case["expected"]
    if "error" in exp:
        if exp != {"error": "ValueError"}:
            raise VectorError(f"{where}: an error case's 'expected' must be exactly {{'error': 'ValueError'}}")
        return
    missing = [k for k in fn.outputs if k not in exp]
    if missing:
        raise VectorError(f"{where}: 'expected' lacks outputs {missing} of {case['function']}")
    _check_guidance(where, case)
    if "trace" in fn.outputs and not (isinstance(exp["trace"], list)
                                      and all(isinstance(st, dict) for st in exp["trace"])):
        raise VectorError(f"{where}: expected 'trace' must be a list of per-step objects")


def _check_guidance(where: str, case: dict) -> None:
    """A guided case's optional 'guidance' argument: the parameters that define its weights ([CF-27])."""
    if case["function"] not in ALTERNATES or ALTERNATES[case["function"]].needs not in case["args"]:
        return
    g = case["args"][ALTERNATES[case["function"]].needs]
    if not isinstance(g, dict) or sorted(g) != sorted(GUIDANCE_KEYS):
        raise VectorError(f"{where}: 'guidance' must be an object with exactly the keys {list(GUIDANCE_KEYS)}")
    ints = all(isinstance(g[k], int) and not isinstance(g[k], bool) for k in ("H", "s", "d", "end"))
    if not ints or not all(isinstance(g[k], str) for k in ("variant", "schedule")) \
            or isinstance(g["max_guidance"], bool) or not isinstance(g["max_guidance"], (int, float)):
        raise VectorError(f"{where}: 'guidance' holds integers H, s, d, end, strings variant, schedule and a "
                          "number max_guidance")


# ---------------------------------------------------------------- calling

def _field_params(data: dict, name) -> dict:
    fields = data.get("fields", {})
    if name not in fields:
        raise VectorError(f"{data['_file']}: case names unknown field {name!r}")
    return {k: _array(f"field {name!r} {k}", v, np.float64) for k, v in fields[name]["params"].items()}


def _all_ints(value) -> bool:
    """Whether every number of a (nested) JSON list was written as an integer ([CF-23])."""
    if isinstance(value, list):
        return all(_all_ints(v) for v in value)
    return isinstance(value, int) and not isinstance(value, bool)


def _array(what: str, value, dtype) -> np.ndarray:
    try:
        return np.asarray(value, dtype=dtype)
    except (TypeError, ValueError) as exc:
        raise VectorError(f"{what} is not a rectangular array of numbers ({_line(exc)})") from None


def _prepare_arg(key: str, value, data: dict):
    """One argument as the adapter receives it ([CF-7], [CF-23]): float arrays as float64 arrays,
    integer sequences as int64 arrays (float64 when an element is written as a float, so the
    implementation sees the non-integer it must reject), the rest as parsed."""
    if key == "field":
        return _field_params(data, value)
    if value is None or isinstance(value, (str, dict, bool)):
        return value
    if key in FLOAT_ARRAYS or (key == "t" and isinstance(value, list)):
        return _array(f"argument {key!r}", value, np.float64)
    if key in INT_ARRAYS:
        return _array(f"argument {key!r}", value, np.int64 if _all_ints(value) else np.float64)
    return value


def build_args(fn: Fn, case: dict, data: dict, flipped: bool) -> list:
    """Positional arguments of the call, mapped to the adapter's time convention ([CF-10])."""
    args = []
    for key in fn.args:
        if key not in case["args"]:
            raise VectorError(f"{data['_file']}: case {case['id']!r} lacks argument {key!r} ([CF-24])")
        try:
            v = _prepare_arg(key, case["args"][key], data)
        except VectorError as exc:
            raise VectorError(f"{data['_file']}: case {case['id']!r}: {exc} ([CF-24])") from None
        if flipped and key in fn.time_args:
            v = 1.0 - np.asarray(v, dtype=np.float64) if isinstance(v, np.ndarray) else 1.0 - float(v)
        if flipped and key in fn.vel_args:
            v = -v
        args.append(v)
    return args


class CaseUnsupported(Exception):
    """The implementation declined the case (NotImplementedError, or "unsupported" over the protocol) ([CF-26])."""


class CaseFailure(Exception):
    """A case failed; the message is one line. ``ratio`` is the worst |got - want| / tolerance when a
    number was out of tolerance, inf when none could be compared (exact-match mismatch, wrong shape,
    type or kind of result, exception) ([CF-5], [CF-14])."""

    def __init__(self, message: str, ratio: float = math.inf):
        super().__init__(message)
        self.ratio = float(ratio)


def _to_np(adapter, value, what: str) -> np.ndarray:
    conv = getattr(adapter, "to_numpy", None) or np.asarray
    try:
        arr = np.asarray(conv(value))
    except BaseException as exc:
        if _fatal(exc):
            raise
        raise CaseFailure(f"{what}: cannot convert {type(value).__name__} to an array "
                          f"({_describe(exc)})") from None
    if arr.dtype == object:
        raise CaseFailure(f"{what}: not a numeric array (got {type(value).__name__})")
    return arr


def _normalize(fn: Fn, fname: str, out, adapter, flipped: bool) -> dict:
    """Adapter return value -> {output name: array} in the spec's convention."""
    if fn.kind == "value":
        got = {fn.outputs[0]: out}
    elif fn.kind == "tuple" or fn.kind == "sample":
        if not isinstance(out, (tuple, list)) or len(out) != len(fn.outputs):
            raise CaseFailure(f"{fname} must return a tuple ({', '.join(fn.outputs)}), got {type(out).__name__}"
                              + (f" of length {len(out)}" if isinstance(out, (tuple, list)) else ""))
        got = dict(zip(fn.outputs, out))
    else:
        if not hasattr(out, "keys"):
            raise CaseFailure(f"{fname} must return a mapping with keys {list(fn.outputs)}, "
                              f"got {type(out).__name__}")
        missing = [k for k in fn.outputs if k not in out]
        if missing:
            raise CaseFailure(f"{fname} result lacks keys {missing}")
        got = {k: out[k] for k in fn.outputs}
    res = {}
    for k, v in got.items():
        if k == "trace":
            res[k] = None if v is None else _normalize_trace(v, fname, adapter, flipped)
            continue
        a = _to_np(adapter, v, f"{fname} output {k!r}")
        if flipped and k in fn.time_out:
            a = 1.0 - a
        if flipped and k in fn.vel_out:
            a = -a
        res[k] = a
    return res


def _normalize_trace(trace, fname, adapter, flipped) -> list:
    if not isinstance(trace, (list, tuple)):
        raise CaseFailure(f"{fname} trace must be a list of per-step dicts or None, got {type(trace).__name__}")
    steps = []
    for i, step in enumerate(trace):
        if not hasattr(step, "keys"):
            raise CaseFailure(f"{fname} trace step {i} must be a dict, got {type(step).__name__}")
        st = {}
        for k in step.keys():
            a = _to_np(adapter, step[k], f"{fname} trace step {i} key {k!r}")
            if flipped and k in TRACE_TIME_KEYS:
                a = 1.0 - a
            if flipped and k in TRACE_VEL_KEYS:
                a = -a
            st[k] = a
        steps.append(st)
    return steps


def compare(what: str, got: np.ndarray, want, tol: dict, integer: bool = False) -> float:
    """Worst |got - want| / (abs + rel |want|) ([CF-5]); raise CaseFailure when above 1."""
    if not isinstance(tol, dict) or not {"abs", "rel"} <= set(tol):
        raise ValueError(f"tol must be a dict with keys 'abs' and 'rel' ([CF-5]), got {tol!r}")
    w = np.asarray(want, dtype=np.float64)
    g = np.asarray(got)
    if g.dtype.kind not in "biuf":
        raise CaseFailure(f"{what}: expected numbers, got dtype {g.dtype}")
    if g.dtype.kind == "b" and not integer:
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
    err = np.abs(g - w)
    bound = tol["abs"] + tol["rel"] * np.abs(w)
    if integer:
        bound = np.zeros_like(err)
    ratio = np.where(err == 0, 0.0, np.divide(err, bound, out=np.full_like(err, np.inf), where=bound > 0))
    worst = float(ratio.max()) if ratio.size else 0.0
    if worst > 1.0:
        i = np.unravel_index(int(np.argmax(ratio)), ratio.shape) if ratio.ndim else ()
        idx = f"[{', '.join(map(str, i))}]" if i else ""
        times = "exact match required" if integer or not math.isfinite(worst) else f"{worst:.3g} x tolerance"
        raise CaseFailure(f"{what}{idx}: got {_number(g[i], integer)!r}, expected {_number(w[i], integer)!r} "
                          f"({times})", worst)
    return worst


def _number(x, integer: bool):
    """A plain Python number for messages: an int for integer outputs, else a float (never np.float64(...))."""
    v = float(x)
    return int(v) if integer and v.is_integer() else v


def check_outputs(fn: Fn, fname: str, got: dict, expected: dict, tol: dict) -> tuple[float, str]:
    worst, note = 0.0, ""
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
                    worst = max(worst, compare(f"trace step {i} {k2}", st[k2], ws[k2], tol))
            continue
        worst = max(worst, compare(k, got[k], expected[k], tol, k in fn.int_out))
    return worst, note


def _signature_problem(func, fname: str, fn: Fn) -> str | None:
    import inspect
    try:
        sig = inspect.signature(func)
    except (TypeError, ValueError):
        return None  # builtins without a signature are tried as they are
    try:
        sig.bind(*fn.args)
    except TypeError:
        return (f"adapter.{fname}{sig} cannot be called as {fname}({', '.join(fn.args)}); "
                f"see spec/40-conformance.md [CF-7]")
    return None


def _line(exc: BaseException) -> str:
    text = str(exc).strip().splitlines()
    return (text[0] if text else "")[:300]


def _where(exc: BaseException) -> str:
    """file:line of the innermost frame outside this runner, to point at the adapter's code."""
    frames = [f for f in traceback.extract_tb(exc.__traceback__) if not f.filename.endswith("runner.py")]
    if not frames:
        return ""
    f = frames[-1]
    return f" ({Path(f.filename).name}:{f.lineno})"


def run_case(adapter, fname: str, fn: Fn, case: dict, data: dict, flipped: bool,
             sig_problems: dict | None = None) -> tuple[float, str]:
    """Run one case through the adapter's forms of ``fname`` in turn ([CF-27]); a form raising
    NotImplementedError passes the case on to the next, and a case no form takes is unsupported ([CF-26])."""
    declined = []
    for attr, form_fn, needs in forms(adapter, fname) or [(fname, fn, None)]:
        if needs is not None and needs not in case["args"]:
            declined.append(f"{attr} needs the case's '{needs}', which it does not carry")
            continue
        if sig_problems and sig_problems.get(attr):
            raise CaseFailure(sig_problems[attr])
        try:
            return _run_form(adapter, attr, form_fn, fn, case, data, flipped)
        except CaseUnsupported as exc:
            declined.append(str(exc))
    raise CaseUnsupported("; ".join(declined))


def _run_form(adapter, attr: str, form_fn: Fn, fn: Fn, case: dict, data: dict, flipped: bool) -> tuple[float, str]:
    func = getattr(adapter, attr)
    args = build_args(form_fn, case, data, flipped)
    expected = case["expected"]
    try:
        out = func(*args)
    except NotImplementedError as exc:
        raise CaseUnsupported(f"{attr} raised {_describe(exc)}") from None
    except ValueError as exc:
        if "error" in expected:
            return 0.0, ""
        raise CaseFailure(f"{attr} raised {_describe(exc)}{_where(exc)}") from None
    except BaseException as exc:  # SystemExit and the like fail the case too ([CF-18])
        if _fatal(exc):
            raise
        if "error" in expected:
            raise CaseFailure(f"invalid input must raise ValueError, {attr} raised {_describe(exc)}"
                              f"{_where(exc)}") from None
        raise CaseFailure(f"{attr} raised {_describe(exc)}{_where(exc)}") from None
    if "error" in expected:
        raise CaseFailure(f"{attr} accepted invalid input (expected ValueError, [N-7])")
    got = _normalize(fn, attr, out, adapter, flipped)
    return check_outputs(fn, attr, got, expected, case["tolerance"])


def run(impl, vectors_dir=None, only=None, files=None) -> RunResult:
    """Run every case against ``impl`` (an adapter spec string or an adapter object) ([CF-13]).

    ``only``: optional collection of function names to restrict the run;
    ``files``: vectors already read (and checked, [CF-24]) by :func:`load_vectors`.
    Raises AdapterError / VectorError with a one-line message when nothing can run; a case raising
    anything but KeyboardInterrupt, SystemExit included, is a failed case ([CF-18]).
    """
    t0 = time.perf_counter()
    if only is not None:
        if isinstance(only, (str, bytes)) or not hasattr(only, "__iter__"):
            raise ValueError(f"only must be None or a collection of interface function names, got {only!r}")
        only = set(only)
        unknown = sorted(str(f) for f in only if f not in INTERFACE)
        if unknown:
            raise ValueError(f"only names unknown interface functions {unknown}; known: {sorted(INTERFACE)}")
    if isinstance(impl, str):
        adapter, impl_name = load_adapter(impl), impl
    else:
        from .adapter import check_adapter
        check_adapter(impl)
        adapter, impl_name = impl, getattr(impl, "name", "?")
    files = load_vectors(vectors_dir) if files is None else files
    flipped = getattr(adapter, "time_convention", "data_at_1") == "noise_at_1"
    supported = set(supported_functions(adapter))
    sig_problems = {attr: _signature_problem(getattr(adapter, attr), attr, form_fn)
                    for f in supported for attr, form_fn, _ in forms(adapter, f)}
    result = RunResult(impl_name, adapter.name, "noise_at_1" if flipped else "data_at_1", FORMAT_VERSION,
                       sorted({str(d.get("spec_version")) for d in files}))
    for data in files:
        for case in data["cases"]:
            fname = case.get("function")
            if only is not None and fname not in only:
                continue
            cr = CaseResult(case.get("id", "?"), data["_file"], fname, list(case.get("requirements", [])), "pass")
            if fname not in INTERFACE:  # load_vectors refuses such files; a hand-built list may hold one
                raise VectorError(f"{data['_file']}: case {cr.id!r} names unknown interface function {fname!r}")
            if fname not in supported:
                cr.status, cr.message = "unsupported", f"adapter has no {fname}"
            else:
                c0 = time.perf_counter()
                try:
                    cr.worst, cr.message = run_case(adapter, fname, INTERFACE[fname], case, data, flipped,
                                                    sig_problems)
                except CaseUnsupported as exc:
                    cr.status, cr.message = "unsupported", f"{UNSUPPORTED_CASE}: {exc}"
                except CaseFailure as exc:
                    cr.status, cr.message, cr.worst = "fail", str(exc), exc.ratio
                except VectorError:
                    raise  # a malformed case stops the run: status 2 ([CF-24])
                except BaseException as exc:  # a bug while mapping the adapter's output still gives one line
                    if _fatal(exc):
                        raise
                    cr.status, cr.message, cr.worst = "fail", f"{_describe(exc)}{_where(exc)}", math.inf
                cr.seconds = time.perf_counter() - c0
            result.cases.append(cr)
    result.seconds = time.perf_counter() - t0
    return result


# ---------------------------------------------------------------- reporting

def format_summary(res: RunResult, max_failures: int = MAX_LISTED_FAILURES) -> str:
    """Human-readable summary: one line per requirement id, unsupported functions, failures ([CF-14])."""
    lines = [f"softrtc conformance: impl {res.impl} (adapter '{res.adapter_name}', {res.time_convention}), "
             f"vectors format {res.format_version}, spec {', '.join(res.spec_versions)}"]
    for rid, e in res.by_requirement().items():
        n = e["pass"] + e["fail"]
        extra = f", {e['unsupported']} unsupported" if e["unsupported"] else ""
        worst = f"worst {e['worst']:.3g} x tol" if n else "worst -"
        lines.append(f"  {e['status']:<11s} {rid:<6s} {worst:<20s} {n:>5d} cases{extra}"
                     + (f" ({e['fail']} failed)" if e["fail"] else ""))
    uns: dict[str, int] = {}
    declined: dict[str, int] = {}
    for c in res.cases:
        if c.status == "unsupported" and c.message.startswith(UNSUPPORTED_CASE):
            for r in c.requirements:
                declined[r] = declined.get(r, 0) + 1
        elif c.status == "unsupported":
            uns[c.function] = uns.get(c.function, 0) + 1
    if uns:
        lines.append("unsupported (adapter lacks the function): "
                     + ", ".join(f"{f} ({n} cases)" for f, n in sorted(uns.items())))
    if declined:  # [CF-26]
        lines.append("unsupported cases (the implementation raised NotImplementedError, or no form of the function "
                     "takes the case), per requirement: "
                     + ", ".join(f"{r} ({n})" for r, n in sorted(declined.items(), key=lambda kv: _req_key(kv[0]))))
    untraced = sum(1 for c in res.cases if c.status == "pass" and c.message == TRACE_NOT_PROVIDED)
    if untraced:
        lines.append(f"{untraced} sampler cases passed without a trace: their chunks are checked, their per-step "
                     "values (blended state, denoised estimate, error, pull-back) are not ([CF-11])")
    fails = [c for c in res.cases if c.status == "fail"]
    if fails:
        lines.append(f"failures ({len(fails)}; first {min(len(fails), max_failures)} shown):")
        for c in fails[:max_failures]:
            lines.append(f"  FAIL {c.id}: {c.message}")
    n = res.counts
    lines.append(f"{'PASS' if res.ok else 'FAIL'}: {len(res.cases)} cases: {n['pass']} passed, {n['fail']} failed, "
                 f"{n['unsupported']} unsupported; {res.seconds:.1f} s")
    if n["pass"] == 0 and n["fail"] == 0:
        lines.append("no supported case ran: the adapter provides none of the interface functions")
    return "\n".join(lines)


def report_dict(res: RunResult) -> dict:
    """The --report JSON document ([CF-15])."""
    return {"impl": res.impl, "adapter": res.adapter_name, "time_convention": res.time_convention,
            "format_version": res.format_version, "spec_versions": res.spec_versions, "ok": res.ok,
            "seconds": round(res.seconds, 3), "counts": res.counts,
            "requirements": {k: {kk: (vv if not isinstance(vv, float) or math.isfinite(vv) else "inf")
                                 for kk, vv in v.items()} for k, v in res.by_requirement().items()},
            "cases": [{k: (v if not isinstance(v, float) or math.isfinite(v) else "inf")
                       for k, v in asdict(c).items()} for c in res.cases]}


def write_junit(res: RunResult, path) -> None:
    """JUnit XML: one testsuite per vector file, one testcase per case ([CF-15])."""
    root = ET.Element("testsuites", name=f"softrtc-conformance-{res.adapter_name}",
                      tests=str(len(res.cases)), failures=str(res.counts["fail"]),
                      skipped=str(res.counts["unsupported"]), time=f"{res.seconds:.3f}")
    suites: dict[str, ET.Element] = {}
    for c in res.cases:
        s = suites.get(c.file)
        if s is None:
            s = suites[c.file] = ET.SubElement(root, "testsuite", name=f"conformance.{Path(c.file).stem}")
            s.attrib.update(tests="0", failures="0", skipped="0")
        s.set("tests", str(int(s.get("tests")) + 1))
        tc = ET.SubElement(s, "testcase", classname=f"conformance.{Path(c.file).stem}.{c.function}", name=c.id,
                           time=f"{c.seconds:.6f}")
        ET.SubElement(tc, "properties")
        props = tc.find("properties")
        ET.SubElement(props, "property", name="requirements", value=" ".join(c.requirements))
        if c.status == "fail":
            s.set("failures", str(int(s.get("failures")) + 1))
            ET.SubElement(tc, "failure", message=c.message, type="ConformanceFailure")
        elif c.status == "unsupported":
            s.set("skipped", str(int(s.get("skipped")) + 1))
            ET.SubElement(tc, "skipped", message=c.message)
    write_atomic(path, lambda f: ET.ElementTree(root).write(f, encoding="utf-8", xml_declaration=True), binary=True)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--impl", required=True,
                        help="built-in adapter (reference, jax, torch, torch-flipped), module[:ATTR] "
                             "or path/file.py[:ATTR]")
    parser.add_argument("--vectors", type=input_dir(), default=None,
                        help="vector directory (default: the vectors shipped with softrtc)")
    parser.add_argument("--report", type=output_file(), default=None, help="write a JSON report to this file")
    parser.add_argument("--junit", type=output_file(), default=None, help="write JUnit XML to this file")
    parser.add_argument("--only", type=comma_list("value", _interface_function), default=None,
                        help="comma-separated interface functions to run (default: all): "
                             + ", ".join(sorted(INTERFACE)))


def _interface_function(name: str) -> str:
    if name not in INTERFACE:
        raise argparse.ArgumentTypeError(f"{name!r} is not an interface function; choose from "
                                         f"{', '.join(sorted(INTERFACE))}")
    return name


def run_from_args(args) -> int:
    """Exit status: 0 all supported cases pass, 1 some failed or none ran, 2 nothing could run ([CF-16])."""
    only = None if args.only is None else set(args.only)
    try:
        res = run(args.impl, args.vectors, only)
    except (AdapterError, VectorError) as exc:
        return command_error(getattr(args, "_prog", "softrtc conformance run"), exc)
    print(format_summary(res))
    try:
        for out in (args.report, args.junit):
            if out:
                Path(out).parent.mkdir(parents=True, exist_ok=True)
        if args.report:
            text = json.dumps(report_dict(res), indent=1, sort_keys=True) + "\n"
            write_atomic(args.report, lambda f: f.write(text))
        if args.junit:
            write_junit(res, args.junit)
    except OSError as exc:
        return command_error(getattr(args, "_prog", "softrtc conformance run"), f"cannot write report: {exc}")
    return 0 if res.ok else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.runner",
                                     description="Run the softrtc conformance vectors against an implementation.")
    add_arguments(parser)
    parser.set_defaults(_prog=parser.prog)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
