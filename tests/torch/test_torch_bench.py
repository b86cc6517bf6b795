"""`softrtc bench torch`: rows, ratios and targets from an injected clock; the command's checks ([PT-8])."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

pytest.importorskip("torch")

from softrtc.torch import bench  # noqa: E402

CHUNK_MS = {"naive": 2.0, "train_hard": 2.1, "train_soft": 2.2, "naive_straightforward": 3.0,
            "train_soft_straightforward": 3.5, "inference_soft": 4.0}
TRAIN_MS = {"plain": 10.0, "hard": 11.0, "soft": 11.2}


class ScriptedClock:
    """A clock whose every timed call lasts the row's scripted duration: the bench calls clock() before and
    after each row call, rows in the order of bench.CHUNK_ROWS (per batch size), then TRAIN_ROWS."""

    def __init__(self, rounds_chunk: int, batch_sizes: int, rounds_train: int):
        durations = []
        for _ in range(batch_sizes):
            durations += [CHUNK_MS[k] for _ in range(rounds_chunk) for k in bench.CHUNK_ROWS]
        durations += [TRAIN_MS[k] for _ in range(rounds_train) for k in bench.TRAIN_ROWS]
        self.durations, self.now, self.calls = durations, 0.0, 0

    def __call__(self) -> float:
        if self.calls % 2:
            self.now += self.durations[self.calls // 2] / 1e3
        self.calls += 1
        return self.now


@pytest.mark.slow
def test_ratios_and_targets_from_a_scripted_clock(tmp_path):
    """[PT-8] Medians and ratios come from the clock the benchmark is given (no wall clock): with scripted
    durations, train-time samplers / naive = 2.2 / 2 = 1.10 (FAIL at 1.05), soft / hard step = 11.2 / 11 =
    1.018 (PASS at 1.03), soft / plain = 1.12 (PASS at 1.15); the fast and straightforward chunks agree
    (a measured value, not scripted); the JSON round-trips and the table prints every row."""
    cfg = bench.BenchConfig(calls=3, warmup=1, batch_sizes=(1, 32), train_batch=4, train_calls=2, arch="tiny")
    clock = ScriptedClock(4, 2, 3)
    res = bench.run_benchmark(cfg, clock=clock)
    assert clock.calls == 2 * (len(clock.durations))  # every timed call used the injected clock
    for B in ("1", "32"):
        assert res["chunk"][B]["train_soft"]["ratio"] == pytest.approx(1.1)
        assert res["chunk"][B]["inference_soft"]["ms"] == pytest.approx(4.0)
    assert res["train"]["soft"]["over_hard"] == pytest.approx(11.2 / 11)
    assert res["train"]["soft"]["over_plain"] == pytest.approx(1.12)
    verdict = {t["name"]: t["passed"] for t in res["targets"]}
    assert verdict == {"train-time samplers / naive, batch 1": False, "train-time samplers / naive, batch 32": False,
                       "soft / hard training step": True, "soft / plain flow-matching step": True,
                       "fast and straightforward chunks agree": True}
    assert 0 <= res["agreement"] < 1e-5
    path = tmp_path / "b.json"
    bench.write_json(res, path)
    back = bench.read_json(path)
    assert back["targets"] == res["targets"] and json.loads(path.read_text())["chunk"] == res["chunk"]
    table = bench.format_table(back)
    for label in bench.CHUNK_LABELS.values():
        assert label in table
    assert "FAIL  train-time samplers / naive, batch 1" in table and "PASS  soft / hard training step" in table


@pytest.mark.slow
def test_bench_config_and_command_line_checks(tmp_path):
    """[PT-8], [N-7] BenchConfig rejects bad values naming them; the command exits 2 with one line for a bad
    option or an unreadable --table file, and prints the table of a result file with --table; the adaln
    network runs through the same rows with fast and straightforward chunks agreeing."""
    with pytest.raises(ValueError, match="calls"):
        bench.BenchConfig(calls=0)
    with pytest.raises(ValueError, match="execute_horizon"):
        bench.BenchConfig(execute_horizon=8)
    with pytest.raises(ValueError, match="batch_sizes"):
        bench.BenchConfig(batch_sizes=())
    run = lambda *a: subprocess.run([sys.executable, "-m", "softrtc.cli", "bench", "torch", *a],  # noqa: E731
                                    capture_output=True, text=True, timeout=120)
    r = run("--calls", "0")
    assert r.returncode == 2 and "--calls" in r.stderr
    r = run("--execute-horizon", "8", "--arch", "tiny")  # H = 8: s must leave an overlap
    assert r.returncode == 2 and r.stderr.startswith("softrtc bench torch: error: --execute-horizon must be an "
                                                     "integer in [1, 7], got 8")
    r = run("--table", str(tmp_path / "missing.json"))
    assert r.returncode == 2 and "--table" in r.stderr and len(r.stderr.strip().splitlines()) == 1
    with pytest.raises(ValueError, match="architecture must be one of"):
        bench.BenchConfig(architecture="film")
    res = bench.run_benchmark(bench.BenchConfig(calls=1, warmup=0, batch_sizes=(1,), train_calls=0, arch="tiny"))
    bench.write_json(res, tmp_path / "r.json")
    r = run("--table", str(tmp_path / "r.json"))
    assert r.returncode == 0 and r.stdout.strip() == bench.format_table(res)
    # [PT-6] with the chapter-P network the fast path gives the straightforward chunks too, and the table says
    # which network ran
    ada = bench.run_benchmark(bench.BenchConfig(calls=1, warmup=0, batch_sizes=(2,), train_calls=1, arch="tiny",
                                                architecture="adaln"))
    assert ada["agreement"] < 1e-5 and "tiny policy, adaln network (" in bench.format_table(ada)
    assert "adaln" not in bench.format_table(res)
