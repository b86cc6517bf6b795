"""The arm experiment's result files are checked as they are read ([AX-12]) and its workers end with the run
([AX-13]).

A tiny hand-written results folder (two rows, two delays, three episodes) is damaged one way at a time; each
damage is one ValueError naming the file (and the line), never a changed report.
"""

from __future__ import annotations

import csv
import json
import os
import select
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from softrtc.arm import result_files as rf
from softrtc.arm.report_summary import load_results

FIELDS = ("row", "seed", "delay", "episode", "env_seed", "success", "completed", "completion", "steps",
          "success_step", "D1", "D2", "D3", "boundary", "mean_abs_action")
BUDGET = {"main_seeds": 2, "main_episodes": 3, "sweep_seeds": 1, "sweep_episodes": 2, "finetune_steps": 4,
          "max_steps": 60}
# s = 6, H = 10: executable delays 0 .. 4.
MANIFEST = {"task": "overlap4", "execute_horizon": 6, "H": 10, "budget": "quick", "budget_values": BUDGET,
            "seed0": 10000, "key_seed": 0, "order": ["naive", "train_hard"],
            "rows": {"naive": {"tier": "main", "eval_key": "aaaa", "train_key": None},
                     "train_hard": {"tier": "main", "eval_key": "bbbb", "train_key": "hard"}}}


def _episode(row, seed, delay, i, **over):
    ep = {"row": row, "seed": seed, "delay": delay, "episode": i, "env_seed": 10000 + i, "success": i % 2,
          "completed": 2, "completion": 0.5, "steps": 60, "success_step": -1, "D1": 0.1, "D2": 0.2, "D3": 0.3,
          "boundary": 0.05, "mean_abs_action": 1.0}
    return dict(ep, **over)


def _write_cell(folder, key, seed, delay, episodes):
    path = folder / "episodes" / f"{key}_s{seed}_d{delay}.csv"
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=FIELDS)
        w.writeheader()
        w.writerows(episodes)
    return path


@pytest.fixture
def folder(tmp_path):
    task = tmp_path / "overlap4"
    (task / "episodes").mkdir(parents=True)
    (task / "finetunes").mkdir()
    (task / "manifest.json").write_text(json.dumps(MANIFEST))
    (task / "prior_error.json").write_text(json.dumps({"rms": {"1": [0.1]}, "sigma": [[0.1, 0.2]], "episodes": 1}))
    (task / "finetunes" / "hard_seed1.json").write_text(json.dumps(
        {"key": "hard", "seed": 1, "steps": 4, "final_loss": 0.5, "seconds": 1.0, "sha256_16": "0123456789abcdef"}))
    for d in (0, 4):
        _write_cell(task, "aaaa", 0, d, [_episode("naive", 0, d, i) for i in range(3)])
        _write_cell(task, "bbbb", 1, d, [_episode("train_hard", 1, d, i) for i in range(3)])
    return task


def _fails(folder, pattern):
    with pytest.raises(ValueError, match=pattern):
        load_results(folder)


def test_valid_folder_loads(folder):
    """AX-12: the intact folder gives its four cells, three episodes each, as written."""
    res = load_results(folder)
    assert sorted(res["cells"]) == [("naive", 0, 0), ("naive", 0, 4), ("train_hard", 1, 0), ("train_hard", 1, 4)]
    assert [e["success"] for e in res["cells"][("naive", 0, 4)]] == [0, 1, 0]
    assert res["finetunes"]["hard_seed1"]["final_loss"] == 0.5


@pytest.mark.parametrize("damage, line, pattern", [
    ({"D2": "nan"}, 3, r"D2 must be a finite number, got nan"),
    ({"boundary": "inf"}, 3, r"boundary must be a finite number, got inf"),
    ({"completion": "7.0"}, 3, r"completion must lie in \[0, 1\], got 7.0"),
    ({"success": "2"}, 3, r"success must be 0 or 1, got 2"),
    ({"success": "yes"}, 3, r"success must be an integer, got 'yes'"),
    ({"delay": "3"}, 3, r"seed 1 and delay 3 differ from the file name's s1 and d4"),
    ({"episode": "0"}, 3, r"repeats an episode: episode 0, expected 1"),
])
def test_damaged_episode_rows_name_file_and_line(folder, damage, line, pattern):
    """AX-12: NaN or infinite metrics, completion 7, success 2 or 'yes', a row of another delay, a repeated
    episode: each is an error naming the file and its line (the header is line 1)."""
    eps = [_episode("train_hard", 1, 4, i) for i in range(3)]
    eps[1].update(damage)
    path = _write_cell(folder, "bbbb", 1, 4, eps)
    _fails(folder, rf"episode file {str(path)!r} line {line}.*{pattern}")


def test_cells_against_the_task_and_the_budget(folder):
    """AX-12: rows appended twice, more episodes than the budget, a delay past the task's 0 .. 4, a seed past
    the budget's (or 0 for a fine-tuned row), an eval key of no row: each is an error naming the file."""
    eps = [_episode("train_hard", 1, 4, i) for i in range(3)]
    path = _write_cell(folder, "bbbb", 1, 4, eps + eps)
    _fails(folder, rf"{str(path)!r} holds 6 episodes; the budget gives its rows at most 3")
    _write_cell(folder, "bbbb", 1, 4, eps[:2] + eps[1:2])
    _fails(folder, rf"{str(path)!r} line 4 repeats an episode: episode 1, expected 2")
    _write_cell(folder, "bbbb", 1, 4, eps)
    bad = _write_cell(folder, "bbbb", 1, 9, [_episode("train_hard", 1, 9, 0)])
    _fails(folder, rf"{str(bad)!r}: delay 9 is not among the task's delays 0 .. 4")
    bad.unlink()
    bad = _write_cell(folder, "bbbb", 3, 0, [_episode("train_hard", 3, 0, 0)])
    _fails(folder, rf"{str(bad)!r}: seed 3 is not among the budget's seeds of its rows \(1 .. 2\)")
    bad.unlink()
    bad = _write_cell(folder, "bbbb", 0, 0, [_episode("train_hard", 0, 0, 0)])
    _fails(folder, r"seed 0 is not among")
    bad.unlink()
    bad = _write_cell(folder, "cccc", 0, 0, [_episode("x", 0, 0, 0)])
    _fails(folder, rf"{str(bad)!r}: eval key 'cccc' belongs to no row of the manifest")
    bad.unlink()
    load_results(folder)


def test_damaged_json_files_name_themselves(folder):
    """AX-12: a half-written manifest, NaN in prior_error.json or in a fine-tune record, a record without its
    digest: each is one error naming the file."""
    manifest = folder / "manifest.json"
    text = manifest.read_text()
    manifest.write_text(text[: len(text) // 2])
    _fails(folder, rf"manifest {str(manifest)!r} is damaged \(not valid JSON")
    manifest.write_text(json.dumps(dict(MANIFEST, rows="x")))
    _fails(folder, r"has no valid 'rows'")
    manifest.write_text(text)
    prior = folder / "prior_error.json"
    prior.write_text('{"rms": {"1": [NaN]}, "sigma": [[0.1]]}')
    _fails(folder, rf"prior error {str(prior)!r} is damaged .*NaN is not a finite number")
    prior.write_text('{"rms": {}, "sigma": [[-0.1]]}')
    _fails(folder, r"sigma row 0 must be a list of finite numbers >= 0")
    prior.write_text('{"rms": {}, "sigma": [[0.1]]}')
    record = folder / "finetunes" / "hard_seed1.json"
    record.write_text('{"final_loss": NaN, "sha256_16": "0123456789abcdef", "steps": 4}')
    _fails(folder, rf"fine-tune record {str(record)!r} is damaged")
    record.write_text('{"final_loss": 0.5, "steps": 4}')
    _fails(folder, r"has no 16-digit checkpoint digest")


def test_resume_names_a_half_written_manifest(tmp_path):
    """AX-12: `arm experiment` resuming into a folder whose manifest.json was cut short stops with an error
    naming the file, before any work."""
    from softrtc.arm.experiment import run_experiment

    task = tmp_path / "out" / "overlap4"
    task.mkdir(parents=True)
    (task / "manifest.json").write_text('{"task": "overlap4", "budget_val')
    with pytest.raises(ValueError, match=rf"manifest {str(task / 'manifest.json')!r} is damaged"):
        run_experiment("overlap4", "quick", out=tmp_path / "out", work=tmp_path / "work", log=lambda m: None)
    assert not (task / "prior_error.json").exists()


def test_a_checkpoint_without_its_record_is_fine_tuned_again(tmp_path, monkeypatch):
    """AX-13: a fine-tuned checkpoint whose record file was lost is not reused silently: it is fine-tuned
    again and its record written; a fine-tune that no longer gives the checkpoint it replaces is an error."""
    import hashlib

    import softrtc.arm.checkpoints as ck
    from softrtc.arm import experiment as ex

    calls = []

    def fake_finetune(key, row, task, seed, budget, data, base, sigma, path):
        calls.append((key, seed))
        Path(path).write_bytes(b"checkpoint A")
        return {"key": key, "seed": seed, "steps": budget.finetune_steps, "final_loss": 0.25, "seconds": 0.0,
                "sha256_16": hashlib.sha256(b"checkpoint A").hexdigest()[:16], "window": None}

    monkeypatch.setattr(ex, "_finetune", fake_finetune)
    monkeypatch.setattr(ex, "_demos", lambda *a: None)
    monkeypatch.setattr(ex, "_run_cell", lambda args: (args[-1], 0.0))
    monkeypatch.setattr(ck, "load_arm_checkpoint", lambda path: object())
    out, work = tmp_path / "out", tmp_path / "work"
    (out / "overlap4").mkdir(parents=True)
    (out / "overlap4" / "prior_error.json").write_text(json.dumps({"rms": {}, "sigma": [[0.0] * 4] * 10}))
    ckpt = work / "overlap4" / "quick" / "hard_seed1.npz"
    ckpt.parent.mkdir(parents=True)
    ckpt.write_bytes(b"checkpoint A")
    kw = dict(out=out, work=work, rows=["train_hard"], delays=[0], seeds=[1], tiers=("main",), workers=1,
              log=lambda m: None)
    ex.run_experiment("overlap4", "quick", **kw)
    record = out / "overlap4" / "finetunes" / "hard_seed1.json"
    assert calls == [("hard", 1)] and json.loads(record.read_text())["final_loss"] == 0.25
    ex.run_experiment("overlap4", "quick", **kw)
    assert calls == [("hard", 1)]  # checkpoint and record both there: reused
    record.unlink()
    ckpt.write_bytes(b"checkpoint B")
    want = hashlib.sha256(b"checkpoint B").hexdigest()[:16]
    with pytest.raises(ValueError, match=rf"but the checkpoint {str(ckpt)} it replaces records {want}"):
        ex.run_experiment("overlap4", "quick", **kw)
    assert not ckpt.exists() and not record.exists()


# A script that runs job_runner with two workers blocked forever; each worker first writes its pid to a FIFO.
_RUNNER = textwrap.dedent("""
    import os, sys, threading
    from softrtc.arm.workers import job_runner

    def job(fifo):
        with open(fifo, "w") as f:
            f.write(f"{os.getpid()}\\n")
        threading.Event().wait()

    if __name__ == "__main__":
        with job_runner(2) as run:
            for _ in run(job, [sys.argv[1]] * 2):
                pass
""")


def _wait_gone(pid: int, timeout: float) -> bool:
    """True when process ``pid`` has ended (exited or a zombie) within ``timeout`` seconds (a pidfd, no polling)."""
    try:
        fd = os.pidfd_open(pid)
    except ProcessLookupError:
        return True
    try:
        return bool(select.select([fd], [], [], timeout)[0])
    finally:
        os.close(fd)


@pytest.mark.skipif(not hasattr(os, "pidfd_open"), reason="needs Linux pidfds")
@pytest.mark.parametrize("sig, status", [(signal.SIGTERM, 143), (signal.SIGKILL, -9)])
def test_workers_end_with_the_run(tmp_path, sig, status):
    """AX-13: SIGTERM to a run ends it with status 143 after its workers are gone; SIGKILL (no cleanup
    possible) ends them through the parent-death signal. Both within seconds, not when their jobs end."""
    script = tmp_path / "runner.py"
    script.write_text(_RUNNER)
    fifo = tmp_path / "pids"
    os.mkfifo(fifo)
    parent = subprocess.Popen([sys.executable, str(script), str(fifo)], stderr=subprocess.PIPE)
    try:
        # Read-write: the FIFO has a writer (this end) throughout, so a read waits for the workers' lines
        # instead of ending at the first worker's close.
        with os.fdopen(os.open(fifo, os.O_RDWR)) as f:
            pids = [int(f.readline()), int(f.readline())]
        assert parent.poll() is None and all(not _wait_gone(p, 0) for p in pids)
        parent.send_signal(sig)
        assert parent.wait(timeout=60) == status
        assert all(_wait_gone(p, 60) for p in pids), "a worker outlived the run"
    finally:
        if parent.poll() is None:
            parent.kill()


def test_resume_reads_episode_files_with_the_same_checks(folder):
    """AX-12: the experiment's own reader (used to find complete cells on a resume) names the file, line and
    field of a value of the wrong type, as the report's does."""
    from softrtc.arm.experiment import read_episodes

    eps = [_episode("naive", 0, 0, i) for i in range(3)]
    eps[2]["steps"] = "12.5"
    path = _write_cell(folder, "aaaa", 0, 0, eps)
    with pytest.raises(ValueError, match=rf"^episode file {str(path)!r} line 4: steps must be an integer, got '12.5'$"):
        read_episodes(path)
