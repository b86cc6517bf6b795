"""The arm results page's real-time study table and its committed results ([A-25])."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
RESULTS = ROOT / "results" / "arm" / "realtime" / "results.csv"
BEGIN = "<!-- arm-study:begin (python -m softrtc.arm.study results/arm/realtime/results.csv) -->\n"
END = "<!-- arm-study:end -->"


def test_readme_study_table_is_the_committed_results():
    """A-25: the study table of the arm results page (docs/reports/arm.md) is what `python -m softrtc.arm.study`
    recomputes from the committed results.csv; the run has at least 20 trials per method, run interleaved (each trial's methods in an order
    rotated by the trial index)."""
    pytest.importorskip("jax")
    from softrtc.arm.study import read_results, table_from_results

    text = (ROOT / "docs" / "reports" / "arm.md").read_text()
    assert BEGIN in text and END in text
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    assert block == "```\n" + table_from_results(RESULTS) + "\n```\n"
    runs = read_results(RESULTS)
    methods = ["naive", "train_hard", "train_soft"]
    assert list(runs) == methods and all(len(v) >= 20 for v in runs.values())
    with open(RESULTS, newline="") as f:
        rows = list(csv.DictReader(f))
    for i in range(len(rows) // 3):
        trial = rows[3 * i: 3 * i + 3]
        assert {int(r["trial"]) for r in trial} == {i} and len({r["env_seed"] for r in trial}) == 1
        assert [r["method"] for r in trial] == methods[i % 3:] + methods[:i % 3]
