"""Tests of the level screen ([KS-1]..[KS-7]).

The two programs of the screen are run on a hand-made task whose step
counter is its observation and whose reward is the executed action's first
entry, so returns are sums computed here by hand. One slow test runs the
command end to end on a kinetix-env level at its own sizes, twice.
"""

from __future__ import annotations

import json
import math
import types

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from softrtc.kinetix import env as kenv  # noqa: E402
from softrtc.kinetix import screen as ks  # noqa: E402
from softrtc.kinetix.ppo import PPOConfig  # noqa: E402

L = 8  # the counting task's episode length


class CountingTask:
    """Observation ``[t, 0, 0]`` (steps taken), reward = executed action entry 0, episode of ``L`` steps
    ending solved, then an automatic reset ([K-9]); no execution noise."""

    obs_dim, action_dim = 3, kenv.ACTION_DIM
    env_params = types.SimpleNamespace(max_timesteps=10)

    def reset(self, key):
        return jnp.zeros(3, jnp.float32), jnp.zeros((), jnp.int32)

    def step(self, key, t, action):
        t1 = t + 1
        done = t1 >= L
        t_next = jnp.where(done, 0, t1)
        obs = jnp.zeros(3, jnp.float32).at[0].set(t_next.astype(jnp.float32))
        return obs, t_next, action[0], done, {"solved": done}


def newest_step(params, x):
    """Action entry 0 = the step counter of the newest observation in the expert input ([KP-1]: the 4th of 4)."""
    return jnp.zeros((x.shape[0], kenv.ACTION_DIM), x.dtype).at[:, 0].set(x[:, 3 * CountingTask.obs_dim])


def test_delayed_execution_acts_on_the_input_of_step_t_minus_d():
    """KS-4: with delay d the action executed at step t is the policy's at the input of step t - d, and the
    reset input during an episode's first d steps: return = sum over t < 8 of max(t - d, 0) (28, 21, 15, 6
    for d = 0, 1, 2, 4); every episode is the env's first, of 8 steps, solved."""
    delays = np.array([0, 1, 2, 4, 0])
    keys = jax.random.split(jax.random.key(0), delays.size)
    out = ks.delayed_expert_outcomes(CountingTask(), None, keys, delays, act=newest_step)
    want = [sum(max(t - d, 0) for t in range(L)) for d in delays]
    assert want == [28, 21, 15, 6, 28]
    np.testing.assert_array_equal(out["return"], np.asarray(want, np.float32))
    np.testing.assert_array_equal(out["length"], [L] * delays.size)
    assert out["solved"].all()
    with pytest.raises(ValueError, match="^delays must be a non-empty 1-D integer array"):
        ks.delayed_expert_outcomes(CountingTask(), None, keys, delays - 1, act=newest_step)
    with pytest.raises(ValueError, match="^keys must be one PRNG key per delay"):
        ks.delayed_expert_outcomes(CountingTask(), None, keys[:2], delays, act=newest_step)


def test_held_input_is_the_one_of_the_block_start_minus_d():
    """KS-4: with hold s the action at step t acts on the input of step c - d, c = t - (t mod s): for s = 4,
    8 steps, return = 4 max(-d, 0) + 4 max(4 - d, 0) = 16, 12, 8, 0 for d = 0, 1, 2, 4 (hand-summed); hold 1
    is the test above; a hold outside [1, 64] is an error naming it."""
    delays = np.array([0, 1, 2, 4])
    keys = jax.random.split(jax.random.key(0), delays.size)
    out = ks.delayed_expert_outcomes(CountingTask(), None, keys, delays, act=newest_step, hold=4)
    want = [sum(max(t - t % 4 - d, 0) for t in range(L)) for d in delays]
    assert want == [16, 12, 8, 0]
    np.testing.assert_array_equal(out["return"], np.asarray(want, np.float32))
    with pytest.raises(ValueError, match="^hold must be"):
        ks.delayed_expert_outcomes(CountingTask(), None, keys, delays, act=newest_step, hold=0)
    with pytest.raises(ValueError, match="^hold must be"):
        ks.ScreenConfig(hold=65)
    # KS-6: hold 1 is written as no key (as before the option), and a config without it reads back as hold 1.
    assert "hold" not in ks.ScreenConfig(hold=1).to_dict() and ks.ScreenConfig().to_dict()["hold"] == 4
    assert ks.ScreenConfig.from_dict(ks.ScreenConfig(hold=1).to_dict()) == ks.ScreenConfig(hold=1)
    assert ks.ScreenConfig.from_dict(ks.ScreenConfig().to_dict()) == ks.ScreenConfig()
    with pytest.raises(ValueError, match=r"^screen config has unknown keys \['holds'\]"):
        ks.ScreenConfig.from_dict(dict(ks.ScreenConfig().to_dict(), holds=2))


def test_baselines_hold_constant_actions_and_draw_random_ones():
    """KS-2: a constant-action env executes its action at every step of its first episode (return 8 a[0]);
    a random-action env draws uniform motors in [-1, 1], so its return differs and stays within [-8, 8].
    Rows past one call of BATCH envs come back in order."""
    consts = np.zeros((ks.BATCH + 3, kenv.ACTION_DIM), np.float32)
    consts[:, 0] = np.linspace(-1, 1, ks.BATCH + 3)
    rand = np.zeros(ks.BATCH + 3, bool)
    rand[-2:] = True
    keys = jax.random.split(jax.random.key(1), rand.size)
    out = ks.episode_outcomes(CountingTask(), keys, consts, rand)
    np.testing.assert_allclose(out["return"][:-2], L * consts[:-2, 0], rtol=1e-6, atol=1e-6)
    assert np.all(np.abs(out["return"][-2:]) <= L) and out["return"][-1] != out["return"][-2]
    np.testing.assert_array_equal(out["length"], [L] * rand.size)
    with pytest.raises(ValueError, match="^random_mask must be a bool array"):
        ks.episode_outcomes(CountingTask(), keys, consts, rand.astype(int))
    with pytest.raises(ValueError, match=r"^actions must have shape \[n >= 1, 6\]"):
        ks.episode_outcomes(CountingTask(), keys, consts[:, :4], rand)


def test_constant_action_grid_over_used_entries():
    """KS-2: 5 values per used motor, 3 per used thruster, zeros elsewhere; past 243 actions the coarse grid
    (3 and 2 values): 1 motor -> 5, 2 motors + 1 thruster -> 75, 4 motors + 2 thrusters -> 3^4 * 2^2 = 324."""
    a = ks.constant_actions((1,), ())
    assert a.shape == (5, 6) and sorted(a[:, 1].tolist()) == [-1.0, -0.5, 0.0, 0.5, 1.0]
    assert not a[:, [0, 2, 3, 4, 5]].any()
    b = ks.constant_actions((0, 3), (5,))
    assert b.shape == (75, 6) and set(b[:, 5].tolist()) == {0.0, 0.5, 1.0} and not b[:, [1, 2, 4]].any()
    assert len({tuple(r) for r in b.tolist()}) == 75
    c = ks.constant_actions((0, 1, 2, 3), (4, 5))
    assert c.shape == (324, 6) and set(c[:, 0].tolist()) == {-1.0, 0.0, 1.0} and set(c[:, 4].tolist()) == {0.0, 1.0}
    assert ks.constant_actions((), ()).shape == (1, 6)


def test_used_entries_of_package_levels():
    """KS-2: m_h5_angry_birds drives one motor, bound to action entry 1, and no thruster; s_h4_thrust_aim one
    thruster bound to thruster binding 0 (action entry 4) and no motor (its one joint is inactive). Read
    from the level files' joints and thrusters (the kinetix editor's layout)."""
    lv = kenv.load_level("m_h5_angry_birds@own")
    assert ks.used_action_entries(lv) == ((1,), ())
    assert ks.used_action_entries(kenv.load_level("s_h4_thrust_aim@own")) == ((), (4,))


def _base(best):
    return {"constant": [{"action": [0.0] * 6, "solved": 0.0}, {"action": [1.0] + [0.0] * 5, "solved": best}]}


def _delays(*rates):
    return {"rows": [{"delay": d, "solved": r} for d, r in zip((0, 1, 2, 4), rates)]}


def test_verdict_rules_and_reasons():
    """KS-5: kept only with no constant action at the threshold, the expert at 0.8 at d = 0 and a fall of at
    least 0.2 to the largest delay; a dropped level names every rule it fails, with its numbers."""
    cfg = ks.ScreenConfig()
    v = ks.screen_verdict(_base(0.2), _delays(0.97, 0.66, 0.41, 0.09), cfg)
    assert v["kept"] and v["reasons"] == ["no constant action solves it (best 0.20), the expert solves 0.97 at "
                                          "d = 0 and 0.09 at d = 4"]
    v = ks.screen_verdict(_base(0.5), _delays(0.79, 0.7, 0.7, 0.6), cfg)
    assert not v["kept"] and len(v["reasons"]) == 3
    assert v["reasons"][0] == "a constant action solves it: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0] solves 0.50 >= 0.5"
    assert v["reasons"][1] == "the expert solves 0.79 < 0.8 at d = 0"
    assert v["reasons"][2].startswith("its solve rate does not fall with delay: 0.79 at d = 0, 0.60 at d = 4")
    # A fall of 0.25 >= 0.2 with the other rules met keeps the level.
    assert ks.screen_verdict(_base(0.0), _delays(0.9, 0.9, 0.8, 0.65), cfg)["kept"]
    # KS-6: no expert measured is fine only when a constant action drops the level.
    v = ks.screen_verdict(_base(0.5), None, cfg)
    assert not v["kept"] and v["reasons"] == ["a constant action solves it: [1.0, 0.0, 0.0, 0.0, 0.0, 0.0] "
                                              "solves 0.50 >= 0.5"]
    with pytest.raises(ValueError, match="^delays must be the delay measurements"):
        ks.screen_verdict(_base(0.49), None, cfg)


def test_screen_config_checks_and_ppo_iterations():
    """KS-1, KS-3: PPO iterations = ceil(steps / 8192) with the screen's 32 x 256 PPO; delays increase from 0;
    rates lie in [0, 1]; each bad field is one ValueError naming it."""
    assert ks.SCREEN_PPO.batch_size == 8192
    assert ks.ScreenConfig(ppo_steps=82_000).ppo_updates == math.ceil(82_000 / 8192) == 11
    assert ks.ScreenConfig(ppo_steps=8192).ppo_updates == 1
    assert ks.ScreenConfig(delays=[0, 2]).delays == (0, 2)
    for kw, msg in (({"delays": (1, 2)}, "^delays must be increasing"), ({"delays": (0,)}, "^delays must be"),
                    ({"delays": 3}, "^delays must be a sequence"), ({"min_drop": 1.5}, "^min_drop must be"),
                    ({"episodes": 0}, "^episodes must be"), ({"const_threshold": float("nan")}, "^const_threshold"),
                    ({"ppo": {}}, "^ppo must be a PPOConfig")):
        with pytest.raises(ValueError, match=msg):
            ks.ScreenConfig(**kw)


def test_screen_table_lists_every_level_with_reasons():
    """KS-7: one row per level with the best constant action, random actions, PPO steps and minutes and the
    expert per delay, then the reasons."""
    cfg = ks.ScreenConfig(delays=(0, 4))
    r = {"level": "m_h5_angry_birds", "kept": False, "reasons": ["the expert solves 0.50 < 0.8 at d = 0"],
         "constant_best": {"solved": 0.25}, "random_solved": 0.125, "ppo_env_steps": 81920, "ppo_wall_s": 510.0,
         "expert_by_delay": [{"delay": 0, "solved": 0.5}, {"delay": 4, "solved": 0.25}]}
    text = ks.format_screen([r], cfg)
    assert "| m_h5_angry_birds | no | 0.25 | 0.12 | 81920 | 8.5 | 0.50 | 0.25 |" in text
    assert "- **m_h5_angry_birds** (dropped): the expert solves 0.50 < 0.8 at d = 0." in text
    # A level dropped by a constant action before PPO: dashes, not numbers, where nothing was measured.
    r2 = dict(r, level="m_arm_up", constant_best={"solved": 1.0}, random_solved=0.0, ppo_env_steps=0,
              ppo_wall_s=0.0, expert_by_delay=None)
    assert "| m_arm_up | no | 1.00 | 0.00 | - | - | - | - |" in ks.format_screen([r, r2], cfg)


@pytest.mark.slow
def test_screen_command_end_to_end_and_resume(tmp_path, capsys, restore_cache):
    """KS-1, KS-6, KS-7: the command screens a kinetix-env level at its own sizes with tiny budgets, writes
    the per-level stages, screen.json and screen.md; run again it reads every stage back (files unchanged);
    other thresholds change the verdict without measuring again; other episodes into the same folder are an
    error naming the stage file."""
    from softrtc.cli import main

    out = tmp_path / "screen"
    argv = ["kinetix", "screen", "--levels", "s_h4_thrust_aim@own", "--out", str(out), "--ppo-steps", "64",
            "--episodes", "2", "--delays", "0,2", "--ppo-envs", "4", "--ppo-num-steps", "16",
            "--ppo-minibatches", "2", "--no-progress", "--no-compile-cache"]
    assert main(argv) == 0
    level = out / "s_h4_thrust_aim@own"
    stages = {n: (level / n).read_bytes() for n in ("baselines.json", "delays.json", "screen.json")}
    res = json.loads(stages["screen.json"])
    assert res["constant_count"] == 3 and res["ppo_env_steps"] == 64 and len(res["ppo_curve"]) == 1
    assert [r["delay"] for r in res["expert_by_delay"]] == [0, 2]
    assert "| s_h4_thrust_aim@own |" in (out / "screen.md").read_text()
    assert main(argv) == 0
    assert {n: (level / n).read_bytes() for n in stages} == stages
    assert "s_h4_thrust_aim@own: dropped" in capsys.readouterr().out
    # Other thresholds recompute the verdict only; other episodes meet the baselines of 2 episodes.
    assert main(argv + ["--expert-threshold", "0.0", "--min-drop", "0.0", "--const-threshold", "1.0"]) == 0
    assert {n: (level / n).read_bytes() for n in ("baselines.json", "delays.json")} == \
        {n: stages[n] for n in ("baselines.json", "delays.json")}
    assert "s_h4_thrust_aim@own: kept" in capsys.readouterr().out
    bad = list(argv)
    bad[bad.index("--episodes") + 1] = "3"
    assert main(bad) == 2
    assert "baselines.json from another screen configuration" in capsys.readouterr().err


@pytest.mark.slow
def test_screen_stops_at_a_constant_action_that_solves_the_level(tmp_path, restore_cache):
    """KS-5, KS-6: m_h5_angry_birds, which the half-speed motor solves open loop, is dropped after its
    baselines: no PPO folder, no delays stage, a screen.json and a row with dashes for what was not run."""
    from softrtc.cli import main

    out = tmp_path / "screen"
    assert main(["kinetix", "screen", "--levels", "m_h5_angry_birds@own", "--out", str(out), "--episodes", "2",
                 "--delays", "0,2", "--no-progress", "--no-compile-cache"]) == 0
    level = out / "m_h5_angry_birds@own"
    res = json.loads((level / "screen.json").read_text())
    assert not res["kept"] and res["expert_by_delay"] is None and res["ppo_env_steps"] == 0
    assert res["reasons"][0].startswith("a constant action solves it: [0.0, 0.5, 0.0, 0.0, 0.0, 0.0]")
    assert not (level / "ppo").exists() and not (level / "delays.json").exists()
    assert "| m_h5_angry_birds@own | no | 1.00 |" in (out / "screen.md").read_text()


def test_committed_m_h5_baselines_drop_the_level():
    """KS-8, KS-2, KS-5: the committed baselines of m_h5_angry_birds: one used entry (motor 1), 5 constant
    actions of 64 episodes, the half-speed motor solving all 64 and random actions 4 of 64; with them the
    level is dropped on the constant-action rule whatever its expert does (even a perfect, delay-sensitive one)."""
    from pathlib import Path

    base = json.loads((Path(__file__).resolve().parents[2] / "results" / "kinetix" / "screen" / "m_h5_angry_birds"
                       / "baselines.json").read_text())
    assert base["meta"] == {"level": "m_h5_angry_birds", "episodes": 64, "seed": 0, "format": ks.FORMAT}
    assert (base["motor_entries"], base["thruster_entries"]) == ([1], [])
    assert [r["action"][1] for r in base["constant"]] == list(ks.MOTOR_GRID)
    assert [r["solved"] for r in base["constant"]] == [0.0, 0.0, 0.0, 1.0, 0.0]
    assert base["random"]["solved"] == 4 / 64
    v = ks.screen_verdict(base, _delays(1.0, 0.5, 0.2, 0.0), ks.ScreenConfig())
    assert not v["kept"] and v["reasons"] == ["a constant action solves it: [0.0, 0.5, 0.0, 0.0, 0.0, 0.0] solves "
                                              "1.00 >= 0.5"]


def test_committed_screen_report_is_its_results():
    """KS-7, KS-8, KS-5: the committed screen.md is format_screen of the committed screen.json, and every
    level's verdict there is the one screen_verdict gives from its committed stage files."""
    from pathlib import Path

    root = Path(__file__).resolve().parents[2] / "results" / "kinetix"
    folders = sorted(p.parent for p in root.glob("screen*/screen.json"))
    assert {f.name for f in folders} >= {"screen", "screen-hold4"}
    for d in folders:
        _check_screen_folder(d)


def _check_screen_folder(d):
    res = json.loads((d / "screen.json").read_text())
    config = ks.ScreenConfig.from_dict(res["config"])
    assert (d / "screen.md").read_text() == ks.format_screen(res["levels"], config)
    for r in res["levels"]:
        base = json.loads((d / r["level"] / "baselines.json").read_text())
        if r["expert_by_delay"] is None:  # dropped by a constant action: no PPO, no delays stage (KS-6)
            assert r["ppo_env_steps"] == 0 and not (d / r["level"] / "delays.json").exists()
            delays = None
        else:
            delays = json.loads((d / r["level"] / "delays.json").read_text())
        v = ks.screen_verdict(base, delays, config)
        assert (v["kept"], v["reasons"]) == (r["kept"], r["reasons"])
