"""LeRobot's RTC through the conformance runner, and its compatibility report (spec/41-thirdparty.md)."""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("lerobot")

from softrtc.conformance import report, report_case, runner  # noqa: E402
from softrtc.conformance.adapter import ALTERNATES  # noqa: E402
from softrtc.conformance.adapters import lerobot_notes  # noqa: E402
from softrtc.conformance.adapters.lerobot import ADAPTER, INSTALL_HINT, RTCConfig, RTCProcessor, _schedule  # noqa: E402
from softrtc.reference import guidance, velocity  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
REPORT_MD = ROOT / "conformance" / "thirdparty" / "lerobot" / "lerobot-0.4.4.md"
REPORT_JSON = REPORT_MD.with_suffix(".json")
README = ROOT / "docs" / "reports" / "lerobot.md"


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


@pytest.fixture(scope="module")
def fresh_report():
    return report.build("lerobot")


def _guidance_file(vector_files) -> dict:
    return next(d for d in vector_files if d["_file"].endswith("guidance.json"))


def _weights(H, d, e, schedule):
    return RTCProcessor(RTCConfig(prefix_attention_schedule=_schedule(schedule))).get_prefix_weights(d, e, H).numpy()


def test_committed_report_matches_a_fresh_run(fresh_report):
    """[TP-1] [TP-2] [TP-4] The committed report and its JSON agree with a fresh run of LeRobot through the
    runner (numbers within the rounding tolerance), and the Markdown is the rendering of the JSON.
    Regenerate with: softrtc conformance report --impl lerobot --out conformance/thirdparty/lerobot/lerobot-0.4.4.md"""
    committed = json.loads(REPORT_JSON.read_text())
    assert report.differences(committed, json.loads(report.json_text(fresh_report))) == []
    assert REPORT_MD.read_text() == report.render(committed)
    # what the report must hold: versions, every failing id diagnosed with a smallest case, reasons
    assert committed["versions"]["implementation"]["lerobot"] == "0.4.4"
    for rid, f in committed["failing"].items():
        assert committed["requirements"][rid]["status"] == "FAIL" and f["diagnosis"] and f["cases"]
        assert all("expected" in c or "raised" in str(c["actual"]) for c in f["cases"])
    unsupported_ids = [r for r, e in committed["requirements"].items() if e["unsupported"]]
    assert sorted(committed["unsupported"]) == sorted(unsupported_ids)
    assert all(u["why"] for u in committed["unsupported"].values())


def test_report_counts_equal_the_runner_on_its_own(vector_files, fresh_report):
    """[TP-2] [CF-14] The report's counts are the runner's: the same adapter run by `runner.run` gives the same
    pass / fail / unsupported totals and the same failing ids."""
    res = runner.run(ADAPTER, files=vector_files)
    assert fresh_report["counts"] == res.counts
    assert sorted(fresh_report["failing"]) == sorted(r for r, e in res.by_requirement().items() if e["status"] == "FAIL")


def test_readme_holds_the_summary_of_the_committed_report():
    """[TP-5] The LeRobot compatibility page's summary is `softrtc conformance report --summary
    conformance/thirdparty/lerobot/lerobot-0.4.4.json`, verbatim between its markers."""
    text = README.read_text()
    m = re.search(r"<!-- lerobot-summary:start -->\n(.*?)<!-- lerobot-summary:end -->", text, re.S)
    assert m, "docs/reports/lerobot.md lacks the lerobot-summary markers"
    assert m.group(1) == report.summary(json.loads(REPORT_JSON.read_text()))


def test_guided_chunks_are_the_reference_without_the_field_vjp(vector_files):
    """[G-3] [TP-3] The G-3 diagnosis, checked: on every guided case LeRobot's chunk equals the NumPy reference's
    guided sampler whose field VJP is replaced by zero (pull-back = weighted error), within float32 error, and
    differs from the reference with the VJP wherever some weight is nonzero."""
    data = _guidance_file(vector_files)

    class NoJacobian(velocity.ReferenceVelocityField):
        def vjp(self, obs, x, t, cotangent):
            return np.zeros_like(np.asarray(x, dtype=np.float64))

    cases = [c for c in data["cases"] if c["function"] == "guided_sample"]
    assert len(cases) >= 10
    form = ALTERNATES["guided_sample"]
    for case in cases:
        a = case["args"]
        args = [report_case._argument(k, a[k], data, form.fn, True) for k in form.fn.args]
        chunk, _ = getattr(ADAPTER, form.name)(*args)
        chunk = chunk.numpy().astype(np.float64)
        params = data["fields"][a["field"]]["params"]
        inputs = [np.asarray(a[k], dtype=np.float64) for k in ("obs", "noise", "prior", "weights")]
        no_jac = guidance.guided_sample(NoJacobian(params), *inputs, a["T"], a["max_guidance"])
        full = guidance.guided_sample(velocity.ReferenceVelocityField(params), *inputs, a["T"], a["max_guidance"])
        np.testing.assert_allclose(chunk, no_jac, atol=2e-6, rtol=2e-6, err_msg=case["id"])
        if np.any(inputs[3] > 0):
            assert np.max(np.abs(chunk - full)) > 1e-2, case["id"]
        else:  # W = 0: guidance has nothing to pull, both are the naive sampler ([G-6])
            np.testing.assert_allclose(chunk, full, atol=2e-6, rtol=2e-6, err_msg=case["id"])


def test_lerobot_prefix_weights_are_the_spec_weights_as_mapped_in_v4():
    """[V-4] [W-4] [W-2] LeRobot's get_prefix_weights(d, E, H) against hand-computed weights: the worked example
    of [W-4] (d = 2, e = 6, H = 10, linear), the ZEROS schedule as hard weights, the end winning for d > E
    (the alternative of [W-2]) and E > H ending the window at H."""
    np.testing.assert_allclose(_weights(10, 2, 6, "linear"), [1, 1, .8, .6, .4, .2, 0, 0, 0, 0], atol=1e-7)
    np.testing.assert_array_equal(_weights(6, 2, 6, "zeros"), [1, 1, 0, 0, 0, 0])
    np.testing.assert_array_equal(_weights(6, 3, 5, "ones"), [1, 1, 1, 1, 1, 0])
    np.testing.assert_array_equal(_weights(8, 3, 2, "linear"), [1, 1, 0, 0, 0, 0, 0, 0])  # end wins
    np.testing.assert_allclose(_weights(8, 3, 9, "linear"), [1, 1, 1, 5 / 6, 4 / 6, 3 / 6, 2 / 6, 1 / 6], atol=1e-7)


def test_lerobot_guided_window_ends_at_the_left_over():
    """[V-4] [W-6] LeRobot's guided step lowers execution_horizon to the rows of the left-over it is given (the clip
    of [W-6]): with H = 8, d = 1 and a left-over of 3 rows, E = 6 guides tokens 0..2 with 1, 2/3, 1/3."""
    import torch
    proc = RTCProcessor(RTCConfig(enabled=True, prefix_attention_schedule=_schedule("linear"), debug=True))
    x = torch.zeros(8, 2)
    proc.denoise_step(x, torch.ones(3, 2), 1, 0.5, lambda z: torch.zeros_like(z), execution_horizon=6)
    w = proc.get_all_debug_steps()[-1].weights.reshape(-1).numpy()
    np.testing.assert_allclose(w, [1, 2 / 3, 1 / 3, 0, 0, 0, 0, 0], atol=1e-7)


def test_queue_executes_the_committed_prefix_then_the_new_chunk():
    """[X-4] [V-4] The adapter's executor on LeRobot's ActionQueue, H = 6, s = 3, delays 0, 2: steps 0..2 run
    chunk 0's tokens 0..2, steps 3..4 its tokens 3..4 (the committed prefix), step 5 chunk 1's token 2."""
    chunks = np.arange(2 * 6 * 1, dtype=np.float64).reshape(2, 6, 1)
    out = ADAPTER.execute_chunks(chunks, np.array([0, 2]), 3)
    np.testing.assert_array_equal(out["chunk_index"].numpy(), [0, 0, 0, 0, 0, 1])
    np.testing.assert_array_equal(out["token_index"].numpy(), [0, 1, 2, 3, 4, 2])
    np.testing.assert_array_equal(out["actions"].numpy().ravel(), [0, 1, 2, 3, 4, 8])


@pytest.mark.slow  # a fresh interpreter imports torch and torch._dynamo (LeRobot's debug tracker uses it)
def test_importing_the_adapter_loads_no_dataset_or_vision_stack():
    """[TP-6] Importing the LeRobot adapter in a fresh process imports LeRobot's three RTC modules from the
    installed package and none of datasets, torchvision, transformers, huggingface_hub, draccus; the bare
    lerobot.policies package used while importing them is gone afterwards."""
    code = ("import json, sys\n"
            "import softrtc.conformance.adapters.lerobot as a\n"
            "heavy = [m for m in ('datasets', 'torchvision', 'transformers', 'huggingface_hub', 'draccus', "
            "'lerobot.datasets') if m in sys.modules]\n"
            "rtc = sorted(m for m in sys.modules if m.startswith('lerobot.policies.rtc.'))\n"
            "print(json.dumps({'heavy': heavy, 'rtc': rtc, 'stub': 'lerobot.policies' in sys.modules, "
            "'file': a.RTCProcessor.__module__ and sys.modules[a.RTCProcessor.__module__].__file__}))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300, check=True)
    got = json.loads(out.stdout.strip().splitlines()[-1])
    assert got["heavy"] == [] and got["stub"] is False
    assert {"lerobot.policies.rtc.modeling_rtc", "lerobot.policies.rtc.action_queue",
            "lerobot.policies.rtc.configuration_rtc"} <= set(got["rtc"])
    assert Path(got["file"]).parts[-4:] == ("lerobot", "policies", "rtc", "modeling_rtc.py")


def test_missing_lerobot_names_the_install_step():
    """[TP-6] [TP-1] Without LeRobot the adapter's import fails with the install step, and the report command
    gives one error line with exit status 2."""
    code = ("import sys\nsys.modules['lerobot'] = None\n"
            "from softrtc.conformance.cli import main\n"
            "sys.exit(main(['report', '--impl', 'lerobot', '--out', sys.argv[1]]))\n")
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        out = subprocess.run([sys.executable, "-c", code, str(Path(tmp) / "r.md")], capture_output=True, text=True,
                             timeout=300)
        assert out.returncode == 2 and not list(Path(tmp).iterdir())
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("python -m softrtc.conformance report: error:")
    assert INSTALL_HINT in lines[0]


@pytest.fixture()
def small_vectors(tmp_path, monkeypatch):
    """The guidance vectors alone, without index.json: a quick run that still has failing and unsupported ids.
    N-12 fails only in the weights and sampler files, outside this subset, so its diagnosis is set aside here
    (a diagnosis of an id that does not fail stops the report, [TP-3])."""
    monkeypatch.setattr(lerobot_notes, "DIAGNOSES", {k: v for k, v in lerobot_notes.DIAGNOSES.items() if k != "N-12"})
    d = tmp_path / "vectors"
    d.mkdir()
    shutil.copy(ROOT / "conformance" / "vectors" / "guidance.json", d / "guidance.json")
    return d


def test_report_stops_when_a_note_is_missing_or_stale(small_vectors, monkeypatch):
    """[TP-3] A failing id without a diagnosis, a diagnosis missing a failing function, a diagnosis of an id that
    passes, and an absent function without a reason each stop the report with a message naming it."""
    diags = dict(lerobot_notes.DIAGNOSES)
    monkeypatch.setattr(lerobot_notes, "DIAGNOSES", {k: v for k, v in diags.items() if k != "G-3"})
    with pytest.raises(report.ReportError, match=r"G-3 fails but .* has no diagnosis"):
        report.build("lerobot", small_vectors)
    narrowed = dict(diags, **{"G-4": dict(diags["G-4"], functions=["guided_sample"])})
    monkeypatch.setattr(lerobot_notes, "DIAGNOSES", narrowed)
    with pytest.raises(report.ReportError, match=r"G-4 fails in \['guidance_weight'\]"):
        report.build("lerobot", small_vectors)
    monkeypatch.setattr(lerobot_notes, "DIAGNOSES", dict(diags, **{"G-6": diags["G-3"]}))
    with pytest.raises(report.ReportError, match=r"diagnoses \['G-6'\], which do not fail"):
        report.build("lerobot", small_vectors)
    monkeypatch.setattr(lerobot_notes, "DIAGNOSES", diags)
    monkeypatch.setattr(lerobot_notes, "UNSUPPORTED_FUNCTIONS", {})
    metrics = small_vectors.parent / "metrics_only"
    metrics.mkdir()
    shutil.copy(ROOT / "conformance" / "vectors" / "metrics.json", metrics / "metrics.json")
    with pytest.raises(report.ReportError, match=r"no reason why \w+ is unsupported"):
        report.build("lerobot", metrics)


def test_check_and_summary_commands(small_vectors, tmp_path, capsys):
    """[TP-1] [TP-4] [TP-5] The command writes the report and its JSON, --check passes on them and fails (status 1)
    once a number moves beyond the tolerance, --summary prints the README summary, bad options exit 2."""
    parser = argparse.ArgumentParser()
    report.add_arguments(parser)

    def run(*argv):
        return report.run_from_args(parser.parse_args(list(argv)))

    out = tmp_path / "r" / "lerobot.md"
    assert run("--impl", "lerobot", "--out", str(out), "--vectors", str(small_vectors)) == 0
    doc = json.loads(out.with_suffix(".json").read_text())
    assert out.read_text() == report.render(doc) and "## Failing requirements" in out.read_text()
    assert run("--impl", "lerobot", "--out", str(out), "--vectors", str(small_vectors), "--check") == 0
    assert run("--summary", str(out.with_suffix(".json"))) == 0
    assert capsys.readouterr().out.endswith(report.summary(doc))
    doc["counts"]["pass"] += 1
    out.with_suffix(".json").write_text(report.json_text(doc))
    assert run("--impl", "lerobot", "--out", str(out), "--vectors", str(small_vectors), "--check") == 1
    text = capsys.readouterr().out
    assert "report.counts.pass" in text and "stale" in text
    assert run("--impl", "nope", "--out", str(out)) == 2
    assert run("--impl", "lerobot", "--out", str(tmp_path / "r.txt")) == 2
    assert run("--summary", str(tmp_path / "missing.json")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and all(": error: " in line for line in err)
    assert "must be one of ['lerobot']" in err[0] and "must name a .md file" in err[1]


def test_differences_tolerate_rounding_only():
    """[TP-4] Numbers, also inside strings, agree within 1e-2 relative; words, integers' structure and keys must be
    equal; the comparison names where two reports differ."""
    a = {"n": 6170.0, "msg": "chunk[7, 1]: got 0.5483, expected -0.1806", "k": [1, 2]}
    assert report.differences(a, {"n": 6171.0, "msg": "chunk[7, 1]: got 0.5484, expected -0.1806", "k": [1, 2]}) == []
    assert report.differences(a, dict(a, n=6400.0)) == ["report.n: 6170.0 != fresh 6400.0"]
    assert report.differences(a, dict(a, msg="chunk[7, 1]: got 0.61, expected -0.1806"))[0].startswith("report.msg")
    assert report.differences(a, dict(a, msg="chunk[7, 0]: got 0.5483, expected -0.1806"))[0].startswith("report.msg")
    assert report.differences(a, dict(a, msg="chunk[7, 1]: had 0.5483, expected -0.1806"))[0].startswith("report.msg")
    assert report.differences(a, dict(a, k=[1, 2, 3])) == ["report.k: 2 entries, fresh 3"]
    assert report.differences(a, {"n": 6170.0, "k": [1, 2]}) == ["report.msg: only in the committed report"]
