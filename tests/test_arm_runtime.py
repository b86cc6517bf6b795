"""Real-time arm runtime (spec chapter R in spec/10-arm.md): alignment, late chunks, stalls, crashes."""

import numpy as np
import jax
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.runtime import RuntimeConfig, jitter_summary, predict_delay, run_realtime_episode  # noqa: E402
from softrtc.arm.executor import episode_metrics  # noqa: E402


class RampPolicy:
    """A fast stand-in policy: joint targets ramp away from the observed joints; injectable faults."""

    method = "ramp"

    def __init__(self, H=10, s=5, crash_at=None):
        self.H, self.s, self.crash_at = H, s, crash_at
        self.calls = []

    def generate(self, obs, prior, d, key):
        c = len(self.calls)
        self.calls.append((None if prior is None else np.array(prior), d))
        if self.crash_at is not None and c == self.crash_at:
            raise RuntimeError("injected crash")
        q = np.asarray(obs[0:3])
        j = np.arange(1, self.H + 1)[:, None]
        # Distinct per chunk so the source of every executed action is identifiable.
        return np.concatenate([q + 0.002 * j + 1e-4 * c, np.full((self.H, 1), 0.1 * (c % 5))], axis=1)


def _check_aligned(rec, H, s):
    """R-4: every chunk action is token k - r_c of chunk c at tick k; never a committed-prefix token."""
    for k, (c, j) in enumerate(zip(rec.chunk_index, rec.token_index)):
        if c < 0:
            assert rec.hold[k] and j == -1
            np.testing.assert_array_equal(rec.actions[k], rec.actions[k - 1])
            continue
        assert j == k - rec.request_step[c], (k, c, j)
        assert 0 <= j < H
        np.testing.assert_array_equal(rec.actions[k], rec.chunks[c][j])
        if c >= 1:
            # R-4, S-5: chunk c runs from token max(predicted, realized delay) on; its committed prefix never.
            assert j >= rec.exec_delays[c] >= rec.delays[c], (k, c, j, rec.exec_delays[c], rec.delays[c])


def test_runtime_realized_delay_alignment_and_prediction():
    """R-1, R-2, R-3, R-4, R-8, R-9, X-1, X-3, X-4: switches, delays, priors and latency in a clean run."""
    pol = RampPolicy()
    rec = run_realtime_episode(pol, 3, jax.random.key(0), RuntimeConfig(added_latency_s=0.02), max_steps=60)
    # Wall-clock timing on a shared machine: a rare late chunk is allowed (it is handled by R-5).
    assert rec.fault is None and rec.steps == 60 and rec.accepted.mean() >= 0.75
    H, s, dmax = 10, 5, 5
    _check_aligned(rec, H, s)
    assert rec.request_step[0] == 0 and rec.delays[0] == 0
    acc = np.nonzero(rec.accepted)[0]
    for c in acc[1:]:
        if not rec.accepted[c - 1] or pol.calls[c][0] is None:
            continue  # a restart after a late chunk (covered by the next test)
        assert rec.request_step[c] == rec.request_step[c - 1] + s  # requests every s ticks
        assert 1 <= rec.delays[c] <= dmax
        assert rec.exec_delays[c] == max(rec.delays[c], rec.realized_delays[c])
        prev_real = [int(np.ceil(rec.latencies_s[0] / rec.dt))] + [int(x) for x in rec.realized_delays[1:c] if x >= 0]
        if rec.accepted[:c].all():
            assert rec.delays[c] == predict_delay(prev_real[-5:], dmax)
        # the prior passed to the sampler is the previous chunk shifted by s, zero-padded.
        prior, d = pol.calls[c]
        np.testing.assert_allclose(prior[: H - s], rec.chunks[c - 1][s:], atol=1e-6)
        assert np.all(prior[H - s:] == 0) and d == rec.delays[c]
        # The switch tick: the first tick of chunk c.
        first = np.nonzero(rec.chunk_index == c)[0]
        if first.size:
            assert first[0] == rec.request_step[c] + rec.exec_delays[c]
    # 20 ms of added latency: at least one tick, never beyond the deadline of R-5.
    assert all(1 <= rec.realized_delays[c] <= dmax for c in acc[1:])
    assert rec.periods_s.size == 59
    j = jitter_summary(rec.periods_s)
    assert 15.0 < j["p50_ms"] < 30.0
    m = episode_metrics(rec)
    assert m["latency_ms"] >= 20.0


def test_runtime_late_chunk_is_rejected_and_arm_holds():
    """R-5, R-6, R-4, X-1: a chunk later than min(s, H - s) ticks is rejected; hold, restart, continue."""
    pol = RampPolicy()
    lat = lambda c: 0.2 if c == 3 else 0.02  # noqa: E731 - request 3 stalls for 10 ticks
    rec = run_realtime_episode(pol, 4, jax.random.key(1), RuntimeConfig(), max_steps=70, added_latency=lat)
    assert rec.fault is None and rec.steps == 70
    kinds = [e[1] for e in rec.events]
    assert "late_reject" in kinds and "restart_request" in kinds and "hold_start" in kinds
    assert not rec.accepted[3] and rec.realized_delays[3] == -2
    assert not np.any(rec.chunk_index == 3)  # never executed
    assert rec.hold.sum() >= 1
    _check_aligned(rec, 10, 5)
    # The restart request has no prior and d = 0 ([X-2]); execution resumes aligned afterwards.
    restarts = [e[2] for e in rec.events if e[1] == "restart_request"]
    assert all(pol.calls[c][0] is None and pol.calls[c][1] == 0 for c in restarts)
    assert any(np.any(rec.chunk_index == c) for c in restarts)
    # The control loop kept ticking through the stall.
    assert rec.periods_s.size == 69 and jitter_summary(rec.periods_s)["p50_ms"] < 30.0


def test_runtime_permanent_stall_ends_cleanly():
    """R-6, R-7: a worker that never answers in time ends the episode with a stall fault."""
    pol = RampPolicy()
    lat = lambda c: 0.8 if c >= 2 else 0.0  # noqa: E731
    cfg = RuntimeConfig(max_hold_ticks=10, join_timeout_s=3.0)
    rec = run_realtime_episode(pol, 5, jax.random.key(2), cfg, max_steps=200, added_latency=lat)
    assert rec.fault is not None and rec.fault.startswith("stall")
    assert rec.steps < 200 and rec.hold[-10:].all()
    assert "worker_not_joined" not in [e[1] for e in rec.events]
    _check_aligned(rec, 10, 5)


def test_runtime_worker_crash_ends_cleanly():
    """R-7: an exception in the inference thread is logged; the loop stops without an undefined action."""
    pol = RampPolicy(crash_at=2)
    rec = run_realtime_episode(pol, 6, jax.random.key(3), RuntimeConfig(added_latency_s=0.0), max_steps=100)
    assert rec.fault is not None and rec.fault.startswith("worker_error: RuntimeError: injected crash")
    assert any(e[1] == "worker_error" and "injected crash" in e[2] for e in rec.events)
    assert rec.steps < 100 and np.all(np.isfinite(rec.actions))
    assert "worker_not_joined" not in [e[1] for e in rec.events]
    _check_aligned(rec, 10, 5)
    # A crash on the very first request also ends cleanly with no action at all.
    rec0 = run_realtime_episode(RampPolicy(crash_at=0), 6, jax.random.key(3), RuntimeConfig(), max_steps=10)
    assert rec0.steps == 0 and rec0.fault.startswith("worker_error")


def test_predict_delay_rule_and_validation():
    """R-3, N-7: max of recent realized delays, at least 1, at most min(s, H - s); inputs validated."""
    assert predict_delay([2, 3, 1], 5) == 3
    assert predict_delay([0], 5) == 1
    assert predict_delay([9, 2], 5) == 5
    for bad in ([], [1.5], [-1], [True]):
        with pytest.raises(ValueError, match="recent_delays"):
            predict_delay(bad, 5)
    with pytest.raises(ValueError, match="max_delay"):
        predict_delay([1], 0)
    with pytest.raises(ValueError, match="added_latency_s"):
        RuntimeConfig(added_latency_s=-1.0)
    with pytest.raises(ValueError, match="latency_window"):
        RuntimeConfig(latency_window=0)
    with pytest.raises(ValueError, match="max_steps"):
        run_realtime_episode(RampPolicy(), 0, jax.random.key(0), max_steps=0)
    with pytest.raises(ValueError, match="env_seed"):
        run_realtime_episode(RampPolicy(), -1, jax.random.key(0))
    with pytest.raises(ValueError, match="key"):
        run_realtime_episode(RampPolicy(), 0, 0)
    with pytest.raises(ValueError, match="periods_s"):
        jitter_summary([])


def test_runtime_helpers_validate_inputs():
    """N-7, R-3: predict_delay and jitter_summary reject what they cannot mean."""
    from softrtc.arm.runtime import jitter_summary

    for bad in (5, [True], [-1], [1.5]):
        with pytest.raises(ValueError, match="^recent_delays"):
            predict_delay(bad, 3)
    for bad in ([-1.0, 0.02], [True, False], [], [float("nan")]):
        with pytest.raises(ValueError, match="^periods_s"):
            jitter_summary(bad)
    assert predict_delay([2, 3], 4) == 3 and jitter_summary([0.02, 0.02])["p50_ms"] == pytest.approx(20.0)
