"""The moving-tray world ([A-27]) and the delay-sensitive task ``drift`` ([AX-8])."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.env import ArmConfig, ArmSortEnv  # noqa: E402
from softrtc.arm.expert import ScriptedExpert, run_expert_episode  # noqa: E402
from softrtc.arm.expert_chunks import delay_screen, expert_chunk, run_expert_chunk_episode  # noqa: E402
from softrtc.arm.scene import BIN_Y  # noqa: E402
from softrtc.arm.tasks import DRIFT_CONFIG, get_task  # noqa: E402


def _hold(env):
    return np.concatenate([env.joint_positions(), [0.0]])


def _box_track(cfg, seed, steps):
    env = ArmSortEnv(cfg)
    obs = env.reset(seed)
    xs = [obs[[30, 32]]]
    for _ in range(steps):
        obs, _ = env.step(_hold(env))
        xs.append(obs[[30, 32]])
    return env, np.array(xs)


def test_trays_hop_on_their_schedule_deterministically():
    """A-27: the trays move only by their seed's hops, at most box_hop_speed * dt per tick, within the hop range,
    and land on each destination; the same seed gives the same track, another seed another."""
    cfg = dataclasses.replace(DRIFT_CONFIG, max_steps=300)
    env, xs = _box_track(cfg, 7, 299)
    _, again = _box_track(cfg, 7, 299)
    np.testing.assert_array_equal(xs, again)
    _, other = _box_track(cfg, 8, 299)
    assert not np.array_equal(xs, other)
    start = np.array(cfg.box_centers)  # no jitter in this task
    np.testing.assert_allclose(xs[0], start)
    step = cfg.box_hop_speed / cfg.control_hz
    assert np.all(np.abs(np.diff(xs, axis=0)) <= step + 1e-9)
    lo, hi = cfg.box_hop_interval
    for b, hops in enumerate(env._scene.hops):
        ticks = sorted(hops)
        assert len(ticks) >= 300 // hi - 1
        # Gaps between hop starts are within the interval (the first counts from tick 0).
        assert all(lo <= g <= hi for g in np.diff([0] + ticks))
        for t in ticks:
            assert abs(hops[t] - start[b]) <= cfg.box_hop_range
        # Before the first hop the tray stands still; a hop whose next start leaves time to arrive lands exactly.
        assert np.all(xs[: ticks[0] + 1, b] == start[b])
        for t, nxt in zip(ticks, ticks[1:] + [300]):
            prev = xs[t, b]
            need = math.ceil(abs(hops[t] - prev) / step - 1e-9)
            if t + need < nxt and t + need <= 299:
                assert xs[t + need, b] == pytest.approx(hops[t], abs=1e-9)
        assert np.any(np.abs(np.diff(xs[:, b])) > step / 2)  # it did move


def test_static_world_unchanged_by_moving_trays():
    """A-27: with box_hop_range = 0 (every task but drift) the boxes are static walls on the static body."""
    env = ArmSortEnv(ArmConfig())
    env.reset(0)
    assert env._scene.box_bodies == [] and env._scene.hops == []
    x0 = env.box_centers()
    for _ in range(30):
        env.step(_hold(env))
    np.testing.assert_array_equal(env.box_centers(), x0)


def test_part_beside_the_table_falls_out_of_reach():
    """A-27: the table ends at table_half_width; a part that misses it and the trays falls to the bin at BIN_Y,
    where the arm cannot reach it, and is not completed."""
    cfg = dataclasses.replace(DRIFT_CONFIG, box_hop_interval=(5000, 5000))  # no hop: trays stay at their centres
    env = ArmSortEnv(cfg)
    env.reset(3)
    body = env._scene.objects[2][0]
    # Between the table's edge (0.17) and the gray tray's inner wall (0.32 - 0.06 - 0.01 = 0.25).
    body.position = (0.205, 0.05)
    for _ in range(40):
        obs, info = env.step(_hold(env))
    h = cfg.object_sizes[2][1]
    assert obs[10 + 5 * 2 + 1] == pytest.approx(BIN_Y + h / 2, abs=2e-3)
    assert not info["completed"][2]
    from softrtc.arm.env import inverse_kinematics

    with pytest.raises(ValueError, match="reachable"):
        inverse_kinematics((0.205, BIN_Y + h + 0.003), cfg)


def test_moving_tray_config_checks():
    """A-12, A-27: hop interval, speed, range and rim are checked, and a tray that could reach over the table is
    refused, naming the field."""
    for fields, name in ((dict(box_hop_interval=(0, 5)), "box_hop_interval"),
                         (dict(box_hop_interval=(9, 5)), "box_hop_interval"),
                         (dict(box_hop_interval=(5,)), "box_hop_interval"),
                         (dict(box_hop_speed=0.0), "box_hop_speed"),
                         (dict(box_hop_range=-0.01), "box_hop_range"),
                         (dict(box_hop_range=math.nan), "box_hop_range"),
                         (dict(tray_rim_height=0.0), "tray_rim_height"),
                         (dict(box_hop_range=0.09), "box_centers")):
        with pytest.raises(ValueError, match=name):
            dataclasses.replace(DRIFT_CONFIG, **fields)


def test_expert_chunk_leaves_the_world_alone():
    """AX-8: the chunk is rolled out on a frozen copy: the env's state is untouched, the first action is the
    expert's action for the current observation, and the copy's trays do not hop."""
    cfg = DRIFT_CONFIG
    env = ArmSortEnv(cfg)
    expert = ScriptedExpert(cfg)
    obs = env.reset(5)
    for _ in range(40):
        obs, _ = env.step(expert.act(obs))
    before = env._observe()
    chunk = expert_chunk(env, expert, 10)
    np.testing.assert_array_equal(env._observe(), before)
    assert chunk.shape == (10, 4)
    np.testing.assert_array_equal(chunk[0], expert.act(before))
    with pytest.raises(ValueError, match="horizon"):
        expert_chunk(env, expert, 0)
    with pytest.raises(ValueError, match="delay"):
        run_expert_chunk_episode(cfg, 0, 5, 6)


@pytest.mark.slow
def test_drift_expert_solves_and_chunked_expert_runs():
    """AX-8: the closed-loop expert solves drift seeds (10000, 10001); the screen's chunked expert at s = 1,
    d = 0 is the closed-loop expert up to the copy's rounding, and reports per-delay rates in [0, 1]."""
    for seed in (10000, 10001):
        r = run_expert_episode(seed, DRIFT_CONFIG)
        assert r["success"] and r["success_step"] < 1000
    short = dataclasses.replace(DRIFT_CONFIG, max_steps=120)
    out = delay_screen(short, 5, [0, 5], [10000])
    assert set(out) == {0, 5} and all(0.0 <= v["success"] <= 1.0 for v in out.values())


def test_drift_task_and_its_base():
    """AX-8, A-21: drift runs s = 5 (delays 0..5) in the moving-tray world and has its own shipped base, trained
    as the base in that world (its feature statistics differ from the default world's base); drift_overlap4 runs
    that world and base with s = 6."""
    from softrtc.arm.checkpoints import default_checkpoint_dir, load_arm_checkpoint, load_policies

    task = get_task("drift")
    assert (task.execute_horizon, task.max_delay) == (5, 5)
    assert task.env_config.box_hop_range > 0 and get_task("easy").env_config.box_hop_range == 0
    path = task.base_checkpoint()
    assert path == default_checkpoint_dir() / "drift" / "base.npz" and path.is_file()
    base = load_arm_checkpoint(path)
    assert base.trained_as == "naive"
    pol = load_policies(path.parent, methods=("naive",))["naive"]
    shipped = load_arm_checkpoint(default_checkpoint_dir() / "base.npz")
    assert not np.allclose(pol.normalizer.obs_mean, shipped.normalizer.obs_mean)
    assert get_task("easy").base_checkpoint() == default_checkpoint_dir() / "base.npz"
    # drift_overlap4: the same world and base with overlap4's geometry (s = 6, delays 0..4), where the paper's
    # window runs past the overlap and zero padding trains and samples differently from clip.
    from softrtc.arm.experiment import rows_for, train_key

    o4 = get_task("drift_overlap4")
    assert (o4.execute_horizon, o4.max_delay, o4.env_config, o4.base_checkpoint()) == (6, 4, DRIFT_CONFIG, path)
    rows = {r.name: r for r in rows_for(o4)}
    assert train_key(rows["soft2_zeros"], o4) != train_key(rows["soft2_clip"], o4)
    assert train_key(rows["soft2_zeros"], task) == train_key(rows["soft2_clip"], task)


def test_expert_and_features_skip_a_part_out_of_reach():
    """A-13, A-17, A-27: a part below the table top is out of play: the expert goes for the next part and the
    policy features name the next part as current; with every other part placed nothing is left."""
    from softrtc.arm.features import FEATURE_DIM, policy_features

    cfg = dataclasses.replace(DRIFT_CONFIG, box_hop_interval=(5000, 5000))
    env = ArmSortEnv(cfg)
    expert = ScriptedExpert(cfg)
    obs = env.reset(4)
    lost = obs.copy()
    lost[10 + 1] = BIN_Y + 0.02  # blue0 lies in the bin
    f = policy_features(lost)
    assert f.shape == (FEATURE_DIM,)
    np.testing.assert_array_equal(f[34:38], [0, 1, 0, 0])
    # The part offset is blue1's position minus the tip, computed by hand.
    np.testing.assert_allclose(f[38:40], lost[15:17] - lost[6:8])
    np.testing.assert_array_equal(policy_features(obs)[34:38], [1, 0, 0, 0])
    # The expert heads for blue1: its commanded tip is the carrot toward blue1's waypoint, worked out by hand
    # from [A-13] (the arm starts at home, above carry_height, so it travels at carry height or descends).
    from softrtc.arm.env import forward_kinematics

    ec = expert.config
    tip = obs[6:8]
    x1, top = obs[15], obs[16] + cfg.object_sizes[1][1] / 2
    goal = np.array([x1, top + ec.grasp_clearance])
    target = np.array([x1, max(ec.carry_height, goal[1])]) if abs(tip[0] - x1) > ec.lift_tol else goal
    delta = target - tip
    carrot = tip + delta * min(np.hypot(*delta), ec.lookahead) / np.hypot(*delta)
    np.testing.assert_allclose(forward_kinematics(expert.act(lost)[:3], cfg), carrot, atol=1e-9)
    assert abs(x1 - obs[10]) > 0.05  # blue0 lies elsewhere, so the carrot is not blue0's
    done = lost.copy()
    for k in (1, 2, 3):
        done[10 + 5 * k + 4] = 1.0
    assert not policy_features(done)[34:38].any() and not policy_features(done)[38:42].any()


@pytest.mark.slow
def test_experiment_on_drift_starts_from_its_base(tmp_path):
    """AX-3, AX-8: `run_experiment('drift', ...)` records the drift base's digest (not the shipped one's) and runs
    its episodes in the moving-tray world."""
    import hashlib
    import json

    from softrtc.arm.checkpoints import default_checkpoint_dir
    from softrtc.arm.experiment import read_episodes, run_experiment

    r = run_experiment("drift", "quick", out=tmp_path / "res", work=tmp_path / "work", rows=["naive"],
                       delays=[5], tiers=("main",), workers=1, log=lambda *_: None)
    assert r["cells"] == 1 and r["ran"] == 1
    manifest = json.loads((tmp_path / "res" / "drift" / "manifest.json").read_text())
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()[:16]  # noqa: E731
    assert manifest["base_sha256_16"] == digest(get_task("drift").base_checkpoint())
    assert manifest["base_sha256_16"] != digest(default_checkpoint_dir() / "base.npz")
    (cell,) = (tmp_path / "res" / "drift" / "episodes").glob("*_d5.csv")
    # The quick budget: 2 paired episodes of 60 ticks (too short to sort four parts).
    eps = read_episodes(cell)
    assert [(e["delay"], e["env_seed"], e["steps"], e["success"]) for e in eps] == [(5, 10000, 60, 0),
                                                                                    (5, 10001, 60, 0)]


def test_screen_command_runs_the_tasks_screen(monkeypatch, capsys):
    """AX-8: `softrtc arm screen --task drift -n 3` runs the closed-loop expert and the chunked expert on env seeds
    10000..10002 in the task's world, at the task's s and every executable delay."""
    from softrtc.arm import expert, expert_chunks
    from softrtc.cli import build_parser

    seen = {"closed": []}
    monkeypatch.setattr(expert, "run_expert_episode",
                        lambda sd, cfg: seen["closed"].append((sd, cfg)) or {"success": sd != 10001})
    monkeypatch.setattr(expert_chunks, "delay_screen",
                        lambda cfg, s, delays, seeds: seen.update(screen=(cfg, s, list(delays), list(seeds))) or
                        {d: {"success": 0.5, "completion": 0.75} for d in delays})
    args = build_parser().parse_args(["arm", "screen", "--task", "drift", "-n", "3"])
    assert args.func(args) == 0
    assert seen["closed"] == [(10000, DRIFT_CONFIG), (10001, DRIFT_CONFIG), (10002, DRIFT_CONFIG)]
    assert seen["screen"] == (DRIFT_CONFIG, 5, [0, 1, 2, 3, 4, 5], [10000, 10001, 10002])
    out = capsys.readouterr().out
    assert "solves 2/3" in out and out.count("success 0.50") == 6
