"""The reduced Kinetix study's block on the Kinetix results page is the report of its committed result files
([KP-14])."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from softrtc.kinetix.study_report import curve_summary, report

ROOT = Path(__file__).resolve().parents[2]
BEGIN, END = "<!-- kinetix-study:begin -->\n", "<!-- kinetix-study:end -->"


def test_curve_summary_by_hand():
    """KP-14: steady rate leaves the first (compiling) iteration out; solve rate over the last 5 iterations
    with episodes; the best iteration's; episodes summed."""
    rows = [{"update": i, "env_steps": 100.0 * i, "wall_s": 50.0 + 10 * (i - 1), "episodes": 2.0,
             "solved": s} for i, s in zip(range(1, 8), [0.0, math.nan, 0.5, 0.0, 0.25, 0.25, 0.0])]
    s = curve_summary(rows)
    assert s["iterations"] == 7 and s["env_steps"] == 700 and s["wall_s"] == 110.0
    assert s["steps_per_s"] == 600 / 60
    assert s["solved_last"] == (0.5 + 0.0 + 0.25 + 0.25 + 0.0) / 5 and s["solved_max"] == 0.5
    assert s["episodes"] == 14
    with pytest.raises(ValueError, match="^rows must hold"):
        curve_summary([])


def test_readme_study_block_matches_the_committed_results():
    """KP-14: the Kinetix results page's learning-curve table and cost estimate are what study_report prints from
    results/kinetix/study/ and results/kinetix/bench.json."""
    text = (ROOT / "docs" / "reports" / "kinetix.md").read_text()
    assert BEGIN in text and END in text
    block = text.split(BEGIN, 1)[1].split(END, 1)[0]
    assert block == report(ROOT / "results" / "kinetix" / "study")


def test_readme_bench_block_matches_the_committed_bench():
    """KC-6: the Kinetix results page's compile and throughput table is format_compile_bench of
    results/kinetix/bench.json."""
    import json

    pytest.importorskip("jax")
    pytest.importorskip("kinetix")
    from softrtc.kinetix.compile_bench import format_compile_bench

    text = (ROOT / "docs" / "reports" / "kinetix.md").read_text()
    begin, end = "<!-- kinetix-bench:begin -->\n", "<!-- kinetix-bench:end -->"
    block = text.split(begin, 1)[1].split(end, 1)[0]
    res = json.loads((ROOT / "results" / "kinetix" / "bench.json").read_text())
    assert block == "```\n" + format_compile_bench(res) + "```\n"
