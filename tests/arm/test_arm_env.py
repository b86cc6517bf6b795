"""Tests for the pymunk arm sorting environment, expert and demos (spec/10-arm.md)."""

import dataclasses
import math

import numpy as np
import pytest

pytest.importorskip("pymunk")

from softrtc.arm.demos import generate_demos, load_demos, rollout_noisy_episode  # noqa: E402
from softrtc.arm.env import (  # noqa: E402
    ACTION_DIM,
    OBS_DIM,
    OBS_SLICES,
    ArmConfig,
    ArmSortEnv,
    forward_kinematics,
    inverse_kinematics,
)
from softrtc.arm.expert import ScriptedExpert, expert_success_rate, run_expert_episode  # noqa: E402


def _hold(env):
    """Action that keeps the arm where it is with the gripper open."""
    return np.concatenate([env.joint_positions(), [0.0]])


def _run_until(env, expert, obs, pred, limit=1000):
    info = None
    for _ in range(limit):
        obs, info = env.step(expert.act(obs))
        if pred(obs, info):
            return obs, info
    raise AssertionError("condition never reached")


def test_scene_constants_and_units():
    """A-1, A-4: gravity, slop, table, 50 Hz control with fixed substeps."""
    cfg = ArmConfig()
    env = ArmSortEnv(cfg)
    env.reset(0)
    space = env._scene.space
    assert tuple(space.gravity) == (0.0, -9.81)
    assert space.collision_slop == 0.0005
    assert cfg.control_hz == 50 and cfg.dt == 0.02
    assert cfg.physics_dt == pytest.approx(0.002)
    _, info = env.step(_hold(env))
    assert info["t"] == 1 and info["time_s"] == pytest.approx(0.02)
    assert space.current_time_step == pytest.approx(cfg.physics_dt)


def test_kinematics_roundtrip_and_convention():
    """A-2: FK/IK agree, q1 = 0 hangs straight down, unreachable targets raise."""
    cfg = ArmConfig()
    tip = forward_kinematics(np.zeros(3))
    assert tip == pytest.approx([0.0, 0.45 - sum(cfg.link_lengths)])
    rng = np.random.default_rng(0)
    for _ in range(50):
        p = np.array([rng.uniform(-0.45, 0.45), rng.uniform(0.0, 0.25)])
        q = inverse_kinematics(p)
        assert q[1] <= 0
        assert forward_kinematics(q) == pytest.approx(p, abs=1e-9)
        # The last link points straight down.
        assert math.cos(-math.pi / 2 + np.sum(q)) == pytest.approx(0.0, abs=1e-9)
        assert math.sin(-math.pi / 2 + np.sum(q)) == pytest.approx(-1.0, abs=1e-9)
    with pytest.raises(ValueError, match="reachable"):
        inverse_kinematics(np.array([2.0, 0.0]))
    with pytest.raises(ValueError, match="ee_xy"):
        inverse_kinematics(np.array([0.0, np.nan]))
    with pytest.raises(ValueError, match="q must"):
        forward_kinematics(np.zeros(2))


def test_motors_track_targets_and_arm_does_not_collide():
    """A-3: rate-controlled motors reach a commanded target; arm links collide with nothing."""
    env = ArmSortEnv()
    env.reset(1)
    target = inverse_kinematics(np.array([0.1, 0.12]))
    for _ in range(75):
        obs, _ = env.step(np.concatenate([target, [0.0]]))
    assert env.joint_positions() == pytest.approx(target, abs=5e-3)
    assert np.all(np.abs(obs[OBS_SLICES["qdot"]]) < 0.05)
    assert obs[OBS_SLICES["ee"]] == pytest.approx([0.1, 0.12], abs=5e-3)
    for body in env._scene.links:
        for shape in body.shapes:
            assert shape.filter.mask == 0
    motors = env._scene.motors
    assert all(m.max_force == env.config.motor_max_force for m in motors)


def test_observation_and_action_layout():
    """A-7, A-8: dims, slices, initial flags and box entries."""
    env = ArmSortEnv()
    obs = env.reset(3)
    assert env.obs_dim == OBS_DIM == 34 and env.action_dim == ACTION_DIM == 4
    assert obs.shape == (34,) and obs.dtype == np.float64
    assert obs[OBS_SLICES["q"]] == pytest.approx(env.joint_positions())
    assert obs[6:8] == pytest.approx(forward_kinematics(env.joint_positions()), abs=1e-6)
    assert obs[8] == 0.0 and obs[9] == 0.0
    objs = obs[10:30].reshape(4, 5)
    assert np.all(objs[:, 3] == 0) and np.all(objs[:, 4] == 0)
    boxes = obs[30:34]
    assert boxes[[0, 2]] == pytest.approx(env.box_centers())
    assert boxes[1] == 0.0 and boxes[3] == 0.0
    assert list(env.action_low) == [-math.pi, -3.0, -math.pi, 0.0]
    assert list(env.action_high) == [math.pi, 3.0, math.pi, 1.0]


def test_scene_placement_is_valid():
    """A-5: parts rest on the table in range and apart; boxes jittered within bounds."""
    cfg = ArmConfig()
    env = ArmSortEnv(cfg)
    for seed in range(20):
        obs = env.reset(seed)
        objs = obs[10:30].reshape(4, 5)
        widths = np.array([s[0] for s in cfg.object_sizes])
        heights = np.array([s[1] for s in cfg.object_sizes])
        assert np.all(objs[:, 0] >= -0.18) and np.all(objs[:, 0] <= 0.18)
        assert objs[:, 1] == pytest.approx(heights / 2)
        for i in range(4):
            for j in range(i + 1, 4):
                gap = abs(objs[i, 0] - objs[j, 0]) - (widths[i] + widths[j]) / 2
                assert gap >= cfg.object_min_gap
        c = env.box_centers()
        assert abs(c[0] + 0.34) <= 0.02 and abs(c[1] - 0.32) <= 0.02


def test_same_seed_is_bitwise_deterministic():
    """A-6, A-4: same seed + same actions -> identical observations and infos."""
    def trajectory(seed):
        env = ArmSortEnv()
        expert = ScriptedExpert()
        obs = env.reset(seed)
        out_obs, out_act, out_info = [obs], [], []
        for _ in range(200):
            a = expert.act(obs)
            obs, info = env.step(a)
            out_obs.append(obs)
            out_act.append(a)
            out_info.append((info["t"], info["holding"], tuple(info["completed"])))
        return np.array(out_obs), np.array(out_act), out_info

    o1, a1, i1 = trajectory(7)
    o2, a2, i2 = trajectory(7)
    assert np.array_equal(o1, o2) and np.array_equal(a1, a2) and i1 == i2
    o3, _, _ = trajectory(8)
    assert not np.array_equal(o1[0], o3[0])


def test_action_validation():
    """A-8: out-of-range, wrong-shape and non-finite actions raise ValueError naming the entry."""
    env = ArmSortEnv()
    env.reset(0)
    good = _hold(env)
    for i, bad in [(0, 3.5), (1, -3.1), (2, 4.0), (3, 1.2), (3, -0.1)]:
        a = good.copy()
        a[i] = bad
        with pytest.raises(ValueError, match=rf"action\[{i}\]"):
            env.step(a)
    with pytest.raises(ValueError, match=r"^action must have shape \(4,\), got \(3,\)$"):
        env.step(good[:3])
    a = good.copy()
    a[0] = np.nan
    with pytest.raises(ValueError, match="^action must be finite"):
        env.step(a)
    with pytest.raises(ValueError, match="^action must be a real"):
        env.step(["a", "b", "c", "d"])
    assert env.t == 0  # rejected actions do not advance time
    _, info = env.step(good)
    assert info["t"] == 1


def test_gripper_grasp_carry_release():
    """A-9: close on nothing stays empty; close near a part welds it; opening releases it."""
    env = ArmSortEnv()
    expert = ScriptedExpert()
    obs = env.reset(2)
    # Closing far from every part: gripper closed but empty.
    obs, info = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert obs[8] == 1.0 and obs[9] == 0.0 and info["holding"] == -1
    obs, _ = env.step(np.concatenate([env.joint_positions(), [0.0]]))
    assert obs[8] == 0.0
    obs, info = _run_until(env, expert, obs, lambda o, i: o[9] == 1.0)
    k = info["holding"]
    assert k == 0 and obs[10 + 5 * k + 3] == 1.0
    offset = obs[10 + 5 * k: 12 + 5 * k] - obs[6:8]
    # Keep the gripper closed and lift: the part moves rigidly with the tip.
    q_up = inverse_kinematics(obs[6:8] + np.array([0.0, 0.08]))
    for _ in range(40):
        obs, info = env.step(np.concatenate([q_up, [1.0]]))
    assert info["holding"] == k
    assert obs[10 + 5 * k: 12 + 5 * k] - obs[6:8] == pytest.approx(offset, abs=2e-3)
    assert abs(obs[10 + 5 * k + 2]) < 0.02
    y_held = obs[10 + 5 * k + 1]
    obs, info = env.step(np.concatenate([q_up, [0.0]]))
    assert info["holding"] == -1 and obs[9] == 0.0
    for _ in range(30):
        obs, info = env.step(np.concatenate([q_up, [0.0]]))
    assert obs[10 + 5 * k + 1] < y_held - 0.05  # released part fell


def test_grasp_only_on_close_transition():
    """A-9: a gripper that was already closed does not grasp a part it reaches later."""
    env = ArmSortEnv()
    obs = env.reset(4)
    part = obs[10:12]
    top = part[1] + ArmConfig().object_sizes[0][1] / 2
    q_above = inverse_kinematics(np.array([part[0], top + 0.1]))
    q_touch = inverse_kinematics(np.array([part[0], top + 0.003]))
    for _ in range(60):
        obs, _ = env.step(np.concatenate([q_above, [1.0]]))
    for _ in range(60):
        obs, info = env.step(np.concatenate([q_touch, [1.0]]))
    assert info["holding"] == -1
    obs, _ = env.step(np.concatenate([q_touch, [0.0]]))
    obs, info = env.step(np.concatenate([q_touch, [1.0]]))
    assert info["holding"] == 0


def test_completion_rules():
    """A-10: a part counts only in its own box and when not held; success needs all four."""
    cfg = ArmConfig()
    env = ArmSortEnv(cfg)
    env.reset(5)
    c = env.box_centers()
    bodies = [b for b, _ in env._scene.objects]
    bodies[0].position = (c[0] - 0.05, 0.02)
    bodies[1].position = (c[1], 0.02)  # blue part in the gray box
    bodies[2].position = (c[1] - 0.03, 0.015)
    bodies[3].position = (c[1], 0.2)  # above the walls
    assert env.completed() == [True, False, True, False]
    bodies[1].position = (c[0] + 0.05, 0.02)
    bodies[3].position = (c[1] + 0.03, 0.015)
    assert env.completed() == [True, True, True, True]
    bodies[0].position = (c[0] - cfg.box_inner_widths[0] / 2 - 0.001, 0.02)
    assert env.completed()[0] is False


def test_done_step_limit_and_info():
    """A-11: done at max_steps, info keys, RuntimeError after done or before reset."""
    env = ArmSortEnv(dataclasses.replace(ArmConfig(), max_steps=5))
    with pytest.raises(RuntimeError):
        env.step(np.zeros(4))
    env.reset(0)
    for i in range(5):
        _, info = env.step(_hold(env))
        assert info["done"] == (i == 4)
    assert set(info) >= {"t", "time_s", "success", "completed", "num_completed", "done",
                         "success_step", "success_time_s", "holding"}
    assert info["success"] is False and info["success_step"] is None
    with pytest.raises(RuntimeError):
        env.step(_hold(env))


def test_success_time_reported():
    """A-10, A-11, A-14: a solved episode reports success_step and seconds and stops."""
    env = ArmSortEnv()
    expert = ScriptedExpert()
    obs = env.reset(0)
    while not env.done:
        obs, info = env.step(expert.act(obs))
    assert info["success"] and info["completed"] == [True] * 4
    assert info["success_step"] == env.t < env.config.max_steps
    assert info["success_time_s"] == pytest.approx(info["success_step"] * 0.02)
    assert np.all(obs[10:30].reshape(4, 5)[:, 4] == 1.0)


def test_argument_validation():
    """A-12: configs, seeds and counts are validated with ValueError naming the argument."""
    with pytest.raises(ValueError, match="seed"):
        ArmSortEnv().reset(-1)
    with pytest.raises(ValueError, match="seed"):
        ArmSortEnv().reset(1.0)
    with pytest.raises(ValueError, match="seed"):
        ArmSortEnv().reset(True)
    for field, value in [("control_hz", 0), ("control_hz", 50.0), ("substeps", 0), ("max_steps", 0),
                         ("motor_gain", -1.0), ("grasp_radius", float("nan")),
                         ("object_masses", (0.3, 0.3, 0.1, 0.0))]:
        with pytest.raises(ValueError, match=field):
            ArmSortEnv(dataclasses.replace(ArmConfig(), **{field: value}))
    with pytest.raises(ValueError, match="joint_low"):
        ArmSortEnv(dataclasses.replace(ArmConfig(), joint_low=(4.0, -3.0, -3.0)))
    with pytest.raises(ValueError, match="config"):
        ArmSortEnv(config="default")
    with pytest.raises(ValueError, match="n must"):
        expert_success_rate(n=0)
    with pytest.raises(ValueError, match="seed0"):
        expert_success_rate(n=1, seed0=-2)
    with pytest.raises(ValueError, match="obs"):
        ScriptedExpert().act(np.zeros(5))


def test_expert_is_stateless_and_valid():
    """A-13: act is a pure function of obs and returns in-range actions."""
    env = ArmSortEnv()
    expert = ScriptedExpert()
    obs = env.reset(11)
    for _ in range(150):
        a = expert.act(obs)
        assert np.array_equal(a, ScriptedExpert().act(obs.copy()))
        assert np.all(a >= env.action_low) and np.all(a <= env.action_high)
        obs, _ = env.step(a)


def test_expert_recovers_from_missed_grasp():
    """A-13: closed-but-empty gripper is opened and the grasp retried."""
    env = ArmSortEnv()
    expert = ScriptedExpert()
    obs = env.reset(6)
    obs, _ = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert obs[8] == 1.0 and obs[9] == 0.0
    assert expert.act(obs)[3] == 0.0
    obs, info = _run_until(env, expert, obs, lambda o, i: i["success"])
    assert info["success"]


def test_expert_success_subset():
    """A-14: the clean expert solves seeds 0..9 (fast subset of the 100-seed check)."""
    results = [run_expert_episode(s) for s in range(10)]
    rate = sum(r["success"] for r in results) / len(results)
    assert rate >= 0.95


@pytest.mark.slow
def test_expert_success_rate_100_seeds():
    """A-14: at least 95% of seeds 0..99."""
    assert expert_success_rate(n=100, seed0=0, verbose=False) >= 0.95


def test_demos_file_format_and_labels(tmp_path):
    """A-15, A-16: file layout, clean labels for visited states, noisy executed actions."""
    path = tmp_path / "demos.npz"
    summary = generate_demos(2, seed=3, noise_std=0.03, path=path)
    d = load_demos(path)
    n = summary["steps"]
    assert d["obs"].shape == (n, OBS_DIM) and d["action"].shape == (n, ACTION_DIM)
    assert d["executed_action"].shape == (n, ACTION_DIM)
    assert d["obs"].dtype == np.float32 and d["action"].dtype == np.float32
    assert list(d["episode_start"]) == [0, d["episode_length"][0]]
    assert np.array_equal(d["episode_id"], np.repeat([0, 1], d["episode_length"]))
    assert d["success"].shape == (2,) and d["completed"].shape == (2, 4)
    assert np.all(d["success"]) and summary["success_rate"] == 1.0
    assert np.all(d["success_step"] == d["episode_length"])
    assert float(d["noise_std"]) == 0.03 and int(d["seed"]) == 3 and int(d["control_hz"]) == 50
    # Gripper never noised; joint targets noised; labels within limits.
    assert np.array_equal(d["action"][:, 3], d["executed_action"][:, 3])
    assert not np.allclose(d["action"][:, :3], d["executed_action"][:, :3])
    # Re-run episode 0 to check labels are the expert's clean action on the visited states.
    children = np.random.SeedSequence(3).spawn(2)
    env_seed = int(children[0].generate_state(1, dtype=np.uint32)[0])
    assert d["env_seed"][0] == env_seed
    ep = rollout_noisy_episode(ArmSortEnv(), ScriptedExpert(), env_seed,
                               np.random.default_rng(children[0]), 0.03, 0.005, 0.15, 10)
    expert = ScriptedExpert()
    for t in range(0, len(ep["obs"]), 37):
        assert np.array_equal(ep["action"][t], expert.act(ep["obs"][t]))
    assert np.array_equal(ep["obs"].astype(np.float32), d["obs"][: d["episode_length"][0]])


def test_demos_deterministic_and_validated(tmp_path):
    """A-15, A-12: same arguments give identical files; bad arguments raise ValueError."""
    a = load_demos(generate_demos(1, seed=5, noise_std=0.05, path=tmp_path / "a.npz")["path"])
    b = load_demos(generate_demos(1, seed=5, noise_std=0.05, path=tmp_path / "b.npz")["path"])
    assert a.keys() == b.keys()
    for k in a:
        assert np.array_equal(a[k], b[k]), k
    with pytest.raises(ValueError, match="num_episodes"):
        generate_demos(0, 0, 0.01, tmp_path / "c.npz")
    with pytest.raises(ValueError, match="seed"):
        generate_demos(1, -1, 0.01, tmp_path / "c.npz")
    with pytest.raises(ValueError, match="noise_std"):
        generate_demos(1, 0, -0.1, tmp_path / "c.npz")
    with pytest.raises(ValueError, match="path"):
        generate_demos(1, 0, 0.01, tmp_path / "c.txt")
    with pytest.raises(ValueError, match="path"):
        generate_demos(1, 0, 0.01, tmp_path / "missing" / "c.npz")
    with pytest.raises(ValueError, match="perturb_prob"):
        generate_demos(1, 0, 0.01, tmp_path / "c.npz", perturb_prob=2.0)


def test_noisy_perturbed_episodes_still_finish(tmp_path):
    """A-13, A-15: with noise and frequent perturbations the re-planning expert still succeeds."""
    summary = generate_demos(3, seed=9, noise_std=0.05, path=tmp_path / "p.npz",
                             perturb_prob=0.02, perturb_std=0.2)
    d = load_demos(tmp_path / "p.npz")
    assert summary["success_rate"] == 1.0
    # Perturbations actually moved the executed targets far from the labels.
    assert np.max(np.abs(d["executed_action"][:, :3] - d["action"][:, :3])) > 0.2


def test_configs_and_normalizer_reject_nan_bools_and_wrong_lengths():
    """N-7, A-1, A-8, A-13, A-18: no NaN, boolean, negative size or wrong-length field reaches the simulation."""
    import math

    from softrtc.arm import env as E
    from softrtc.arm import expert as X
    from softrtc.arm import features as P

    bad_configs = [dict(joint_low=(math.nan, -3.0, -math.pi)), dict(joint_low=(-1.0, -1.0)),
                   dict(base=(math.nan, 0.45)), dict(table_half_width=-1.0), dict(box_inner_widths=(-0.2, 0.14)),
                   dict(object_min_gap=math.nan), dict(motor_gain=True), dict(link_lengths=(True, 0.28, 0.1)),
                   dict(box_center_jitter=math.nan), dict(home_ee=(0.0,))]
    for fields in bad_configs:
        with pytest.raises(ValueError, match="^config\\."):
            E.forward_kinematics([0.0, 0.0, 0.0], E.ArmConfig(**fields))
    for falsy in (0, False, ""):
        with pytest.raises(ValueError, match="config must be an ArmConfig"):
            E.forward_kinematics([0.0, 0.0, 0.0], falsy)
    with pytest.raises(ValueError, match="^q must be"):
        E.forward_kinematics([True, False, True])
    with pytest.raises(ValueError, match="^action must be"):
        E.ArmSortEnv().validate_action([True, False, False, True])
    for fields in (dict(lookahead=math.nan), dict(carry_height=-5.0), dict(align_tol=True)):
        with pytest.raises(ValueError, match=f"^{next(iter(fields))} must be"):
            X.ExpertConfig(**fields)
    rng = np.random.default_rng(0)
    norm = P.Normalizer.fit(rng.random((5, P.FEATURE_DIM)), rng.random((5, 4)))
    with pytest.raises(ValueError, match=r"^actions must have shape \[M >= 2, 4\]"):
        P.Normalizer.fit(rng.random((5, P.FEATURE_DIM)), rng.random((1, 4)))
    with pytest.raises(ValueError, match="^actions must be finite with last axis 4"):
        P.Normalizer.fit(rng.random((5, P.FEATURE_DIM)), rng.random((5, 3)))
    with pytest.raises(ValueError, match="^features must be finite"):
        norm.obs(np.full(P.FEATURE_DIM, np.nan))
    with pytest.raises(ValueError, match="^a must be finite with last axis 4"):
        norm.act(np.zeros((3, 1)))
    np.testing.assert_allclose(norm.unact(norm.act(np.ones(4))), np.ones(4))


def test_demo_loader_rejects_a_npy_file(tmp_path):
    """N-7, A-16: a .npy array where the .npz archive is expected is a ValueError naming the path."""
    p = tmp_path / "x.npy"
    np.save(p, np.zeros(3))
    with pytest.raises(ValueError, match="single .npy array"):
        load_demos(p)
    with pytest.raises(ValueError, match="existing .npz"):
        load_demos(tmp_path / "none.npz")


def test_config_geometry_is_checked_at_construction():
    """A-12, A-5, A-2: a scene that cannot be built fails in ArmConfig, naming the field, not later at reset."""
    cases = [(dict(home_ee=(5.0, 5.0)), r"^config\.home_ee .*reachable"),
             (dict(home_ee=(0.0, -0.02)), r"^config\.home_ee must lie above the table"),  # reachable, under the table
             (dict(object_x_range=(-0.1, 0.1)), r"^config\.object_x_range is too narrow"),
             (dict(object_x_range=(-0.74, 0.18)), r"^config\.object_x_range must keep every part on the table"),
             (dict(box_centers=(-0.70, 0.32)), r"^config\.box_centers\[0\] .* off the table"),
             # On the table at its nominal centre, off it once jittered by 0.02: the margin counts jitter.
             (dict(box_centers=(-0.63, 0.32)), r"^config\.box_centers\[0\] .* off the table"),
             (dict(box_centers=(-0.34, 0.70)), r"^config\.box_centers\[1\] .* off the table"),
             (dict(box_centers=(0.20, 0.32)), r"^config\.box_centers .* overlap")]
    for fields, msg in cases:
        with pytest.raises(ValueError, match=msg):
            ArmConfig(**fields)
    ArmConfig(box_centers=(-0.619, 0.32))  # on the table for every jitter draw
    # Without the check, home_ee below the table is a valid IK target: the rule is the config's, not IK's.
    assert inverse_kinematics(np.array([0.0, -0.02]))[1] <= 0
    # The narrowest range that admits a placement: widest parts at the ends, three gaps ([A-5]).
    w = sorted(s[0] for s in ArmConfig().object_sizes)
    need = sum(w) - (w[-1] + w[-2]) / 2 + 3 * ArmConfig().object_min_gap
    ArmConfig(object_x_range=(-need / 2 - 1e-9, need / 2 + 1e-9))
    with pytest.raises(ValueError, match="object_x_range"):
        ArmConfig(object_x_range=(-need / 2 + 1e-6, need / 2 - 1e-6))


def test_part_placement_draw_sequence_and_give_up():
    """A-5, A-6: box offsets, then whole redraws of all four part centres; reset gives up after 10,000 attempts."""
    cfg = ArmConfig()
    env = ArmSortEnv(cfg)
    widths = np.array([s[0] for s in cfg.object_sizes])
    redraws = 0
    for seed in range(30):
        obs = env.reset(seed)
        # The spec's procedure, written out: a port following it gets the same scene bitwise.
        rng = np.random.default_rng(seed)
        boxes = np.array(cfg.box_centers) + rng.uniform(-cfg.box_center_jitter, cfg.box_center_jitter, size=2)
        for attempt in range(10_000):
            xs = rng.uniform(*cfg.object_x_range, size=4)
            if all(abs(xs[i] - xs[j]) >= (widths[i] + widths[j]) / 2 + cfg.object_min_gap
                   for i in range(4) for j in range(i + 1, 4)):
                break
        redraws += attempt
        np.testing.assert_array_equal(obs[10:30].reshape(4, 5)[:, 0], xs)
        np.testing.assert_array_equal(obs[[30, 32]], boxes)
    assert redraws > 0  # the seeds exercise rejected attempts
    # A range that admits a placement only at its exact edges: the sampler gives up, naming the field.
    w = sorted(widths)
    need = sum(w) - (w[-1] + w[-2]) / 2 + 3 * cfg.object_min_gap
    tight = ArmSortEnv(dataclasses.replace(cfg, object_x_range=(-need / 2, need / 2)))
    with pytest.raises(ValueError, match=r"^config\.object_x_range .*10000 placements"):
        tight.reset(0)


def _part_below_tip(env, k, gap):
    """Put part k (upright, at rest) under the gripper tip with its top `gap` below the tip; return the distance."""
    sc = env._scene
    tip = env._ee_position()
    body, shape = sc.objects[k]
    h = env.config.object_sizes[k][1]
    body.position = (float(tip[0]), float(tip[1]) - gap - h / 2)
    body.angle = 0.0
    sc.space.reindex_shapes_for_body(body)
    return shape.point_query(tuple(tip)).distance


def test_grasp_reach_is_inclusive_and_ties_go_to_the_lowest_index():
    """A-9: a part at exactly grasp_radius is within reach; equally near parts go to the lowest index."""
    env = ArmSortEnv()
    env.reset(0)
    d = _part_below_tip(env, 0, 0.012)
    assert 0.0 < d < 0.015
    env.config = dataclasses.replace(env.config, grasp_radius=d)  # the part at exactly grasp_radius
    _, info = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert info["holding"] == 0
    env.reset(0)
    env.config = dataclasses.replace(env.config, grasp_radius=np.nextafter(d, 0.0))  # just outside reach
    assert _part_below_tip(env, 0, 0.012) == d
    _, info = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert info["holding"] == -1
    # blue1 and blue0 at the same pose: exactly equal distances, the lower index wins.
    env = ArmSortEnv()
    env.reset(0)
    d1 = _part_below_tip(env, 1, 0.005)
    assert _part_below_tip(env, 0, 0.005) == d1
    _, info = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert info["holding"] == 0
    # Both within reach, the nearer wins even with the higher index (not the first found).
    env = ArmSortEnv()
    env.reset(0)
    far, near = _part_below_tip(env, 0, 0.010), _part_below_tip(env, 1, 0.002)
    assert near < far < env.config.grasp_radius
    _, info = env.step(np.concatenate([env.joint_positions(), [1.0]]))
    assert info["holding"] == 1


def test_kinematics_and_expert_reject_non_numbers():
    """A-12, A-2, A-13: booleans and strings are not coordinates, angles or observations."""
    for bad in ([True, False], ["0.1", "0.1"], np.array([1, 0], bool)):
        with pytest.raises(ValueError, match="^ee_xy must be"):
            inverse_kinematics(bad)
    for bad in (True, np.bool_(False), "0", None, float("nan"), [0.0]):
        with pytest.raises(ValueError, match="^tool_angle must be"):
            inverse_kinematics(np.array([0.0, 0.1]), tool_angle=bad)
    # NumPy scalars are numbers.
    q = inverse_kinematics(np.array([0.0, 0.1]), tool_angle=np.float32(-math.pi / 2))
    np.testing.assert_allclose(forward_kinematics(q), [0.0, 0.1], atol=1e-6)
    for bad in (np.zeros(OBS_DIM, bool), np.array(["0"] * OBS_DIM)):
        with pytest.raises(ValueError, match="^obs must be"):
            ScriptedExpert().act(bad)
