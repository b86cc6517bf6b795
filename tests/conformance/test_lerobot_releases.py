"""LeRobot's compatibility matrix: the 0.6.1 report in its own environment, the matrix, the reproducer and
the pull-back patch (spec/41-thirdparty.md [TP-7]..[TP-10])."""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softrtc.conformance.adapters import lerobot_matrix

ROOT = Path(__file__).resolve().parents[2]
FOLDER = ROOT / "conformance" / "thirdparty" / "lerobot"
NEW_VENV = ROOT / ".venv-lerobot-0.6.1"
NEW_PY = NEW_VENV / "bin" / "python"
DIFF = FOLDER / "lerobot-0.6.1-pullback-jacobian.diff"


def _new_env():
    """The 0.6.1 environment `make test` builds; skipped without it (which `make test` does not tolerate)."""
    if not NEW_PY.is_file():
        pytest.skip(f"needs the LeRobot 0.6.1 environment {NEW_VENV.name} (make {NEW_VENV.name}/.installed)")
    return NEW_PY


def _installed_lerobot(py) -> Path:
    out = subprocess.run([str(py), "-c", "import importlib.util as u; print(u.find_spec('lerobot').origin)"],
                         capture_output=True, text=True, check=True, timeout=120)
    return Path(out.stdout.strip()).parent


def _patched_copy(py, tmp_path) -> Path:
    """A copy of the installed LeRobot package with the diff's modeling_rtc.py part applied by `patch -p2`."""
    src = tmp_path / "site"
    shutil.copytree(_installed_lerobot(py), src / "lerobot", ignore=shutil.ignore_patterns("__pycache__"))
    hunk = tmp_path / "modeling.diff"
    hunk.write_text(_source_hunks())
    subprocess.run(["patch", "-p2", "--silent", "-d", str(src), "-i", str(hunk)], check=True, timeout=60)
    return src


def _source_hunks() -> str:
    """The diff's part that changes modeling_rtc.py (the rest updates LeRobot's tests)."""
    parts = DIFF.read_text().split("--- a/")
    return "".join("--- a/" + p for p in parts[1:] if p.startswith("src/lerobot/policies/rtc/modeling_rtc.py"))


def test_matrix_is_the_rendering_of_the_committed_reports():
    """[TP-7] matrix.md is the rendering of the two committed release reports, and names both releases, their
    Python versions and counts; the ids changing status between them are listed."""
    docs = lerobot_matrix.load_reports()
    text = (FOLDER / "matrix.md").read_text()
    assert text == lerobot_matrix.render(docs)
    assert docs["0.4.4"]["versions"]["python"] == "3.11" and docs["0.6.1"]["versions"]["python"] == "3.12"
    for release, d in docs.items():
        n = d["counts"]
        assert f"| {release} | {d['versions']['python']} |" in text and f"{n['pass']} / {n['fail']} / " in text


def test_both_releases_fail_the_same_ids_and_only_glue_changes():
    """[TP-7] The committed reports: every requirement id has the same status in 0.4.4 and 0.6.1 (denoise_step is
    unchanged), and the ids that 0.4.4 passes through the adapter's glue only are LeRobot's own code in 0.6.1
    (euler_integrate)."""
    docs = lerobot_matrix.load_reports()
    old, new = docs["0.4.4"]["requirements"], docs["0.6.1"]["requirements"]
    assert {r: e["status"] for r, e in old.items()} == {r: e["status"] for r, e in new.items()}
    assert [r for r, e in old.items() if e["glue_only"]] and not [r for r, e in new.items() if e["glue_only"]]
    assert "G-3" in docs["0.6.1"]["failing"] and docs["0.6.1"]["failing"]["G-3"]["kind"] == "defect"


def test_finding_classes():
    """[TP-9] A diagnosis kind splits into defect, consequence and spec strictness."""
    assert lerobot_matrix.finding_class("defect") == ["defect"]
    assert lerobot_matrix.finding_class("consequence of G-3") == ["consequence"]
    assert lerobot_matrix.finding_class("no check of t < 1; consequence of G-3") == ["spec strictness", "consequence"]
    assert lerobot_matrix.finding_class("no input checks; a different error type") == ["spec strictness"]


def test_committed_padding_cases_against_hand_computed_weights():
    """[TP-8] [W-6] H = 8, d = 1, a left-over of 3 rows, e = 6, linear: denoise_step clips the window to the
    left-over (1, 2/3, 1/3, 0, ...) in both releases; 0.6.1's rollout padding makes it [W-6]'s zeros
    (1, 5/6, 4/6, 3/6, 2/6, 1/6, 0, 0) and pulls tokens 3, 4, 5 toward the zero action."""
    docs = lerobot_matrix.load_reports()
    for release in ("0.4.4", "0.6.1"):
        case = docs[release]["own_cases"]["cases"][0]
        assert (case["H"], case["d"], case["left_over_rows"], case["execution_horizon"]) == (8, 1, 3, 6)
        np.testing.assert_allclose(case["denoise_step"]["weights"], [1, 2 / 3, 1 / 3, 0, 0, 0, 0, 0], atol=1e-4)
        assert case["denoise_step"]["option"] == "clip" and case["denoise_step"]["pulled_toward_zero"] == []
    assert "rollout" not in docs["0.4.4"]["own_cases"]["cases"][0]
    roll = docs["0.6.1"]["own_cases"]["cases"][0]["rollout"]
    np.testing.assert_allclose(roll["weights"], [1, 5 / 6, 4 / 6, 3 / 6, 2 / 6, 1 / 6, 0, 0], atol=1e-4)
    assert roll["option"] == "zeros" and roll["pulled_toward_zero"] == [3, 4, 5]
    full = docs["0.6.1"]["own_cases"]["cases"][-1]  # a left-over as long as the window: both paths agree
    assert full["left_over_rows"] == full["execution_horizon"] and full["rollout"]["weights"] == full["spec_clip"]


@pytest.mark.slow  # the whole vector set through LeRobot 0.6.1 in its own interpreter (about 100 s)
def test_release_0_6_1_report_is_fresh():
    """[TP-4] [TP-7] `softrtc conformance report --impl lerobot --check` in the 0.6.1 environment (Python 3.12):
    the committed report of that release agrees with a fresh run."""
    py = _new_env()
    out = subprocess.run([str(py), "-m", "softrtc.conformance", "report", "--impl", "lerobot",
                          "--out", str(FOLDER / "lerobot-0.6.1.md"), "--check"],
                         capture_output=True, text=True, timeout=900, cwd=ROOT)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]


def test_reproducer_shows_the_defect_with_torch_and_lerobot_only():
    """[TP-10] reproduce.py imports nothing of softrtc and, on the released LeRobot, exits 1 with the
    pull-back equal to the weighted error and away from autograd's VJP."""
    src = (FOLDER / "reproduce.py").read_text()
    assert not re.search(r"^\s*(import|from)\s+softrtc", src, re.M)
    pytest.importorskip("lerobot")
    out = subprocess.run([sys.executable, str(FOLDER / "reproduce.py")], capture_output=True, text=True,
                         timeout=300, cwd=FOLDER.parent)
    assert out.returncode == 1, out.stdout + out.stderr
    nums = dict(re.findall(r"max \|(.+?)\|\s+= (\S+)", out.stdout))
    assert float(nums["pull-back - weighted error"]) == 0.0
    assert float(nums["pull-back - autograd VJP"]) > 1e-2 and "DEFECT" in out.stdout


@pytest.mark.slow  # copies LeRobot 0.6.1, patches it and runs the guided cases in its interpreter
def test_patch_makes_the_guided_cases_pass(tmp_path):
    """[TP-10] [G-3] The diff applied (`patch -p2`) to a copy of the installed LeRobot 0.6.1: the reproducer exits
    0 and every guided_sample case of the vectors passes through the unchanged adapter; the values of
    LeRobot's two updated tests (test_denoise_step_with_prev_chunk, test_denoise_step_uses_custom_execution_horizon:
    the diff's + and context lines) are what the patched denoise_step returns on those tests' inputs."""
    py = _new_env()
    site = _patched_copy(py, tmp_path)
    env = dict(os.environ, PYTHONPATH=str(site))
    rep = subprocess.run([str(py), str(FOLDER / "reproduce.py")], capture_output=True, text=True, env=env,
                         timeout=300)
    assert rep.returncode == 0 and "OK:" in rep.stdout, rep.stdout + rep.stderr
    run = subprocess.run([str(py), "-m", "softrtc.conformance", "run", "--impl", "lerobot", "--in-process",
                          "--only", "guided_sample", "--report", str(tmp_path / "r.json")],
                         capture_output=True, text=True, env=env, timeout=900, cwd=ROOT)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    cases = json.loads((tmp_path / "r.json").read_text())["cases"]
    valid = [c for c in cases if ".reject." not in c["id"]]
    assert len(valid) >= 17 and all(c["status"] == "pass" for c in valid)
    # LeRobot's own tests, updated by the diff: 1 x 20 x 1 ones, prior 0.1 (20 or 15 rows), delay 5, time 0.5,
    # v = x / 2; the diff's + and context lines of each expected tensor are what the patched step returns
    stub = ("import sys, types, importlib, pathlib\n"
            "import lerobot\nroot = pathlib.Path(lerobot.__file__).parent\n"
            "for n in ('lerobot.configs', 'lerobot.policies', 'lerobot.policies.rtc'):\n"
            "    m = sys.modules[n] = types.ModuleType(n); m.__path__ = [str(root.joinpath(*n.split('.')[1:]))]\n"
            "sys.modules['lerobot.configs'].RTCAttentionSchedule = "
            "importlib.import_module('lerobot.configs.types').RTCAttentionSchedule\n")
    for test, rows, horizon, cfg in (
            ("test_denoise_step_with_prev_chunk", 20, None,
             "enabled=True, prefix_attention_schedule=RTCAttentionSchedule.LINEAR, max_guidance_weight=10.0, "
             "execution_horizon=10, debug=False"),
            ("test_denoise_step_uses_custom_execution_horizon", 15, 15, "execution_horizon=10")):
        block = DIFF.read_text().split(f"def {test}", 1)[1].split("\n def ", 1)[0]
        expected = [float(v) for v in re.findall(r"^[+ ]\s+\[(-?\d+\.\d+)\],$", block, re.M)[:20]]
        code = ("import json, torch\n"
                "from lerobot.policies.rtc.configuration_rtc import RTCConfig\n"
                "from lerobot.policies.rtc.modeling_rtc import RTCProcessor\n"
                "from lerobot.configs.types import RTCAttentionSchedule\n"
                f"p = RTCProcessor(RTCConfig({cfg}))\n"
                f"r = p.denoise_step(torch.ones(1, 20, 1), torch.full((1, {rows}, 1), 0.1), 5, torch.tensor(0.5), "
                f"lambda x: x * 0.5, execution_horizon={horizon})\n"
                "print(json.dumps(r.reshape(-1).tolist()))\n")
        got = subprocess.run([str(py), "-c", stub + code], capture_output=True, text=True, env=env, timeout=300)
        assert got.returncode == 0, got.stderr
        values = json.loads(got.stdout.strip().splitlines()[-1])
        assert len(expected) >= 10 and expected[0] == 1.475  # 0.5 + 2 * 0.75 * 0.65, by hand
        np.testing.assert_allclose(values[:len(expected)], expected, atol=1e-4, err_msg=test)
        np.testing.assert_allclose(values[-4:], 0.5, atol=1e-6)  # past the window: v = x / 2, unguided
