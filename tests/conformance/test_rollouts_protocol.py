"""Conformance rollouts across processes and files (spec/42-rollouts.md): the child protocol with its field
requests, the JavaScript port, the rollout vectors and their replay, the command's reports and exit status."""

from __future__ import annotations

import json
import shutil
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

from softrtc.cli import main as cli_main
from softrtc.conformance import rollout, rollout_vectors
from softrtc.conformance.rollout_loop import Settings

ROOT = Path(__file__).resolve().parents[2]
NODE = shutil.which("node")
JS = ROOT / "conformance" / "ports" / "js" / "rollout.js"
needs_node = pytest.mark.skipif(NODE is None, reason="node (Node.js 20+) not installed")
ALL = ("naive", "train_hard", "train_soft", "inference_hard", "inference_soft")


@needs_node
def test_js_port_passes_in_closed_loop_and_on_the_vectors():
    """CR-4, CR-1, CR-10, CR-11, X-3, X-4, R-4, G-3 The JavaScript port, asking the runner for every field value
    and VJP, makes every chunk of short episodes of all five methods and every recorded request within a
    millionth of the tolerance (it computes in float64 on the served float32 field)."""
    out = rollout.run(impl_cmd=f"{NODE} {JS}", settings=Settings(ALL, 1, (1, 2, 3, 4, 5), 25))
    res = out["result"]
    assert res.ok and res.isolation == "child process" and res.adapter_name == "softrtc-js", \
        rollout.summary_text(out)
    assert max(c.worst for c in res.cases) < 1e-6
    rep = rollout_vectors.replay(impl_cmd=f"{NODE} {JS}")["result"]
    assert rep.ok and rep.counts["pass"] == 200 and max(c.worst for c in rep.cases) < 1e-6


CHILD = r'''
import json, sys
print(json.dumps({"protocol": "softrtc-conformance", "version": 1, "name": "probe", "functions": ["rollout_chunk"]}),
      flush=True)
for line in sys.stdin:
    req = json.loads(line)
    print(json.dumps({"id": req["id"], "field": "velocity", "x": [[0.0]], "t": [0.0]}), flush=True)
    ans = json.loads(sys.stdin.readline())
    if req["args"]["prev"] is not None:
        print("not a reply", flush=True)
        continue
    print(json.dumps({"id": req["id"], "error": {"kind": "exception", "type": "Probe", "message": ans["error"]}}),
          flush=True)
'''


def test_child_field_request_refused_and_broken_child_replaced(tmp_path):
    """CR-4, CR-6, CF-30 A field request with a wrong shape is answered with an error naming the argument, not
    served; the child's error reply fails the request and ends the episode, whose first request it names."""
    probe = tmp_path / "probe.py"
    probe.write_text(CHILD)
    out = rollout.run(impl_cmd=f"{sys.executable} {probe}", settings=Settings(("naive",), 2, (1,), 20))
    res = out["result"]
    assert not res.ok and res.counts["pass"] == 0
    assert all(ep.requests == 0 and ep.error.startswith("request 0") for ep in out["episodes"])
    assert "field request refused" in res.cases[0].message and "x must" in res.cases[0].message


def test_rollout_vectors_content_and_integrity(tmp_path):
    """CR-10, CF-25 The shipped rollout vectors: 200 requests of 2 episodes of each of the five methods, at most
    20 requests each, every delay 0..5, early and late arrivals, under 1 MB, the served checkpoint named with
    its digest; a copy changed by one digit or of another format major version is refused."""
    header, cases = rollout_vectors.load()
    assert len(cases) == 200 and set(header["methods"]) == set(ALL)
    assert header["checkpoint"] == "softrtc/arm/checkpoints/drift/base.npz" and len(header["checkpoint_sha256"]) == 64
    per_episode = {}
    for c in cases:
        per_episode.setdefault(c["id"].rsplit(".r", 1)[0], []).append(c)
    assert len(per_episode) == 10 and all(len(v) <= 20 for v in per_episode.values())
    args = [c["args"] for c in cases]
    assert {a["d"] for a in args} == {0, 1, 2, 3, 4, 5}
    assert any(a["arrival"] > a["d"] for a in args) and any(a["arrival"] < a["d"] for a in args)
    folder = rollout_vectors.rollouts_dir()
    assert (folder / rollout_vectors.FILE).stat().st_size < 1_000_000
    bad = tmp_path / "rollouts"
    shutil.copytree(folder, bad)
    raw = (bad / rollout_vectors.FILE).read_text()
    (bad / rollout_vectors.FILE).write_text(raw.replace('"d":1,', '"d":2,', 1))
    with pytest.raises(ValueError, match="SHA-256"):
        rollout_vectors.load(bad)
    idx = json.loads((folder / "index.json").read_text())
    idx["format_version"] = "2.0"
    text = raw.replace('"format_version":"1.0"', '"format_version":"2.0"')
    (bad / rollout_vectors.FILE).write_text(text)
    import hashlib
    idx["files"][rollout_vectors.FILE]["sha256"] = hashlib.sha256(text.encode()).hexdigest()
    (bad / "index.json").write_text(json.dumps(idx))
    with pytest.raises(ValueError, match="format_version"):
        rollout_vectors.load(bad)


@pytest.mark.parametrize("impl", ["torch", "torch-flipped", "jax"])
def test_libraries_pass_the_rollout_vectors(impl):
    """CR-10, CR-11, CR-5 The PyTorch library (both conventions) and the JAX twin answer every recorded request
    within a tenth of its tolerance."""
    res = rollout_vectors.replay(impl, in_process=True)["result"]
    assert res.ok and res.counts["pass"] == 200, rollout.format_summary(res)
    assert max(c.worst for c in res.cases) < 0.1


def test_mutant_fails_the_rollout_vectors_with_its_diagnosis():
    """CR-10, CR-9, X-3 The prior-shift mutant fails recorded requests of the blended and guided methods, each
    diagnosed [X-3]; its naive requests pass."""
    res = rollout_vectors.replay("mutant-prior-shift", in_process=True)["result"]
    failed = [c for c in res.cases if c.status == "fail"]
    assert failed and all("X-3" in c.requirements and "diagnosis [X-3]" in c.message for c in failed)
    assert all(c.status == "pass" for c in res.cases if ".naive." in c.id)


def test_command_reports_and_exit_status(tmp_path, capsys):
    """CR-8, CR-6, CR-7, CF-15 The command writes the JSON report (with the rollout section), JUnit XML (one
    testcase per output of each request) and the effect file; a mutant exits 1 with its failing requirement in
    the summary, an implementation that cannot be loaded exits 2 with one error line."""
    rep, junit, eff = tmp_path / "r.json", tmp_path / "r.xml", tmp_path / "e.json"
    code = cli_main(["conformance", "rollout", "--impl", "mutant-late-dropped", "--in-process", "--methods", "naive",
                     "--episodes", "1", "--max-steps", "60", "--delays", "1,2", "--report", str(rep),
                     "--junit", str(junit), "--effect", str(eff)])
    text = capsys.readouterr().out
    assert code == 1 and "FAIL        R-4" in text and "first divergence at request" in text
    doc = json.loads(rep.read_text())
    assert doc["ok"] is False and doc["requirements"]["R-4"]["status"] == "FAIL"
    assert doc["rollout"]["settings"]["max_steps"] == 60 and len(doc["rollout"]["episodes"]) == 1
    cases = ET.parse(junit).getroot().iter("testcase")
    assert sum(1 for _ in cases) == len(doc["cases"]) == 2 * doc["rollout"]["episodes"][0]["requests"]
    effect = json.loads(eff.read_text())
    assert set(effect["paired"]) == {"naive"} and effect["first_divergence"][0]["method"] == "naive"
    assert cli_main(["conformance", "rollout", "--impl", str(tmp_path / "missing.py"), "--in-process"]) == 2
    assert "softrtc conformance rollout: error:" in capsys.readouterr().err


NESTED = r'''
import json, sys
print(json.dumps({"protocol": "softrtc-conformance", "version": 1, "name": "nested", "functions": ["rollout_chunk"]}),
      flush=True)
for line in sys.stdin:
    print("[" * 100000 + "]" * 100000, flush=True)
'''


def test_deeply_nested_reply_fails_the_request_in_one_line(tmp_path):
    """CR-6, CF-18 A reply nested deeper than the JSON parser follows fails its request with one protocol-error
    line; the runner does not crash with a RecursionError."""
    probe = tmp_path / "nested.py"
    probe.write_text(NESTED)
    out = rollout.run(impl_cmd=f"{sys.executable} {probe}", settings=Settings(("naive",), 1, (1,), 20))
    res = out["result"]
    assert not res.ok and res.counts["pass"] == 0
    assert "protocol error" in res.cases[0].message and "\n" not in res.cases[0].message


@pytest.mark.parametrize("opt,value,msg", [("--episodes", "\u0661", "episodes must be an integer in [1, 10000]"),
                                           ("--delays", "0,\u0663", "each delay must be an integer in [0, 5]"),
                                           ("--max-steps", "1001", "max_steps must be an integer in [1, 1000]"),
                                           ("--seed", "-1", "seed must be an integer in [0, 2147483647]"),
                                           ("--case-timeout", "nan", "case_timeout must be a finite number")])
def test_rollout_options_checked_at_the_door(capsys, opt, value, msg):
    """N-11, CR-1 Options of `conformance rollout` take ASCII digits within the library's ranges; anything else
    is one usage error (status 2) before any episode runs."""
    with pytest.raises(SystemExit) as exc:
        cli_main(["conformance", "rollout", "--impl", "reference", opt, value])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert msg in err and "Traceback" not in err
