"""Exact behaviour of the simulator packages that the broader tests leave open.

Arm (spec/10-arm.md, chapters X and R): what the simulated-delay executor hands
the policy for every request (prior, delay, key); the real-time runtime's
realized, predicted and executed delays, switch ticks, late rejection, hold
ticks and stall length, measured with a policy whose answers are released at
chosen control ticks so that the timeline is deterministic; the study table's
object count.

Kinetix (spec/20-kinetix.md, chapter M): the rollout's per-episode return,
length and solved flag on a counting stand-in environment; the per-level keys
and delays that ``evaluate`` passes to its rollouts and how it labels the rows;
the bootstrap interval and the column layout of the pooled table; the
objective and window that ``finetune_level`` trains with.
"""

from __future__ import annotations

import dataclasses
import math
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from conftest import SHARED_LEVELS_REASON

ROOT = Path(__file__).resolve().parents[1]
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


class _Gate:
    """Releases the answer to request c right after the control tick r_c + D_c - 1 has stepped the env,
    so that it is available at the start of tick r_c + D_c: a realized delay of exactly D_c ticks."""

    def __init__(self, realized):
        self.realized = realized
        self.req_tick, self.release, self.returned = {}, {}, {}
        self.env = None

    def latency(self, c):
        # Called in the control thread when request c is made ([R-8]), before that tick's env step.
        self.req_tick[c] = 0 if self.env is None else self.env.t
        self.release[c], self.returned[c] = threading.Event(), threading.Event()
        return 0.0

    def after_step(self, t):
        for c, r in list(self.req_tick.items()):
            if c >= 1 and r + self.realized(c) == t and not self.release[c].is_set():
                self.release[c].set()
                self.returned[c].wait(2.0)
                time.sleep(0.05)  # lets the worker hand the chunk over before the next tick starts, under load too


class _GatedPolicy:
    method = "gated"

    def __init__(self, gate, H=10, s=5):
        self.gate, self.H, self.s = gate, H, s
        self.calls = []

    def generate(self, obs, prior, d, key):
        c = len(self.calls)
        self.calls.append((None if prior is None else np.array(prior), d))
        if c >= 1:
            self.gate.release[c].wait(5.0)
        j = np.arange(1, self.H + 1)[:, None]
        out = np.concatenate([np.asarray(obs[0:3]) + 0.002 * j + 1e-4 * c, np.full((self.H, 1), 0.1 * (c % 5))],
                             axis=1)
        if c >= 1:
            self.gate.returned[c].set()
        return out


def _gated_episode(monkeypatch, realized, max_steps):
    import jax

    from softrtc.arm import runtime as R

    gate = _Gate(realized)

    class GatedEnv(R.ArmSortEnv):
        def reset(self, seed):
            gate.env = self
            return super().reset(seed)

        def step(self, action):
            out = super().step(action)
            gate.after_step(self.t)
            return out

    monkeypatch.setattr(R, "ArmSortEnv", GatedEnv)
    pol = _GatedPolicy(gate)
    rec = R.run_realtime_episode(pol, 3, jax.random.key(0), R.RuntimeConfig(added_latency_s=0.0),
                                 max_steps=max_steps, added_latency=gate.latency)
    return rec, pol


def test_runtime_delays_switches_and_late_chunk_on_a_gated_timeline(monkeypatch):
    """R-2, R-3, R-4, R-5, R-9, A-23: realized delay k - r, prediction from the window, executed prefix
    max(predicted, realized), switch at r + that, a chunk not back by r + min(s, H - s) rejected with -2,
    holds until a fresh request (no prior, d = 0) is back, and the delay given to the sampler is the one logged."""
    pytest.importorskip("pymunk")
    dmax, window = 5, 5
    wanted = {1: 3, 2: 1, 3: 2, 4: 6}  # request 4 comes back at 6 > dmax ticks: late
    rec, pol = _gated_episode(monkeypatch, lambda c: wanted.get(c, 2), 45)
    assert rec.fault is None and rec.steps == 45
    assert list(rec.request_step) == [0, 5, 10, 15, 20, 26, 31, 36, 41]
    assert list(rec.realized_delays) == [0, 3, 1, 2, -2, 2, 2, 2, 2]
    assert list(rec.accepted) == [True, True, True, True, False, True, True, True, True]
    # written out: the first latency in ticks, then every accepted chunk's realized delay.
    recent = [math.ceil(rec.latencies_s[0] / rec.dt)]
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
    assert ("late_reject" in [e[1] for e in rec.events]) and (25, "late_reject", 4) in rec.events


def test_runtime_stall_ends_after_exactly_max_hold_ticks():
    """R-6, R-5: the episode ends with fault stall after exactly max_hold_ticks consecutive hold ticks."""
    pytest.importorskip("pymunk")
    import jax

    from softrtc.arm.runtime import RuntimeConfig, run_realtime_episode

    class Fast:
        method, H, s = "fast", 10, 5

        def generate(self, obs, prior, d, key):
            j = np.arange(1, 11)[:, None]
            return np.concatenate([np.asarray(obs[0:3]) + 0.002 * j, np.full((10, 1), 0.2)], axis=1)

    cfg = RuntimeConfig(max_hold_ticks=10, join_timeout_s=3.0)
    # Request 2 (tick 10) takes 0.8 s: late at tick 15, and the worker stays busy far past tick 25.
    rec = run_realtime_episode(Fast(), 5, jax.random.key(2), cfg, max_steps=200,
                               added_latency=lambda c: 0.8 if c >= 2 else 0.0)
    assert rec.fault is not None and rec.fault.startswith("stall")
    run = len(rec.hold) - np.nonzero(~rec.hold)[0][-1] - 1  # trailing consecutive holds
    assert run == 10 and rec.fault == "stall: 10 consecutive hold ticks"
    assert rec.steps == np.nonzero(rec.hold)[0][0] + 10


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


def test_pooled_bootstrap_interval_is_the_specified_resampling():
    """M-5, M-4, KE-7: the pooled interval resamples the per-level values with
    default_rng(seed).integers(0, n, (B, n)) and takes the 2.5% / 97.5% quantiles of the means."""
    pytest.importorskip("jax")
    pytest.importorskip("kinetix")
    from softrtc.kinetix import harness as KH

    rng = np.random.default_rng(4)
    levels = [f"level{i}" for i in range(9)]
    rows = [{"method": "naive", "level": lv, "delay": d, "episode": e, "return": float(rng.normal()),
             "solved": bool(rng.integers(2)), "length": 5, "delta": float(rng.random()), "jerk": float(rng.random())}
            for lv in levels for d in (0, 3) for e in range(3)]
    B = 2000
    for seed in (0, 5):
        summ = KH.summarize(rows, bootstrap_resamples=B, bootstrap_seed=seed)
        per = {r["level"]: r for r in summ["per_level"] if r["scope"] == "overall"}
        pooled = {r["scope"]: r for r in summ["pooled"]}["overall"]
        idx = np.random.default_rng(seed).integers(0, len(levels), (B, len(levels)))
        for k in ("return", "delta"):
            v = np.array([per[lv][k] for lv in levels])
            means = v[idx].mean(axis=1)
            lo, hi = np.quantile(means, [0.025, 0.975])
            assert pooled[k] == pytest.approx(v.mean(), rel=1e-12)
            assert (pooled[k + "_lo"], pooled[k + "_hi"]) == pytest.approx((lo, hi), rel=1e-12), (seed, k)


def test_main_table_columns_read_their_scope_and_metric():
    """KE-8, M-7: each column of the main table shows the pooled value of its own scope and metric."""
    pytest.importorskip("jax")
    pytest.importorskip("kinetix")
    from softrtc.kinetix import harness as KH

    vals = {("overall", "return"): 1.111, ("overall", "solved"): 0.222, ("overall", "delta"): 0.333,
            ("overall", "jerk"): 0.444, ("high", "return"): 5.555, ("high", "solved"): 0.666,
            ("high", "delta"): 0.777, ("high", "jerk"): 0.888}
    pooled = []
    for scope in ("overall", "high"):
        r = {"method": "naive", "scope": scope, "levels": 2}
        for k in ("return", "solved", "delta", "jerk"):
            v = vals[(scope, k)]
            r |= {k: v, k + "_lo": v - 0.001, k + "_hi": v + 0.001}
        pooled.append(r)
    lines = KH.main_table({"pooled": pooled}).splitlines()
    header = [c.strip() for c in lines[0].strip("|").split("|")]
    cells = [c.strip() for c in lines[2].strip("|").split("|")]
    assert cells[0] == "Base Naive"
    want = {"Overall Return": ("overall", "return"), "Overall Solve": ("overall", "solved"),
            "High-delay Solve": ("high", "solved"), "High-delay Jerk ↓": ("high", "jerk"),
            "Overall Delta ↓": ("overall", "delta"), "Overall Jerk ↓": ("overall", "jerk"),
            "High-delay Delta ↓": ("high", "delta")}
    assert header[1:] == list(want)
    for name, cell in zip(header[1:], cells[1:]):
        v = vals[want[name]]
        assert cell == f"{v:.3f} [{v - 0.001:.3f}, {v + 0.001:.3f}]", name


# ----------------------------------------------------------------------------- kinetix: rollout outcome


@dataclasses.dataclass(frozen=True)
class CountingTask:
    """A stand-in level: episodes of level[0] steps, back to back ([K-9]); episode number level[1] is solved.

    The reward of step t (1-based) of episode e is t + 100 e, so every step's reward is distinct.
    """

    level: Any
    env: Any
    obs_dim: int = 3
    action_dim: int = 2

    def _obs(self, state):
        import jax.numpy as jnp

        return jnp.stack([state[0].astype(jnp.float32), state[1].astype(jnp.float32), jnp.float32(0.0)])

    def reset(self, key):
        import jax.numpy as jnp

        state = (jnp.int32(0), jnp.int32(0))
        return self._obs(state), state

    def step(self, key, state, action):
        import jax.numpy as jnp

        t, ep = state
        t1 = t + 1
        done = t1 >= self.level[0]
        solved = done & (ep == self.level[1])
        reward = t1.astype(jnp.float32) + 100.0 * ep.astype(jnp.float32)
        state = (jnp.where(done, 0, t1), jnp.where(done, ep + 1, ep))
        return self._obs(state), state, reward, done, {"solved": solved}


def test_rollout_return_length_and_solved_cover_the_first_episode_only():
    """KE-7, M-4, X-6, K-9, K-10, KE-6: return sums the rewards through the step that ends the env's first
    episode, solved is that step's flag, later episodes count for nothing; segments follow [X-4]."""
    pytest.importorskip("kinetix")
    import flax.nnx as nnx
    import jax
    import jax.numpy as jnp

    from softrtc.jax.policy import FlowPolicy, PolicyConfig
    from softrtc.kinetix import harness as KH
    from softrtc.reference import executor as ref_executor

    Hc, s, C, T = 8, 4, 6, 2
    cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=Hc)
    pol = FlowPolicy(obs_dim=3, action_dim=2, config=cfg, rngs=nnx.Rngs(0))
    graphdef, _ = nnx.split(pol)
    task = CountingTask(level=jnp.array([7, 1], jnp.int32), env=type("Env", (), {})())
    fn = jax.jit(KH._build_rollout_fn(task, graphdef, "rtc", Hc, 2, s, T, C))
    keys = jax.random.split(jax.random.key(0), 5)
    delays = jnp.arange(5, dtype=jnp.int32)
    table = jnp.asarray(KH.rollout_weight_table(KH.parse_method("train_hard"), Hc, s))

    def run(length, solved_episode):
        out = fn(nnx.state(pol), jnp.array([length, solved_episode], jnp.int32), table, keys, delays)
        return {k: np.asarray(v) for k, v in jax.device_get(out).items()}

    # Episodes end at steps 7, 14, 21 of 24; only the second one is solved: the first episode is not.
    out = run(7, 1)
    assert list(out["length"]) == [7] * 5 and out["ended"].all()
    np.testing.assert_array_equal(out["return"], np.full(5, sum(range(1, 8)), np.float32))
    assert not out["solved"].any()
    out = run(7, 0)
    assert out["solved"].all() and list(out["length"]) == [7] * 5
    # No episode ends within the C s = 24 steps: length 24, every reward, not solved.
    out = run(30, 0)
    assert list(out["length"]) == [24] * 5 and not out["ended"].any() and not out["solved"].any()
    np.testing.assert_array_equal(out["return"], np.full(5, sum(range(1, 25)), np.float32))
    for e, d in enumerate(np.asarray(delays)):
        ref = ref_executor.execute_chunks(out["chunks"][e].astype(np.float64), [0] + [int(d)] * (C - 1), s)
        np.testing.assert_array_equal(out["actions"][e], ref["actions"].astype(np.float32))


# ----------------------------------------------------------------------------- kinetix: evaluate


@pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)
def test_evaluate_passes_each_levels_keys_and_delays_and_labels_rows(monkeypatch):
    """KE-5, KE-1, KE-8, M-4: level l's rollout gets episode e's key fold_in(fold_in(key(seed), index of l), e)
    at every delay, delays repeated per episode, and each row carries its own env's delay, episode and outcome."""
    pytest.importorskip("kinetix")
    import flax.nnx as nnx
    import jax

    from softrtc.jax.policy import FlowPolicy, PolicyConfig
    from softrtc.kinetix import env as kenv
    from softrtc.kinetix import harness as KH

    seen = []

    class FakeRollout:
        _compiled, compile_s = True, 0.0

        def __call__(self, policy, spec, level, keys, delays):
            n = len(delays)
            seen.append((spec.label, level, np.asarray(jax.random.key_data(keys)), np.asarray(delays)))
            li = kenv.LEVEL_NAMES.index(level)
            ret = np.arange(n, dtype=np.float64) + 1000.0 * li
            actions = np.zeros((n, 8, kenv.ACTION_DIM), np.float32)
            actions[:, :, 0] = np.arange(8)[None, :] * (1 + np.arange(n))[:, None]
            return {"actions": actions, "length": np.full(n, 8), "return": ret, "solved": ret % 2 == 1}

    monkeypatch.setattr(KH, "make_rollout", lambda *a, **k: FakeRollout())
    pol = FlowPolicy(obs_dim=kenv.OBS_DIM, action_dim=kenv.ACTION_DIM,
                     config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1,
                                         action_chunk_size=8), rngs=nnx.Rngs(0))
    E, ds = 3, (0, 2, 4)
    cfg = KH.EvalConfig(levels=("grasp_easy", "catapult"), methods=("naive",), delays=ds, episodes=E, seed=9,
                        levels_dir=str(LEVELS_DIR))
    res = KH.evaluate(cfg, pol, progress=False)
    assert [(m, lv) for m, lv, _, _ in seen] == [("naive", "grasp_easy"), ("naive", "catapult")]
    for _, lv, keys, delays in seen:
        want = np.asarray(jax.random.key_data(KH.episode_keys(9, lv, E)))
        np.testing.assert_array_equal(keys, np.tile(want, (len(ds), 1)), err_msg=lv)
        np.testing.assert_array_equal(delays, np.repeat(ds, E))
    assert not np.array_equal(seen[0][2], seen[1][2])
    rows = res["episodes"]
    assert len(rows) == 2 * E * len(ds)
    for j, r in enumerate(rows):
        i = j % (E * len(ds))
        li = kenv.LEVEL_NAMES.index(r["level"])
        assert (r["delay"], r["episode"]) == (ds[i // E], i % E)
        assert r["return"] == i + 1000.0 * li and r["solved"] == ((i + 1000 * li) % 2 == 1)
        assert r["delta"] == pytest.approx(1 + i) and r["jerk"] == 0.0 and r["length"] == 8


# ----------------------------------------------------------------------------- kinetix: fine-tuning


def _release_files(tmp_path, level="grasp_easy", H=8, obs_dim=5, action_dim=2):
    """A pickled release pure dict ([P-8]) and an expert .npz ([K-14]) for one level."""
    import pickle

    import flax.nnx as nnx
    import jax

    from softrtc.jax.policy import FlowPolicy, PolicyConfig, state_pure_dict
    from softrtc.kinetix import data as kdata

    bc = tmp_path / "bc" / "3" / "policies"
    bc.mkdir(parents=True)
    cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=H)
    pol = FlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=cfg, rngs=nnx.Rngs(1))
    with open(bc / f"worlds_l_{level}.pkl", "wb") as f:
        pickle.dump(jax.tree.map(np.asarray, state_pure_dict(pol)), f)
    data = tmp_path / "data"
    data.mkdir()
    rng = np.random.default_rng(2)
    S, E = 20, 2
    done = np.zeros((S, E), bool)
    done[9, 1] = True
    np.savez(data / kdata.expert_data_filename(level),
             obs=rng.normal(size=(S, E, obs_dim)).astype(np.float32),
             action=rng.uniform(-1, 1, size=(S, E, action_dim)).astype(np.float32),
             done=done, solved=done.astype(np.float32), return_=np.zeros((S, E), np.float32),
             length=np.zeros((S, E), np.float32))
    return tmp_path / "bc", data


def test_finetune_trains_the_requested_objective_and_window(tmp_path, monkeypatch):
    """KE-10, T-3, W-7, K-17: hard trains method 'hard'; soft trains method 'soft' with the window given
    (the paper's main window by default); one epoch is floor(n / batch) steps over the n = E*S - H + 1 examples."""
    pytest.importorskip("kinetix")
    from softrtc.kinetix import finetune as ft
    from softrtc.reference import endpoints as ref_endpoints
    from softrtc.reference.weights import SoftWindow

    bc, data = _release_files(tmp_path)
    calls = []

    def fake_train(policy, arrays, config, key, steps, progress=True):
        calls.append((config, steps, arrays[0].shape[0]))
        return policy, np.array([0.5], np.float32)

    monkeypatch.setattr(ft, "train", fake_train)
    n = 2 * 20 - 8 + 1
    window = SoftWindow(ref_endpoints.offset(1, 8))
    for method, win, want_window in (("hard", None, SoftWindow()), ("soft", None, SoftWindow()),
                                     ("soft", window, window)):
        out = tmp_path / f"out_{method}_{len(calls)}"
        meta = ft.finetune_level(data, bc, "grasp_easy", method, out, window=win, batch_size=8, progress=False)
        config, steps, examples = calls[-1]
        assert config.method == method and meta["train_config"]["method"] == method
        assert config.window == want_window
        assert examples == n and steps == n // 8 == meta["steps"]
        assert (config.d_min, config.d_max, config.execute_horizon, config.batch_size) == (0, 4, 4, 8)
