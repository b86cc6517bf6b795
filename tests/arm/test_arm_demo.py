"""The arm part of `softrtc demo` (softrtc/arm/demo.py): paired episodes of the base's methods on drift, their
table, the committed cells beside them, the plot, and its checks at the door."""

from __future__ import annotations

import csv

import pytest

pytest.importorskip("jax")
pytest.importorskip("pymunk")
pytest.importorskip("matplotlib")

from softrtc.arm import demo as D  # noqa: E402
from softrtc.arm import experiment as E  # noqa: E402
from softrtc.arm.tasks import get_task  # noqa: E402


def test_table_counts_successes_and_averages_by_hand():
    """A-24, M-1: "solved/N" and the mean D2 and boundary jump of a cell; a delay a row lacks shows "-"."""
    out = {"naive": {1: [{"success": True, "D2": 0.1, "boundary": 0.2},
                         {"success": False, "D2": 0.3, "boundary": 0.4}],
                     5: [{"success": False, "D2": 0.5, "boundary": 0.7}]},
           "inference_hard": {1: [{"success": 1, "D2": 0.2, "boundary": float("nan")}]}}
    lines = D.format_table(out, {"naive": "Naive (base)"}).splitlines()
    assert lines[0].split()[:3] == ["method", "d=1:", "solved"] and "d=5:" in lines[0]
    assert lines[2].split() == ["Naive", "(base)", "1/2", "0.2000", "0.3000", "0/1", "0.5000", "0.7000"]
    # a NaN boundary is left out of the mean (an episode with one chunk has none); no d = 5 cell: "-"
    assert lines[3].split() == ["inference_hard", "1/1", "0.2000", "nan", "-", "-", "-"]


@pytest.mark.slow
def test_demo_episodes_are_the_experiments_cells(tmp_path, capsys):
    """AX-2, X-1: the demo's episodes are the experiment's cell episodes of the same row, delay, env seed and
    sampler key (run here through the experiment's own cell runner), for every row the shipped base runs;
    the table, the committed cells (read from a results folder) and the plot come out."""
    task = get_task("drift")
    res_root = tmp_path / "results"
    (res_root / "drift" / "episodes").mkdir(parents=True)
    rows = {r.name: r for r in E.rows_for(task)}
    for name in D.DEMO_ROWS:
        path = res_root / "drift" / "episodes" / f"{E.eval_key(rows[name], task)}_s0_d2.csv"
        E._run_cell((str(task.base_checkpoint()), "drift", rows[name], 0, 2, 2, 10_000, 0, 12, str(path)))
    png = tmp_path / "arm.png"
    out = D.run_demo(png, episodes=2, delays=(2,), max_steps=12, results_root=res_root)
    text = capsys.readouterr().out
    assert list(out) == list(D.DEMO_ROWS)
    for name in D.DEMO_ROWS:
        with open(res_root / "drift" / "episodes" / f"{E.eval_key(rows[name], task)}_s0_d2.csv") as f:
            want = list(csv.DictReader(f))
        got = out[name][2]
        assert [e["steps"] for e in got] == [int(w["steps"]) for w in want] == [12, 12]
        assert [e["success"] for e in got] == [bool(int(w["success"])) for w in want]
        assert [e["D2"] for e in got] == pytest.approx([float(w["D2"]) for w in want], rel=1e-12)
        assert [e["boundary"] for e in got] == pytest.approx([float(w["boundary"]) for w in want], rel=1e-12)
    assert "the committed experiment's cells of these rows" in text and f"wrote {png}" in text
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("kwargs,match", [
    ({"delays": (6,)}, r"delays\[0\] must be an integer in \[0, 5\]"),
    ({"delays": ()}, "delays must be a non-empty tuple"),
    ({"delays": (1, 1)}, "must not repeat"),
    ({"episodes": 0}, "episodes must be an integer in"),
    ({"task_name": "nope"}, "task"),
])
def test_bad_arguments_are_refused_before_any_episode(tmp_path, kwargs, match):
    """N-7: every argument is checked at the door with one error naming it."""
    with pytest.raises(ValueError, match=match):
        D.run_demo(tmp_path / "x.png", **kwargs)
    with pytest.raises(ValueError, match="plot_path must be"):
        D.run_demo(tmp_path / "x.svg")
    assert not (tmp_path / "x.png").exists()
