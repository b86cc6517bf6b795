"""Scale-out of the Kinetix evaluation over two JAX processes on this machine ([KD-1]..[KD-4], [KC-5])."""

from __future__ import annotations

import csv
import math
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

from tests.conftest import SHARED_LEVELS_REASON  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()
needs_levels = pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _eval_cmd(out: Path, cache: Path, *extra) -> list:
    return [sys.executable, "-c", "import sys; from softrtc.cli import main; sys.exit(main())", "kinetix", "eval", "--levels", "grasp_easy", "--levels-dir",
            str(LEVELS_DIR), "--episodes", "3", "--delays", "0,2", "--methods", "naive", "--init-seed", "1",
            "--out", str(out), "--no-progress", "--compile-cache", str(cache), *extra]


def test_distributed_options_go_together():
    """KD-1: --coordinator, --num-processes and --process-id go together, the id below the count, and the
    coordinator is HOST:PORT; each mistake is one error line naming the option, status 2."""
    from softrtc.cli import main
    from softrtc.kinetix.distributed import parse_coordinator

    assert parse_coordinator(" localhost:1234 ") == "localhost:1234"
    for bad in ("localhost", "host:0", "host:99999", ":12"):
        with pytest.raises(ValueError, match="^coordinator"):
            parse_coordinator(bad)
    base = ["kinetix", "eval", "--levels", "grasp_easy", "--out", "/tmp/softrtc-never-written"]
    assert main(base + ["--coordinator", "localhost:1234"]) == 2
    assert main(base + ["--coordinator", "localhost:1234", "--num-processes", "2", "--process-id", "2"]) == 2


@needs_levels
@pytest.mark.slow
def test_two_processes_give_the_one_process_table(tmp_path):
    """KD-1, KD-2, KD-3, KD-4, KC-5: an evaluation run as two jax.distributed processes on this machine (one
    CPU device each, the 6 episodes sharded 3 + 3) writes, from process 0 only, the same table.md as one
    process and the same episodes to float32 rounding; process 1 writes nothing; no program is stored for the two-process run."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    one = subprocess.run(_eval_cmd(tmp_path / "one", tmp_path / "cc1"), capture_output=True, text=True, env=env,
                         timeout=1800)
    assert one.returncode == 0, one.stderr[-3000:]
    addr = f"127.0.0.1:{_free_port()}"
    procs = [subprocess.Popen(_eval_cmd(tmp_path / f"two{i}", tmp_path / "cc2", "--coordinator", addr,
                                        "--num-processes", "2", "--process-id", str(i), "--local-devices", "1"),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env) for i in range(2)]
    outs = [p.communicate(timeout=1800) for p in procs]
    for p, (_, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    assert not (tmp_path / "two1").exists()
    assert (tmp_path / "two0" / "table.md").read_text() == (tmp_path / "one" / "table.md").read_text()
    # Per episode: identifiers, flags and lengths exact; real values to float32 rounding (XLA compiles a
    # batch of 3 per device differently from a batch of 6, which moves last digits of delta and jerk).
    rows = [list(csv.DictReader(open(tmp_path / d / "episodes.csv"))) for d in ("two0", "one")]
    assert len(rows[0]) == len(rows[1]) == 6
    for a, b in zip(*rows):
        assert [a[k] for k in ("method", "level", "delay", "episode", "solved", "length")] == \
            [b[k] for k in ("method", "level", "delay", "episode", "solved", "length")]
        for k in ("return", "delta", "jerk"):
            assert math.isclose(float(a[k]), float(b[k]), rel_tol=1e-5, abs_tol=1e-6), (k, a, b)
    assert "| Base Naive |" in outs[0][0] and "| Method |" not in outs[1][0]  # gloo's own lines aside, silent
    assert list((tmp_path / "cc2" / "programs").glob("*.bin")) == []
    assert len(list((tmp_path / "cc1" / "programs").glob("kinetix_rollout-*.bin"))) == 1
