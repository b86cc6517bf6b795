"""Real-time arm runtime (spec chapter R in spec/10-arm.md): alignment, late chunks, stalls, crashes, bad chunks.

Every episode here but one runs on a :class:`SimulatedClock` ([R-10]): a
policy call takes no simulated time, a request is back exactly its added
latency after it was made, and so every tick, delay and switch is known in
advance and asserted exactly. No test sleeps or bounds wall-clock time.
"""

import threading

import jax
import numpy as np
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.clock import SimulatedClock, WallClock  # noqa: E402
from softrtc.arm.executor import episode_metrics  # noqa: E402
from softrtc.arm.runtime import RuntimeConfig, jitter_summary, predict_delay, run_realtime_episode  # noqa: E402

DT = 0.02  # the arm's control period (50 Hz)


def ticks(n: float) -> float:
    """An added latency that brings a request back after exactly ceil(n) ticks (n not an integer)."""
    return n * DT


class RampPolicy:
    """A fast stand-in policy: joint targets ramp away from the observed joints; injectable faults."""

    method = "ramp"

    def __init__(self, H=10, s=5, crash_at=None, bad=None):
        self.H, self.s, self.crash_at, self.bad = H, s, crash_at, bad or {}
        self.calls = []

    def generate(self, obs, prior, d, key):
        c = len(self.calls)
        self.calls.append((None if prior is None else np.array(prior), d))
        if self.crash_at is not None and c == self.crash_at:
            raise RuntimeError("injected crash")
        if c in self.bad:
            return self.bad[c]
        q = np.asarray(obs[0:3])
        j = np.arange(1, self.H + 1)[:, None]
        # Distinct per chunk so the source of every executed action is identifiable.
        return np.concatenate([q + 0.002 * j + 1e-4 * c, np.full((self.H, 1), 0.1 * (c % 5))], axis=1)


def run(policy=None, seed=3, latency=None, config=None, max_steps=60, **kw):
    clock = SimulatedClock()
    rec = run_realtime_episode(policy or RampPolicy(), seed, jax.random.key(seed),
                               config or RuntimeConfig(added_latency_s=ticks(1.5)), max_steps=max_steps,
                               added_latency=latency, clock=clock, **kw)
    return rec, clock


def _check_aligned(rec, H):
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
    """R-1, R-2, R-3, R-4, R-8, R-9, R-10, X-1, X-3, X-4: with latencies of 1.5, 2.5, 0.5 and 3.5 ticks the realized
    delays are 2, 3, 1 and 4 ticks; prediction, executed prefix, switch ticks, priors and latencies follow."""
    back = {0: 0.5, 1: 2.5, 2: 0.5, 3: 3.5}  # ticks after the request; others 1.5
    pol = RampPolicy()
    rec, _ = run(pol, latency=lambda c: ticks(back.get(c, 1.5)))
    H, s, dmax = 10, 5, 5
    assert rec.fault is None and rec.steps == 60 and rec.accepted.all()
    assert list(rec.request_step) == list(range(0, 60, 5))  # every s ticks
    assert list(rec.realized_delays) == [0, 3, 1, 4] + [2] * 8
    # R-3 by hand: the first latency counts ceil(0.5) = 1 tick; then max of the last 5 realized delays, >= 1.
    # The 4 of chunk 3 leaves the window of 5 after chunk 8.
    assert list(rec.delays) == [0, 1, 3, 3, 4, 4, 4, 4, 4, 2, 2, 2]
    assert list(rec.exec_delays) == [0, 3, 3, 4, 4, 4, 4, 4, 4, 2, 2, 2]  # max(predicted, realized)
    np.testing.assert_allclose(rec.latencies_s, [ticks(back.get(c, 1.5)) for c in range(12)], rtol=0, atol=1e-12)
    np.testing.assert_allclose(rec.periods_s, DT, rtol=0, atol=1e-12)
    assert rec.periods_s.size == 59 and not rec.hold.any()
    _check_aligned(rec, H)
    for c in range(1, 12):
        # The switch tick: the first tick of chunk c is its request tick plus its executed prefix.
        assert np.nonzero(rec.chunk_index == c)[0][0] == rec.request_step[c] + rec.exec_delays[c]
        # the prior passed to the sampler is the previous chunk shifted by s, zero-padded.
        prior, d = pol.calls[c]
        np.testing.assert_allclose(prior[: H - s], rec.chunks[c - 1][s:], atol=1e-6)
        assert np.all(prior[H - s:] == 0) and d == rec.delays[c] <= dmax
    assert episode_metrics(rec)["latency_ms"] == pytest.approx(1000 * np.mean([ticks(back.get(c, 1.5))
                                                                                 for c in range(12)]))
    assert jitter_summary(rec.periods_s)["p50_ms"] == pytest.approx(20.0)


def test_runtime_late_chunk_is_rejected_and_arm_holds():
    """R-5, R-6, R-4, R-9, X-2: request 3 (tick 15) takes 9.5 ticks: rejected at tick 20, hold from tick 20, a fresh
    request at tick 25 once the worker is idle (no prior, d = 0), back at 27, executed aligned from there."""
    pol = RampPolicy()
    rec, _ = run(pol, seed=4, latency=lambda c: ticks(9.5 if c == 3 else 1.5), max_steps=70)
    assert rec.fault is None and rec.steps == 70
    assert (20, "late_reject", 3) in rec.events and (25, "restart_request", 4) in rec.events
    assert (20, "hold_start", None) in rec.events
    assert list(np.nonzero(rec.hold)[0]) == list(range(20, 27))
    assert not rec.accepted[3] and rec.realized_delays[3] == rec.exec_delays[3] == -2
    assert rec.latencies_s[3] == pytest.approx(ticks(9.5))  # logged on arrival although rejected
    assert not np.any(rec.chunk_index == 3)  # never executed
    assert rec.request_step[4] == 25 and pol.calls[4][0] is None and pol.calls[4][1] == 0
    assert rec.realized_delays[4] == 2 and rec.exec_delays[4] == 2
    assert list(rec.chunk_index[27:30]) == [4, 4, 4] and list(rec.token_index[27:30]) == [2, 3, 4]
    _check_aligned(rec, 10)
    assert rec.periods_s.size == 69


def test_runtime_permanent_stall_ends_cleanly():
    """R-6, R-7, A-24: request 2 never comes back in time: late at tick 15, holds through tick 24, fault stall after
    exactly 10 hold ticks; the worker is joined when its answer is due within join_timeout_s, logged otherwise."""
    lat = lambda c: 0.8 if c >= 2 else 0.0  # noqa: E731 - 40 ticks
    rec, _ = run(latency=lat, config=RuntimeConfig(max_hold_ticks=10, join_timeout_s=3.0), max_steps=200)
    assert rec.fault == "stall: 10 consecutive hold ticks" and (25, "stall", None) in rec.events
    assert rec.steps == 25 and list(np.nonzero(rec.hold)[0]) == list(range(15, 25))
    assert "worker_not_joined" not in [e[1] for e in rec.events]  # due at tick 50, 0.5 s after the end
    _check_aligned(rec, 10)
    rec2, _ = run(latency=lat, config=RuntimeConfig(max_hold_ticks=10, join_timeout_s=0.2), max_steps=200)
    assert rec2.events[-1] == (25, "worker_not_joined", None)
    # a stalled trial's throughput is over the full trial of max_steps ticks, not the ticks it ran.
    import dataclasses

    assert rec.step_limit == 200
    m = episode_metrics(dataclasses.replace(rec, num_completed=2))
    assert m["throughput"] == pytest.approx(2 / (200 * DT / 60.0))
    assert m["duration_s"] == pytest.approx(rec.steps * DT)


def test_runtime_worker_crash_ends_cleanly():
    """R-7: request 2 (tick 10) raises; at tick 11 the loop ends without a command for that tick, with the
    exception in the fault and its traceback in the events; a crash of request 0 ends with no action at all."""
    rec, _ = run(RampPolicy(crash_at=2), seed=6, config=RuntimeConfig(added_latency_s=0.0), max_steps=100)
    assert rec.fault == "worker_error: RuntimeError: injected crash"
    (ev,) = [e for e in rec.events if e[1] == "worker_error"]
    assert ev[0] == 11 and "Traceback" in ev[2] and "injected crash" in ev[2]
    assert rec.steps == 11 and np.all(np.isfinite(rec.actions))
    assert "worker_not_joined" not in [e[1] for e in rec.events]
    _check_aligned(rec, 10)
    rec0, _ = run(RampPolicy(crash_at=0), seed=6, max_steps=10)
    assert rec0.steps == 0 and rec0.fault == "worker_error: RuntimeError: injected crash"


def _good_chunk(H=10):
    return np.concatenate([np.full((H, 3), 0.1), np.full((H, 1), 0.5)], axis=1)


@pytest.mark.parametrize("bad, why", [
    (_good_chunk() + 0j, "has dtype complex128 (not a real number type)"),
    (_good_chunk().astype(str), "has dtype <U32 (not a real number type)"),
    (np.ones((10, 4), bool), "has dtype bool (not a real number type)"),
    ([[0.1] * 4] * 9 + [[0.1] * 3], "is not an array (ValueError)"),
    (_good_chunk()[:, :3], "has shape [10, 3], not [10, 4]"),
    (np.where(np.arange(10)[:, None] == 4, np.nan, _good_chunk()), "has non-finite values"),
    (np.where((np.arange(10)[:, None] == 7) & (np.arange(4) == 1), 3.5, _good_chunk()),
     "has token 7 action[1] = 3.5 outside its range [-3.0, 3.0]"),
    (np.where(np.arange(4) == 3, 1.25, _good_chunk()), "has token 0 action[3] = 1.25 outside its range [0.0, 1.0]"),
])
def test_a_chunk_the_runtime_cannot_execute_is_a_logged_fault(bad, why):
    """R-7, A-8, N-7: a complex, string or boolean chunk is refused before any cast (not read as its real part,
    parsed or read as 0/1); a ragged, mis-shaped, non-finite chunk or one outside the action bounds ends the
    episode with a logged fault and a bad_chunk event, for the first chunk and a later one, and the record of the
    ticks run so far is returned, never raised."""
    rec, _ = run(RampPolicy(bad={2: bad}), max_steps=60)
    assert rec.fault == f"worker_error: chunk 2 {why}"
    assert (12, "bad_chunk", 2) in rec.events  # requested at tick 10, back at tick 12
    assert rec.steps == 12 and not rec.accepted[2] and np.isnan(rec.chunks[2]).all()
    assert set(rec.chunk_index.tolist()) == {0, 1} and np.all(np.isfinite(rec.actions))
    m = episode_metrics(rec)
    assert m["fault"] == rec.fault
    rec0, _ = run(RampPolicy(bad={0: bad}), max_steps=60)
    assert rec0.fault == f"worker_error: chunk 0 {why}" and rec0.steps == 0 and rec0.events == [(0, "bad_chunk", 0)]


def test_predict_delay_rule_and_validation():
    """R-3, N-7: max of recent realized delays, at least 1, at most min(s, H - s); inputs validated."""
    assert predict_delay([2, 3, 1], 5) == 3
    assert predict_delay([0], 5) == 1
    assert predict_delay([9, 2], 5) == 5
    for bad in ([], [1.5], [-1], [True], 5):
        with pytest.raises(ValueError, match="^recent_delays must be a non-empty sequence of integers >= 0"):
            predict_delay(bad, 5)
    with pytest.raises(ValueError, match="^max_delay must be an integer >= 1, got 0"):
        predict_delay([1], 0)
    with pytest.raises(ValueError, match=r"^added_latency_s must be a finite number in \[0.0, 10.0\]"):
        RuntimeConfig(added_latency_s=-1.0)
    with pytest.raises(ValueError, match=r"^latency_window must be an integer in \[1, 1000\]"):
        RuntimeConfig(latency_window=0)
    with pytest.raises(ValueError, match=r"^max_steps must be an integer in \[1, 1000\], got 0"):
        run_realtime_episode(RampPolicy(), 0, jax.random.key(0), max_steps=0)
    with pytest.raises(ValueError, match="^env_seed must be an integer >= 0, got -1"):
        run_realtime_episode(RampPolicy(), -1, jax.random.key(0))
    with pytest.raises(ValueError, match=r"^key must be a typed JAX PRNG key"):
        run_realtime_episode(RampPolicy(), 0, 0)
    for bad in (object(), WallClock, "wall"):
        with pytest.raises(ValueError, match="^clock must provide now, sleep_until, sleep, task_started"):
            run_realtime_episode(RampPolicy(), 0, jax.random.key(0), clock=bad)


def test_jitter_summary_percentiles_and_validation():
    """R-9, N-7: p50, p99, max and mean of the periods in ms, by hand; bad periods name periods_s."""
    j = jitter_summary([0.02] * 98 + [0.03, 0.12])
    assert j["p50_ms"] == pytest.approx(20.0) and j["max_ms"] == pytest.approx(120.0) and j["n"] == 100
    # numpy's linear percentile: position 0.99 * 99 = 98.01 between 30 ms and 120 ms.
    assert j["p99_ms"] == pytest.approx(30.0 + 0.01 * 90.0)
    assert j["mean_ms"] == pytest.approx((98 * 20.0 + 30.0 + 120.0) / 100)
    for bad in ([-1.0, 0.02], [True, False], [], [float("nan")], [[0.02], [0.02, 0.03]]):
        with pytest.raises(ValueError, match="^periods_s"):
            jitter_summary(bad)


def test_runtime_ticks_on_an_absolute_schedule_after_a_slow_tick(monkeypatch):
    """R-1, R-10: the env step of tick 10 takes 0.1 s (5 ticks): tick 11 starts at once when it ends, ticks 12 to 15
    whose start times have passed follow back to back, tick 16 starts on schedule at T0 + 16 dt; none is skipped."""
    from softrtc.arm import runtime as R

    clock = SimulatedClock()

    class SlowTickEnv(R.ArmSortEnv):
        def step(self, action):
            out = super().step(action)
            if self.t == 11:  # the step of tick 10
                clock.advance(0.1)
            return out

    monkeypatch.setattr(R, "ArmSortEnv", SlowTickEnv)
    rec = run_realtime_episode(RampPolicy(), 3, jax.random.key(0), RuntimeConfig(added_latency_s=ticks(0.5)),
                               max_steps=30, clock=clock)
    assert rec.steps == 30 and rec.periods_s.size == 29 and rec.fault is None
    want = np.full(29, DT)
    want[10] = 0.1          # tick 10 -> 11: the slow step
    want[11:15] = 0.0       # ticks 12..15 were due: back to back
    np.testing.assert_allclose(rec.periods_s, want, rtol=0, atol=1e-12)
    starts = np.concatenate([[0.0], np.cumsum(rec.periods_s)])
    np.testing.assert_allclose(starts[15:], np.arange(15, 30) * DT, rtol=0, atol=1e-12)
    _check_aligned(rec, 10)


def test_added_latency_results_are_validated():
    """R-8, N-7: a per-request latency that is not a finite number of seconds in [0, 10] is a ValueError."""
    for bad in (-1.0, float("nan"), float("inf"), "0.01", True, None, 11.0):
        # Request 0 is fine; the bad value comes with request 1, mid-episode.
        lat = lambda c, bad=bad: 0.0 if c == 0 else bad  # noqa: E731
        with pytest.raises(ValueError, match=r"^added_latency\(1\) must be a finite number in \[0.0, 10.0\]"):
            run(latency=lat, max_steps=30)
        # The worker was stopped before the error left the runtime.
        assert not any(t.name == "softrtc-arm-inference" and t.is_alive() for t in threading.enumerate())
    with pytest.raises(ValueError, match="^added_latency must be None or a callable"):
        run_realtime_episode(RampPolicy(), 0, jax.random.key(0), added_latency=0.1)
    # NumPy numbers are numbers: 0.5 ticks as float32 gives realized delays of 1 tick.
    rec, _ = run(latency=lambda c: np.float32(ticks(0.5)), max_steps=12)
    assert rec.fault is None and rec.steps == 12 and list(rec.realized_delays[1:]) == [1, 1]


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


def test_simulated_clock_wakes_the_worker_at_its_own_time():
    """R-10: simulated time moves only in sleep_until, and only once the busy worker waits; a sleeper is woken with
    the clock at its deadline (not at the target), and join tells whether the worker ends within the timeout."""
    clock = SimulatedClock()
    seen = []

    def worker():
        seen.append(("start", clock.now()))
        clock.sleep(0.3)
        seen.append(("woke", clock.now()))
        clock.task_done()

    clock.task_started()
    t = threading.Thread(target=worker)
    t.start()
    clock.sleep_until(0.1)  # the worker sleeps until 0.3: time stops at 0.1
    assert clock.now() == 0.1 and seen == [("start", 0.0)]
    clock.sleep_until(1.0)
    assert seen == [("start", 0.0), ("woke", 0.3)] and clock.now() == 1.0
    assert clock.join(t, 0.5) is True and not t.is_alive()
    clock.advance(0.25)
    assert clock.now() == 1.75
    clock.sleep_until(0.5)  # a time already passed: no wait, time does not go back
    assert clock.now() == 1.75
    for bad in (-1.0, float("nan"), True, "1"):
        with pytest.raises(ValueError, match="^seconds must be a finite number of seconds >= 0"):
            clock.advance(bad)
    with pytest.raises(ValueError, match="^start must be"):
        SimulatedClock(start=-1.0)


def test_runtime_on_the_wall_clock_keeps_every_chunk_aligned():
    """R-1, R-4, R-10: the default wall clock runs the same runtime; whatever the timing on this machine, every
    executed action is the aligned token of its chunk or a hold, and one period is logged per tick after the first."""
    rec = run_realtime_episode(RampPolicy(), 3, jax.random.key(0), RuntimeConfig(added_latency_s=ticks(1.5)),
                               max_steps=20)
    assert rec.steps >= 1 and rec.accepted[0] and list(rec.chunk_index[:1]) == [0]  # the first chunk waits ([R-2])
    assert rec.periods_s.size == rec.steps - 1 and np.all(rec.periods_s >= 0)
    _check_aligned(rec, 10)
