"""Exact behaviour of the arm package that the broader tests leave open (spec/10-arm.md, chapters X and R).

What the simulated-delay executor hands the policy for every request (prior,
delay, key); the real-time runtime's realized, predicted and executed delays,
switch ticks, late rejection, hold ticks and stall length, on a simulated
clock ([R-10]) that brings each answer back at a chosen control tick, so that
the timeline is deterministic; the study table's object count.
"""
from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import SHARED_LEVELS_REASON

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()


# ----------------------------------------------------------------------------- arm: simulated executor


class RecordingPolicy:
    """Returns a distinct valid chunk per request and records what each request received."""

    method = "recording"

    def __init__(self, H=10, s=5):
        self.H, self.s = H, s
        self.calls = []

    def generate(self, obs, prior, d, key):
        import jax

        c = len(self.calls)
        self.calls.append((None if prior is None else np.array(prior), d, np.asarray(jax.random.key_data(key))))
        j = np.arange(self.H)[:, None]
        q = np.asarray(obs[0:3]) + 0.003 * j + 0.01 * (c + 1)
        return np.concatenate([q, np.full((self.H, 1), 0.25 + 0.05 * (c % 3))], axis=1)


def test_simulated_executor_hands_each_request_its_prior_delay_and_key():
    """A-22, X-3, X-4, X-6, N-9: request c gets shift_prior(chunk c-1, s), its own d_c and fold_in(key, c)."""
    pytest.importorskip("pymunk")
    import jax

    from softrtc.arm.executor import run_simulated_episode

    H, s = 10, 5
    delays = [0, 1, 3, 5, 2, 4]  # the last entry repeats
    pol = RecordingPolicy(H, s)
    key = jax.random.key(17)
    rec = run_simulated_episode(pol, 4, delays, key, max_steps=40)
    C = len(rec.chunks)
    assert C == 8 and len(pol.calls) == C
    want_d = [delays[min(c, len(delays) - 1)] for c in range(C)]
    assert list(rec.delays) == want_d
    for c, (prior, d, kd) in enumerate(pol.calls):
        np.testing.assert_array_equal(kd, np.asarray(jax.random.key_data(jax.random.fold_in(key, c))),
                                      err_msg=f"key of request {c}")
        assert d == want_d[c], (c, d)
        if c == 0:
            assert prior is None
            continue
        # written out: Y[j] = P[j + s] for j < H - s, 0 beyond.
        want = np.zeros((H, 4))
        want[: H - s] = rec.chunks[c - 1][s:]
        # (the JAX executor shifts in float32; consecutive tokens differ by 3e-3)
        np.testing.assert_allclose(prior, want, rtol=0, atol=1e-6, err_msg=f"prior of request {c}")
        # the segment of request c, from the chunks the policy returned.
        seg = rec.actions[c * s:(c + 1) * s]
        np.testing.assert_array_equal(seg[:d], rec.chunks[c - 1][s:s + d])
        np.testing.assert_array_equal(seg[d:], rec.chunks[c][d:s])


# ----------------------------------------------------------------------------- arm: real-time runtime


class _StampedPolicy:
    """Chunks distinct per request; records the prior and delay each request received."""

    method = "stamped"

    def __init__(self, H=10, s=5):
        self.H, self.s = H, s
        self.calls = []

    def generate(self, obs, prior, d, key):
        c = len(self.calls)
        self.calls.append((None if prior is None else np.array(prior), d))
        j = np.arange(1, self.H + 1)[:, None]
        return np.concatenate([np.asarray(obs[0:3]) + 0.002 * j + 1e-4 * c, np.full((self.H, 1), 0.1 * (c % 5))],
                              axis=1)


def _timed_episode(realized, max_steps):
    """On a simulated clock ([R-10]) request c >= 1 is back after exactly realized(c) ticks (its latency is
    realized(c) - 1/2 ticks); request 0 after half a tick."""
    import jax

    from softrtc.arm import runtime as R
    from softrtc.arm.clock import SimulatedClock

    dt = 0.02
    pol = _StampedPolicy()
    rec = R.run_realtime_episode(pol, 3, jax.random.key(0), R.RuntimeConfig(added_latency_s=0.0),
                                 max_steps=max_steps, added_latency=lambda c: (realized(c) - 0.5) * dt if c else dt / 2,
                                 clock=SimulatedClock())
    return rec, pol


def test_runtime_delays_switches_and_late_chunk_on_a_simulated_timeline():
    """R-2, R-3, R-4, R-5, R-9, R-10, A-23: realized delay k - r, prediction from the window, executed prefix
    max(predicted, realized), switch at r + that, a chunk not back by r + min(s, H - s) rejected with -2,
    holds until a fresh request (no prior, d = 0) is back, and the delay given to the sampler is the one logged."""
    pytest.importorskip("pymunk")
    dmax, window = 5, 5
    wanted = {1: 3, 2: 1, 3: 2, 4: 6}  # request 4 comes back at 6 > dmax ticks: late
    rec, pol = _timed_episode(lambda c: wanted.get(c, 2), 45)
    assert rec.fault is None and rec.steps == 45
    assert list(rec.request_step) == [0, 5, 10, 15, 20, 26, 31, 36, 41]
    assert list(rec.realized_delays) == [0, 3, 1, 2, -2, 2, 2, 2, 2]
    assert list(rec.accepted) == [True, True, True, True, False, True, True, True, True]
    # written out: the first latency in ticks, then every accepted chunk's realized delay.
    recent = [math.ceil(rec.latencies_s[0] / rec.dt)]
    assert recent == [1]
    for c in range(1, len(rec.chunks)):
        restart = c == 5
        pred = 0 if restart else min(max(1, max(recent[-window:])), dmax)
        assert rec.delays[c] == pred, (c, rec.delays[c], pred)
        assert pol.calls[c][1] == pred  # what the sampler received
        assert (pol.calls[c][0] is None) == restart
        if rec.accepted[c]:
            recent.append(int(rec.realized_delays[c]))
            assert rec.exec_delays[c] == max(pred, rec.realized_delays[c]), c
            ticks = np.nonzero(rec.chunk_index == c)[0]
            assert ticks[0] == rec.request_step[c] + rec.exec_delays[c], c
            assert np.all(rec.token_index[ticks] == ticks - rec.request_step[c])
        else:
            assert rec.exec_delays[c] == -2 and not np.any(rec.chunk_index == c)
    # Request 2 was predicted 3 ticks and came back after 1: its first 3 tokens are never executed.
    assert rec.delays[2] == 3 and rec.exec_delays[2] == 3
    # late at tick 20 + 5; holds until the restart chunk (requested at 26, back at 28) takes over.
    assert list(np.nonzero(rec.hold)[0]) == [25, 26, 27]
    assert (25, "late_reject", 4) in rec.events and (26, "restart_request", 5) in rec.events


def test_runtime_stall_ends_after_exactly_max_hold_ticks():
    """R-6, R-5, R-10: the episode ends with fault stall after exactly max_hold_ticks consecutive hold ticks."""
    pytest.importorskip("pymunk")
    import jax

    from softrtc.arm.clock import SimulatedClock
    from softrtc.arm.runtime import RuntimeConfig, run_realtime_episode

    cfg = RuntimeConfig(max_hold_ticks=10, join_timeout_s=3.0)
    # Request 2 (tick 10) takes 0.8 s: late at tick 15, and the worker stays busy far past tick 25.
    rec = run_realtime_episode(_StampedPolicy(), 5, jax.random.key(2), cfg, max_steps=200,
                               added_latency=lambda c: 0.8 if c >= 2 else 0.0, clock=SimulatedClock())
    assert rec.fault == "stall: 10 consecutive hold ticks"
    run = len(rec.hold) - np.nonzero(~rec.hold)[0][-1] - 1  # trailing consecutive holds
    assert run == 10 and rec.steps == 25 == np.nonzero(rec.hold)[0][0] + 10


# ----------------------------------------------------------------------------- arm: study table


def test_study_counts_every_completed_part():
    """A-25, A-24: Obj. counts the parts completed in every trial (failed ones included) out of 4 per trial."""
    from softrtc.arm.study import format_table, summarize

    trial = {"success": False, "completed": 3, "fault": None, "completion": 0.75, "throughput": 9.0,
             "D1": 0.1, "D2": 0.2, "D3": 0.3, "boundary": 0.5, "latency_ms": 60.0, "hold_ticks": 0}
    rows = [trial, dict(trial, success=True, completed=4, completion=1.0), dict(trial, completed=1, completion=0.25)]
    row = summarize(rows)
    assert (row["successes"], row["objects"], row["objects_total"], row["trials"]) == (1, 8, 12, 3)
    assert row["completion"] == pytest.approx(2 / 3)
    line = format_table({"train_hard": row}).splitlines()[2]
    assert " 1/3 " in line and " 8/12 " in line


# ----------------------------------------------------------------------------- kinetix: summaries
