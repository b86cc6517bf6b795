"""Pinned behaviours of the conformance runner (spec/40-conformance.md).

Each test fixes one rule by which the runner decides whether an implementation
conforms, with an adapter or value that is wrong in exactly that respect: the
tolerance rule |got - want| <= abs + rel |want| (both signs of the error, the
boundary, abs and rel in their places), exact comparison of integer outputs,
refusal of wrong shapes, of booleans and of any non-finite value, rejection
cases that need a ValueError, every key of every step of a sampler trace, the
exit status, and the counts written to the JSON and JUnit reports.
"""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapters.reference import ReferenceAdapter

REF = ReferenceAdapter()


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


class _Only:
    name = "pinned"

    def __init__(self, **fns):
        for k, v in fns.items():
            setattr(self, k, v)


def _split(res, function):
    """(value cases, reject cases) of ``function`` in a run."""
    cases = [c for c in res.cases if c.function == function]
    return [c for c in cases if ".reject." not in c.id], [c for c in cases if ".reject." in c.id]


# ---------------------------------------------------------------- the tolerance rule

def test_tolerance_abs_and_rel_in_their_places(tmp_path):
    """[CF-5], [CF-6] A number passes when |got - want| <= abs + rel |want|: abs is the absolute part,
    rel scales |want| (not |got|), and each case's own tolerance is used, also when abs != rel."""
    only_abs, only_rel = {"abs": 1.0, "rel": 0.0}, {"abs": 0.0, "rel": 0.5}
    assert runner.compare("v", 0.9, 0.001, only_abs) == pytest.approx(0.899)
    with pytest.raises(runner.CaseFailure):
        runner.compare("v", 14.0, 10.0, {"abs": 0.5, "rel": 0.0})
    with pytest.raises(runner.CaseFailure):
        runner.compare("v", 0.4, 0.0, only_rel)
    assert runner.compare("v", 12.0, 10.0, only_rel) == pytest.approx(0.4)
    with pytest.raises(runner.CaseFailure) as info:  # 0.6 |want| = 0.6 < 1; 0.6 |got| would be 1.2
        runner.compare("v", 2.0, 1.0, {"abs": 0.0, "rel": 0.6})
    assert info.value.ratio == pytest.approx(1.0 / 0.6)

    # The same rule end to end, on a vector file whose cases state abs != rel.
    # want 0.5, got 1.4: within abs = 1, outside rel = 1 (1 * 0.5).
    def case(cid, tol):
        return {"id": cid, "function": "standard_error", "requirements": ["M-6"], "tolerance": tol,
                "args": {"values": [1.0, 3.0]}, "expected": {"value": 0.5}}
    cases = [case("M.standard_error.abs", only_abs), case("M.standard_error.rel", {"abs": 0.0, "rel": 1.0})]
    (tmp_path / "m.json").write_text(json.dumps({"format_version": "1.0", "spec_version": "0.1.0",
                                                 "cases": cases}))
    res = runner.run(_Only(standard_error=lambda values: 1.4), vectors_dir=tmp_path)
    assert {c.id: c.status for c in res.cases} == {"M.standard_error.abs": "pass", "M.standard_error.rel": "fail"}


def test_error_exactly_at_tolerance_passes():
    """[CF-5] The bound is inclusive: an error equal to abs + rel |want| passes with ratio 1."""
    assert runner.compare("v", 1.5, 1.0, {"abs": 0.5, "rel": 0.0}) == 1.0
    assert runner.compare("v", np.array([0.0, 2.5]), [0.0, 2.0], {"abs": 0.25, "rel": 0.125}) == 1.0


def test_errors_below_the_expected_value_fail(vector_files):
    """[CF-5], [CF-16] The error is an absolute value: a result below the expected value fails as one
    above it does, in compare and for a whole run (F-1)."""
    tol = {"abs": 1e-5, "rel": 1e-5}
    with pytest.raises(runner.CaseFailure, match="x tolerance") as info:
        runner.compare("w", 0.0998, 0.1, tol)
    assert info.value.ratio == pytest.approx(2e-4 / (1e-5 + 1e-6), rel=1e-6)
    with pytest.raises(runner.CaseFailure, match=r"w\[1\]"):
        runner.compare("w", np.array([0.1, -1.0]), [0.1, 0.0], tol)
    res = runner.run(_Only(velocity=lambda field, obs, x, t: REF.velocity(field, obs, x, t) - 1e-4),
                     files=vector_files, only={"velocity"})
    values = [c for c in res.cases if c.function == "velocity" and ".reject." not in c.id]
    assert not res.ok and values and all(c.status == "fail" and 1.0 < c.worst < 11.0 for c in values)


def test_integer_outputs_are_exact_whatever_the_tolerance(vector_files):
    """[CF-5], [CF-7] Integer outputs (the executor's chunk and token indices, X-4, X-5) are compared
    exactly, even in cases whose tolerance for the real outputs is not 0 (1e-6 for copied actions), and
    must be integers: a real within the tolerance of the expected integer fails as the wrong kind."""
    with pytest.raises(runner.CaseFailure, match="exact match required") as info:
        runner.compare("d", np.array([2, 6]), [2, 5], {"abs": 1.0, "rel": 1e-6}, integer=True)
    assert info.value.ratio == np.inf
    with pytest.raises(runner.CaseFailure, match="expected an integer, got 5.0000001") as info:
        runner.compare("d", 5.0000001, 5, {"abs": 1e-6, "rel": 1e-6}, integer=True)
    assert info.value.ratio == np.inf
    assert runner.compare("d", np.array([2, 5]), [2, 5], {"abs": 1e-6, "rel": 1e-6}, integer=True) == 0.0

    for key in ("chunk_index", "token_index"):
        def nudged(chunks, delays_, s, key=key):
            out = dict(REF.execute_chunks(chunks, delays_, s))
            out[key] = np.asarray(out[key], dtype=np.float64) + 1e-7
            return out
        res = runner.run(_Only(execute_chunks=nudged), files=vector_files, only={"execute_chunks"})
        values, _ = _split(res, "execute_chunks")
        assert values and all(c.status == "fail" and c.worst == np.inf and key in c.message
                              and "expected integers, got an array of float64" in c.message for c in values), key


def test_wrong_shape_is_never_broadcast(vector_files):
    """[CF-5], [CF-18] A result of another shape fails, ratio inf, even where broadcasting would make the
    numbers agree (a length-1 array for an all-zero weight vector); only a one-element result for a
    scalar output is taken as that scalar."""
    for got in (0.0, np.zeros(1), np.zeros((2, 1))):
        with pytest.raises(runner.CaseFailure, match="shape") as info:
            runner.compare("w", got, [0.0, 0.0], {"abs": 1e-5, "rel": 1e-5})
        assert info.value.ratio == np.inf
    assert runner.compare("v", np.array([0.5]), 0.5, {"abs": 1e-5, "rel": 1e-5}) == 0.0

    res = runner.run(_Only(hard_weights=lambda H, d: np.zeros(1) if d == 0 else REF.hard_weights(H, d)),
                     files=vector_files, only={"hard_weights"})
    values, _ = _split(res, "hard_weights")
    d0 = [c for c in values if c.id.endswith(".d0")]
    assert d0 and all(c.status == "fail" and "shape [1]" in c.message for c in d0)
    assert all(c.status == "pass" for c in values if c not in d0)


def test_any_non_finite_value_fails(vector_files):
    """[CF-5], [CF-18] One NaN or infinite entry fails the case, however many entries agree."""
    for bad in (np.nan, np.inf, -np.inf):
        with pytest.raises(runner.CaseFailure, match=r"non-finite value \(NaN or inf\) at index \[2\]"):
            runner.compare("w", np.array([0.1, 0.2, bad]), [0.1, 0.2, 0.3], {"abs": 1e-5, "rel": 1e-5})

    def last_nan(H, d):
        w = np.array(REF.hard_weights(H, d), dtype=np.float64)
        w[-1] = np.nan
        return w
    res = runner.run(_Only(hard_weights=last_nan), files=vector_files, only={"hard_weights"})
    values, _ = _split(res, "hard_weights")
    assert not res.ok and values and all(c.status == "fail" and "non-finite" in c.message
                                         and c.worst == np.inf for c in values)


def test_booleans_are_not_real_numbers(vector_files):
    """[CF-5], [CF-18] A boolean array is the wrong kind of result for a real output, even where its
    0/1 values equal the expected weights (hard weights, W-8)."""
    with pytest.raises(runner.CaseFailure, match="booleans"):
        runner.compare("w", np.array([True, False]), [1.0, 0.0], {"abs": 1e-5, "rel": 1e-5})
    res = runner.run(_Only(hard_weights=lambda H, d: np.asarray(REF.hard_weights(H, d)).astype(bool)),
                     files=vector_files, only={"hard_weights"})
    values, _ = _split(res, "hard_weights")
    assert not res.ok and values and all(c.status == "fail" and "booleans" in c.message for c in values)


# ---------------------------------------------------------------- invalid inputs

def test_invalid_input_must_raise_value_error(vector_files):
    """[CF-7], [N-7], [CF-5], [CF-18] A reject case passes only when the call raises ValueError: an
    implementation that accepts the invalid input, or raises another exception type, fails it
    with ratio inf; its other cases are unaffected."""
    def accepting(rule, d):
        try:
            return REF.endpoint(rule, d)
        except ValueError:
            return 0

    def type_error(rule, d):
        try:
            return REF.endpoint(rule, d)
        except ValueError as exc:
            raise TypeError(str(exc)) from None

    for fn, needle in ((accepting, "endpoint accepted invalid input (expected ValueError, [N-7])"),
                       (type_error, "invalid input must raise ValueError, endpoint raised TypeError")):
        res = runner.run(_Only(endpoint=fn), files=vector_files, only={"endpoint"})
        values, rejects = _split(res, "endpoint")
        assert not res.ok and len(rejects) >= 5
        assert all(c.status == "fail" and c.worst == np.inf and needle in c.message for c in rejects), needle
        assert values and all(c.status == "pass" for c in values)
        assert res.by_requirement()["N-7"]["status"] == "FAIL"


# ---------------------------------------------------------------- sampler traces

def _rtc_with_trace(edit):
    def rtc_sample(field, obs, noise, prior, w, T):
        chunk, trace = REF.rtc_sample(field, obs, noise, prior, w, T)
        return chunk, edit([dict(step) for step in trace])
    return rtc_sample


def _bump(key, step=0):
    def edit(trace):
        trace[step][key] = np.asarray(trace[step][key]) + 1e-2
        return trace
    return edit


def _drop(key):
    def edit(trace):
        del trace[-1][key]
        return trace
    return edit


@pytest.mark.parametrize("edit,needle", [
    (_bump("blended_state"), "trace step 0 blended_state"),
    (_bump("time"), "trace step 0 time"),
    (_bump("velocity", step=-1), "velocity"),
    (_drop("blended_state"), "lacks keys ['blended_state']"),
    (lambda trace: [], "trace has 0 steps"),
    (lambda trace: trace[:1], "trace has 1 steps"),
], ids=["blended-state", "time", "last-velocity", "missing-key", "empty", "truncated"])
def test_every_trace_step_and_key_is_compared(edit, needle, vector_files):
    """[CF-11], [S-3], [CF-14] With a correct chunk, a trace that is wrong in one key of one step, lacks
    a key, or has fewer steps than expected (an empty list included) fails the case, naming it."""
    res = runner.run(_Only(rtc_sample=_rtc_with_trace(edit)), files=vector_files, only={"rtc_sample"})
    values, rejects = _split(res, "rtc_sample")
    if needle == "trace has 1 steps":  # a one-step sampler's trace is whole after truncation
        values = [c for c in values if ".T1." not in c.id]
    assert values and all(c.status == "fail" and needle in c.message for c in values), values[0].message
    assert not res.ok and rejects and all(c.status == "pass" for c in rejects)
    assert "without a trace" not in runner.format_summary(res)


def test_trace_none_checks_the_chunk_only(vector_files):
    """[CF-11] An adapter returning None as trace passes on its chunk, each case says "trace not
    provided", and the summary counts such cases on a line of their own."""
    res = runner.run(_Only(rtc_sample=_rtc_with_trace(lambda trace: None)), files=vector_files,
                     only={"rtc_sample"})
    values, _ = _split(res, "rtc_sample")
    assert res.ok and values and all(c.message == runner.TRACE_NOT_PROVIDED for c in values)
    assert f"{len(values)} sampler cases passed without a trace" in runner.format_summary(res)


# ---------------------------------------------------------------- exit status and reports

_FILE_ADAPTER = """from softrtc.conformance.adapters.reference import ReferenceAdapter
name = {name!r}
_REF = ReferenceAdapter()
{body}
"""


def _adapter_file(tmp_path, name, body=""):
    path = tmp_path / f"{name}.py"
    path.write_text(_FILE_ADAPTER.format(name=name, body=body))
    return str(path)


def test_exit_status(tmp_path, capsys):
    """[CF-16], [CF-14] `run` exits 0 when every supported case passes, 1 when a case fails and also 1
    when no case is supported (nothing was checked)."""
    passing = _adapter_file(tmp_path, "passing", "endpoint = _REF.endpoint")
    failing = _adapter_file(tmp_path, "failing", "def endpoint(rule, d):\n    return _REF.endpoint(rule, d) + 1")
    empty = _adapter_file(tmp_path, "empty")
    assert runner.main(["--impl", passing, "--only", "endpoint"]) == 0
    assert runner.main(["--impl", failing, "--only", "endpoint"]) == 1
    assert runner.main(["--impl", empty, "--only", "endpoint"]) == 1
    out = capsys.readouterr().out
    assert "no supported case ran" in out and out.rstrip().splitlines()[-2].startswith("FAIL: ")


def test_report_and_junit_count_failures(tmp_path, vector_files, capsys):
    """[CF-15], [CF-14], [CF-9] The JSON report and the JUnit XML of a failing run count its failed and
    unsupported cases: the report's counts, the testsuites' and each testsuite's failures and skipped
    attributes match the failure and skipped elements and the run itself."""
    body = "def hard_weights(H, d):\n    return _REF.hard_weights(H, d) + 1e-4"
    impl = _adapter_file(tmp_path, "offset", body)
    rep, junit = tmp_path / "r.json", tmp_path / "j.xml"
    status = runner.main(["--impl", impl, "--only", "hard_weights,endpoint", "--report", str(rep),
                          "--junit", str(junit)])
    capsys.readouterr()
    res = runner.run(impl, files=vector_files, only={"hard_weights", "endpoint"})
    n = res.counts
    assert status == 1 and n["fail"] > 0 and n["unsupported"] > 0 and n["pass"] > 0

    data = json.loads(rep.read_text())
    assert data["ok"] is False and data["counts"] == n
    assert sum(c["status"] == "fail" for c in data["cases"]) == n["fail"]
    assert data["requirements"]["W-8"]["status"] == "FAIL" and data["requirements"]["E-1"]["status"] == "UNSUPPORTED"

    root = ET.parse(junit).getroot()
    assert (root.get("tests"), root.get("failures"), root.get("skipped")) == \
        (str(len(res.cases)), str(n["fail"]), str(n["unsupported"]))
    assert len(root.findall("testsuite/testcase/failure")) == n["fail"]
    assert len(root.findall("testsuite/testcase/skipped")) == n["unsupported"]
    for suite in root.findall("testsuite"):
        cases = suite.findall("testcase")
        assert suite.get("tests") == str(len(cases))
        assert suite.get("failures") == str(sum(tc.find("failure") is not None for tc in cases)), suite.get("name")
        assert suite.get("skipped") == str(sum(tc.find("skipped") is not None for tc in cases)), suite.get("name")
    weights_suite = root.find("testsuite[@name='conformance.weights']")
    hand_suite = root.find("testsuite[@name='conformance.worked_examples']")
    assert int(weights_suite.get("failures")) + int(hand_suite.get("failures")) == n["fail"]
