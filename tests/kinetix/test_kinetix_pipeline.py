"""Tests of the Kinetix pipeline: experts, PPO, data generation, behaviour cloning ([KP-1]..[KP-13]).

The end-to-end test runs the four commands of the release's pipeline on one
level with tiny budgets, then fine-tunes and evaluates the result.
"""

from __future__ import annotations

import csv
import json
import math
import pickle
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from softrtc.kinetix import env as kenv  # noqa: E402
from softrtc.kinetix import expert as kexp  # noqa: E402
from softrtc.kinetix.curves import plot_curves, read_curve_csv, write_curve_csv  # noqa: E402
from softrtc.kinetix.ppo import PPOConfig, train_reward  # noqa: E402
from softrtc.kinetix.recorder import select_experts, steps_per_env  # noqa: E402
from tests.conftest import SHARED_LEVELS_REASON  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()
needs_levels = pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)
PNG = b"\x89PNG\r\n\x1a\n"


def test_expert_layout_and_file_round_trip(tmp_path):
    """KP-1, KP-3: input width 4*679+6 = 2722; release layout (actor/critic layers 0, 2, 4, logstd);
    a pickled file with digit-string layer keys (as another writer may store them) loads to the same arrays."""
    assert kexp.expert_obs_dim() == 2722
    p = kexp.init_expert(jax.random.key(0), obs_dim=10, width=8)
    assert kexp.expert_dims(p) == (10, 6, 8)
    assert p["actor"]["layers"][4]["kernel"].shape == (8, 6) and p["critic"]["layers"][4]["kernel"].shape == (8, 1)
    assert np.all(np.asarray(p["logstd"]) == 0) and np.all(np.asarray(p["actor"]["layers"][0]["bias"]) == 0)
    kexp.save_expert(tmp_path / "a.pkl", p)
    q = kexp.load_expert(tmp_path / "a.pkl")
    for a, b in zip(jax.tree.leaves(p), jax.tree.leaves(q)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    raw = pickle.loads((tmp_path / "a.pkl").read_bytes())
    raw["actor"]["layers"] = {str(k): v for k, v in raw["actor"]["layers"].items()}
    (tmp_path / "b.pkl").write_bytes(pickle.dumps(raw))
    assert kexp.expert_dims(kexp.load_expert(tmp_path / "b.pkl")) == (10, 6, 8)
    bad = dict(raw, logstd=np.zeros(5, np.float32))
    (tmp_path / "c.pkl").write_bytes(pickle.dumps(bad))
    with pytest.raises(ValueError, match="^params has inconsistent shapes: logstd"):
        kexp.load_expert(tmp_path / "c.pkl")
    with pytest.raises(FileNotFoundError, match="^path must name an existing expert file"):
        kexp.load_expert(tmp_path / "missing.pkl")


def test_squashed_gaussian_log_prob_matches_change_of_variables():
    """KP-2: log p(a) = log N(u; mean, std) - sum log|d squash/du| with u = atanh(a) for motors and
    logit(a) for thrusters, computed here from the closed-form derivatives (1 - a^2 and a(1 - a))."""
    rng = np.random.default_rng(0)
    mean = rng.normal(size=(5, 6)).astype(np.float32)
    std = np.exp(rng.normal(size=(5, 6)) * 0.3).astype(np.float32)
    u = (mean + std * rng.normal(size=(5, 6))).astype(np.float64)
    a = np.concatenate([np.tanh(u[:, :4]), 1 / (1 + np.exp(-u[:, 4:]))], axis=1)
    gauss = (-0.5 * ((u - mean) / std) ** 2 - np.log(std) - 0.5 * np.log(2 * np.pi)).sum(1)
    jac = np.log(1 - a[:, :4] ** 2).sum(1) + np.log(a[:, 4:] * (1 - a[:, 4:])).sum(1)
    got = kexp.action_log_prob(jnp.asarray(mean), jnp.asarray(std), jnp.asarray(a, jnp.float32))
    np.testing.assert_allclose(np.asarray(got), gauss - jac, rtol=2e-3, atol=2e-3)
    s = np.asarray(kexp.squash(jnp.asarray([[50.0] * 6, [-50.0] * 6], jnp.float32)))
    assert np.all(np.abs(s[:, :4]) <= kexp.MAX_ACTION) and np.all((s[:, 4:] > 0) & (s[:, 4:] < 1))


def test_history_append_and_reset():
    """KP-1: the history appends the new observation (oldest dropped) and keeps the action; after an
    episode end it repeats the reset observation with a zero previous action."""
    obs0 = jnp.arange(2 * 3, dtype=jnp.float32).reshape(2, 3)
    h, a = kexp.history_reset(obs0)
    assert h.shape == (2, 4, 3) and np.all(np.asarray(h[0]) == np.asarray(obs0[0]))
    assert np.all(np.asarray(a) == 0) and a.shape == (2, 6)
    obs1 = obs0 + 100
    act = jnp.ones((2, 6))
    h2, a2 = kexp.history_step(h, a, obs1, act, jnp.array([False, True]))
    np.testing.assert_array_equal(np.asarray(h2[0]), np.stack([obs0[0]] * 3 + [obs1[0]]))
    np.testing.assert_array_equal(np.asarray(a2[0]), np.ones(6))
    np.testing.assert_array_equal(np.asarray(h2[1]), np.stack([obs1[1]] * 4))
    np.testing.assert_array_equal(np.asarray(a2[1]), np.zeros(6))
    x = kexp.expert_input(h2, a2)
    np.testing.assert_array_equal(np.asarray(x[0, :3]), np.asarray(obs0[0]))
    np.testing.assert_array_equal(np.asarray(x[0, 9:12]), np.asarray(obs1[0]))
    np.testing.assert_array_equal(np.asarray(x[0, 12:]), np.ones(6))


def test_train_reward_hand_values():
    """KP-5: penalty distance/6/256 per step without positive reward, (256 - t) times on the last step."""
    r = train_reward(jnp.array([0.0, 0.0, 1.0, -1.0]), jnp.array([3.0, 3.0, 3.0, 1.5]),
                     jnp.array([10, 10, 10, 200]), jnp.array([False, True, True, True]))
    p = 3.0 / 6 / 256
    np.testing.assert_allclose(np.asarray(r), [-p, -246 * p, 1.0, -1.0 - 56 * (1.5 / 6 / 256)], rtol=1e-6)


def test_ppo_config_and_steps_per_env_validate():
    """KP-4, KP-10: ranges named; minibatches divide the batch; steps per env rounded up to blocks."""
    assert PPOConfig().batch_size == 65536 and PPOConfig().minibatch_size == 8192
    with pytest.raises(ValueError, match="^num_minibatches must divide"):
        PPOConfig(num_envs=3, num_steps=5, num_minibatches=2)
    with pytest.raises(ValueError, match=r"^gamma must be a real number in \[0.0, 1.0\]"):
        PPOConfig(gamma=1.5)
    with pytest.raises(ValueError, match="^lr must be"):
        PPOConfig(lr=0.0)
    assert steps_per_env(1_000_000, 128, 256) == 31 * 256
    assert steps_per_env(16, 2, 8) == 8 and steps_per_env(17, 2, 8) == 8 and steps_per_env(18, 2, 8) == 16
    with pytest.raises(ValueError, match="^num_envs must be"):
        steps_per_env(10, 0, 8)


def test_select_experts_threshold_rule(tmp_path):
    """KP-9: per seed folder a checkpoint at or above the threshold (random among them), else the best one
    marked below threshold; stats without a policy file are ignored; no checkpoint at all is an error."""
    name = "worlds_l_grasp_easy"

    def ck(seed, update, solved, policy=True):
        d = tmp_path / f"seed_{seed}" / str(update)
        (d / "stats").mkdir(parents=True)
        (d / "stats" / f"{name}.json").write_text(json.dumps({"returned_episode_solved": solved}))
        if policy:
            (d / "policies").mkdir()
            (d / "policies" / f"{name}.pkl").write_bytes(b"x")

    ck(0, 0, 0.1), ck(0, 20, 0.7), ck(0, 40, 0.9), ck(0, 60, 0.95, policy=False)
    ck(1, 0, 0.2), ck(1, 20, 0.4), ck(1, 40, float("nan"))
    picks = {select_experts(tmp_path, "grasp_easy", 0.65, seed)[0]["update"] for seed in range(20)}
    assert picks == {20, 40}
    sel = select_experts(tmp_path, "grasp_easy", 0.65, 0)
    assert sel[1] == {"seed_dir": "seed_1", "update": 20, "path": str(tmp_path / "seed_1" / "20" / "policies" /
                                                                           f"{name}.pkl"),
                      "solved": 0.4, "good": False}
    with pytest.raises(FileNotFoundError, match="has no seed_"):
        select_experts(tmp_path, "catapult")
    with pytest.raises(ValueError, match="^solve_rate_threshold must be"):
        select_experts(tmp_path, "grasp_easy", 1.5)


def test_strong_types_keeps_values_and_keys():
    """KP-7: strong_types makes weak leaves strong with the same dtype and values and keeps typed keys."""
    tree = {"t": jnp.full((2,), 3), "x": jnp.ones((2,), jnp.float32), "k": jax.random.key(1)}
    assert jax.core.get_aval(tree["t"]).weak_type
    out = jax.jit(kenv.strong_types)(tree)
    assert not jax.core.get_aval(out["t"]).weak_type and out["t"].dtype == tree["t"].dtype
    np.testing.assert_array_equal(np.asarray(out["t"]), [3, 3])
    assert jnp.issubdtype(out["k"].dtype, jax.dtypes.prng_key)
    np.testing.assert_array_equal(np.asarray(jax.random.key_data(out["k"])),
                                  np.asarray(jax.random.key_data(tree["k"])))


def test_curves_csv_and_png(tmp_path):
    """KP-8: the curve CSV keeps the column order with empty cells for missing values; the PNG is a PNG."""
    rows = [{"update": 1, "env_steps": 64, "solved": 0.0}, {"update": 2, "env_steps": 128, "solved": float("nan")}]
    write_curve_csv(tmp_path / "c.csv", rows, ("update", "env_steps", "solved", "loss"))
    assert (tmp_path / "c.csv").read_text().splitlines()[0] == "update,env_steps,solved,loss"
    back = read_curve_csv(tmp_path / "c.csv")
    assert back[0]["env_steps"] == 64.0 and math.isnan(back[1]["solved"]) and math.isnan(back[0]["loss"])
    plot_curves(tmp_path / "c.csv", tmp_path / "c.png", ys=("solved", "nope"))
    assert (tmp_path / "c.png").read_bytes()[:8] == PNG
    with pytest.raises(ValueError, match="^ys must name"):
        plot_curves(tmp_path / "c.csv", tmp_path / "d.png", ys=("nope",))


def _cli(*argv) -> int:
    from softrtc.cli import main

    return main(list(argv))


TINY_PPO = ["--num-envs", "2", "--num-steps", "8", "--num-minibatches", "2", "--num-epochs", "1",
            "--layer-width", "8", "--log-interval", "1", "--no-progress"]
TINY_POLICY = ["--channel-dim", "8", "--channel-hidden-dim", "8", "--token-hidden-dim", "4", "--num-layers", "1",
               "--chunk-size", "8"]


@needs_levels
@pytest.mark.slow
def test_pipeline_end_to_end_tiny(tmp_path, capsys, restore_cache):
    """KP-4, KP-6, KP-7, KP-8, KP-9, KP-10, KP-11, KP-12, KP-13, KP-15, KC-1: train-expert -> generate-data ->
    train-bc -> finetune -> eval on one level with tiny budgets, every file in the release's layout; a
    resumed PPO run equals the uninterrupted one bitwise; recorded data obey the done/length/return
    bookkeeping of [K-14]; generate-data run again reads the recorded level back."""
    run, cc = tmp_path / "run", ["--compile-cache", str(tmp_path / "cc")]
    lv = ["--levels", "grasp_easy", "--levels-dir", str(LEVELS_DIR)]
    # 2 iterations, then resumed to 3; a second run goes to 3 in one go.
    assert _cli("kinetix", "train-expert", *lv, "--out", str(run), "--updates", "2", *TINY_PPO, *cc) == 0
    assert _cli("kinetix", "train-expert", *lv, "--out", str(run), "--updates", "3", *TINY_PPO, *cc) == 0
    assert _cli("kinetix", "train-expert", *lv, "--out", str(tmp_path / "run3"), "--updates", "3", *TINY_PPO,
                *cc) == 0
    from softrtc.kinetix import ppo as kppo

    # One compiled PPO iteration served the fresh run, its resumption and the repeated run ([KP-7]).
    assert kppo._PROGRAMS and all(update._cache_size() == 1 for _, update in kppo._PROGRAMS.values())
    name = "worlds_l_grasp_easy"
    for u in (0, 1, 2):
        stats = json.loads((run / "seed_0" / str(u) / "stats" / f"{name}.json").read_text())
        assert {"returned_episode_returns", "returned_episode_solved", "returned_episode_lengths"} <= set(stats)
        a = kexp.load_expert(run / "seed_0" / str(u) / "policies" / f"{name}.pkl")
        b = kexp.load_expert(tmp_path / "run3" / "seed_0" / str(u) / "policies" / f"{name}.pkl")
        for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
            np.testing.assert_array_equal(np.asarray(x), np.asarray(y))  # resumed == uninterrupted
        assert kexp.expert_dims(a) == (2722, 6, 8)
    with open(run / "seed_0" / f"curve_{name}.csv") as f:
        rows = list(csv.DictReader(f))
    assert [int(r["update"]) for r in rows] == [1, 2, 3] and [int(r["env_steps"]) for r in rows] == [16, 32, 48]
    assert (run / "seed_0" / f"curve_{name}.png").read_bytes()[:8] == PNG

    assert _cli("kinetix", "generate-data", "--run", str(run), *lv, "--num-envs", "2", "--num-steps", "32",
                "--batch-size", "8", "--no-progress", *cc) == 0
    from softrtc.kinetix.data import load_expert_data

    d = load_expert_data(run / "data" / f"{name}.npz")
    assert d.obs.shape == (16, 2, 679) and d.action.shape == (16, 2, 6)
    assert np.all(np.abs(d.action[..., :4]) < 1) and np.all((d.action[..., 4:] > 0) & (d.action[..., 4:] < 1))
    meta = json.loads((run / "data" / f"{name}.meta.json").read_text())
    assert len(meta["experts"]) == 1 and meta["experts"][0]["good"] is False
    for e in range(2):  # length on a done row = steps since the previous done; the next obs is the reset obs
        last = -1
        for s in range(16):
            if d.done[s, e]:
                assert d.length[s, e] == s - last
                if s + 1 < 16:
                    np.testing.assert_array_equal(d.obs[s + 1, e], d.obs[0, e])
                last = s
            elif last == -1:
                assert d.length[s, e] == 0 and d.return_[s, e] == 0
    # [KP-15] the same command again reads the level back (the data file is not written again).
    recorded = (run / "data" / f"{name}.npz").stat().st_mtime_ns
    capsys.readouterr()
    assert _cli("kinetix", "generate-data", "--run", str(run), *lv, "--num-envs", "2", "--num-steps", "32",
                "--batch-size", "8", "--no-progress", *cc) == 0
    assert "(already recorded, read back)" in capsys.readouterr().out
    assert (run / "data" / f"{name}.npz").stat().st_mtime_ns == recorded

    bc = tmp_path / "bc"
    assert _cli("kinetix", "train-bc", "--data", str(run / "data"), "--levels", "grasp_easy", "--out", str(bc),
                "--epochs", "2", "--batch-size", "4", "--warmup-steps", "0", *TINY_POLICY, "--no-progress", *cc) == 0
    with open(bc / f"curve_{name}.csv") as f:
        bc_rows = list(csv.DictReader(f))
    # 16 * 2 - 8 + 1 = 25 examples, 6 batches of 4 per epoch.
    assert [(int(r["epoch"]), int(r["steps"]), int(r["examples"])) for r in bc_rows] == [(1, 6, 25), (2, 12, 25)]
    assert all(math.isfinite(float(r["loss"])) for r in bc_rows)
    from softrtc.kinetix.finetune import find_bc_file

    assert find_bc_file(bc, "grasp_easy") == bc / "2" / "policies" / f"{name}.pkl"

    ft = tmp_path / "ft"
    assert _cli("kinetix", "finetune", "--data", str(run / "data"), "--bc", str(bc), "--method", "hard",
                "--levels", "grasp_easy", "--batch-size", "4", "--out", str(ft), "--no-progress", *cc) == 0
    ev = tmp_path / "eval"
    capsys.readouterr()
    assert _cli("kinetix", "eval", "--levels", "grasp_easy", "--levels-dir", str(LEVELS_DIR), "--episodes", "1",
                "--delays", "0,2", "--methods", "naive,train_hard", "--policy-dir", str(bc),
                "--method-policy", f"train_hard={ft}", "--out", str(ev), "--no-progress", *cc) == 0
    table = (ev / "table.md").read_text()
    assert "| Base Naive |" in table and "| Train Hard RTC |" in table
    with open(ev / "episodes.csv") as f:
        assert len(list(csv.DictReader(f))) == 4
