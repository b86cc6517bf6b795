"""Benchmark requests are checked against the machine's memory before any work ([B-16])."""

from __future__ import annotations

import pytest

from softrtc import _memory
from softrtc.cli import main

# [B-16] The benchmark architecture: H = 8, 4 layers, channel_dim 256 + channel_hidden_dim 512, 64 bytes per
# unit: 8 * 4 * 768 * 64 = 1572864 bytes per example.
PER_EXAMPLE = 8 * 4 * 768 * 64


def test_step_bytes_hand_values():
    """B-16: the estimate is linear in the batch: 1572864 bytes per example of the benchmark architecture,
    above XLA's measured 1.51 MB per example of the training step at batch 512."""
    assert _memory.step_bytes(1, 8, 4, 256, 512) == PER_EXAMPLE == 1572864
    assert _memory.step_bytes(65536, 8, 4, 256, 512) == 103079215104
    assert PER_EXAMPLE > 1.51e6
    _memory.check_fits("--x", 10, 100, 100)  # exactly what is available fits
    _memory.check_fits("--x", 10, 100, None)  # unknown memory: not checked
    with pytest.raises(ValueError, match=r"^--x 10 needs about 0.0 GB \(0.00 MB per example\), more than"):
        _memory.check_fits("--x", 10, 101, 100)
    assert _memory.available_bytes() is None or _memory.available_bytes() > 0


def _status(argv):
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


@pytest.mark.parametrize("argv, option, batch", [
    (["bench", "runtime", "--train-batch", "65536"], "--train-batch", 65536),
    (["bench", "runtime", "--batch-sizes", "1,65536", "--train-calls", "0"], "--batch-sizes entry", 65536),
    (["bench", "vjp", "--batch-sizes", "4096"], "--batch-sizes entry", 4096),
    (["bench", "torch", "--train-batch", "65536"], "--train-batch", 65536),
    (["bench", "torch", "--batch-sizes", "65536"], "--batch-sizes entry", 65536),
])
def test_bench_requests_too_large_for_the_machine_fail_at_once(argv, option, batch, tmp_path, capsys,
                                                                monkeypatch):
    """B-16 N-11: with 4 GB available, a batch whose estimate exceeds it ends the command with status 2 and
    one line naming the option and both sizes, before the benchmark starts (no progress line, no file)."""
    if argv[1] == "torch":
        pytest.importorskip("torch")
    monkeypatch.setattr(_memory, "available_bytes", lambda: 4 * 10**9)
    out = tmp_path / "b.json"
    assert _status(argv + ["--calls", "1", "--out", str(out)]) == 2
    need = batch * PER_EXAMPLE
    assert capsys.readouterr().err == (
        f"softrtc {' '.join(argv[:2])}: error: {option} {batch} needs about {need / 1e9:.1f} GB "
        f"({PER_EXAMPLE / 1e6:.2f} MB per example), more than the 4.0 GB this machine has available; "
        f"use a smaller {option}\n")
    assert not out.exists()
