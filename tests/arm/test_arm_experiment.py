"""The arm experiment: paired statistics, shared fine-tunes, the noisy-prior variant, the pipeline, the report."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from softrtc.arm import paired_stats as ps
from softrtc.arm.experiment import DEFAULT_WINDOW, PAPER_WINDOW, eval_key, rows_for, train_key
from softrtc.arm.tasks import TASKS, get_task

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "arm"


def test_mcnemar_exact_hand_values():
    """AX-7: exact McNemar from the discordant pairs: 0 vs 5 gives 2 / 2^5; ties give 1; pairing broadcasts a base row."""
    a = np.array([[1, 1, 1, 1, 1, 0, 1]])
    b = np.array([[0, 0, 0, 0, 0, 0, 1]])
    r = ps.mcnemar_exact(a, b)
    assert (r["b10"], r["b01"]) == (5, 0)
    assert r["p"] == pytest.approx(2 / 32)
    assert ps.mcnemar_exact(b, b)["p"] == 1.0
    # 1 vs 3 discordant: p = 2 * (C(4,0) + C(4,1)) / 16 = 10/16.
    r = ps.mcnemar_exact(np.array([[1, 0, 0, 0, 1]]), np.array([[0, 1, 1, 1, 1]]))
    assert (r["b10"], r["b01"], r["p"]) == (1, 3, pytest.approx(10 / 16))
    # A one-row base is paired with every seed row of the other method.
    r = ps.mcnemar_exact(np.array([[1, 0]]), np.array([[0, 0], [0, 1]]))
    assert (r["b10"], r["b01"]) == (2, 1)
    with pytest.raises(ValueError, match="0/1"):
        ps.mcnemar_exact(np.array([[0.5]]), np.array([[1]]))


def test_cluster_bootstrap_and_paired_difference():
    """AX-7: a constant matrix has a zero-width interval; a - a is 0 with p = 1; a shift by c is c with p near 0."""
    r = ps.cluster_bootstrap(np.full((3, 10), 0.25), 200, 0)
    assert (r["mean"], r["lo"], r["hi"], r["n"]) == (0.25, 0.25, 0.25, 30)
    rng = np.random.default_rng(1)
    a = rng.normal(size=(3, 40))
    same = ps.paired_difference(a, a, 300, 0)
    assert (same["diff"], same["lo"], same["hi"], same["p"]) == (0.0, 0.0, 0.0, 1.0)
    shifted = ps.paired_difference(a + 0.5, a, 300, 0)
    assert shifted["diff"] == pytest.approx(0.5) and shifted["lo"] == pytest.approx(0.5)
    assert shifted["p"] == 0.0
    # NaN entries (undefined metrics) are left out of the mean, not counted as 0.
    v = np.array([[1.0, np.nan, 3.0]])
    assert ps.cluster_bootstrap(v, 100, 0)["mean"] == 2.0
    # The interval covers the mean and widens with the spread between seeds.
    wide = ps.cluster_bootstrap(np.array([[0.0] * 20, [1.0] * 20, [0.5] * 20]), 500, 0)
    assert wide["lo"] < 0.5 < wide["hi"]
    with pytest.raises(ValueError, match="num_resamples"):
        ps.cluster_bootstrap(v, 0, 0)
    with pytest.raises(ValueError, match="same number of episodes"):
        ps.paired_difference(np.zeros((1, 3)), np.zeros((1, 4)))


def test_rows_share_fine_tunes_and_episodes_where_identical():
    """AX-2, AX-3, W-8, W-10: lam 1 and L 0 are Train Hard RTC; clip and zeros share where the window stays
    inside the overlap; the paper configuration is the default rule and schedule with zero padding."""
    for name, task in TASKS.items():
        rows = {r.name: r for r in rows_for(task)}
        for r in ("soft1_clip", "soft1_zeros", "offset0_clip", "offset0_zeros"):
            assert train_key(rows[r], task) == "hard"
            assert eval_key(rows[r], task) == eval_key(rows["train_hard"], task)
        # The cross-evaluation runs another sampler on the same fine-tune.
        assert train_key(rows["soft2_clip_hard_sampler"], task) == train_key(rows["soft2_clip"], task)
        assert eval_key(rows["soft2_clip_hard_sampler"], task) != eval_key(rows["soft2_clip"], task)
    easy, o4 = get_task("easy"), get_task("overlap4")
    rows = {r.name: r for r in rows_for(easy)}
    # easy: overlap 5 = h_max, so the paper's window never runs past it and zero padding changes nothing.
    assert eval_key(rows["soft2_zeros"], easy) == eval_key(rows["soft2_clip"], easy)
    rows = {r.name: r for r in rows_for(o4)}
    # overlap4: at d = 3, 4 the window reaches token 4, past the overlap of 4 (the paper's geometry).
    assert train_key(rows["soft2_zeros"], o4) != train_key(rows["soft2_clip"], o4)
    assert PAPER_WINDOW.overflow == "zeros" and DEFAULT_WINDOW.overflow == "clip"
    assert PAPER_WINDOW.rule == DEFAULT_WINDOW.rule and PAPER_WINDOW.schedule == DEFAULT_WINDOW.schedule


def test_tasks():
    """AX-1: easy is the study's s = 5; overlap4 runs s = 6 with delays 0..4 like the paper's H = 8, s = 4."""
    assert (get_task("easy").execute_horizon, get_task("easy").max_delay) == (5, 5)
    assert (get_task("overlap4").execute_horizon, get_task("overlap4").max_delay) == (6, 4)
    with pytest.raises(ValueError, match="task must be one of"):
        get_task("hard")


def test_prior_noise_with_zero_sigma_is_the_soft_fine_tune():
    """AX-5: with sigma = 0 the noisy-prior objective is chapter T's soft step (same draws, same batches)."""
    import dataclasses

    import jax

    from softrtc.arm.policy_config import ArmPolicyConfig, new_model
    from softrtc.arm.prior_noise import train_prior_noise
    from softrtc.arm.training import arm_train_config
    from softrtc.jax.training import train

    cfg = ArmPolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1,
                          execute_horizon=6)
    model = new_model(cfg, 0)
    rng = np.random.default_rng(0)
    obs = rng.normal(size=(20, model.obs_dim)).astype(np.float32)
    act = rng.normal(size=(20, 10, 4)).astype(np.float32)
    tc = dataclasses.replace(arm_train_config("train_soft", cfg, 3, batch_size=8), window=PAPER_WINDOW)
    ref, ref_loss = train(model, {"obs": obs, "actions": act}, tc, jax.random.key(3), 3, progress=False)
    got, loss = train_prior_noise(model, obs, act, tc, jax.random.key(3), 3, np.zeros((10, 4)))
    np.testing.assert_allclose(loss, ref_loss, rtol=1e-5, atol=1e-6)
    for x, y in zip(jax.tree.leaves(jax.tree.map(np.asarray, ref)), jax.tree.leaves(jax.tree.map(np.asarray, got))):
        np.testing.assert_allclose(x, y, rtol=1e-4, atol=1e-6)
    # A non-zero sigma changes the run (it perturbs the window tokens' input).
    _, noisy = train_prior_noise(model, obs, act, tc, jax.random.key(3), 3, np.full((10, 4), 0.5))
    assert not np.allclose(noisy, ref_loss)
    with pytest.raises(ValueError, match="sigma"):
        train_prior_noise(model, obs, act, tc, jax.random.key(3), 3, np.zeros((9, 4)))


@pytest.mark.slow
def test_quick_experiment_pipeline(tmp_path):
    """AX-4, AX-6: `softrtc arm experiment --quick` runs every stage, writes cells and a report, and resumes
    without fine-tuning for complete cells; a fine-tune that no longer gives its recorded checkpoint stops the
    run. On overlap4, where clip and zero padding differ for the main rows."""
    env = {**os.environ, "JAX_PLATFORMS": "cpu"}
    cmd = [sys.executable, "-m", "softrtc.cli", "arm", "experiment", "--task", "overlap4", "--quick", "--out",
           str(tmp_path / "res"),
           "--work", str(tmp_path / "work"), "--report"]
    out = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    task = tmp_path / "res" / "overlap4"
    manifest = json.loads((task / "manifest.json").read_text())
    from softrtc.arm.report import load_results

    cells = load_results(task)["cells"]
    # Shared rows read the same episode file; every file has the quick budget's episodes.
    assert cells[("soft1_clip", 1, 0)] is cells[("train_hard", 1, 0)]
    assert ("naive", 0, 4) in cells and ("soft2_clip_prior_noise", 1, 4) in cells
    for f in (task / "episodes").glob("*.csv"):
        lines = f.read_text().strip().splitlines()
        assert len(lines) in (1 + manifest["budget_values"]["main_episodes"],
                              1 + manifest["budget_values"]["sweep_episodes"])
    assert len(list((task / "finetunes").glob("*.json"))) == 6
    report = (tmp_path / "res" / "REPORT.md").read_text()
    assert report.count("Verdict: **") >= 7
    for png in ("frontier.png", "sweeps.png", "success_by_delay.png", "window_weights.png"):
        assert (task / png).stat().st_size > 1000
    # Resuming does not recompute a complete cell, nor fine-tune for one (an empty work folder here).
    fresh = cmd[:-3] + ["--work", str(tmp_path / "work2")]
    again = subprocess.run(fresh, capture_output=True, text=True, env=env, cwd=tmp_path)
    assert again.returncode == 0 and ", 0 run now" in again.stdout, again.stderr[-3000:]
    assert "fine-tune" not in again.stdout and not list((tmp_path / "work2").glob("**/*.npz"))
    # A cell to extend whose fine-tune no longer gives the recorded checkpoint is an error, not a mixed cell.
    hard = task / "finetunes" / "hard_seed1.json"
    rec = json.loads(hard.read_text())
    hard.write_text(json.dumps(dict(rec, sha256_16="0" * 16)))
    (tmp_path / "work" / "overlap4" / "quick" / "hard_seed1.npz").unlink()
    (task / "episodes" / f"{manifest['rows']['train_hard']['eval_key']}_s1_d0.csv").unlink()
    bad = subprocess.run(cmd[:-1], capture_output=True, text=True, env=env, cwd=tmp_path)
    assert bad.returncode != 0 and "records 0000000000000000" in bad.stderr and "use another --out" in bad.stderr
    assert not (tmp_path / "work" / "overlap4" / "quick" / "hard_seed1.npz").exists()


def test_committed_report_matches_results():
    """AX-6: the committed REPORT.md and the README's arm table are what `softrtc arm report` makes of the results."""
    from softrtc.arm.report import (README_BEGIN, README_END, README_TASK, load_results, render_readme_table,
                                    render_report, summarize)

    tasks = sorted(p.parent.name for p in RESULTS.glob("*/manifest.json"))
    assert tasks, "results/arm holds no experiment results"
    res = {t: load_results(RESULTS / t) for t in tasks}
    sums = {t: summarize(r) for t, r in res.items()}
    assert (RESULTS / "REPORT.md").read_text() == render_report(res, sums)
    readme = (ROOT / "README.md").read_text()
    i, j = readme.find(README_BEGIN), readme.find(README_END)
    assert 0 <= i < j
    assert readme[i:j + len(README_END)] == render_readme_table(res[README_TASK], sums[README_TASK])
    # Every verdict in the report has its evidence and every interval is ordered.
    for t, r in res.items():
        for row, e in sums[t].items():
            for scope in e["scopes"].values():
                for st in scope.values():
                    if math.isfinite(st["lo"]):
                        assert st["lo"] <= st["mean"] + 1e-12 and st["mean"] <= st["hi"] + 1e-12


def test_report_says_what_a_larger_budget_would_add_and_checks_the_readme_task(tmp_path):
    """AX-6: a main row whose paired high-delay success interval against Train Hard includes 0 is listed with the
    factor of episodes x seeds that would exclude 0 were the difference to hold ((half-width / |diff|)^2, here
    (0.10 / 0.05)^2 = 4); rows whose interval excludes 0 are not; the README's task must be among the results."""
    from softrtc.arm.report import _larger_budget, write_report

    m = {"rows": {"train_hard": {"tier": "main"}, "a": {"tier": "main"}, "b": {"tier": "main"},
                  "c": {"tier": "sweep"}},
         "order": ["train_hard", "a", "b", "c"]}
    summary = {"a": {"vs_hard": {"high": {"success": {"diff": 0.05, "lo": -0.05, "hi": 0.15}}}},
               "b": {"vs_hard": {"high": {"success": {"diff": -0.2, "lo": -0.3, "hi": -0.1}}}},
               "c": {"vs_hard": {"high": {"success": {"diff": 0.0, "lo": -0.1, "hi": 0.1}}}}}
    (line, _) = _larger_budget(summary, m)
    assert "`a` +0.05 [-0.05, 0.15] (about 4x the episodes x seeds" in line
    assert "`b`" not in line and "`c`" not in line
    summary["a"]["vs_hard"]["high"]["success"] = {"diff": 0.2, "lo": 0.1, "hi": 0.3}
    assert _larger_budget(summary, m)[0].startswith("Every main row's high-delay success difference")
    (tmp_path / "easy").mkdir()
    (tmp_path / "easy" / "manifest.json").write_text("{}")
    with pytest.raises(ValueError, match=r"readme_task must be one of the result tasks \['easy'\], got 'drift'"):
        write_report(tmp_path, readme=tmp_path / "README.md", readme_task="drift")


def test_sign_flip_test_hand_values():
    """AX-7: the env seed is the unit: 3 columns all +1 give 2 of 8 sign patterns as extreme (p = 1/4); the
    columns of 3 fine-tuning seeds are averaged first, so 300 episodes over 3 env seeds still give 8 patterns."""
    r = ps.sign_flip_test(np.array([[1, 1, 1]]), np.array([[0, 0, 0]]))
    assert r["p"] == 0.25 and r["diff"] == 1.0 and r["n_env"] == 3
    a = np.array([[1, 1, 1], [1, 1, 1], [1, 1, 0]])
    b = np.array([[0, 0, 0]])  # a base row, paired with every seed row
    r = ps.sign_flip_test(a, b)
    # column means of a - b: 1, 1, 2/3 -> mean 8/9; only the all-plus and all-minus patterns reach |8/9|.
    assert abs(r["diff"] - 8 / 9) < 1e-12 and r["p"] == 0.25
    # One column of differences {+1, -1} averages to 0: that env seed carries no evidence.
    r = ps.sign_flip_test(np.array([[1, 0, 1], [0, 0, 1]]), np.array([[0, 0, 0], [1, 0, 0]]))
    assert r["n_env"] == 3 and abs(r["diff"] - 1 / 3) < 1e-12
    # 2 patterns of 8 reach |mean| = 1/3 with deltas (0, 0, 1): + and - on the third column, any sign on zeros:
    # |(0 + 0 +- 1)| / 3 = 1/3 for all 8 patterns -> p = 1.
    assert r["p"] == 1.0
    assert ps.sign_flip_test(np.array([[1, 0]]), np.array([[1, 0]]))["p"] == 1.0


def test_sign_flip_test_monte_carlo_matches_binomial():
    """AX-7: above 16 env seeds the test draws patterns; with deltas all +1 (E = 20) the exact p is 2 / 2^20,
    so the Monte Carlo estimate is its floor 1 / (1 + resamples); with 14 of 20 at +1 and 6 at -1 the exact
    two-sided p is P(|2K - 20| >= 8), K ~ Bin(20, 1/2)."""
    import math
    r = ps.sign_flip_test(np.ones((1, 20)), np.zeros((1, 20)), 4000, 1)
    assert r["p"] == 1 / 4001
    a = np.array([[1.0] * 14 + [0.0] * 6])
    b = np.array([[0.0] * 14 + [1.0] * 6])
    exact = sum(math.comb(20, k) for k in range(21) if abs(2 * k - 20) >= 8) / 2 ** 20
    r = ps.sign_flip_test(a, b, 20000, 0)
    assert abs(r["p"] - exact) < 0.01, (r["p"], exact)


def test_holm_hand_values_and_checks():
    """AX-7: Holm's step-down adjustment, computed by hand; NaN is outside the family."""
    assert ps.holm([0.01, 0.04, 0.03]) == [0.03, 0.06, 0.06]
    out = ps.holm([0.2, float("nan"), 0.01])
    assert out[0] == 0.2 and out[2] == 0.02 and math.isnan(out[1])
    assert ps.holm([0.6, 0.6]) == [1.0, 1.0]
    for bad in ([1.5], [-0.1], [float("inf")], "x"):
        with pytest.raises(ValueError, match="pvalues"):
            ps.holm(bad)
