"""Argument validation of the arm test bed (spec/10-arm.md [A-12], [R-7], [R-8]; spec/00-overview.md [N-7])."""

import re
import dataclasses
import os

import numpy as np
import jax
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.env import ArmConfig, ArmSortEnv, forward_kinematics, inverse_kinematics  # noqa: E402
from softrtc.arm.expert import ExpertConfig, ScriptedExpert, run_expert_episode  # noqa: E402
from softrtc.arm.demos import generate_demos, rollout_noisy_episode  # noqa: E402
from softrtc.arm.executor import episode_metrics, run_simulated_episode  # noqa: E402
from softrtc.arm.checkpoints import load_policies  # noqa: E402
from softrtc.arm.features import FEATURE_DIM, Normalizer, policy_features  # noqa: E402
from softrtc.arm.policies import untrained_policy  # noqa: E402
from softrtc.arm.policy_config import ArmPolicyConfig  # noqa: E402
from softrtc.arm.training import train_arm_policies  # noqa: E402
from softrtc.arm.runtime import RuntimeConfig, jitter_summary, run_realtime_episode  # noqa: E402
from softrtc.arm.clock import SimulatedClock  # noqa: E402
from softrtc.arm import study  # noqa: E402

HUGE = 10**400
SMALL = ArmPolicyConfig(horizon=4, execute_horizon=2, num_steps=1, channel_dim=8, channel_hidden_dim=8,
                        token_hidden_dim=4, num_layers=1)


def _raises(name, fn, *args, **kw):
    """fn(*args, **kw) raises ValueError whose message starts with the argument ``name`` ([N-7])."""
    with pytest.raises(ValueError) as e:
        fn(*args, **kw)
    assert re.match(rf"{re.escape(name)}(?![\w])", str(e.value)), f"message does not start with {name!r}: {e.value}"


@pytest.fixture(scope="module")
def obs():
    return ArmSortEnv(ArmConfig(max_steps=5)).reset(0)


@pytest.fixture(scope="module")
def pol():
    return untrained_policy(0, "naive", SMALL)


class _ChunkPolicy:
    """Stand-in policy that returns a given chunk for request ``bad_at`` and a valid chunk otherwise."""

    method = "stub"

    def __init__(self, bad, bad_at, H=4, s=2):
        self.H, self.s, self.bad, self.bad_at, self.c = np.int64(H), np.int64(s), bad, bad_at, 0

    def generate(self, obs, prior, d, key):
        c, self.c = self.c, self.c + 1
        if c == self.bad_at:
            return self.bad
        return np.concatenate([np.tile(np.asarray(obs[0:3]), (int(self.H), 1)), np.zeros((int(self.H), 1))], 1)


def test_arrays_reject_non_real_ragged_and_empty(obs, pol):
    """[N-7] [A-12] string/bool/complex/ragged/empty arrays are rejected naming the argument."""
    env = ArmSortEnv(ArmConfig(max_steps=5))
    env.reset(0)
    for bad in (obs.astype(str), obs.astype(bool), obs + 0.5j):
        _raises("obs", policy_features, bad)
        _raises("obs", pol.generate, bad, None, 0, jax.random.key(0))
    _raises("obs", policy_features, np.zeros((0, 34)))
    ragged = [[0.0], [0.0, 1.0], 0.0]
    _raises("q", forward_kinematics, ragged)
    _raises("ee_xy", inverse_kinematics, [[0.0], [0.0, 1.0]])
    _raises("action", env.validate_action, [[0.0], 1.0, 2.0, 3.0])
    _raises("action", env.step, [[0.0], 1.0, 2.0, 3.0])
    _raises("obs", ScriptedExpert().act, [[0.0], *obs[1:]])
    _raises("obs", policy_features, [[0.0], *obs[1:]])
    _raises("periods_s", jitter_summary, [[0.1], 0.2])
    c0 = pol.generate(obs, None, 0, jax.random.key(0))
    for bad in (c0.astype(str), c0.astype(bool), c0 + 0.5j):
        _raises("prior", pol.generate, obs, bad, 1, jax.random.key(0))
    d = pol.normalizer.to_dict()
    for conv in (str, bool, complex):
        _raises("data['obs_mean']", Normalizer.from_dict, {**d, "obs_mean": [conv(x) for x in d["obs_mean"]]})
    for name, meth in (("features", pol.normalizer.obs), ("a", pol.normalizer.act), ("z", pol.normalizer.unact)):
        _raises(name, meth, np.zeros((0, FEATURE_DIM if name == "features" else 4)))
    _raises("methods", load_policies, None, [])
    # valid calls
    assert policy_features(obs).shape == (FEATURE_DIM,)
    assert Normalizer.from_dict(d).obs_mean.shape == (FEATURE_DIM,)
    assert pol.generate(obs, c0, 1, jax.random.key(1)).shape == (4, 4)


def test_huge_integers_are_value_errors():
    """[N-7] [A-12] [R-8] an integer too large for a float is a ValueError naming the argument, not OverflowError."""
    _raises("config.motor_gain", ArmConfig, motor_gain=HUGE)
    _raises("config.link_lengths", ArmConfig, link_lengths=(HUGE, 0.28, 0.1))
    _raises("tool_angle", inverse_kinematics, [0.0, 0.25], None, HUGE)
    _raises("lookahead", ExpertConfig, lookahead=HUGE)
    _raises("added_latency_s", RuntimeConfig, added_latency_s=HUGE)
    _raises("join_timeout_s", RuntimeConfig, join_timeout_s=HUGE)
    cfg = ArmConfig(max_steps=5)
    env, ex = ArmSortEnv(cfg), ScriptedExpert(cfg)
    rng = np.random.default_rng(0)
    for name in ("noise_std", "perturb_prob", "perturb_std"):
        args = {"noise_std": 0.0, "perturb_prob": 0.0, "perturb_std": 0.0, name: HUGE}
        _raises(name, rollout_noisy_episode, env, ex, 0, rng, **args)
    _raises("env_seed", rollout_noisy_episode, env, ex, -1, rng, 0.0)
    _raises("learning_rate", train_arm_policies, "/nonexistent-never/x", learning_rate=HUGE, verbose=False)
    _raises("noise_std", train_arm_policies, "/nonexistent-never/x", noise_std=HUGE, verbose=False)
    _raises("added_latency_s", study.run_study, trials=1, added_latency_s=HUGE)
    # NumPy scalars are numbers for ExpertConfig as for ArmConfig.
    assert ExpertConfig(lookahead=np.float64(0.04)).lookahead == 0.04
    assert RuntimeConfig(added_latency_s=np.float32(0.0)).added_latency_s == 0.0
    assert rollout_noisy_episode(env, ex, 0, rng, 0.0)["obs"].shape[1] == 34


def test_paths_and_seeds_checked_before_work(tmp_path):
    """[A-12] [A-16] paths and seeds raise ValueError naming the argument before any episode or training runs."""
    cfg = ArmConfig(max_steps=5)
    _raises("seed", generate_demos, 2, 2**63, 0.1, str(tmp_path / "s.npz"), env_config=cfg)
    (tmp_path / "dir.npz").mkdir()
    _raises("path", generate_demos, 1, 0, 0.1, str(tmp_path / "dir.npz"), env_config=cfg)
    _raises("env_config", generate_demos, 1, 0, 0.1, str(tmp_path / "s.npz"), env_config="x")
    _raises("expert_config", generate_demos, 1, 0, 0.1, str(tmp_path / "s.npz"), expert_config="x")
    afile = tmp_path / "afile"
    afile.write_text("x")
    _raises("out_dir", train_arm_policies, str(afile), verbose=False)
    _raises("out_dir", study.run_study, trials=1, out_dir=str(afile), verbose=False)
    _raises("out_dir", train_arm_policies, str(afile / "sub"), verbose=False)
    _raises("max_steps", study.run_study, trials=1, out_dir=str(tmp_path / "st"), max_steps=0)
    assert not (tmp_path / "st").exists()
    other = tmp_path / "other.npz"
    np.savez(other, a=np.zeros(3))
    _raises("demos", train_arm_policies, str(tmp_path / "tr"), demos=str(other), verbose=False)
    assert not (tmp_path / "tr").exists()
    # valid call
    info = generate_demos(1, 2**63 - 1, 0.1, str(tmp_path / "ok.npz"), env_config=cfg)
    assert info["episodes"] == 1 and os.path.isfile(tmp_path / "ok.npz")


def test_expert_and_config_messages():
    """[A-12] [A-13] slot_x checks obj and box_x; config arguments are named as the caller wrote them."""
    ex = ScriptedExpert()
    for bad in (-1, 4, 2.5, None, "x", True):
        _raises("obj", ex.slot_x, bad, 0.0)
    for bad in (None, float("nan"), "x", HUGE):
        _raises("box_x", ex.slot_x, 0, bad)
    _raises("env_config", run_expert_episode, 0, env_config="x")
    _raises("expert_config", run_expert_episode, 0, env_config=ArmConfig(max_steps=5), expert_config="x")
    _raises("env_config", ScriptedExpert, "x")
    assert ex.slot_x(0, 0.0) < 0.0 < ex.slot_x(1, 0.0)


def test_episode_metrics_checks_record_fields(pol):
    """[A-24] [A-12] episode_metrics rejects a record with bad dt or success_step, naming the field."""
    rec = run_simulated_episode(pol, 0, 1, jax.random.key(0), max_steps=6)
    _raises("record.dt", episode_metrics, dataclasses.replace(rec, dt=0.0))
    _raises("record.success_step", episode_metrics, dataclasses.replace(rec, success=True, success_step=None))
    _raises("record.success_step", episode_metrics, dataclasses.replace(rec, success=True, success_step=0))
    _raises("key", run_simulated_episode, pol, 0, 1, jax.random.split(jax.random.key(0), 2), max_steps=6)
    _raises("key", pol.generate, np.zeros(34), None, 0, jax.random.split(jax.random.key(0), 2))
    _raises("env_config", run_simulated_episode, pol, 0, 1, jax.random.key(0), env_config="x")
    assert episode_metrics(rec)["duration_s"] == pytest.approx(6 * rec.dt)


def test_study_helpers_name_missing_keys(tmp_path, pol):
    """[A-25] [A-26] [A-12] summarize/format_table/plot_traces raise ValueError naming the bad argument."""
    _raises("per_trial", study.summarize, [{}])
    _raises("rows", study.format_table, {"naive": {}})
    _raises("records", study.plot_traces, {"naive": 5}, str(tmp_path / "t.png"))
    rec = run_simulated_episode(pol, 0, 1, jax.random.key(0), max_steps=6)
    _raises("path", study.plot_traces, {"naive": rec}, str(tmp_path / "missing" / "t.png"))
    row = study.summarize([episode_metrics(rec), episode_metrics(rec)])
    assert "Base" in study.format_table({"naive": row})


def test_runtime_bad_chunks_are_faults(obs):
    """[R-7] [R-8] a bad first or later chunk ends the episode with a recorded fault; keys and configs are checked."""
    k = jax.random.key(0)
    rc = RuntimeConfig(added_latency_s=0.0)
    cfg = ArmConfig(max_steps=40)
    for bad in (np.zeros((2, 4)), np.zeros((4, 3)), np.full((4, 4), np.nan)):
        for at in (0, 1):
            rec = run_realtime_episode(_ChunkPolicy(bad, at), 0, k, rc, env_config=cfg, clock=SimulatedClock())
            assert rec.fault is not None and rec.fault.startswith("worker_error"), rec.fault
            assert any(e[1] == "bad_chunk" for e in rec.events)
    _raises("key", run_realtime_episode, _ChunkPolicy(None, -1), 0, jax.random.split(k, 2), rc, env_config=cfg)
    _raises("env_config", run_realtime_episode, _ChunkPolicy(None, -1), 0, k, rc, env_config="x")
    _raises("added_latency", run_realtime_episode, _ChunkPolicy(None, -1), 0, k, rc, env_config=cfg,
            added_latency=lambda c: HUGE)
    # valid: np.int64 H and s are accepted
    rec = run_realtime_episode(_ChunkPolicy(None, -1), 0, k, rc, max_steps=10, env_config=cfg, clock=SimulatedClock())
    assert rec.fault is None and rec.steps == 10


def test_study_refuses_a_checkpoint_in_the_wrong_role(tmp_path, capsys):
    """[A-21] [A-25] A Train Soft checkpoint copied to base.npz is refused by its stored training method, by the
    library and by `softrtc arm study`, with the file and both methods named; the shipped folder loads."""
    import shutil

    from softrtc.arm.checkpoints import default_checkpoint_dir
    from softrtc.cli import main

    src = default_checkpoint_dir()
    for name in ("base", "train_hard", "train_soft"):
        shutil.copy(src / f"{name}.npz", tmp_path / f"{name}.npz")
    shutil.copy(src / "train_soft.npz", tmp_path / "base.npz")
    want = (f"checkpoint {str(tmp_path / 'base.npz')!r} was trained as 'train_soft' (its stored training method), "
            f"but base.npz must hold the policy trained as 'naive', which method 'naive' runs")
    with pytest.raises(ValueError) as info:
        load_policies(tmp_path, ["train_hard", "naive"])
    assert str(info.value) == want
    with pytest.raises(ValueError, match="which method 'inference_soft' runs$"):
        load_policies(tmp_path, ["inference_soft"])
    assert main(["arm", "study", "--checkpoints", str(tmp_path), "--trials", "1", "--out",
                 str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err.strip().splitlines()[-1] == f"softrtc arm study: error: {want}"
    assert not (tmp_path / "out").exists()  # refused before any trial ran
    shutil.copy(src / "train_hard.npz", tmp_path / "train_soft.npz")
    with pytest.raises(ValueError, match="was trained as 'train_hard'.*train_soft.npz must hold the policy trained "
                                         "as 'train_soft'"):
        load_policies(tmp_path, ["train_soft"])
    pols = load_policies(src, ["naive", "inference_hard", "train_hard", "train_soft"])
    assert [p.trained_as for p in pols.values()] == ["naive", "naive", "train_hard", "train_soft"]


def test_arm_loader_refuses_appended_bytes(tmp_path):
    """[A-18] [T-12] A shipped checkpoint with bytes appended is a damaged file, named in the one error."""
    from softrtc.arm.checkpoints import default_checkpoint_dir, load_arm_checkpoint

    raw = (default_checkpoint_dir() / "base.npz").read_bytes()
    (tmp_path / "base.npz").write_bytes(raw + b"\n")
    with pytest.raises(ValueError, match=r"base\.npz.*1 bytes after the end of the archive"):
        load_arm_checkpoint(tmp_path / "base.npz")
    with pytest.raises(ValueError, match=r"base\.npz.*1 bytes after"):
        load_policies(tmp_path, ["naive"])


@pytest.mark.parametrize("option, message", [
    (["--delays", "\u0661"], "argument --delays: each delay must be an integer in [0, 5], got '\u0661'"),
    (["--delays", "\uff11"], "argument --delays: each delay must be an integer in [0, 5], got '\uff11'"),
    (["--delays", "6"], "argument --delays: each delay must be an integer in [0, 5], got 6"),
    (["--task", "overlap4", "--delays", "5"], "delays must be integers in [0, 4], got [5]"),
    (["--seeds", "0"], "argument --seeds: each seed must be an integer in [1, 2147483647], got 0"),
    (["--seeds", "99999999999"], "argument --seeds: each seed must be an integer in [1, 2147483647], got 99999999999"),
    (["--seeds", "4"], "seeds must be integers in [1, 3] (the full budget's fine-tuning seeds), got [4]"),
    (["--quick", "--seeds", "1,2"], "seeds must be integers in [1, 1] (the quick budget's fine-tuning seeds), "
                                    "got [1, 2]"),
])
def test_experiment_delays_and_seeds_are_checked_at_the_door(option, message, tmp_path, capsys):
    """[AX-4] [N-11] `arm experiment` takes ASCII delays of the task's range and 1-based seeds of the budget;
    anything else ends with one error line and status 2 before any folder is made or anything is computed."""
    from softrtc.cli import main

    argv = ["arm", "experiment", "--out", str(tmp_path / "out"), "--work", str(tmp_path / "work")] + option
    try:
        rc = main(argv)
    except SystemExit as exc:
        rc = exc.code
    assert rc == 2
    assert capsys.readouterr().err.splitlines()[-1] == f"softrtc arm experiment: error: {message}"
    assert list(tmp_path.iterdir()) == []
