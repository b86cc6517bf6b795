"""The screen and the single-level study as run: the spec's numbers are those of the committed files ([KS-9], [KS-10])."""

from __future__ import annotations

import csv
import json
import re
from collections import defaultdict
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SCREEN = ROOT / "results" / "kinetix" / "screen"
EVAL = ROOT / "results" / "kinetix" / "study" / "eval" / "m_h0_unicycle"
SPEC = (ROOT / "spec" / "20-kinetix.md").read_text()


def _section(rid):
    start = SPEC.index(f"**[{rid}]**")
    nxt = SPEC.find("- **[", start + 1)
    return SPEC[start:nxt if nxt > 0 else None]


def _solve(seed):
    acc = defaultdict(list)
    with open(EVAL / f"seed_{seed}" / "episodes.csv") as f:
        for r in csv.DictReader(f):
            acc[(r["method"], int(r["delay"]))].append(r["solved"] in ("True", "1"))
    return {k: sum(v) / len(v) for k, v in acc.items()}


def test_screened_levels_none_kept():
    """KS-9: every level the spec lists as screened has a completed screen that drops it, with the stated reason."""
    text = _section("KS-9")
    listed = re.findall(r"`([sml]_[a-z0-9_]+)`", text.split("None is kept")[0])
    assert len(listed) == 12, listed
    for level in listed:
        res = json.loads((SCREEN / level / "screen.json").read_text())
        assert res["level"] == level and res["kept"] is False
    for level in ("l_h14_simple_thruster", "m_arm_up", "m_arm_left"):
        res = json.loads((SCREEN / level / "screen.json").read_text())
        assert max(c["solved"] for c in json.loads((SCREEN / level / "baselines.json").read_text())["constant"]) == 1.0
        assert any("constant action solves" in r for r in res["reasons"])
    unicycle = json.loads((SCREEN / "m_h0_unicycle" / "screen.json").read_text())
    rates = [round(d["solved"], 2) for d in unicycle["expert_by_delay"]]
    assert rates == [1.0, 1.0, 1.0, 0.95]
    assert len(unicycle["reasons"]) == 1 and "does not fall with delay" in unicycle["reasons"][0]
    # The stopped level has its baselines only, and its baselines solve nothing.
    base = json.loads((SCREEN / "m_h14_thrustblock" / "baselines.json").read_text())
    assert max(c["solved"] for c in base["constant"]) == 0.0
    assert not (SCREEN / "m_h14_thrustblock" / "screen.json").exists()


def test_study_numbers_are_the_committed_episodes():
    """KS-10: the base misses 0.8x the expert at d = 0, the chunked policies lose with delay, and the lam = 1
    rows repeat Train Hard seed 0 episode for episode (an empty window at H = 8, s = 4)."""
    s0 = _solve(0)
    text = _section("KS-10")
    assert f"{s0[('naive', 0)]:.2f}" == "0.53" and f"{s0[('naive', 4)]:.2f}" == "0.27"
    assert f"{s0[('train_hard', 0)]:.2f}" == "0.80" and f"{s0[('train_hard', 4)]:.2f}" == "0.41"
    for needle in ("0.53 at d = 0 and 0.27", "0.80 and 0.41", "0.53\n  against 0.8 x 1.00"):
        assert needle in text, needle
    assert s0[("naive", 0)] < 0.8 * 1.0
    rows = defaultdict(dict)
    with open(EVAL / "seed_0" / "episodes.csv") as f:
        for r in csv.DictReader(f):
            rows[r["method"]][(r["delay"], r["episode"])] = tuple(r[k] for k in ("return", "solved", "delta", "jerk"))
    assert rows["train_soft:delay_scaled:1"] == rows["train_hard"]
    assert rows["train_soft:delay_scaled:1:zeros"] == rows["train_hard"]
    assert rows["train_soft:delay_scaled:2"] != rows["train_hard"]
