"""The rollout vectors inside `softrtc conformance run` (spec/42-rollouts.md [CR-10], spec/40-conformance.md
[CF-13]): replayed after the other cases on the served field, in the same summary, JSON and JUnit reports;
unsupported for an implementation without rollout_chunk; left out on request, with the run saying so.

The runs use a copy of the shipped vectors whose rollout file is cut to the first CUT requests of the first
episode of each method (re-indexed), so each test replays 15 recorded requests instead of 200."""

from __future__ import annotations

import hashlib
import json
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from softrtc.cli import main as cli_main
from softrtc.conformance import rollout_vectors, runner
from softrtc.conformance.results import UNSUPPORTED_CASE

ROOT = Path(__file__).resolve().parents[2]
VECTORS = ROOT / "conformance" / "vectors"
CUT = 3
METHODS = ("naive", "train_hard", "train_soft", "inference_hard", "inference_soft")
N_ROLLOUT = CUT * len(METHODS)  # 15 requests: 5 first requests (prev None) and 10 blended or guided ones

REFERENCE_PLUS = """from softrtc.conformance.adapters.reference import ReferenceAdapter
from softrtc.conformance.rollout_impls import MUTANTS, ReferenceRollout
name = "{name}"
endpoint = ReferenceAdapter().endpoint
{extra}
"""


@pytest.fixture(scope="module")
def cut_vectors(tmp_path_factory) -> Path:
    """The shipped vectors with rollouts/rollouts_arm.json cut to requests r000..r002 of ep000 of each method,
    alone in rollouts/ (any other world's file removed), its index.json rewritten for it (digest, case count)."""
    d = tmp_path_factory.mktemp("cut") / "vectors"
    shutil.copytree(VECTORS, d)
    folder = d / "rollouts"
    doc = json.loads((folder / rollout_vectors.FILE).read_text())
    keep = {f"CR.arm.{m}.ep000.r{c:03d}" for m in METHODS for c in range(CUT)}
    doc["cases"] = [c for c in doc["cases"] if c["id"] in keep]
    assert len(doc["cases"]) == N_ROLLOUT
    text = json.dumps(doc, sort_keys=True)
    (folder / rollout_vectors.FILE).write_text(text)
    for other in folder.iterdir():
        if other.name not in (rollout_vectors.FILE, "index.json"):
            other.unlink()
    index = json.loads((folder / "index.json").read_text())
    entry = dict(index["files"][rollout_vectors.FILE], cases=N_ROLLOUT, sha256=hashlib.sha256(text.encode()).hexdigest())
    index["files"] = {rollout_vectors.FILE: entry}
    (folder / "index.json").write_text(json.dumps(index))
    return d


def _endpoint_cases() -> int:
    return sum(1 for p in VECTORS.glob("*.json") if p.name != "index.json"
               for c in json.loads(p.read_text())["cases"] if c["function"] == "endpoint")


def _adapter(tmp_path, name: str, extra: str) -> Path:
    f = tmp_path / f"{name}.py"
    f.write_text(REFERENCE_PLUS.format(name=name, extra=extra))
    return f


def test_reference_passes_the_rollout_vectors_in_the_same_reports(cut_vectors, tmp_path, capsys):
    """CR-10, CR-8, CF-13, CF-14, CF-15 `conformance run --impl reference` replays the rollout vectors after the
    other cases, in a child of their own on the served field: every recorded request passes, named
    CR.arm.METHOD.epNNN.rNNN, in the same summary (a line naming the rollout file and its digest), JSON report
    (a `rollouts` section) and JUnit XML (a testsuite of their own with the file's SHA-256)."""
    rep, junit = tmp_path / "r.json", tmp_path / "r.xml"
    code = cli_main(["conformance", "run", "--impl", "reference", "--vectors", str(cut_vectors),
                     "--only", "endpoint,rollout_chunk", "--report", str(rep), "--junit", str(junit)])
    out = capsys.readouterr().out
    assert code == 0, out
    lines = out.splitlines()
    assert lines[2].startswith(f"rollout vectors: {cut_vectors.resolve()}/rollouts/rollouts_arm.json "
                               f"({N_ROLLOUT} cases"), lines[:3]
    assert any(line.split()[:2] == ["PASS", "CR-10"] and f"{N_ROLLOUT} cases" in line for line in lines), out
    doc = json.loads(rep.read_text())
    rolled = [c for c in doc["cases"] if c["function"] == "rollout_chunk"]
    assert len(doc["cases"]) == _endpoint_cases() + N_ROLLOUT and len(rolled) == N_ROLLOUT
    assert {c["id"] for c in rolled} == {f"CR.arm.{m}.ep000.r{c:03d}" for m in METHODS for c in range(CUT)}
    assert all(c["status"] == "pass" and c["worst"] <= 1e-6 for c in rolled)
    want_sha = hashlib.sha256((cut_vectors / "rollouts" / rollout_vectors.FILE).read_bytes()).hexdigest()
    entry = doc["rollouts"]["files"][rollout_vectors.FILE]
    assert doc["rollouts"]["status"] == "run" and entry["cases"] == N_ROLLOUT and entry["env"] == "arm"
    assert entry["sha256"] == want_sha and entry["field"] == "softrtc/arm/checkpoints/drift/base.npz"
    suite = next(s for s in ET.parse(junit).getroot().iter("testsuite") if s.get("name") == "conformance.rollouts_arm")
    assert int(suite.get("tests")) == N_ROLLOUT and int(suite.get("failures")) == 0
    props = {p.get("name"): p.get("value") for p in suite.find("properties")}
    assert props["vector_file_sha256"] == want_sha


def test_a_mutant_fails_the_rollout_vectors_with_its_diagnosis(cut_vectors, tmp_path, capsys):
    """CR-10, CR-9, X-3, CF-16 An adapter whose rollout_chunk shifts the prior by s - 1 (mutant-prior-shift)
    passes its endpoint cases and the first requests (no prior), fails every blended or guided recorded request
    with the diagnosis [X-3], and the run exits 1."""
    f = _adapter(tmp_path, "prior_shift",
                 "rollout_chunk = ReferenceRollout('prior-shift', **MUTANTS['mutant-prior-shift']).rollout_chunk")
    rep = tmp_path / "r.json"
    code = cli_main(["conformance", "run", "--impl", str(f), "--vectors", str(cut_vectors),
                     "--only", "endpoint,rollout_chunk", "--report", str(rep)])
    out = capsys.readouterr().out
    assert code == 1, out
    cases = json.loads(rep.read_text())["cases"]
    rolled = {c["id"]: c for c in cases if c["function"] == "rollout_chunk"}
    first = {cid for cid in rolled if cid.endswith(".r000")}
    assert len(first) == len(METHODS) and all(rolled[cid]["status"] == "pass" for cid in first)
    later = [c for cid, c in rolled.items() if cid not in first and ".naive." not in cid]
    assert len(later) == (CUT - 1) * (len(METHODS) - 1)
    assert all(c["status"] == "fail" and "X-3" in c["requirements"] and "diagnosis [X-3]" in c["message"]
               for c in later)
    assert all(c["status"] == "pass" for c in cases if c["function"] == "endpoint")
    assert any(line.split()[:2] == ["FAIL", "X-3"] for line in out.splitlines()), out


def test_an_implementation_without_rollout_chunk_has_them_unsupported(cut_vectors, tmp_path, capsys):
    """CR-10, CF-9, CF-16 A Python adapter without rollout_chunk (in a child) and a program whose hello line
    does not list it (--impl-cmd) get every recorded request unsupported, never failed, without the field
    being loaded: exit 0 with the endpoint cases passing, 1 when nothing else ran."""
    f = _adapter(tmp_path, "no_rollouts", "")
    rep = tmp_path / "r.json"
    code = cli_main(["conformance", "run", "--impl", str(f), "--vectors", str(cut_vectors),
                     "--only", "endpoint,rollout_chunk", "--report", str(rep)])
    out = capsys.readouterr().out
    assert code == 0, out
    doc = json.loads(rep.read_text())
    assert doc["counts"] == {"pass": _endpoint_cases(), "fail": 0, "unsupported": N_ROLLOUT}
    entry = doc["rollouts"]["files"][rollout_vectors.FILE]
    assert doc["rollouts"]["status"] == entry["status"] == "unsupported" and "field_load_seconds" not in entry
    assert f"unsupported (adapter lacks the function): rollout_chunk ({N_ROLLOUT} cases)" in out
    assert "all unsupported: adapter has no rollout_chunk" in out.splitlines()[2]
    host = f"{sys.executable} -m softrtc.conformance.host --impl reference"
    code = cli_main(["conformance", "run", "--impl-cmd", host, "--vectors", str(cut_vectors),
                     "--only", "rollout_chunk", "--report", str(rep)])
    out = capsys.readouterr().out
    doc = json.loads(rep.read_text())
    assert code == 1 and doc["counts"] == {"pass": 0, "fail": 0, "unsupported": N_ROLLOUT}, out
    assert "its hello line does not list it" in doc["rollouts"]["reason"]


class _NaiveOnly:
    """An in-process adapter whose rollout_chunk has the naive sampler only ([CR-2])."""

    name = "naive-only"

    def __init__(self):
        from softrtc.conformance.rollout_impls import ReferenceRollout

        self._ref = ReferenceRollout()

    def rollout_chunk(self, field, obs, prev, noise, method, **rest):
        if method != "naive":
            raise NotImplementedError(f"method {method}")
        return self._ref.rollout_chunk(field, obs, prev, noise, method, **rest)


def test_a_method_the_implementation_lacks_is_unsupported(cut_vectors):
    """CR-2, CR-10, CF-26 NotImplementedError for a method makes its recorded requests unsupported (per case),
    the naive ones pass, and the run succeeds."""
    res = runner.run(_NaiveOnly(), cut_vectors, only={"rollout_chunk"}, in_process=True)
    assert res.ok and res.counts == {"pass": CUT, "fail": 0, "unsupported": N_ROLLOUT - CUT}
    assert all((c.status == "pass") == (".naive." in c.id) for c in res.cases)
    assert all(c.message.startswith(UNSUPPORTED_CASE) and "method" in c.message
               for c in res.cases if c.status == "unsupported")


def test_no_rollouts_leaves_them_out_and_says_so(cut_vectors, tmp_path, capsys):
    """CR-10, CF-13, CF-39 --no-rollouts runs the other cases only and says on its third line and in the report
    that the rollout vectors were left out; a vector folder without rollouts/ says so too; rollout vectors that
    do not match their index stop the run before any case (exit 2, one line), as [CF-25]."""
    rep = tmp_path / "r.json"
    code = cli_main(["conformance", "run", "--impl", "reference", "--vectors", str(cut_vectors), "--no-rollouts",
                     "--report", str(rep)])
    out = capsys.readouterr().out
    assert code == 0 and out.splitlines()[2] == "rollout vectors: skipped, left out (--no-rollouts)", out
    doc = json.loads(rep.read_text())
    assert doc["rollouts"] == {"status": "skipped", "reason": "left out (--no-rollouts)"}
    n_cf = sum(len(json.loads(p.read_text())["cases"]) for p in VECTORS.glob("*.json") if p.name != "index.json")
    assert len(doc["cases"]) == n_cf and not any(c["function"] == "rollout_chunk" for c in doc["cases"])

    bare = tmp_path / "bare"
    shutil.copytree(cut_vectors, bare, ignore=shutil.ignore_patterns("rollouts"))
    res = runner.run("reference", bare, only={"endpoint", "rollout_chunk"})
    assert res.ok and res.rollouts["status"] == "skipped" and "has no rollouts/" in res.rollouts["reason"]
    assert not any(c.function == "rollout_chunk" for c in res.cases)

    broken = tmp_path / "broken"
    shutil.copytree(cut_vectors, broken)
    f = broken / "rollouts" / rollout_vectors.FILE
    f.write_text(f.read_text().replace('"d": 1,', '"d": 2,', 1))
    code = cli_main(["conformance", "run", "--impl", "reference", "--vectors", str(broken)])
    captured = capsys.readouterr()
    assert code == 2 and captured.out == "" and len(captured.err.strip().splitlines()) == 1, captured
    assert "SHA-256" in captured.err and rollout_vectors.FILE in captured.err


def test_rollouts_argument_checked_and_only_takes_rollout_chunk(capsys):
    """CF-13, N-7 `rollouts` must be None or a bool; --only names rollout_chunk among its choices."""
    with pytest.raises(ValueError, match="rollouts must be None, True or False"):
        runner.run("reference", rollouts="yes")
    with pytest.raises(SystemExit):
        cli_main(["conformance", "run", "--impl", "reference", "--only", "rollout"])
    assert "rollout_chunk" in capsys.readouterr().err


def test_a_runner_without_jax_skips_them_and_says_why(cut_vectors, monkeypatch):
    """CR-10, CF-16 A runner that cannot serve the field (a NumPy-only install: no JAX, Flax or pymunk) leaves
    the rollout vectors out, naming the missing module and the extra to install, and judges the rest."""
    needs = dict(rollout_vectors.NEEDS, arm=(("numpy", "softrtc_no_such_module"), "arm"))
    monkeypatch.setattr(rollout_vectors, "NEEDS", needs)
    res = runner.run("reference", cut_vectors, only={"endpoint", "rollout_chunk"})
    assert res.ok and res.counts == {"pass": _endpoint_cases(), "fail": 0, "unsupported": 0}
    entry = res.rollouts["files"][rollout_vectors.FILE]
    assert res.rollouts["status"] == entry["status"] == "skipped" and entry["cases"] == N_ROLLOUT
    assert "missing module softrtc_no_such_module" in entry["reason"] == res.rollouts["reason"]
    assert "pip install 'softrtc[arm]'" in runner.format_summary(res).splitlines()[2]
