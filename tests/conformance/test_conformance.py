"""Tests of the conformance suite: vectors, runner, adapters, reports (spec/40-conformance.md)."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

from softrtc.conformance import FORMAT_VERSION, SPEC_VERSION, generate, runner
from softrtc.conformance.adapter import INTERFACE, AdapterError, load_adapter
from softrtc.conformance.adapters.reference import ReferenceAdapter

ROOT = Path(__file__).resolve().parents[2]
VECTORS = ROOT / "conformance" / "vectors"
HAS_TORCH = importlib.util.find_spec("torch") is not None
HAS_JAX = importlib.util.find_spec("jax") is not None


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


def _cli(*args, cwd=ROOT):
    return subprocess.run([sys.executable, "-m", "softrtc.conformance", *args], cwd=cwd, capture_output=True,
                          text=True, timeout=120)


def test_reference_adapter_passes_everything(vector_files):
    """[CF-13], [CF-16], [CF-4] The reference passes every case, none unsupported; the vectors
    cover every chapter E, W, D, C, L, F, S, G, X, M, V (ids E-1..E-6, W-1..W-9, D-1..D-3,
    C-1..C-3, L-1..L-4, F-1, F-2, S-1..S-7, G-1..G-6, X-1..X-5, M-1..M-3, M-5, M-6, V-1, V-3, N-7)."""
    res = runner.run("reference", files=vector_files)
    assert res.ok and res.counts["fail"] == 0 and res.counts["unsupported"] == 0
    reqs = res.by_requirement()
    for rid in ["E-1", "E-2", "E-3", "E-4", "E-5", "E-6", "W-1", "W-2", "W-3", "W-4", "W-5", "W-6", "W-7", "W-8",
                "W-9", "D-1", "D-2", "D-3", "C-1", "C-2", "C-3", "L-1", "L-2", "L-3", "L-4", "F-1", "F-2", "S-1",
                "S-2", "S-3", "S-4", "S-5", "S-6", "S-7", "G-1", "G-2", "G-3", "G-4", "G-5", "G-6", "X-1", "X-2",
                "X-3", "X-4", "X-5", "M-1", "M-2", "M-3", "M-5", "M-6", "V-1", "V-3", "N-7"]:
        assert reqs[rid]["status"] == "PASS", rid


@pytest.mark.skipif(not HAS_TORCH, reason="torch not installed")
@pytest.mark.parametrize("impl", ["torch", "torch-flipped"])
def test_torch_adapters_pass(impl, vector_files):
    """[CF-21], [CF-10], [CF-9] The float32 adapters on softrtc.torch pass in both time conventions
    (V-1, V-3 through the runner's mapping) with no case unsupported: every interface function of
    [CF-7] is ported, the delay tables and draws ([D-1], [D-2], [D-3]), per-token times ([C-1]),
    the field's VJP by autograd ([F-2]), method weights ([S-6]), the shifted prior and executor
    ([X-1], [X-2], [X-3], [X-4], [X-5]) and the metrics ([M-1], [M-2], [M-3], [M-5], [M-6]) included,
    and every function has passing cases in both adapters."""
    res = runner.run(impl, files=vector_files)
    assert res.ok, runner.format_summary(res)
    assert res.counts["unsupported"] == 0, runner.format_summary(res)
    assert res.counts["pass"] == len(res.cases) > 4000
    assert res.time_convention == ("noise_at_1" if impl == "torch-flipped" else "data_at_1")
    passed = {c.function for c in res.cases if c.status == "pass"}
    assert passed == set(INTERFACE), sorted(set(INTERFACE) - passed)


@pytest.mark.skipif(not HAS_TORCH, reason="torch not installed")
def test_torch_adapter_by_path_and_module():
    """[CF-12], [CF-7], [CF-21] Adapters load by built-in name, by file path with :ATTR and by module:ATTR; a file
    inside a package keeps its relative imports; by module name, the flipped adapter's relative import of
    .torch gives the very module the `torch` built-in loads; both are built on softrtc.torch."""
    a = load_adapter(str(ROOT / "conformance" / "adapters" / "torch_flipped.py") + ":ADAPTER")
    assert a.name == "torch-flipped" and a.time_convention == "noise_at_1"
    plain = load_adapter("torch")
    b = load_adapter("softrtc.conformance.adapters.torch_flipped:ADAPTER")
    assert isinstance(b, type(plain)) and type(plain).__module__ == "softrtc.conformance.adapters.torch"
    assert type(a).__bases__[0].__name__ == type(plain).__name__
    assert load_adapter("softrtc.conformance.adapters.reference:ADAPTER").name == "reference"
    assert load_adapter("softrtc.conformance.adapters.reference").name == "reference"
    import softrtc.conformance.adapters.torch as torch_adapter
    import softrtc.torch.weights
    assert torch_adapter.weights is softrtc.torch.weights


JAX_QUICK = {"delay_probs", "loss", "velocity", "velocity_vjp", "rtc_sample", "standard_error"}


@pytest.mark.skipif(not HAS_JAX, reason="jax not installed")
def test_jax_adapter_passes_quick_subset(vector_files):
    """[CF-12], [CF-11] The JAX twin passes a quick subset of functions (chunk-only sampler
    traces); the full run is test_jax_adapter_passes_all (slow). Ids: D-1, D-2, L-2, F-1, F-2, S-3, M-6."""
    res = runner.run("jax", files=vector_files, only=JAX_QUICK)
    assert res.ok, runner.format_summary(res)
    untraced = [c for c in res.cases if c.function == "rtc_sample" and "trace not provided" in c.message]
    assert untraced
    # The summary counts them, so a chunk-only run cannot pass for one that checked per-step values.
    assert f"{len(untraced)} sampler cases passed without a trace" in runner.format_summary(res)
    ref = runner.run("reference", files=vector_files, only={"rtc_sample"})
    assert "without a trace" not in runner.format_summary(ref)


@pytest.mark.slow
@pytest.mark.skipif(not HAS_JAX, reason="jax not installed")
def test_jax_adapter_passes_all(vector_files):
    """[CF-12], [CF-13] The JAX twin passes every case: none failed, none unsupported."""
    res = runner.run("jax", files=vector_files)
    assert res.ok, runner.format_summary(res)
    assert res.counts["unsupported"] == 0 and res.counts["pass"] == len(res.cases), res.counts


# ---------------------------------------------------------------- broken adapters

class _Only:
    name = "broken"

    def __init__(self, **fns):
        for k, v in fns.items():
            setattr(self, k, v)


@pytest.mark.parametrize("fn,needle", [
    (lambda H, d, window, s: np.zeros(H + 1), "shape"),
    (lambda H, d, window, s: np.full(H, np.nan), "non-finite"),
    (lambda H, d, window, s: (_ for _ in ()).throw(RuntimeError("boom")), "weights raised RuntimeError: boom"),
    (lambda H: np.zeros(H), "cannot be called as weights(H, d, window, s)"),
    (lambda H, d, window, s: "nope", "expected numbers"),
])
def test_broken_adapter_clean_messages(fn, needle, vector_files):
    """[CF-18], [CF-16] Wrong shapes, NaN, exceptions, wrong signatures and non-numeric outputs
    fail with a one-line message naming the case, never a traceback."""
    res = runner.run(_Only(weights=fn), files=vector_files, only={"weights"})
    assert not res.ok
    fails = [c for c in res.cases if c.status == "fail" and "accepted invalid input" not in c.message]
    assert fails and all(needle in c.message and "\n" not in c.message for c in fails), fails[0].message
    text = runner.format_summary(res)
    assert "Traceback" not in text and f"FAIL {fails[0].id}: " in text


def test_broken_adapter_loading_errors():
    """[CF-12], [CF-8], [CF-18] Import errors, missing attributes and malformed adapters give AdapterError."""
    with pytest.raises(AdapterError, match="cannot import adapter module"):
        load_adapter("softrtc_no_such_module_xyz")
    with pytest.raises(AdapterError, match="has no attribute 'NOPE'"):
        load_adapter("softrtc.conformance.adapters.reference:NOPE")
    with pytest.raises(AdapterError, match="does not exist"):
        load_adapter("no/such/file.py:ADAPTER")
    with pytest.raises(AdapterError, match="'name'"):
        runner.run(object())

    class BadConv:
        name, time_convention = "bad", "backwards"
    with pytest.raises(AdapterError, match="time_convention"):
        runner.run(BadConv())


def test_cli_broken_adapter_file(tmp_path):
    """[CF-18], [CF-19], [CF-16] From the command line: an adapter file that fails to import
    exits 2 with one line; an adapter raising inside cases exits 1 without a traceback."""
    bad = tmp_path / "bad_import.py"
    bad.write_text("import softrtc_not_a_module\n")
    r = _cli("run", "--impl", f"{bad}:ADAPTER")
    assert r.returncode == 2 and "Traceback" not in r.stderr and len(r.stderr.strip().splitlines()) == 1
    raising = tmp_path / "raising.py"
    raising.write_text("name = 'raising'\n\ndef endpoint(rule, d):\n    raise KeyError(rule['kind'])\n")
    r = _cli("run", "--impl", str(raising))
    assert r.returncode == 1 and "Traceback" not in r.stdout + r.stderr
    assert "endpoint raised KeyError" in r.stdout and "unsupported" in r.stdout


def test_unsupported_listed_not_failed(vector_files, capsys):
    """[CF-9], [CF-14], [CF-16] Cases of missing functions are unsupported and listed; exit 0 when all
    supported cases pass, 1 when no case is supported."""
    ref = ReferenceAdapter()
    partial = _Only(endpoint=ref.endpoint, hard_weights=ref.hard_weights)
    res = runner.run(partial, files=vector_files)
    assert res.ok and res.counts["unsupported"] > 0
    text = runner.format_summary(res)
    assert "unsupported (adapter lacks the function):" in text and "weights (" in text
    assert "PASS" in text.splitlines()[-1]
    none = runner.run(_Only(), files=vector_files)
    assert not none.ok and "no supported case ran" in runner.format_summary(none)


def test_flipped_mapping_is_applied(vector_files):
    """[CF-10], [V-1], [V-3] An adapter that declares noise_at_1 but computes in spec time fails
    the time-carrying cases: the runner really maps t' = 1 - t and u = -v."""
    class Liar(ReferenceAdapter):
        name, time_convention = "liar", "noise_at_1"
    res = runner.run(Liar(), files=vector_files, only={"token_times", "corrupt", "velocity", "loss"})
    failed = {c.function for c in res.cases if c.status == "fail"}
    assert {"token_times", "corrupt", "velocity", "loss"} <= failed


def test_reports_written(tmp_path):
    """[CF-15], [CF-14], [CF-19] `run --report --junit` writes a JSON report and JUnit XML and prints
    one line per requirement id."""
    rep, junit = tmp_path / "r.json", tmp_path / "j.xml"
    r = _cli("run", "--impl", "reference", "--report", str(rep), "--junit", str(junit),
             "--only", "endpoint,loss,execute_chunks")
    assert r.returncode == 0, r.stdout + r.stderr
    assert any(line.split()[:2] == ["PASS", "E-2"] for line in r.stdout.splitlines())
    data = json.loads(rep.read_text())
    assert data["ok"] and data["counts"]["fail"] == 0 and data["requirements"]["X-4"]["status"] == "PASS"
    assert data["format_version"] == FORMAT_VERSION and data["spec_versions"] == [SPEC_VERSION]
    root = ET.parse(junit).getroot()
    assert root.tag == "testsuites" and int(root.get("failures")) == 0
    assert int(root.get("tests")) == len(data["cases"]) and int(root.get("skipped")) == 0
    assert root.find("testsuite/testcase/properties/property").get("name") == "requirements"


def test_reports_are_written_whole_or_not_at_all(vector_files, tmp_path, monkeypatch):
    """[CF-15] A report that fails while being written leaves the previous file as it was and no
    temporary file behind; one that succeeds replaces it."""
    res = runner.run(ReferenceAdapter(), files=vector_files, only={"endpoint"})
    junit = tmp_path / "j.xml"
    junit.write_text("old")
    real_write = ET.ElementTree.write

    def half_then_fail(self, f, *a, **k):
        f.write(b"<testsuites")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ET.ElementTree, "write", half_then_fail)
    with pytest.raises(OSError):
        runner.write_junit(res, junit)
    assert junit.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["j.xml"]
    monkeypatch.setattr(ET.ElementTree, "write", real_write)
    runner.write_junit(res, junit)
    assert ET.parse(junit).getroot().get("tests") == str(len(res.cases))


def test_citation_names_this_version():
    """[CF-2] CITATION.cff cites the version pyproject.toml builds, and the README's conformance claim
    names the format and spec versions the vectors carry."""
    import re
    cff = (ROOT / "CITATION.cff").read_text()
    pyproject = (ROOT / "pyproject.toml").read_text()
    version = re.search(r'^version = "([^"]+)"', pyproject, re.M).group(1)
    assert re.search(r'^version: "([^"]+)"', cff, re.M).group(1) == version
    assert re.search(r"^license: (\S+)", cff, re.M).group(1) in pyproject
    claim = f"passes softrtc conformance vectors format {FORMAT_VERSION}, spec {SPEC_VERSION}"
    assert claim in (ROOT / "README.md").read_text()
    assert claim in (ROOT / "spec" / "40-conformance.md").read_text().replace("\n", " ")


def test_vector_directory_checked_against_its_index(tmp_path):
    """[CF-25], [CF-16], [CF-2] A directory with index.json is checked against it before any case runs: an
    edited file (even one digit), a missing or an unlisted file, or a wrong case count stop the run with
    status 2 naming the file; without index.json the same files are read as a hand-made set."""
    import shutil

    from softrtc.conformance.runner import VectorError, load_vectors

    d = tmp_path / "v"
    shutil.copytree(VECTORS, d)
    assert len(load_vectors(d)) == len(load_vectors())  # an intact copy loads
    loss = d / "loss.json"
    text = loss.read_text()
    i = text.index('"rel":') + len('"rel":')
    loss.write_text(text[:i] + text[i:].replace("1", "2", 1))  # one digit of one tolerance
    with pytest.raises(VectorError, match=r"loss\.json: SHA-256 .* differs from index\.json"):
        load_vectors(d)
    r = _cli("run", "--impl", "reference", "--vectors", str(d))
    assert r.returncode == 2 and "loss.json" in r.stderr and "SHA-256" in r.stderr, r.stderr
    loss.write_text(text)
    (d / "extra.json").write_text((d / "metrics.json").read_text())
    with pytest.raises(VectorError, match="extra.json: not listed in index.json"):
        load_vectors(d)
    (d / "extra.json").unlink()
    (d / "metrics.json").unlink()
    with pytest.raises(VectorError, match="metrics.json: listed in index.json but missing"):
        load_vectors(d)
    shutil.copy(VECTORS / "metrics.json", d / "metrics.json")
    index = json.loads((d / "index.json").read_text())
    index["files"]["loss.json"]["cases"] += 1
    (d / "index.json").write_text(json.dumps(index))
    with pytest.raises(VectorError, match="loss.json: .* cases, index.json lists"):
        load_vectors(d)
    (d / "index.json").unlink()
    loss.write_text(text[:i] + text[i:].replace("1", "2", 1))
    assert len(load_vectors(d)) == len(load_vectors())  # no index: a hand-made set, read as it is


def test_vectors_validate_against_schema():
    """[CF-22], [CF-2], [CF-6] Every vector file validates against spec/vectors.schema.json and
    index.json holds each file's sha256."""
    jsonschema = pytest.importorskip("jsonschema")
    schema = json.loads((ROOT / "spec" / "vectors.schema.json").read_text())
    jsonschema.Draft202012Validator.check_schema(schema)
    validator = jsonschema.Draft202012Validator(schema)
    index = json.loads((VECTORS / "index.json").read_text())
    assert index["format_version"] == FORMAT_VERSION and index["spec_version"] == SPEC_VERSION
    files = sorted(p for p in VECTORS.glob("*.json") if p.name != "index.json")
    assert {p.name for p in files} == set(index["files"])
    total = 0
    for p in files:
        raw = p.read_bytes()
        total += len(raw)
        assert hashlib.sha256(raw).hexdigest() == index["files"][p.name]["sha256"], p.name
        errors = list(validator.iter_errors(json.loads(raw)))
        assert not errors, f"{p.name}: {errors[0].message}"
    assert total < 5_000_000  # [CF-4]: a few MB at most


def _numpy_avx512() -> bool:
    """Whether NumPy dispatches its x86-64-v4 (AVX-512) kernels here, as on the machine the vectors come from."""
    import platform
    try:
        from numpy._core._multiarray_umath import __cpu_features__
    except ImportError:  # a NumPy without this table: the class is unknown, so no byte check
        return False
    return platform.machine() in ("x86_64", "AMD64") and bool(__cpu_features__.get("X86_V4"))


def test_regeneration_reproduces_the_vectors(tmp_path):
    """[CF-1], [CF-3] Regenerating gives the shipped files: byte-identical where NumPy runs its AVX-512
    kernels (x86-64-v4, the shipped vectors' machine class), and everywhere the same cases and integers
    with every real within REGEN_TOL."""
    sizes = generate.generate(tmp_path)
    shipped = {p.name for p in VECTORS.glob("*.json")}
    assert set(sizes) == shipped
    res = generate.compare(tmp_path, VECTORS)
    assert set(res) == shipped - {"index.json"}
    bad = {n: r for n, r in res.items() if not r["within"]}
    assert not bad, f"regenerated vectors differ beyond rounding: {bad}"
    if _numpy_avx512():
        differ = sorted(n for n, r in res.items() if not r["identical"])
        assert not differ, f"{differ} differ from the shipped bytes on an x86-64-v4 machine"
        assert (tmp_path / "index.json").read_bytes() == (VECTORS / "index.json").read_bytes()


def test_compare_flags_changed_vectors(tmp_path):
    """[CF-3] compare() accepts a real moved within REGEN_TOL, flags one moved beyond it, and rejects a
    changed integer or a missing case as a difference beyond rounding."""
    import shutil
    for p in VECTORS.glob("*.json"):
        shutil.copy(p, tmp_path / p.name)
    data = json.loads((VECTORS / "velocity.json").read_text())
    case = next(c for c in data["cases"] if isinstance(c["expected"].get("velocity"), list))
    row = case["expected"]["velocity"][0]
    x = row[0]

    def write(value):
        row[0] = value
        (tmp_path / "velocity.json").write_text(json.dumps(data))
        return generate.compare(tmp_path, VECTORS)["velocity.json"]

    near = write(x + 1e-13 * max(1.0, abs(x)))
    assert not near["identical"] and near["within"]
    far = write(x + 1e-9)
    assert not far["within"] and far["worst"].startswith("velocity.json/cases[")
    row[0] = x
    data["cases"][0]["id"] += "-renamed"
    (tmp_path / "velocity.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match="velocity.json"):
        generate.compare(tmp_path, VECTORS)
    (tmp_path / "velocity.json").unlink()
    with pytest.raises(ValueError, match="velocity.json is missing"):
        generate.compare(tmp_path, VECTORS)
    with pytest.raises(ValueError, match="got_dir"):
        generate.compare(tmp_path / "nope", VECTORS)


def test_generate_check_command(tmp_path):
    """[CF-3], [CF-19] `softrtc conformance generate --check` exits 0 against the shipped vectors and 1 against
    a copy with one real changed beyond rounding, without writing into the directory it checks."""
    import shutil
    cmd = [sys.executable, "-m", "softrtc.conformance", "generate", "--check"]
    ok = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    assert ok.returncode == 0, ok.stderr
    assert "regeneration agrees" in ok.stdout
    for p in VECTORS.glob("*.json"):
        shutil.copy(p, tmp_path / p.name)
    text = (tmp_path / "sampler.json").read_text()
    data = json.loads(text)
    data["cases"][0]["expected"]["chunk"][0][0] += 1e-6
    (tmp_path / "sampler.json").write_text(json.dumps(data))
    before = (tmp_path / "sampler.json").read_bytes()
    bad = subprocess.run(cmd + ["--out", str(tmp_path)], capture_output=True, text=True, cwd=ROOT)
    assert bad.returncode == 1 and "sampler.json" in bad.stdout and "BEYOND" in bad.stdout
    assert (tmp_path / "sampler.json").read_bytes() == before
    missing = subprocess.run(cmd + ["--out", str(tmp_path / "none")], capture_output=True, text=True, cwd=ROOT)
    assert missing.returncode == 2 and "--out must be an existing directory" in missing.stderr
    assert not (tmp_path / "none").exists()


def test_case_structure_and_tolerances(vector_files):
    """[CF-5], [CF-6] Every case names its requirement ids and a tolerance; integer outputs are
    exact, weights use 1e-5 and sampler traces 1e-4."""
    for data in vector_files:
        for case in data["cases"]:
            assert case["requirements"] and {"abs", "rel"} <= set(case["tolerance"]) <= {"abs", "rel", "exact"}
            tol = {k: v for k, v in case["tolerance"].items() if k != "exact"}
            if case["function"] in ("weights", "prefix_weights") and "error" not in case["expected"]:
                assert tol == {"abs": 1e-5, "rel": 1e-5}
            if case["function"] in ("rtc_sample", "guided_sample", "naive_sample") and "error" not in case["expected"]:
                assert tol == {"abs": 1e-4, "rel": 1e-4}
            if case["function"] in ("endpoint", "sample_delay"):
                assert case["tolerance"] == {"abs": 0.0, "rel": 0.0}


def test_loss_reject_case_is_named_for_its_input(vector_files):
    """[CF-4], [N-7] The loss rejection case holds the invalid input its id names (weights above one)."""
    cases = {c["id"]: c for d in vector_files for c in d["cases"]}
    case = cases["L.loss.reject.weights-above-one"]
    assert case["expected"] == {"error": "ValueError"} and max(case["args"]["weights"]) > 1.0
    assert not [cid for cid in cases if "nan" in cid.lower()]  # JSON vectors hold no NaN input ([CF-23])


class _Recorder(ReferenceAdapter):
    """The reference, recording the type of every argument it receives."""

    name = "recorder"

    def __init__(self):
        self.seen = []

    def endpoint(self, rule, d):
        self.seen.append(("endpoint", {"d": d}))
        return super().endpoint(rule, d)

    def execute_chunks(self, chunks, delays_, s):
        self.seen.append(("execute_chunks", {"chunks": chunks, "delays": delays_, "s": s}))
        return super().execute_chunks(chunks, delays_, s)

    def boundary_jump(self, actions, chunk_index):
        self.seen.append(("boundary_jump", {"chunk_index": chunk_index}))
        return super().boundary_jump(actions, chunk_index)

    def bootstrap_interval(self, values, indices, confidence):
        self.seen.append(("bootstrap_interval", {"values": values, "indices": indices, "confidence": confidence}))
        return super().bootstrap_interval(values, indices, confidence)


def test_argument_types(vector_files):
    """[CF-7], [CF-23] Float arrays arrive as float64 arrays; delays, indices and chunk_index as int64
    arrays (float64 when the file writes a float element); scalars as int or float as written."""
    rec = _Recorder()
    res = runner.run(rec, files=vector_files, only={"endpoint", "execute_chunks", "boundary_jump",
                                                    "bootstrap_interval"})
    assert res.ok, runner.format_summary(res)
    by = {}
    for fname, args in rec.seen:
        by.setdefault(fname, []).append(args)
    assert {type(a["d"]) for a in by["endpoint"]} == {int, float}  # float only in E.endpoint.reject.float-d
    assert sum(type(a["d"]) is float for a in by["endpoint"]) == 1
    ex = by["execute_chunks"]
    assert all(isinstance(a["delays"], np.ndarray) and a["chunks"].dtype == np.float64 and type(a["s"]) is int
               for a in ex)
    assert [a["delays"].dtype for a in ex].count(np.dtype(np.float64)) == 1  # X.execute_chunks.reject.float-d
    assert [a["delays"].dtype for a in ex].count(np.dtype(np.int64)) == len(ex) - 1
    bj = [a["chunk_index"].dtype for a in by["boundary_jump"]]
    assert bj.count(np.dtype(np.float64)) == 1  # M.boundary_jump.reject.float-chunk-index
    assert bj.count(np.dtype(np.int64)) == len(bj) - 1
    assert all(a["indices"].dtype == np.int64 and a["values"].dtype == np.float64
               and type(a["confidence"]) is float for a in by["bootstrap_interval"])


_HEADER = '{"format_version":"1.0","spec_version":"0.1.0","cases":['


def _endpoint_case(cid: str, d_text: str) -> str:
    return ('{"id":"%s","function":"endpoint","requirements":["E-1"],"tolerance":{"abs":0.0,"rel":0.0},'
            '"args":{"rule":{"kind":"hard"},"d":%s},"expected":{"error":"ValueError"}}' % (cid, d_text))


def test_json_number_convention(tmp_path):
    """[CF-23] A number written with a fraction or exponent is a float, one written without is an int,
    whatever its value; NaN and Infinity are refused."""
    texts = {"E.endpoint.int": "2", "E.endpoint.frac": "2.0", "E.endpoint.exp": "2e0", "E.endpoint.neg": "-1"}
    (tmp_path / "numbers.json").write_text(_HEADER + ",".join(_endpoint_case(k, v) for k, v in texts.items())
                                           + "]}")
    rec = _Recorder()
    runner.run(rec, vectors_dir=tmp_path)
    assert [type(a["d"]) for _, a in rec.seen] == [int, float, float, int]
    assert [a["d"] for _, a in rec.seen] == [2, 2.0, 2.0, -1]
    for bad in ("NaN", "Infinity", "-Infinity"):
        (tmp_path / "numbers.json").write_text(_HEADER + _endpoint_case("E.endpoint.x", bad) + "]}")
        with pytest.raises(runner.VectorError, match="not a JSON number"):
            runner.load_vectors(tmp_path)


def _valid_case() -> dict:
    return {"id": "E.endpoint.ok", "function": "endpoint", "requirements": ["E-1"],
            "tolerance": {"abs": 0.0, "rel": 0.0}, "args": {"rule": {"kind": "hard"}, "d": 1}, "expected": {"e": 1}}


@pytest.mark.parametrize("change,needle", [
    (lambda c: c["args"].pop("d"), "lacks ['d']"),
    (lambda c: c.update(function="endpoints"), "not an interface function"),
    (lambda c: c["expected"].pop("e"), "lacks outputs ['e']"),
    (lambda c: c.update(expected={"error": "ValueError", "e": 1}), "exactly"),
    (lambda c: c["tolerance"].update(abs=-1.0), "tolerance 'abs'"),
    (lambda c: c.update(requirements=[]), "non-empty list"),
    (lambda c: c.update(args="d=1"), "'args' must be a dict"),
    (lambda c: c.update(function="velocity", args={"field": "nope", "obs": [0.0], "x": [[0.0]], "t": [0.0]},
                        expected={"velocity": [[0.0]]}), "'field' 'nope'"),
])
def test_malformed_case_is_status_2(tmp_path, change, needle):
    """[CF-24], [CF-16] A malformed case in a readable vector file stops loading with one line naming the
    file and the case; nothing runs."""
    case = _valid_case()
    change(case)
    (tmp_path / "bad.json").write_text(json.dumps({"format_version": "1.0", "cases": [_valid_case(), case]}))
    with pytest.raises(runner.VectorError) as info:
        runner.load_vectors(tmp_path)
    assert needle in str(info.value) and "bad.json: case 1" in str(info.value), str(info.value)


def test_malformed_vectors_exit_2(tmp_path):
    """[CF-24], [CF-16] From the command line: a duplicate case id, or an argument that is not a
    rectangular array, exits 2 with one error line and no summary."""
    (tmp_path / "a.json").write_text(json.dumps({"format_version": "1.0", "cases": [_valid_case()]}))
    (tmp_path / "b.json").write_text(json.dumps({"format_version": "1.0", "cases": [_valid_case()]}))
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    assert r.returncode == 2 and r.stdout == "" and "already used in a.json" in r.stderr, r.stdout + r.stderr
    (tmp_path / "b.json").unlink()
    ragged = {"id": "M.standard_error.ragged", "function": "standard_error", "requirements": ["M-6"],
              "tolerance": {"abs": 1e-5, "rel": 1e-5}, "args": {"values": [[1.0, 2.0], [3.0]]},
              "expected": {"value": 0.0}}
    (tmp_path / "a.json").write_text(json.dumps({"format_version": "1.0", "cases": [_valid_case(), ragged]}))
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    assert r.returncode == 2 and r.stdout == "" and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[0].startswith("python -m softrtc.conformance run: error: a.json: case 1 "
                                                       "('M.standard_error.ragged'): argument "
                                                       "'values' is not a rectangular array"), r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_vector_format_version_checked(tmp_path):
    """[CF-2] The runner refuses vector files of another format major version with one line."""
    (tmp_path / "x.json").write_text(json.dumps({"format_version": "2.0", "cases": []}))
    with pytest.raises(runner.VectorError, match="format_version"):
        runner.load_vectors(tmp_path)
    r = _cli("run", "--impl", "reference", "--vectors", str(tmp_path))
    assert r.returncode == 2 and "format_version" in r.stderr and "Traceback" not in r.stderr


def test_comparison_rule():
    """[CF-5] |got - want| <= abs + rel |want| elementwise; integers exactly; shapes must match. A failure
    carries its error ratio (inf when nothing could be compared) and prints plain numbers."""
    tol = {"abs": 1e-5, "rel": 1e-5}
    assert runner.compare("w", np.float32(0.1), 0.1, tol) <= 1.0
    with pytest.raises(runner.CaseFailure, match="x tolerance") as info:
        runner.compare("w", 0.1002, 0.1, tol)
    assert info.value.ratio == pytest.approx(2e-4 / (1e-5 + 1e-6), rel=1e-6)
    with pytest.raises(runner.CaseFailure) as info:
        runner.compare("w", np.array([0.1, 0.1002]), [0.1, 0.1], tol)
    assert str(info.value) == "w[1]: got 0.1002, expected 0.1 (18.2 x tolerance)"
    assert info.value.ratio == pytest.approx(2e-4 / (1e-5 + 1e-6), rel=1e-6)
    with pytest.raises(runner.CaseFailure, match="exact match") as info:
        runner.compare("e", np.array([3]), [4], {"abs": 0.0, "rel": 0.0}, integer=True)
    assert str(info.value) == "e[0]: got 3, expected 4 (exact match required)" and info.value.ratio == np.inf
    with pytest.raises(runner.CaseFailure, match="shape") as info:
        runner.compare("w", np.zeros(3), [0.0, 0.0], tol)
    assert info.value.ratio == np.inf


def test_failed_cases_report_their_error_ratio(vector_files, tmp_path):
    """[CF-5], [CF-14], [CF-15] A failing requirement reports the worst ratio of its failed cases, in the
    summary and in the JSON report: finite when numbers were out of tolerance, inf when an exact match
    failed; never 0."""
    ref = ReferenceAdapter()
    off = _Only(velocity=lambda field, obs, x, t: ref.velocity(field, obs, x, t) + 1e-4,
                endpoint=lambda rule, d: ref.endpoint(rule, d) + 1)
    res = runner.run(off, files=vector_files, only={"velocity", "endpoint"})
    vel = [c for c in res.cases if c.function == "velocity" and ".reject." not in c.id]
    assert vel and all(c.status == "fail" and 1.0 < c.worst < 11.0 for c in vel)
    assert all("np.float64" not in c.message for c in res.cases)
    reqs = res.by_requirement()
    assert reqs["F-1"]["status"] == "FAIL" and 1.0 < reqs["F-1"]["worst"] < 11.0
    assert reqs["E-5"]["status"] == "FAIL" and reqs["E-5"]["worst"] == np.inf
    lines = runner.format_summary(res).splitlines()
    f1 = next(line for line in lines if line.split()[:2] == ["FAIL", "F-1"])
    assert 1.0 < float(f1.split()[3]) < 11.0
    e5 = next(line for line in lines if line.split()[:2] == ["FAIL", "E-5"])
    assert e5.split()[2:5] == ["worst", "inf", "x"]
    rep = runner.report_dict(res)
    assert 1.0 < rep["requirements"]["F-1"]["worst"] < 11.0 and rep["requirements"]["E-5"]["worst"] == "inf"
    assert all(c["worst"] == "inf" or c["worst"] > 1.0 for c in rep["cases"] if c["status"] == "fail")
    json.dumps(rep, allow_nan=False)  # the report stays strict JSON


# ---------------------------------------------------------------- SystemExit and other BaseExceptions

def _exit(*_args):
    sys.exit(0)


def test_system_exit_in_a_case_fails_the_case(vector_files):
    """[CF-18], [CF-16] A case function or to_numpy raising SystemExit (any BaseException but
    KeyboardInterrupt) fails its case with one line naming the exception; KeyboardInterrupt stops the run."""
    res = runner.run(_Only(endpoint=_exit), files=vector_files, only={"endpoint"})
    assert not res.ok and res.counts["fail"] == res.counts["pass"] + res.counts["fail"] > 0
    ok_cases = [c for c in res.cases if not c.id.startswith("E.endpoint.reject.")]
    assert all(c.message.startswith("endpoint raised SystemExit: 0") for c in ok_cases), ok_cases[0].message
    rejects = [c for c in res.cases if c.id.startswith("E.endpoint.reject.")]
    assert rejects and all("invalid input must raise ValueError, endpoint raised SystemExit" in c.message
                           for c in rejects)
    assert all(c.worst == np.inf for c in res.cases)

    class ExitingConversion:
        name = "exiting-conversion"
        hard_weights = staticmethod(ReferenceAdapter().hard_weights)
        to_numpy = staticmethod(_exit)
    res = runner.run(ExitingConversion(), files=vector_files, only={"hard_weights"})
    # Reject cases raise before anything is converted; every other case fails at the conversion.
    converted = [c for c in res.cases if ".reject." not in c.id]
    assert not res.ok and converted and all("cannot convert" in c.message and "SystemExit" in c.message
                                            for c in converted)

    def interrupt(rule, d):
        raise KeyboardInterrupt
    with pytest.raises(KeyboardInterrupt):
        runner.run(_Only(endpoint=interrupt), files=vector_files, only={"endpoint"})


def test_cli_system_exit_is_never_a_pass(tmp_path):
    """[CF-18], [CF-16] From the command line: an adapter whose case function calls sys.exit(0) exits 1
    naming SystemExit; one that raises SystemExit while being imported exits 2 with one error line."""
    in_case = tmp_path / "exits_in_case.py"
    in_case.write_text("import sys\nname = 'exits'\n\ndef endpoint(rule, d):\n    sys.exit(0)\n")
    r = _cli("run", "--impl", str(in_case), "--only", "endpoint")
    assert r.returncode == 1, r.stdout + r.stderr
    assert "endpoint raised SystemExit: 0 (exits_in_case.py:5)" in r.stdout and "Traceback" not in r.stderr
    at_import = tmp_path / "exits_at_import.py"
    at_import.write_text("import sys\nsys.exit()\n")
    r = _cli("run", "--impl", str(at_import))
    assert r.returncode == 2 and r.stdout == "" and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines() == [f"python -m softrtc.conformance run: error: cannot import adapter module '{at_import}' for impl "
                                             f"'{at_import}': SystemExit"]
    with pytest.raises(AdapterError, match="SystemExit: 3"):
        bad = tmp_path / "exits_three.py"
        bad.write_text("raise SystemExit(3)\n")
        load_adapter(str(bad))


# ---------------------------------------------------------------- loading adapter files by path

_REF_ENDPOINT = ("from softrtc.conformance.adapters.reference import ReferenceAdapter\n"
                 "name = {name!r}\nendpoint = ReferenceAdapter().endpoint\n")


def test_adapter_file_named_like_a_standard_module(tmp_path):
    """[CF-12] `--impl dir/random.py` loads that file, not the standard `random`, and leaves `random`
    intact; a package directory named like a standard package (json/) keeps its relative imports."""
    import random
    f = tmp_path / "random.py"
    f.write_text(_REF_ENDPOINT.format(name="my-random"))
    a = load_adapter(str(f))
    assert a.name == "my-random" and a.__file__ == str(f.resolve())
    assert sys.modules["random"] is random and callable(random.random)
    pkg = tmp_path / "json"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "helper.py").write_text(_REF_ENDPOINT.format(name="pkg-json"))
    (pkg / "adapter.py").write_text("from .helper import endpoint, name\n")
    b = load_adapter(f"{pkg / 'adapter.py'}")
    assert b.name == "pkg-json" and sys.modules["json"] is json
    r = _cli("run", "--impl", str(f), "--only", "endpoint")
    assert r.returncode == 0 and "adapter 'my-random'" in r.stdout, r.stdout + r.stderr


def test_generate_rejects_file_as_out_dir(tmp_path):
    """[CF-1], [N-7] generate() names its argument when given a file instead of a directory."""
    f = tmp_path / "file"
    f.write_text("")
    with pytest.raises(ValueError, match="out_dir"):
        generate.generate(f)


def test_run_records_its_own_duration_with_the_runner_clock(monkeypatch, vector_files):
    """[CF-17] The duration a run reports (the figure [CF-17]'s targets are stated in, measured by `softrtc
    conformance run`) is the runner's clock from before the vectors are read to after the child stops; here an
    injected clock reads 100.0 at the start and 130.25 at the end."""
    import time as real_time

    readings = iter([100.0, 130.25])

    class Clock:
        def perf_counter(self):
            return next(readings)

        def __getattr__(self, name):
            return getattr(real_time, name)

    class ByHand:
        """hard_weights written out: 1 on the first d tokens ([W-8])."""
        name = "by-hand"

        def hard_weights(self, H, d):
            return [1.0] * d + [0.0] * (H - d)

    monkeypatch.setattr(runner, "time", Clock())
    res = runner.run(ByHand(), files=vector_files, only=["hard_weights"])
    assert res.counts["pass"] > 0  # its valid-input cases pass; it checks no inputs, so the error cases fail
    assert res.seconds == 30.25
    with pytest.raises(StopIteration):
        next(readings)  # exactly two readings: no other use of the run's clock
