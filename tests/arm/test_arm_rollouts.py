"""Conformance rollouts on the arm with the simulated-delay executor (spec chapters X, S, W; spec/10-arm.md).

An untrained small flow policy keeps these fast; the properties hold for any weights. Its adaLN-zero layers
start at zero ([P-6]), which would make the output ignore flow time, so that a wrong per-token time could not
fail a test: they are given random values here, and the first test checks that the output depends on time.
"""

import numpy as np
import jax
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.executor import episode_metrics, run_simulated_episode  # noqa: E402
from softrtc.arm.policies import ArmPolicy, untrained_policy  # noqa: E402
from softrtc.arm.policy_config import ArmPolicyConfig  # noqa: E402
from softrtc.jax import executor as jexec  # noqa: E402
from softrtc.jax.endpoints import offset  # noqa: E402
from softrtc.jax.weights import SoftWindow  # noqa: E402
from softrtc.reference import executor as rexec  # noqa: E402

STEPS = 40  # 8 chunks of s = 5
CFG = ArmPolicyConfig(channel_dim=16, channel_hidden_dim=32, token_hidden_dim=8, num_layers=2)
_CACHE = {}


def _time_dependent(pol):
    """``pol`` with random values in its zero-initialised adaLN layers: flow time then reaches the output."""
    import flax.nnx as nnx

    graphdef, state = nnx.split(pol.model)
    pure = nnx.to_pure_dict(state)
    key = jax.random.key(123)

    def fill(path, leaf):
        nonlocal key
        if any("adaln" in str(getattr(p, "key", p)) for p in path):
            key, sub = jax.random.split(key)
            return 0.3 * jax.random.normal(sub, leaf.shape, leaf.dtype)
        return leaf

    nnx.replace_by_pure_dict(state, jax.tree_util.tree_map_with_path(fill, pure))
    return ArmPolicy(nnx.merge(graphdef, state), pol.normalizer, CFG, pol.method, trained_as="untrained",
                     window=None if pol.method != "train_soft" else pol.window)


def policy(method, window=None):
    k = (method, None if window is None else "offset0")
    if k not in _CACHE:
        _CACHE[k] = _time_dependent(untrained_policy(7, method, CFG, window=window))
    return _CACHE[k]


def test_the_policy_output_depends_on_flow_time():
    """P-4, P-9, A-22: the premise of the tests below: the policy's velocity changes with the flow time of one
    token (so a wrong per-token time changes the chunks), and the untrained policy alone would not show it."""
    import jax.numpy as jnp

    from softrtc.arm.features import FEATURE_DIM

    obs = jnp.zeros((1, FEATURE_DIM))
    x = jnp.zeros((1, CFG.horizon, 4))
    t = jnp.full((1, CFG.horizon), 0.4)
    t2 = t.at[0, 3].set(0.6)
    model = policy("naive").model
    assert float(jnp.max(jnp.abs(model(obs, x, t2) - model(obs, x, t)))) > 1e-3
    plain = untrained_policy(7, "naive", CFG).model
    np.testing.assert_array_equal(plain(obs, x, t2), plain(obs, x, t))


def rollout(method, delays, seed=11, key=0, window=None):
    return run_simulated_episode(policy(method, window), seed, delays, jax.random.key(key), max_steps=STEPS)


def test_zero_delay_same_actions_for_all_training_time_methods():
    """S-7, E-6, W-9, C-3, A-22, P-9, P-14: with d = 0 train_hard and train_soft execute bitwise identical actions
    (one sampler, zero weights), and naive, which conditions on the shared time, the same within [P-14]."""
    recs = {m: rollout(m, 0) for m in ("naive", "train_hard", "train_soft")}
    hard = recs["train_hard"]
    assert hard.actions.shape == (STEPS, 4)
    np.testing.assert_array_equal(recs["train_soft"].actions, hard.actions)
    np.testing.assert_array_equal(recs["train_soft"].chunks, hard.chunks)
    np.testing.assert_allclose(recs["naive"].actions, hard.actions, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(recs["naive"].chunks, hard.chunks, rtol=1e-4, atol=1e-4)
    # The first chunk is the naive sampler's for every method ([X-2]): bitwise the same.
    np.testing.assert_array_equal(recs["naive"].chunks[0], hard.chunks[0])


def test_offset_zero_window_equals_hard():
    """E-3, W-8, A-22: train_soft with the offset rule L = 0 executes exactly what train_hard executes."""
    hard = rollout("train_hard", 3)
    soft0 = rollout("train_soft", 3, window=SoftWindow(rule=offset(0, 5)))
    np.testing.assert_array_equal(soft0.actions, hard.actions)
    np.testing.assert_array_equal(soft0.chunks, hard.chunks)
    # And the default soft window does differ at d = 3 (its window is not empty, W-7).
    assert not np.array_equal(rollout("train_soft", 3).chunks, hard.chunks)


@pytest.mark.parametrize("method", ["train_hard", "train_soft"])
def test_committed_prefix_comes_from_previous_chunk(method):
    """X-2, X-3, X-4, X-5, A-23: at each switch the first d_c actions came from chunk c-1."""
    delays = [0, 1, 3, 5, 2, 4, 0, 3]
    rec = rollout(method, delays)
    s = 5
    assert list(rec.request_step) == [c * s for c in range(len(rec.chunks))]
    assert list(rec.delays) == delays[: len(rec.chunks)]
    for n in range(rec.steps):
        c, i = divmod(n, s)
        d = rec.delays[c] if c >= 1 else 0
        if i < d:
            assert (rec.chunk_index[n], rec.token_index[n]) == (c - 1, s + i)
            np.testing.assert_array_equal(rec.actions[n], rec.chunks[c - 1][s + i])
        else:
            assert (rec.chunk_index[n], rec.token_index[n]) == (c, i)
            np.testing.assert_array_equal(rec.actions[n], rec.chunks[c][i])
    m = episode_metrics(rec)
    assert np.isfinite(m["D1"]) and np.isfinite(m["boundary"])


def test_jax_and_reference_executors_agree_on_policy_outputs():
    """X-5, N-8, A-23: execute_chunks (JAX and NumPy reference) reproduce the executed actions."""
    delays = [0, 2, 4, 1, 3, 5, 0, 2]
    rec = rollout("train_soft", delays)
    ref = rexec.execute_chunks(rec.chunks, rec.delays, 5)
    jx = jexec.execute_chunks(rec.chunks, np.asarray(rec.delays, np.int32), 5)
    np.testing.assert_array_equal(ref["actions"][: rec.steps], rec.actions)
    np.testing.assert_array_equal(ref["chunk_index"][: rec.steps], rec.chunk_index)
    np.testing.assert_array_equal(ref["token_index"][: rec.steps], rec.token_index)
    np.testing.assert_allclose(np.asarray(jx["actions"])[: rec.steps], rec.actions, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.asarray(jx["chunk_index"]), ref["chunk_index"])
    np.testing.assert_array_equal(np.asarray(jx["token_index"]), ref["token_index"])


def test_same_seed_same_rollout_and_different_key_differs():
    """N-9, A-6, A-22: same policy, env seed, delays and key give a bitwise identical rollout."""
    a = rollout("train_soft", 3, seed=5, key=1)
    b = rollout("train_soft", 3, seed=5, key=1)
    np.testing.assert_array_equal(a.actions, b.actions)
    np.testing.assert_array_equal(a.joint_pos, b.joint_pos)
    c = rollout("train_soft", 3, seed=5, key=2)
    assert not np.array_equal(a.actions, c.actions)


def test_inference_hard_at_zero_delay_is_naive():
    """G-6, G-1, S-6: inference-time hard RTC at d = 0 (W = 0) executes the naive actions."""
    np.testing.assert_allclose(rollout("inference_hard", 0).actions, rollout("naive", 0).actions, atol=1e-6)


def test_simulated_executor_validates_inputs():
    """X-1, N-7, A-12: delays outside [0, min(s, H - s)], d_0 != 0, bad seeds and keys are rejected."""
    with pytest.raises(ValueError, match="delays"):
        rollout("train_hard", 6)
    with pytest.raises(ValueError, match="delays"):
        rollout("train_hard", -1)
    with pytest.raises(ValueError, match=r"delays\[0\]"):
        rollout("train_hard", [2, 2])
    with pytest.raises(ValueError, match="delays"):
        rollout("train_hard", 2.0)
    with pytest.raises(ValueError, match="env_seed"):
        run_simulated_episode(policy("naive"), -1, 0, jax.random.key(0))
    with pytest.raises(ValueError, match="key"):
        run_simulated_episode(policy("naive"), 0, 0, 0)
    with pytest.raises(ValueError, match="max_steps"):
        run_simulated_episode(policy("naive"), 0, 0, jax.random.key(0), max_steps=0)
    with pytest.raises(ValueError, match="d"):
        policy("train_hard").generate(np.zeros(34), np.zeros((10, 4)), 6, jax.random.key(0))
    with pytest.raises(ValueError, match="obs"):
        policy("train_hard").generate(np.zeros(33), None, 0, jax.random.key(0))


def test_chunk_dataset_and_policy_output_head():
    """A-17, A-19, A-8: chunks repeat the last label past an episode's end; chunks lie in the action box."""
    from softrtc.arm.features import action_bounds
    from softrtc.arm.training import chunk_dataset

    data = {"obs": np.arange(5 * 34, dtype=np.float32).reshape(5, 34),
            "action": np.arange(5 * 4, dtype=np.float32).reshape(5, 4),
            "episode_start": np.array([0, 3]), "episode_length": np.array([3, 2])}
    ds = chunk_dataset(data, 4)
    assert ds["obs"].shape == (5, 34) and ds["chunks"].shape == (5, 4, 4)
    np.testing.assert_array_equal(ds["chunks"][1, :, 0], [4, 8, 8, 8])
    np.testing.assert_array_equal(ds["chunks"][3, :, 0], [12, 16, 16, 16])
    with pytest.raises(ValueError, match="horizon"):
        chunk_dataset(data, 0)
    lo, hi = action_bounds()
    rec = rollout("train_soft", 2)
    assert np.all(rec.chunks >= lo) and np.all(rec.chunks <= hi)
    assert CFG.max_delay == 5 and ArmPolicyConfig().horizon == 10 and ArmPolicyConfig().execute_horizon == 5


def test_checkpoint_roundtrip_and_shipped_checkpoints(tmp_path):
    """A-18, A-21, T-11, T-12: a saved policy reloads to the same chunks; the shipped set is small and complete."""
    from softrtc.arm.checkpoints import ARM_FORMAT, default_checkpoint_dir, load_arm_checkpoint, save_arm_checkpoint
    from softrtc.arm.features import FEATURE_DIM
    from softrtc.arm.training import arm_train_config
    from softrtc.jax.checkpoint import read_checkpoint

    p = policy("train_hard")
    tc = arm_train_config("train_hard", CFG, 10)
    path = save_arm_checkpoint(tmp_path / "p.npz", p.model, p.normalizer, CFG, "train_hard", {"note": 1}, tc)
    q = load_arm_checkpoint(path)
    assert q.method == "train_hard" and q.meta == {"note": 1} and q.train_config == tc.to_dict()
    for k in ("obs_mean", "obs_std", "act_mean", "act_std"):
        np.testing.assert_array_equal(getattr(q.normalizer, k), getattr(p.normalizer, k))
    obs = np.linspace(-1, 1, 34)
    c0 = p.generate(obs, None, 0, jax.random.key(3))
    np.testing.assert_array_equal(q.generate(obs, None, 0, jax.random.key(3)), c0)
    np.testing.assert_array_equal(q.generate(obs, c0, 3, jax.random.key(4)), p.generate(obs, c0, 3, jax.random.key(4)))
    with pytest.raises(ValueError, match="path"):
        load_arm_checkpoint(tmp_path / "missing.npz")
    # A train_soft checkpoint samples with the window it was trained with ([W-7]), not the default one.
    import dataclasses

    from softrtc.reference.endpoints import offset
    from softrtc.reference.weights import SoftWindow as RefSoftWindow
    soft_tc = dataclasses.replace(arm_train_config("train_soft", CFG, 10), window=RefSoftWindow(offset(1, 8)))
    soft = load_arm_checkpoint(save_arm_checkpoint(tmp_path / "s.npz", p.model, p.normalizer, CFG, "train_soft",
                                                   None, soft_tc))
    assert soft.window.rule.kind == "offset" and int(soft.window.rule.length) == 1
    assert load_arm_checkpoint(tmp_path / "s.npz", "naive").method == "naive"
    with pytest.raises(ValueError, match="method"):
        save_arm_checkpoint(tmp_path / "q.npz", p.model, p.normalizer, CFG, "inference_soft")
    folder = default_checkpoint_dir()
    files = {f: folder / f for f in ("base.npz", "train_hard.npz", "train_soft.npz")}
    assert sum(f.stat().st_size for f in files.values()) < 5 * 2**20
    for name, f in files.items():
        _, header = read_checkpoint(f)
        arm = header["metadata"]["arm"]
        assert arm["format"] == ARM_FORMAT and arm["config"]["horizon"] == 10
        assert header["policy"]["obs_dim"] == FEATURE_DIM
        assert arm["method"] == {"base.npz": "naive", "train_hard.npz": "train_hard",
                                 "train_soft.npz": "train_soft"}[name]
        assert arm["train_config"]["method"] == {"base.npz": "none", "train_hard.npz": "hard",
                                                 "train_soft.npz": "soft"}[name]
        assert arm["train_config"]["execute_horizon"] == 5 and arm["train_config"]["d_max"] == 5
        assert len(arm["normalizer"]["obs_mean"]) == FEATURE_DIM and len(arm["normalizer"]["act_std"]) == 4


def test_policy_features_mark_the_current_part():
    """A-17: the features append a one-hot of the first part not placed and tip-relative part/box offsets."""
    from softrtc.arm.env import ArmSortEnv
    from softrtc.arm.features import FEATURE_DIM, policy_features

    obs = ArmSortEnv().reset(3)
    f = policy_features(obs)
    assert f.shape == (FEATURE_DIM,)
    np.testing.assert_array_equal(f[:34], obs)
    np.testing.assert_array_equal(f[34:38], [1, 0, 0, 0])
    np.testing.assert_allclose(f[38:40], obs[10:12] - obs[6:8])
    np.testing.assert_allclose(f[40:42], obs[30:32] - obs[6:8])
    done2 = obs.copy()
    done2[[14, 19]] = 1.0  # blue parts placed: the current part is silver0, in the gray box
    g = policy_features(done2)
    np.testing.assert_array_equal(g[34:38], [0, 0, 1, 0])
    np.testing.assert_allclose(g[38:40], obs[20:22] - obs[6:8])
    np.testing.assert_allclose(g[40:42], obs[32:34] - obs[6:8])
    alldone = obs.copy()
    alldone[[14, 19, 24, 29]] = 1.0
    assert not np.any(policy_features(alldone)[34:])
    np.testing.assert_array_equal(policy_features(np.stack([obs, done2]))[1], g)
    with pytest.raises(ValueError, match="obs"):
        policy_features(np.zeros(33))


def test_training_objectives_run_and_change_weights():
    """A-20, T-1, T-3, T-9, D-1, D-4: each objective maps to its chapter-T config; fine-tuning leaves the base intact."""
    import flax.nnx as nnx
    from softrtc.arm.features import FEATURE_DIM, Normalizer, policy_features
    from softrtc.arm.training import arm_train_config, train_flow_policy
    from softrtc.reference.weights import SoftWindow as RefSoftWindow

    rng = np.random.default_rng(0)
    ds = {"obs": rng.normal(size=(32, 34)).astype(np.float32),
          "chunks": rng.normal(size=(32, CFG.horizon, 4)).astype(np.float32)}
    norm = Normalizer.fit(policy_features(ds["obs"]), ds["chunks"].reshape(-1, 4))
    base, losses, tc = train_flow_policy(ds, norm, "naive", 2, 0, config=CFG, batch_size=8)
    assert losses.shape == (2,) and np.all(np.isfinite(losses)) and tc.method == "none"
    assert base.obs_dim == FEATURE_DIM
    before = jax.tree_util.tree_leaves(nnx.state(base))
    soft, _, tc = train_flow_policy(ds, norm, "train_soft", 2, 1, config=CFG, init=base, batch_size=8)
    after = jax.tree_util.tree_leaves(nnx.state(base))
    assert all(np.array_equal(a, b) for a, b in zip(before, after))
    assert any(not np.array_equal(a, b) for a, b in zip(before, jax.tree_util.tree_leaves(nnx.state(soft))))
    assert tc.method == "soft" and tc.window == RefSoftWindow() and tc.execute_horizon == CFG.execute_horizon
    assert (tc.delay_dist, tc.d_min, tc.d_max) == ("uniform", 0, CFG.max_delay)
    assert arm_train_config("train_hard", CFG, 100).method == "hard"
    with pytest.raises(ValueError, match="method"):
        train_flow_policy(ds, norm, "inference_soft", 2, 0, config=CFG)
    with pytest.raises(ValueError, match="steps"):
        train_flow_policy(ds, norm, "naive", 0, 0, config=CFG)
    with pytest.raises(ValueError, match="init"):
        train_flow_policy(ds, norm, "naive", 2, 0, config=CFG, init=object())


def test_study_metrics_table_and_plot(tmp_path):
    """A-24, A-25, A-26, M-1, M-3, M-6: per-trial metrics on joint targets, the table and the trace plot."""
    from softrtc.arm.study import format_table, plot_traces, summarize
    from softrtc.reference.metrics import boundary_jump, difference_norm

    recs = [rollout("train_hard", 3, seed=s) for s in (1, 2)]
    per = [episode_metrics(r) for r in recs]
    for r, m in zip(recs, per):
        assert m["D2"] == difference_norm(r.actions[:, :3], 2)
        assert m["boundary"] == boundary_jump(r.actions[:, :3], r.chunk_index)
        assert m["throughput"] == m["completed"] / (r.steps * r.dt / 60.0)
    row = summarize(per)
    assert row["trials"] == 2 and row["objects_total"] == 8
    assert row["D1_se"] == pytest.approx(np.std([m["D1"] for m in per], ddof=1) / np.sqrt(2))
    text = format_table({"train_hard": row})
    for col in ("Succ.", "Compl.", "Obj.", "Thr.", "D1", "D2", "D3", "Bound.", "Lat.", "Train Hard RTC"):
        assert col in text
    png = plot_traces({"train_hard": recs[0]}, tmp_path / "t.png")
    assert (tmp_path / "t.png").stat().st_size > 1000 and png.endswith(".png")
    with pytest.raises(ValueError, match="per_trial"):
        summarize([])


def _spec_train_config(method, steps, learning_rate):
    """[A-20] written out from spec/10-arm.md (not from the code): the chapter-T config of an arm objective."""
    return {"method": method,
            "window": {"rule": {"kind": "delay_scaled", "lam": 2.0, "h_max": 5}, "schedule": "linear",
                       "parametrization": "rtc", "overflow": "clip"},
            "execute_horizon": 5, "delay_dist": "uniform", "d_min": 0, "d_max": 5, "delay_decay": 1.0,
            "batch_size": 128, "learning_rate": learning_rate, "weight_decay": 1e-4, "adam_b1": 0.9,
            "adam_b2": 0.999, "adam_eps": 1e-8, "grad_clip_norm": 1.0, "warmup_steps": min(200, steps // 10),
            "decay_steps": steps, "final_lr_ratio": 0.05}


def test_arm_train_config_and_shipped_checkpoints_follow_the_spec():
    """A-20, A-21, T-1, T-6, W-7: the whole training config of each objective, and what each shipped file stores."""
    from softrtc.arm.checkpoints import default_checkpoint_dir
    from softrtc.arm.training import arm_train_config
    from softrtc.jax.checkpoint import read_checkpoint

    objective = {"naive": "none", "train_hard": "hard", "train_soft": "soft"}
    for m, tm in objective.items():
        for steps, lr in ((4000, 1e-3), (800, 1e-3 / 3), (50, 1e-3)):
            assert arm_train_config(m, ArmPolicyConfig(), steps, 128, lr).to_dict() == _spec_train_config(tm, steps, lr)
    # The defaults are the command's: batch 128 ([A-20]).
    assert arm_train_config("naive", ArmPolicyConfig(), 4000).to_dict() == _spec_train_config("none", 4000, 1e-3)
    # base 4000 steps at 1e-3, fine-tunes 800 steps at 1e-3 / 3; 400 episodes, seed 0, batch 128.
    shipped = {"base.npz": ("naive", 4000, 1e-3), "train_hard.npz": ("train_hard", 800, 1e-3 / 3),
               "train_soft.npz": ("train_soft", 800, 1e-3 / 3)}
    for name, (m, steps, lr) in shipped.items():
        _, header = read_checkpoint(default_checkpoint_dir() / name)
        arm = header["metadata"]["arm"]
        assert arm["train_config"] == _spec_train_config(objective[m], steps, lr), name
        meta = arm["meta"]
        assert (meta["episodes"], meta["seed"], meta["noise_std"], meta["steps"], meta["finetune_steps"],
                meta["batch_size"], meta["learning_rate"]) == (400, 0, 0.03, 4000, 800, 128, 1e-3), name


def test_train_arm_policies_small_run(tmp_path):
    """A-20, A-18, T-8, T-9, AX-8: demos, base and both fine-tunes end to end; only the checkpoints are written to
    out; a base alone from a task's world."""
    from softrtc.arm.checkpoints import load_arm_checkpoint
    from softrtc.arm.training import arm_train_config, train_arm_policies

    (tmp_path / "demos.npz").write_bytes(b"a file of the user's")
    paths = train_arm_policies(tmp_path, episodes=1, steps=2, finetune_steps=2, seed=5, config=CFG, batch_size=8,
                               verbose=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["base.npz", "demos.npz", "train_hard.npz",
                                                          "train_soft.npz"]
    assert (tmp_path / "demos.npz").read_bytes() == b"a file of the user's"
    assert set(paths) == {"naive", "train_hard", "train_soft"}
    for m, lr in (("naive", 1e-3), ("train_hard", 1e-3 / 3), ("train_soft", 1e-3 / 3)):
        pol = load_arm_checkpoint(paths[m])
        assert pol.trained_as == m and pol.config == CFG
        assert pol.train_config == arm_train_config(m, CFG, 2, 8, lr).to_dict()
        assert pol.meta["episodes"] == 1 and pol.meta["seed"] == 5 and pol.meta["steps"] == 2
        assert (pol.meta.get("finetuned_from") == "base") == (m != "naive")
    # The base is trained from nnx.Rngs(seed) and key(seed); the fine-tunes start from it and differ from it.
    import flax.nnx as nnx

    leaves = {m: jax.tree_util.tree_leaves(nnx.state(load_arm_checkpoint(p).model)) for m, p in paths.items()}
    assert any(not np.array_equal(a, b) for a, b in zip(leaves["naive"], leaves["train_hard"]))
    # AX-8: the base alone, from demonstrations recorded in a task's world.
    from softrtc.arm.tasks import DRIFT_CONFIG

    only = train_arm_policies(tmp_path / "drift", episodes=1, steps=2, seed=5, config=CFG, batch_size=8,
                              verbose=False, env_config=DRIFT_CONFIG, fine_tune=False)
    assert set(only) == {"naive"} and sorted(p.name for p in (tmp_path / "drift").iterdir()) == ["base.npz"]
    drift_base = load_arm_checkpoint(only["naive"])
    # Trained on other observations (the trays' world): other feature statistics than the default world's base.
    assert not np.allclose(drift_base.normalizer.obs_mean, load_arm_checkpoint(paths["naive"]).normalizer.obs_mean)
    for bad, msg in ((dict(batch_size=0), "batch_size"), (dict(out_dir=3), "out_dir"), (dict(episodes=0), "episodes"),
                     (dict(demos=tmp_path / "missing.npz"), "demos"), (dict(env_config=3), "env_config"),
                     (dict(fine_tune=1), "fine_tune")):
        kw = {"out_dir": tmp_path, "episodes": 1, "steps": 1, "config": CFG, "verbose": False, **bad}
        with pytest.raises(ValueError, match=f"^{msg}"):
            train_arm_policies(**kw)


def test_run_study_seeds_keys_and_csv_columns(tmp_path, monkeypatch):
    """A-25, A-24, R-2, N-9: trial i of every method uses env seed seed0 + i and key fold_in(key(key_seed), i);
    the methods run interleaved, trial by trial, in an order rotated by i (A-25)."""
    import csv

    from softrtc.arm import study
    from softrtc.arm.env import ArmSortEnv
    from softrtc.arm.checkpoints import save_arm_checkpoint

    ckpt = tmp_path / "ckpt"
    ckpt.mkdir()
    p = policy("naive")
    for name, m in (("base.npz", "naive"), ("train_hard.npz", "train_hard"), ("train_soft.npz", "train_soft")):
        save_arm_checkpoint(ckpt / name, p.model, p.normalizer, CFG, m)
    calls = []
    real = study.run_realtime_episode

    def recording(pol, env_seed, key, cfg, max_steps=None):
        rec = real(pol, env_seed, key, cfg, max_steps=max_steps)
        calls.append((pol.method, env_seed, key, cfg, max_steps, rec))
        return rec

    monkeypatch.setattr(study, "run_realtime_episode", recording)
    out = study.run_study(ckpt, trials=2, methods=("naive", "train_soft"), added_latency_s=0.0, seed0=123,
                          key_seed=7, out_dir=tmp_path / "out", max_steps=12, plot=False, verbose=False)
    assert [(c[0], c[1]) for c in calls] == [("naive", 123), ("train_soft", 123), ("train_soft", 124), ("naive", 124)]
    for method, env_seed, key, cfg, max_steps, rec in calls:
        i = env_seed - 123
        want = jax.random.fold_in(jax.random.key(7), i)
        np.testing.assert_array_equal(jax.random.key_data(key), jax.random.key_data(want))
        assert cfg.added_latency_s == 0.0 and max_steps == 12 and rec.step_limit == 12
        # Request 0 is made before the clock starts ([R-2]): its chunk is a pure function of seed and key.
        obs = ArmSortEnv().reset(env_seed)
        np.testing.assert_array_equal(rec.chunks[0], p.generate(obs, None, 0, jax.random.fold_in(want, 0)))
    with open(out["paths"]["results"]) as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == ["method", "trial", "env_seed", "success", "completed", "completion", "duration_s",
                             "throughput", "D1", "D2", "D3", "boundary", "latency_ms", "hold_ticks", "fault",
                             "mean_realized_delay"]
    assert [(r["method"], r["trial"], r["env_seed"]) for r in rows] == [
        ("naive", "0", "123"), ("train_soft", "0", "123"), ("train_soft", "1", "124"), ("naive", "1", "124")]
    with open(out["paths"]["summary"]) as f:
        summary = list(csv.DictReader(f))
    stats = [x for k in ("completion", "throughput", "D1", "D2", "D3", "boundary", "latency_ms", "hold_ticks")
             for x in (k, k + "_se")]
    assert list(summary[0]) == ["method", "trials", "successes", "objects", "objects_total", *stats, "faults",
                                "period_p50_ms", "period_p99_ms"]
    assert [r["method"] for r in summary] == ["naive", "train_soft"] and summary[0]["trials"] == "2"
    # The table read back from results.csv is the one the run printed (the README's block is made this way).
    assert study.table_from_results(out["paths"]["results"]) == out["table"]
    with pytest.raises(ValueError, match="^path"):
        study.table_from_results(out["paths"]["summary"])
    assert set(out["paths"]) == {"results", "summary"}


def test_throughput_is_over_the_full_trial():
    """A-24: a solved episode counts up to its success time; any other trial over its max_steps ticks."""
    import dataclasses

    rec = rollout("train_hard", 3)
    assert rec.step_limit == STEPS and rec.steps == STEPS
    cut = dataclasses.replace(rec, steps=10, actions=rec.actions[:10], chunk_index=rec.chunk_index[:10],
                              num_completed=1, step_limit=1000)
    m = episode_metrics(cut)
    assert m["throughput"] == pytest.approx(1 / (1000 * 0.02 / 60.0)) and m["duration_s"] == pytest.approx(0.2)
    solved = dataclasses.replace(rec, num_completed=4, success=True, success_step=STEPS, step_limit=1000)
    assert episode_metrics(solved)["throughput"] == pytest.approx(4 / (STEPS * 0.02 / 60.0))
    with pytest.raises(ValueError, match="step_limit"):
        episode_metrics(dataclasses.replace(rec, step_limit=STEPS - 1))


def test_policy_window_and_chunk_dataset_inputs_are_checked():
    """A-17, A-16, W-7, N-7: a window that is not a JAX SoftWindow and a demo layout that is not [A-16]'s raise."""
    from softrtc.arm.policies import ArmPolicy
    from softrtc.arm.training import chunk_dataset
    from softrtc.reference.weights import SoftWindow as RefSoftWindow

    for bad in ("soft", RefSoftWindow(), 2.0):
        with pytest.raises(ValueError, match="^window must be a softrtc.jax.weights.SoftWindow"):
            untrained_policy(0, "train_soft", CFG, window=bad)
        p = policy("naive")
        with pytest.raises(ValueError, match="^window must be"):
            ArmPolicy(p.model, p.normalizer, CFG, "train_soft", window=bad)
    good = {"obs": np.zeros((5, 34), np.float32), "action": np.zeros((5, 4), np.float32),
            "episode_start": np.array([0, 3]), "episode_length": np.array([3, 2])}
    assert chunk_dataset(good, 4)["chunks"].shape == (5, 4, 4)
    cases = [(dict(episode_start=np.array([0, 4])), r"data\['episode_start'\]"),
             (dict(episode_start=np.array([0, 9])), r"data\['episode_start'\]"),
             (dict(episode_length=np.array([3, 3])), r"data\['episode_start'\]"),
             (dict(episode_length=np.array([5, 0]), episode_start=np.array([0, 5])), r"data\['episode_length'\]"),
             (dict(episode_length=np.array([3])), r"data\['episode_length'\]"),
             (dict(episode_start=np.array([0.0, 3.0])), r"data\['episode_start'\]"),
             (dict(episode_start=np.array([[0, 3]])), r"data\['episode_start'\]"),
             (dict(obs=np.zeros((5, 33))), r"data\['obs'\]"),
             (dict(obs=np.zeros((4, 34))), r"data\['obs'\]"),
             (dict(action=np.full((5, 4), np.nan)), r"data\['action'\]"),
             (dict(action=np.zeros((5, 4), bool)), r"data\['action'\]")]
    for fields, msg in cases:
        with pytest.raises(ValueError, match="^" + msg):
            chunk_dataset({**good, **fields}, 4)


def test_arm_train_command_never_defaults_to_the_shipped_checkpoints(tmp_path, monkeypatch):
    """A-20, A-21, AX-8: `softrtc arm train` writes to ./arm_checkpoints unless --out names another folder; --task
    and --base-only pass the task's world and the base alone."""
    from pathlib import Path

    from softrtc.arm import checkpoints, training
    from softrtc.cli import build_parser

    monkeypatch.chdir(tmp_path)
    args = build_parser().parse_args(["arm", "train"])
    assert args.out == "arm_checkpoints"
    assert Path(args.out).resolve() != checkpoints.default_checkpoint_dir().resolve()
    seen = {}
    monkeypatch.setattr(training, "train_arm_policies", lambda out, **kw: seen.update(out=out, **kw) or {})
    assert args.func(args) == 0
    from softrtc.arm.env import ArmConfig
    from softrtc.arm.tasks import DRIFT_CONFIG

    assert seen == {"out": "arm_checkpoints", "episodes": 400, "steps": 4000, "finetune_steps": 800, "seed": 0,
                    "env_config": ArmConfig(), "fine_tune": True}
    # AX-8: a task's world and the base alone.
    args = build_parser().parse_args(["arm", "train", "--task", "drift", "--base-only"])
    assert args.func(args) == 0
    assert seen["env_config"] == DRIFT_CONFIG and seen["fine_tune"] is False
    assert build_parser().parse_args(["arm", "train", "--out", str(tmp_path / "x")]).out == str(tmp_path / "x")


def test_host_shift_prior_equals_the_jax_twin_bitwise():
    """[X-3] The executor's host shift (NumPy, rounded through float32) equals softrtc.jax.executor.shift_prior
    on float64 chunks, for every s, and zero-fills the last s tokens."""
    from softrtc.arm.executor import _shift_prior
    from softrtc.jax import executor as jexec

    rng = np.random.default_rng(3)
    for s in range(1, 11):
        prev = rng.normal(size=(10, 4)) * 3.0
        got = _shift_prior(prev, s)
        want = np.asarray(jexec.shift_prior(prev, s), np.float64)
        assert got.dtype == np.float64 and np.array_equal(got, want)
        assert np.all(got[10 - s:] == 0.0)
        assert np.array_equal(got[: 10 - s], prev[s:].astype(np.float32).astype(np.float64))
