"""Exact behaviour of the Kinetix package that the broader tests leave open (spec/20-kinetix.md, chapter M).

The rollout's per-episode return, length and solved flag on a counting
stand-in environment; the per-level keys and delays that ``evaluate`` passes to
its rollouts and how it labels the rows; the bootstrap interval and the column
layout of the pooled table; the objective and window that ``finetune_level``
trains with.
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

from tests.conftest import SHARED_LEVELS_REASON

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()


def test_pooled_bootstrap_interval_is_the_specified_resampling():
    """M-5, M-4, KE-7: the pooled interval resamples the per-level values with
    default_rng(seed).integers(0, n, (B, n)) and takes the 2.5% / 97.5% quantiles of the means."""
    pytest.importorskip("jax")
    pytest.importorskip("kinetix")
    from softrtc.kinetix import results as KH

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
    from softrtc.kinetix import results as KH

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
    from softrtc.kinetix import methods as KM
    from softrtc.kinetix import rollout as KR
    from softrtc.reference import executor as ref_executor

    Hc, s, C, T = 8, 4, 6, 2
    cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=Hc)
    pol = FlowPolicy(obs_dim=3, action_dim=2, config=cfg, rngs=nnx.Rngs(0))
    graphdef, _ = nnx.split(pol)
    task = CountingTask(level=jnp.array([7, 1], jnp.int32), env=type("Env", (), {})())
    fn = jax.jit(KR._build_rollout_fn(task, graphdef, "rtc", Hc, 2, s, T, C))
    keys = jax.random.split(jax.random.key(0), 5)
    delays = jnp.arange(5, dtype=jnp.int32)
    table = jnp.asarray(KM.rollout_weight_table(KM.parse_method("train_hard"), Hc, s))

    def run(length, solved_episode):
        out = fn(nnx.state(pol), jnp.array([length, solved_episode], jnp.int32), table, jnp.asarray(False), keys,
                 delays)  # Algorithm 1's step ([KE-13])
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
    from softrtc.kinetix import evaluation as KE
    from softrtc.kinetix import protocol as KP
    from softrtc.kinetix import rollout as KR

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

    monkeypatch.setattr(KE, "make_rollout", lambda *a, **k: FakeRollout())
    pol = FlowPolicy(obs_dim=kenv.OBS_DIM, action_dim=kenv.ACTION_DIM,
                     config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1,
                                         action_chunk_size=8), rngs=nnx.Rngs(0))
    E, ds = 3, (0, 2, 4)
    cfg = KP.EvalConfig(levels=("grasp_easy", "catapult"), methods=("naive",), delays=ds, episodes=E, seed=9,
                        levels_dir=str(LEVELS_DIR))
    res = KE.evaluate(cfg, pol, progress=False)
    assert [(m, lv) for m, lv, _, _ in seen] == [("naive", "grasp_easy"), ("naive", "catapult")]
    for _, lv, keys, delays in seen:
        want = np.asarray(jax.random.key_data(KR.episode_keys(9, lv, E)))
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

    from softrtc.jax.params import state_pure_dict
    from softrtc.jax.policy import FlowPolicy, PolicyConfig
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
