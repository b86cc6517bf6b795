"""The Kinetix study table: reading the evaluation folders, paired statistics over levels, seeds and episodes,
the shared verdicts, the runtime ratios, and the committed page block ([KR-1]..[KR-7])."""

from __future__ import annotations

import csv
import math
import re
from pathlib import Path

import numpy as np
import pytest

from softrtc import verdicts as shared
from softrtc.arm import report_verdicts as arm_verdicts
from softrtc.kinetix import study_table as st
from softrtc.paired_stats import nested_bootstrap

ROOT = Path(__file__).resolve().parents[2]
FIELDS = ["method", "level", "delay", "episode", "return", "solved", "length", "delta", "jerk"]
LEVELS = ("m_h0_unicycle", "l_h4_cartpole")
EPISODES = 24


def _write(folder: Path, rows: list) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    with open(folder / "episodes.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(rows)
    return folder / "episodes.csv"


def _episode(method, level, d, e, seed, *, solved, ret, jerk, delta):
    return {"method": method, "level": level, "delay": d, "episode": e, "return": ret, "solved": solved,
            "length": 40, "delta": delta, "jerk": jerk}


def _hard(level, d, e, seed):
    """Train Hard's episode: varies with level, delay, episode and seed, so nothing is constant by accident."""
    li = LEVELS.index(level)
    ret = 0.3 + 0.05 * li + 0.01 * ((7 * e + 3 * d + seed) % 11)
    return {"solved": (e + d + seed + li) % 3 != 0, "ret": ret, "jerk": 0.02 + 0.001 * ((e * 5 + seed) % 7),
            "delta": 0.1 + 0.002 * ((e + d) % 5)}


def make_study(root: Path) -> Path:
    """A study with known answers:

    - inference rows never solve at d >= 3, Train Hard solves 2/3 there: claim 1 supported;
    - ``train_soft:delay_scaled:2`` is Train Hard with return + 0.1 and solve equal on every paired episode, and
      jerk 0.05 higher: its jerk claim is not supported;
    - ``train_soft:delay_scaled:1`` has fine-tuning seed 0 only: its N = 1 claim is inconclusive.
    """
    for lv in LEVELS:
        for seed in (0, 1, 2):
            rows = []
            for d in range(5):
                for e in range(EPISODES):
                    h = _hard(lv, d, e, seed)
                    rows.append(_episode("train_hard", lv, d, e, seed, **h))
                    rows.append(_episode("train_soft:delay_scaled:2", lv, d, e, seed,
                                         **dict(h, ret=h["ret"] + 0.1, jerk=h["jerk"] + 0.05)))
                    if seed == 0:
                        rows.append(_episode("train_soft:delay_scaled:1", lv, d, e, seed, **h))
                        for m in ("naive", "inference_hard", "inference_soft"):
                            rows.append(_episode(m, lv, d, e, seed, solved=d < 3 and e % 2 == 0, ret=0.2,
                                                 jerk=0.03, delta=0.12))
            _write(root / "eval" / lv / f"seed_{seed}", rows)
    return root


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    root = make_study(tmp_path_factory.mktemp("study"))
    data = st.read_study(root)
    return root, data, st.summarize_study(data)


def test_nested_bootstrap_hand_values():
    """KR-3: a level's value is the mean over delays of the mean over its defined entries; the statistic is the
    mean over levels; resampling two constant levels gives the interval between them."""
    # Level A: delay 0 defined once (1), delay 1 twice (3, 5): mean over delays (1 + 4) / 2 = 2.5, not 3.
    a = [[[1.0, float("nan")], [3.0, 5.0]]]
    r = nested_bootstrap([a], 500, 0)
    assert r["mean"] == 2.5 and r["n"] == 3
    r = nested_bootstrap([[[[1.0, 1.0]]], [[[3.0, 3.0]]]], 500, 0)
    assert (r["mean"], r["lo"], r["hi"]) == (2.0, 1.0, 3.0)
    with pytest.raises(ValueError, match=r"blocks\[0\] must be a real array \[seeds >= 1, delays >= 1"):
        nested_bootstrap([[1.0, 2.0]])
    with pytest.raises(ValueError, match="^blocks must be a non-empty list"):
        nested_bootstrap([])


def test_paired_difference_of_a_shifted_row(study):
    """KR-3: a row that is Train Hard + 0.1 return on every paired episode (fine-tuning seed k against seed k)
    differs by 0.1 with the interval [0.1, 0.1]; its equal solve flags differ by 0 with sign-flip p = 1."""
    _, data, summary = study
    t = summary["train_soft:delay_scaled:2"]["vs_hard"]
    for scope in ("overall", "high"):
        assert t[scope]["return"]["diff"] == pytest.approx(0.1, abs=1e-12)
        assert t[scope]["return"]["lo"] == pytest.approx(0.1, abs=1e-12)
        assert t[scope]["return"]["hi"] == pytest.approx(0.1, abs=1e-12)
        assert t[scope]["solved"]["diff"] == 0.0 and t[scope]["solved"]["p_perm"] == 1.0
        assert t[scope]["jerk"]["diff"] == pytest.approx(0.05, abs=1e-12)
    # 2 levels x 24 env keys, every difference +0.1: only the all-plus and all-minus patterns are as extreme,
    # so the Monte Carlo p is (1 + hits) / (1 + 5000) with hits the patterns hitting |mean| 0.1 (about 0).
    assert t["overall"]["return"]["p_perm"] < 0.01 and t["overall"]["return"]["levels"] == 2
    e = summary["train_soft:delay_scaled:2"]
    assert (e["levels"], e["seeds"], e["episodes"], e["delays"]) == (2, 3, EPISODES, [0, 1, 2, 3, 4])
    assert summary["naive"]["seeds"] == 1 and summary["train_soft:delay_scaled:1"]["seeds"] == 1
    # The pairing's seeds: Soft lam 2 pairs 3 with 3, Soft lam 1 its one seed with Train Hard's seed 0, a base
    # row every Train Hard seed.
    assert [summary[r]["vs_hard"]["overall"]["solved"]["seeds"] for r in
            ("train_soft:delay_scaled:2", "train_soft:delay_scaled:1", "naive")] == [3, 1, 3]
    # Inference Hard's high-delay solve is 0 on every episode: mean 0, interval [0, 0].
    s = summary["inference_hard"]["scopes"]["high"]["solved"]
    assert (s["mean"], s["lo"], s["hi"]) == (0.0, 0.0, 0.0)
    # Train Hard's overall solve, by hand: mean over levels of the mean over delays of the mean over
    # (seed, episode).
    want = np.mean([np.mean([np.mean([_hard(lv, d, e, s)["solved"] for s in range(3) for e in range(EPISODES)])
                             for d in range(5)]) for lv in LEVELS])
    assert summary["train_hard"]["scopes"]["overall"]["solved"]["mean"] == pytest.approx(want, abs=1e-12)
    # The per-delay table's means are the mean over levels of each delay's mean.
    want0 = np.mean([np.mean([_hard(lv, 0, e, s)["jerk"] for s in range(3) for e in range(EPISODES)])
                     for lv in LEVELS])
    assert summary["train_hard"]["scopes"]["d0"]["jerk"]["mean"] == pytest.approx(want0, abs=1e-12)


def test_verdicts_supported_not_supported_inconclusive(study):
    """KR-5: the shared claims on the synthetic study: training-time beats inference-time RTC at high delay
    (supported), Soft N = 2's jerk is higher (not supported), Soft N = 1 with one seed (inconclusive), and
    no offset rows (inconclusive)."""
    _, _, summary = study
    v = {x["claim"]: x for x in st.verdicts_of(summary)}
    c1 = v["Training-time RTC beats inference-time RTC at high delay (solve)."]
    assert c1["verdict"] == "supported" and c1["reason"] is None
    c2 = v["Soft N = 2 (spec default, clip; Algorithm 1 step) has lower high-delay jerk than Train Hard at a small "
           "(< 10 points) solve cost."]
    assert c2["verdict"] == "not supported" and c2["reason"] == "jerk is higher than Train Hard's"
    c3 = v["Soft N = 1 (spec default, clip; Algorithm 1 step) nearly matches Hard RTC in solve (paired difference "
           "within 10 points)."]
    assert c3["verdict"] == "inconclusive"
    assert c3["reason"] == "`train_soft:delay_scaled:1` has 1 fine-tuning seed(s), fewer than 3"
    # Its paired difference covers seed 0 only, while the quoted Train Hard value pools 3 seeds: said so.
    assert c3["evidence"].endswith(", paired on the 1 seed both ran)")
    assert "paired on" not in c2["evidence"]
    c4 = v["The offset sweep (clip) trades high-delay solve for smoothness (L = 6 vs L = 0)."]
    assert c4["verdict"] == "inconclusive" and c4["reason"] == "the offset rows L = 0 and L = 6 were not both run"
    assert c4["evidence"] == "no row of the sweep in the results"
    c5 = v["Soft RTC (spec default, clip; Algorithm 1 step) has lower action delta and jerk than Train Hard RTC "
           "over all delays."]
    assert c5["verdict"] == "not supported"


def test_one_verdict_module_for_both_environments():
    """KR-5, AX-7: the arm's verdicts are the shared module's; one summary written with each environment's metric
    names gets the same verdicts in both, and a measured N = 1 row within 10 points is supported."""
    def entry(seeds, **scopes):
        return {"seeds": seeds, "episodes": 64, "scopes": {k: dict(v[0]) for k, v in scopes.items()},
                "vs_hard": {k: dict(v[1]) for k, v in scopes.items()}}

    def summary(S, J, fd, soft2, soft1):
        st_ = lambda m: {"mean": m, "lo": m - 0.01, "hi": m + 0.01}  # noqa: E731
        dt = lambda x: {"diff": x, "lo": x - 0.02, "hi": x + 0.02}  # noqa: E731
        hi = lambda s, j: ({S: st_(s), J: st_(j)}, {S: dt(s - 0.8), J: dt(j - 0.1)})  # noqa: E731
        ov = lambda s, f: ({S: st_(s), **{m: st_(f) for m in fd}}, {S: dt(s - 0.8), **{m: dt(f - 0.1) for m in fd}})  # noqa: E731,E501
        return {"train_hard": entry(3, high=hi(0.8, 0.1), overall=ov(0.8, 0.1)),
                "inference_hard": entry(1, high=hi(0.5, 0.2), overall=ov(0.5, 0.2)),
                "inference_soft": entry(1, high=hi(0.6, 0.2), overall=ov(0.6, 0.2)),
                "naive": entry(1, high=hi(0.4, 0.3), overall=ov(0.4, 0.3)),
                soft2: entry(3, high=hi(0.78, 0.05), overall=ov(0.78, 0.05)),
                soft1: entry(3, high=hi(0.8, 0.1), overall=ov(0.81, 0.1))}

    arm = summary("success", "D2", ("D1", "D2", "D3"), "soft2_clip", "soft1_clip")
    kin = summary("solved", "jerk", ("delta", "jerk"), "train_soft:delay_scaled:2", "train_soft:delay_scaled:1")
    manifest = {"rows": {r: {"eval_key": r} for r in arm}}
    va = arm_verdicts.verdicts(arm, manifest)
    assert va == shared.verdicts(arm, arm_verdicts.ARM, soft2_rows=["soft2_clip"], n1_identical=False)
    vk = st.verdicts_of(kin)
    pick = lambda vs: [x["verdict"] for x in vs if not x["claim"].startswith("Soft N = 1")]  # noqa: E731
    assert pick(va) == pick(vk) == ["supported", "supported", "inconclusive", "inconclusive", "supported"]
    n1 = [x for x in vk if x["claim"].startswith("Soft N = 1")]
    assert [x["verdict"] for x in n1] == ["supported"]  # +0.01 [-0.01, 0.03] lies within 10 points
    kin["train_soft:delay_scaled:1"]["vs_hard"]["overall"]["solved"] = {"diff": -0.2, "lo": -0.25, "hi": -0.15}
    assert [x["verdict"] for x in st.verdicts_of(kin) if x["claim"].startswith("Soft N = 1")] == ["not supported"]
    with pytest.raises(ValueError, match="^env must be a softrtc.verdicts.Environment"):
        shared.verdicts(kin, "kinetix")


def test_damaged_results_are_a_value_error_naming_the_file(tmp_path, capsys):
    """KR-1, KR-6: a bad value, a missing column, a row of another level, a repeated episode or a base row whose
    episodes differ between seed folders is a ValueError naming the file (the command: one line, status 2); no
    eval folder means no results."""
    from softrtc.cli import main

    assert st.read_study(tmp_path) is None
    root = make_study(tmp_path / "s")
    f = root / "eval" / LEVELS[0] / "seed_1" / "episodes.csv"
    good = f.read_text()
    f.write_text(good.replace(",True,", ",maybe,", 1))
    with pytest.raises(ValueError, match=rf"results file '{re.escape(str(f))}': line \d+: field 'solved' must be True, False"):
        st.read_study(root)
    capsys.readouterr()
    assert main(["kinetix", "report", "--study", str(root), "--no-plots"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("softrtc kinetix report: error: results file") and str(f) in err and err.count("\n") == 1
    f.write_text(good.replace("jerk", "jolt", 1))
    with pytest.raises(ValueError, match=rf"results file '{re.escape(str(f))}' must have the columns .* it lacks \['jerk'\]"):
        st.read_study(root)
    f.write_text(good.replace(f",{LEVELS[0]},", f",{LEVELS[1]},", 1))
    with pytest.raises(ValueError, match=rf"'{re.escape(str(f))}': line 2: field 'level' must be '{LEVELS[0]}'"):
        st.read_study(root)
    lines = good.splitlines()
    f.write_text("\n".join(lines + [lines[1]]) + "\n")
    with pytest.raises(ValueError, match=rf"'{re.escape(str(f))}': line {len(lines) + 1}: episode 0 of method 'train_hard' at "
                                         "delay 0 appears twice"):
        st.read_study(root)
    f.write_text(good)
    # A base row copied into seed 1 with the same episodes counts once; with other episodes it is an error.
    base = [r for r in csv.DictReader(open(root / "eval" / LEVELS[0] / "seed_0" / "episodes.csv"))
            if r["method"] == "naive"]
    rows = list(csv.DictReader(open(f)))
    _write(f.parent, rows + base)
    assert st.summarize_study(st.read_study(root))["naive"]["seeds"] == 1
    base[0]["return"] = "9.0"
    _write(f.parent, rows + base)
    with pytest.raises(ValueError, match=rf"results file '{re.escape(str(f))}': base row 'naive' differs from its episodes in"):
        st.read_study(root)
    _write(f.parent, rows)
    (root / "eval" / LEVELS[0] / "seed_x").mkdir()
    with pytest.raises(ValueError, match=r"seed_x' must be a results folder named seed_<k> or seed_<k>.<part>"):
        st.read_study(root)
    (root / "eval" / LEVELS[0] / "seed_x").rmdir()
    # Rows of seed 1 in a second eval run's folder seed_1.more: read as seed 1; the same row in both is an error.
    whole = st.summarize_study(st.read_study(root))
    soft = [r for r in rows if r["method"] == "train_soft:delay_scaled:2"]
    _write(f.parent, [r for r in rows if r["method"] != "train_soft:delay_scaled:2"])
    _write(f.parent.parent / "seed_1.more", soft)
    split = st.summarize_study(st.read_study(root))
    assert split["train_soft:delay_scaled:2"] == whole["train_soft:delay_scaled:2"]
    assert split["train_soft:delay_scaled:2"]["seeds"] == 3
    _write(f.parent, rows)
    with pytest.raises(ValueError, match=r"row 'train_soft:delay_scaled:2' of seed 1 is also in .*seed_1"):
        st.read_study(root)
    for bad in ("seed_1.", "seed_1.Big", "seed_01.x"):
        (root / "eval" / LEVELS[0] / bad).mkdir()
        with pytest.raises(ValueError, match="must be a results folder named"):
            st.read_study(root)
        (root / "eval" / LEVELS[0] / bad).rmdir()
    with pytest.raises(ValueError, match="^study_dir must be an existing folder"):
        st.read_study(tmp_path / "absent")


def test_runtime_ratios_from_the_committed_bench():
    """KR-4: the newest committed `softrtc bench runtime` result gives each row's chunk time over naive; a
    zero-padded window runs its clip row's sampler; rows the bench did not run get none."""
    rt = st.read_runtime(ROOT / "results" / "bench")
    newest = max(int(p.stem.split("-")[1]) for p in (ROOT / "results" / "bench").glob("runtime-*.json"))
    assert rt["file"] == f"results/bench/runtime-{newest}.json"
    assert rt["machine"].startswith("cpu (")
    assert st._runtime_key("train_soft:delay_scaled:2:zeros") == st._runtime_key("train_soft:delay_scaled:2") \
        == "train_soft_lam2"
    assert st._runtime_key("train_soft:delay_scaled:2:consistent") == "train_soft_lam2_consistent"
    assert st._runtime_key("train_soft:delay_scaled:1:zeros") == "train_soft_lam1"
    assert st._runtime_key("train_soft:offset:3") is None and st._runtime_key("naive") == "naive"
    assert st._ratio(rt, "naive", rt["batches"][0]) == "1.00x"
    assert st._ratio(rt, "train_soft:offset:3", rt["batches"][0]) == "–"


def test_block_and_command(study, tmp_path):
    """KR-2, KR-6: rows in order (base rows, Train Hard, the others by name) under the paper's names with levels x
    seeds x episodes; `softrtc kinetix report` prints the block, rewrites the page's and README's blocks between
    the markers and writes the plots; a page without markers ends it with status 2."""
    from softrtc.cli import main

    root, data, summary = study
    assert list(summary) == ["naive", "inference_hard", "inference_soft", "train_hard", "train_soft:delay_scaled:1",
                             "train_soft:delay_scaled:2"]
    block = st.render_block(data, summary, None, "page")
    assert block.startswith(st.BEGIN) and block.endswith(st.END)
    assert "| Train Soft RTC (delay_scaled:2) | 2 x 3 x 24 |" in block
    assert "| Train Soft RTC (delay_scaled:2) | +0.000 [0.000, 0.000] (p 1.000) |" in block
    page = tmp_path / "page.md"
    page.write_text(f"# Page\n\n{st.BEGIN}\nold\n{st.END}\n\ntail\n")
    readme = tmp_path / "README.md"
    readme.write_text(f"x\n{st.BEGIN}\n{st.END}\n")
    out = tmp_path / "plots"
    assert main(["kinetix", "report", "--study", str(root), "--page", str(page), "--readme", str(readme),
                 "--out", str(out), "--bench", str(tmp_path)]) == 0
    assert page.read_text() == f"# Page\n\n{block}\n\ntail\n"
    assert readme.read_text().startswith(f"x\n{st.BEGIN}\n") and "[Kinetix results](docs/reports/kinetix.md)" in \
        readme.read_text()
    for name in st.PLOTS:
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    page.write_text("no markers\n")
    assert main(["kinetix", "report", "--study", str(root), "--page", str(page), "--no-plots"]) == 2
    empty = tmp_path / "empty"
    empty.mkdir()
    assert st.render_block(st.read_study(empty)) == "\n".join(
        [st.BEGIN, "", "The study has no evaluation yet: its `eval/` folder holds no results folder "
         "(`eval/<level>/seed_<k>/`, [KR-1]). Generated by `softrtc kinetix report --study results/kinetix/study`.",
         "", st.END])


def test_committed_page_block_is_the_commands_output():
    """KR-6, KR-7: the Kinetix results page's kinetix-table block (and the README's, where it has the markers) is
    what `softrtc kinetix report` makes of results/kinetix/study/eval and results/bench; without an eval folder
    the page says the study has no evaluation yet."""
    text = (ROOT / "docs" / "reports" / "kinetix.md").read_text()
    i, j = text.find(st.BEGIN), text.find(st.END)
    assert 0 <= i < j
    block = text[i:j + len(st.END)]
    data = st.read_study(ROOT / "results" / "kinetix" / "study")
    summary = None if data is None else st.summarize_study(data)
    if data is None:
        assert "The study has no evaluation yet" in block
    else:
        # Every interval of the committed study is ordered.
        for e in summary.values():
            for scope in ("overall", "high"):
                for s in e["scopes"].get(scope, {}).values():
                    if math.isfinite(s["lo"]):
                        assert s["lo"] <= s["mean"] + 1e-12 <= s["hi"] + 2e-12
    runtime = st.read_runtime(ROOT / "results" / "bench")
    assert block == st.render_block(data, summary, runtime, "page")
    # The README's block, where the README has the markers, is the command's `--readme` block of the same files.
    readme = (ROOT / "README.md").read_text()
    i, j = readme.find(st.BEGIN), readme.find(st.END)
    assert (i < 0) == (j < 0)
    if i >= 0:
        assert readme[i:j + len(st.END)] == st.render_block(data, summary, runtime, "readme")
