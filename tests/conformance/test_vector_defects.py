"""Defects of a vector file are vector errors (status 2, one line naming file and case), found when the file is
read, never a verdict on the implementation ([CF-24], [CF-28]); the generator's command line on a closed pipe
and an empty --out ([CF-19], [N-11])."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softrtc.conformance import runner

ROOT = Path(__file__).resolve().parents[2]


def _case(**change) -> dict:
    case = {"id": "M.standard_error.x", "function": "standard_error", "requirements": ["M-6"],
            "tolerance": {"abs": 1e-5, "rel": 1e-5}, "args": {"values": [1.0, 2.0, 3.0, 4.0]},
            "expected": {"value": 0.6454972243679028}}
    case.update(change)
    return case


def _write(tmp_path, text: str) -> Path:
    (tmp_path / "v.json").write_text('{"format_version":"1.2","cases":[' + text + "]}")
    return tmp_path


def _cli(*args):
    return subprocess.run([sys.executable, "-m", "softrtc.conformance", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=120)


@pytest.mark.parametrize("text,needle", [
    # 1e999 parses to inf in Python: an infinite expected value would make inf - inf = NaN and pass anything.
    (json.dumps(_case()).replace("0.6454972243679028", "1e999"), "overflows a double"),
    (json.dumps(_case()).replace("0.6454972243679028", "-1e999"), "overflows a double"),
    (json.dumps(_case()).replace("[1.0, 2.0, 3.0, 4.0]", "[1.0, 2.0, 1e400, 4.0]"), "overflows a double"),
    (json.dumps(_case(tolerance={"abs": 7.0, "rel": 0.0})).replace("7.0", "1e999"), "tolerance 'abs'"),
    (json.dumps(_case(tolerance={"abs": 2.0, "rel": 0.0})), "tolerance 'abs'"),
    (json.dumps(_case(expected={"value": [0.5, 0.5]})), "has shape [2], its arguments give []"),
    (json.dumps(_case(function="bootstrap_interval", requirements=["M-5"],
                      args={"values": [0.1, 0.9], "indices": [[0, 10 ** 30]], "confidence": 0.9},
                      expected={"interval": [0.1, 0.9]})), "beyond 2^53"),
    (json.dumps(_case(function="endpoint", requirements=["E-5"], tolerance={"abs": 0.0, "rel": 0.0},
                      args={"rule": {"kind": "hard"}, "d": 2}, expected={"e": 2.0})), "written as a float"),
    (json.dumps(_case(function="endpoint", requirements=["E-5"], tolerance={"abs": 0.0, "rel": 0.0},
                      args={"rule": {"kind": "hard", "x": {"y": [[[[[[[[[1]]]]]]]]]}}, "d": 2}, expected={"e": 2})),
     "nested deeper than 8"),
    (json.dumps(_case(tolerance={"abs": 1e-5, "rel": 1e-5, "exact": {"value": [1]}})), "index 1 is outside"),
    (json.dumps(_case(tolerance={"abs": 1e-5, "rel": 1e-5, "loose": True})), "unknown keys ['loose']"),
])
def test_defect_is_a_vector_error(tmp_path, text, needle):
    """[CF-28], [CF-24] A non-finite number, a tolerance outside [0, 1], an expected output of the wrong shape,
    an integer beyond 2^53, an integer output written as a float, nesting beyond the limit, an exact index
    outside its output or an unknown tolerance key stops loading with one line naming file and case."""
    with pytest.raises(runner.VectorError) as info:
        runner.load_vectors(_write(tmp_path, text))
    assert needle in str(info.value) and "v.json: case 0" in str(info.value), str(info.value)


def test_defects_exit_2_with_one_line(tmp_path):
    """[CF-28], [CF-16] From the command line a vector defect (1e999 as an expected value; JSON nested far
    deeper than Python's parser follows) is exit 2 with one error line and no summary, before any case runs."""
    _write(tmp_path, json.dumps(_case()).replace("0.6454972243679028", "1e999"))
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1 and "M.standard_error.x" in lines[0], r.stderr
    (tmp_path / "v.json").write_text('{"format_version":"1.2","cases":[' + "[" * 100000 + "]" * 100000 + "]}")
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "nested too deeply" in lines[0] and "v.json" in lines[0], r.stderr
    assert "Traceback" not in r.stderr and "RecursionError" not in r.stderr


def test_an_infinite_expected_value_never_passes():
    """[CF-28], [CF-5] Defence in depth: compare() fails an infinite expected value instead of letting a NaN
    ratio pass, whatever the answer."""
    for got in (0.0, 1e308, np.inf):
        with pytest.raises(runner.CaseFailure):
            runner.compare("v", got, np.inf, {"abs": 1e-5, "rel": 1e-5})


def test_generate_check_on_a_closed_pipe_and_an_empty_directory(tmp_path):
    """[CF-19], [N-11] `generate --check | true` stops quietly (no error line, the status of a closed pipe);
    `generate --check --out EMPTY_DIR` has nothing to compare with: exit 2 with one line, nothing written."""
    r = subprocess.run(f"{sys.executable} -m softrtc.conformance generate --check | true; "
                       "echo status=${PIPESTATUS[0]} >&2", shell=True, executable="/bin/bash", cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert r.stderr.strip() == "status=141", r.stderr
    empty = tmp_path / "empty"
    empty.mkdir()
    r = _cli("generate", "--check", "--out", str(empty))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and "holds no vector files" in lines[0], r.stderr
    assert list(empty.iterdir()) == []


# ---------------------------------------------------------------- the schema's rules ([CF-38])

def _file(*cases, **top) -> str:
    doc = {"format_version": "1.2", "spec_version": "0.1.0", "chapter": "M", "title": "t", "generator": "g",
           "reference": "r", "cases": list(cases) or [_case()]}
    doc.update(top)
    return json.dumps(doc)


_FIELD = {"params": {"W1": [[0.0]], "Wt": [[0.0]], "Wo": [[0.0]], "b1": [0.0], "W2": [[0.0]], "b2": [0.0]},
          "horizon": 1, "action_dim": 1, "obs_dim": 1, "hidden": 1}


@pytest.mark.parametrize("text,needle", [
    (_file(_case(note="hand-made")), "case 0 ('M.standard_error.x'): unknown keys ['note']"),
    (_file(comment="x"), "unknown top-level keys ['comment']"),
    (_file(_case(args={"values": [1.0, 2.0, 3.0, 4.0], "ddof": 1})),
     "'args' holds ['ddof'], which standard_error(values) does not take"),
    (_file(_case(expected={"value": 0.6454972243679028, "mean": 2.5})),
     "'expected' holds ['mean'], which standard_error does not return"),
    (_file(_case(expected={"error": "ValueError", "value": 1.0})), "exactly {'error': 'ValueError'}"),
    (_file(_case(id="standard_error.x")), "'id' 'standard_error.x' must look like"),
    (_file(_case(requirements=["M-6", "M-6"])), "'requirements' must be"),
    (_file(_case(requirements=["m6"])), "'requirements' must be"),
    (_file(spec_version="1"), "'spec_version' must be"),
    (_file(chapter="metrics"), "'chapter' must be"),
    (_file(title=3), "'title' must be"),
    (_file(cases=[]), "'cases' must be a non-empty list"),
    (_file(fields={"f": dict(_FIELD, extra=1)}), "field 'f': unknown keys ['extra']"),
    (_file(fields={"f": {k: v for k, v in _FIELD.items() if k != "hidden"}}), "field 'f' lacks ['hidden']"),
    (_file(fields={"f": dict(_FIELD, params=dict(_FIELD["params"], W3=[[0.0]]))}), "unknown keys ['W3']"),
    (_file(fields={"f": dict(_FIELD, horizon=0)}), "'horizon' must be an integer >= 1"),
])
def test_what_the_schema_forbids_is_a_vector_error(tmp_path, text, needle):
    """[CF-38], [CF-22], [CF-24] Every rule of spec/vectors.schema.json is checked when a file is read: a key the
    schema does not declare (in a case, at the top level, in a field), an argument the function does not take,
    an output it does not return, an id, requirement, version or chapter off its pattern, an empty case list.
    Each stops loading with one line naming the file (and the case); jsonschema, when installed, refuses the
    same file, so the reader and the schema agree."""
    (tmp_path / "v.json").write_text(text)
    with pytest.raises(runner.VectorError) as info:
        runner.load_vectors(tmp_path)
    assert needle in str(info.value) and str(info.value).startswith("v.json"), str(info.value)
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads((ROOT / "spec" / "vectors.schema.json").read_text())
    if "does not take" in needle or "does not return" in needle:
        return  # per-function arguments and outputs are beyond what the schema's JSON can say
    assert list(jsonschema.Draft202012Validator(schema).iter_errors(json.loads(text))), needle


def test_schema_errors_exit_2_before_any_case_runs(tmp_path):
    """[CF-38], [CF-16] From the command line an extra key in a case is exit 2 with one error line naming the
    file and the case, and no case runs (no summary)."""
    (tmp_path / "v.json").write_text(_file(_case(), _case(id="M.standard_error.y", extra=True)))
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and r.stdout == "" and len(lines) == 1, r.stdout + r.stderr
    assert "v.json: case 1 ('M.standard_error.y'): unknown keys ['extra']" in lines[0]


def test_a_minimal_hand_made_file_still_reads(tmp_path):
    """[CF-38] The descriptive header keys are optional for a hand-made file (the generator writes them all):
    format_version and a non-empty case list suffice, as the schema says."""
    (tmp_path / "v.json").write_text(json.dumps({"format_version": "1.2", "cases": [_case()]}))
    assert len(runner.load_vectors(tmp_path)[0]["cases"]) == 1
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads((ROOT / "spec" / "vectors.schema.json").read_text())
    assert not list(jsonschema.Draft202012Validator(schema).iter_errors(
        {"format_version": "1.2", "cases": [_case()]}))


def test_the_schema_names_every_interface_function():
    """[CF-38], [CF-22], [CF-7] The schema's enumeration of case functions is the interface of [CF-7]: a function
    added to one and not the other would make the reader and the schema disagree on which files are valid."""
    from softrtc.conformance.adapter import INTERFACE

    schema = json.loads((ROOT / "spec" / "vectors.schema.json").read_text())
    assert sorted(schema["$defs"]["case"]["properties"]["function"]["enum"]) == sorted(INTERFACE)
