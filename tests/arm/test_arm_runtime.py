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
    # a rejected late chunk carries -2 in both its realized and its executed-prefix delay.
    assert not rec.accepted[3] and rec.realized_delays[3] == -2 and rec.exec_delays[3] == -2
    assert set(np.nonzero(rec.exec_delays == -2)[0]) == set(np.nonzero(~rec.accepted & (rec.realized_delays == -2))[0])
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
    # a stalled trial's throughput is over the full trial of max_steps ticks, not the ticks it ran.
    import dataclasses

    assert rec.step_limit == 200
    m = episode_metrics(dataclasses.replace(rec, num_completed=2))
    assert m["throughput"] == pytest.approx(2 / (200 * 0.02 / 60.0))
    assert m["duration_s"] == pytest.approx(rec.steps * 0.02)


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


def test_runtime_ticks_on_an_absolute_schedule_after_a_slow_tick(monkeypatch):
    """R-1: one slow tick does not shift later ticks; tick k starts at T0 + k dt, none is skipped."""
    import time

    from softrtc.arm import runtime as R

    slow_tick, slow_s, dt = 10, 0.1, 0.02

    class SlowTickEnv(R.ArmSortEnv):
        def step(self, action):
            out = super().step(action)
            if self.t == slow_tick + 1:  # the step of tick `slow_tick`
                time.sleep(slow_s)
            return out

    monkeypatch.setattr(R, "ArmSortEnv", SlowTickEnv)
    rec = run_realtime_episode(RampPolicy(), 3, jax.random.key(0), RuntimeConfig(added_latency_s=0.0), max_steps=50)
    assert rec.steps == 50 and rec.periods_s.size == 49  # no tick skipped
    starts = np.concatenate([[0.0], np.cumsum(rec.periods_s)])  # tick start times relative to tick 0 (= T0)
    # The slow tick is late by 5 ticks: the next tick starts at once, after the slow one.
    assert rec.periods_s[slow_tick] >= slow_s
    # Catch-up: ticks whose start time passed run back to back; from tick 16 on the schedule holds again.
    offsets = starts[20:] - np.arange(20, 50) * dt
    assert np.median(offsets) < 0.25 * dt, offsets
    # Every tick starts no earlier than its scheduled time.
    assert np.all(starts - np.arange(50) * dt > -1e-3)


def test_added_latency_results_are_validated():
    """R-8, N-7: a per-request latency that is not a finite number of seconds in [0, 10] is a ValueError."""
    import threading

    for bad in (-1.0, float("nan"), float("inf"), "0.01", True, None, 11.0):
        # Request 0 is fine; the bad value comes with request 1, mid-episode.
        lat = lambda c, bad=bad: 0.0 if c == 0 else bad  # noqa: E731
        with pytest.raises(ValueError, match=r"^added_latency\(1\) must be a finite number in \[0.0, 10.0\]"):
            run_realtime_episode(RampPolicy(), 0, jax.random.key(0), RuntimeConfig(), max_steps=30, added_latency=lat)
        # The worker was stopped before the error left the runtime.
        assert not any(t.name == "softrtc-arm-inference" and t.is_alive() for t in threading.enumerate())
    with pytest.raises(ValueError, match="^added_latency must be None or a callable"):
        run_realtime_episode(RampPolicy(), 0, jax.random.key(0), added_latency=0.1)
    # NumPy numbers are numbers.
    rec = run_realtime_episode(RampPolicy(), 0, jax.random.key(0), RuntimeConfig(), max_steps=12,
                               added_latency=lambda c: np.float32(0.0))
    assert rec.fault is None and rec.steps == 12


def test_runtime_config_takes_numpy_scalars_but_not_booleans():
    """R-3, R-6, R-8, N-7: NumPy integers and floats are accepted and stored as Python numbers; booleans are not."""
    cfg = RuntimeConfig(added_latency_s=np.float32(0.25), latency_window=np.int64(3), max_hold_ticks=np.int32(7),
                        join_timeout_s=np.int64(1))
    assert (cfg.added_latency_s, cfg.latency_window, cfg.max_hold_ticks, cfg.join_timeout_s) == (0.25, 3, 7, 1.0)
    assert type(cfg.latency_window) is int and type(cfg.added_latency_s) is float
    for field, bad in (("latency_window", np.bool_(True)), ("latency_window", True), ("max_hold_ticks", 2.0),
                       ("added_latency_s", np.bool_(False)), ("added_latency_s", "0.1"),
                       ("join_timeout_s", float("nan")), ("latency_window", np.int64(0))):
        with pytest.raises(ValueError, match=f"^{field} must be"):
            RuntimeConfig(**{field: bad})
