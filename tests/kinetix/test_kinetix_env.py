"""Tests of spec chapter K: Kinetix benchmark env and the expert-data loader."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tests.conftest import SHARED_LEVELS_REASON

from softrtc.kinetix import data as kdata

ROOT = Path(__file__).resolve().parents[2]
SHARED_LEVELS = (ROOT.parent / "shared" / "kinetix-levels").resolve()
ALL_LEVELS = {
    "car_launch", "cartpole_thrust", "catapult", "catcher_v3", "chain_lander", "grasp_easy",
    "h17_unicycle", "hard_lunar_lander", "mjc_half_cheetah", "mjc_swimmer", "mjc_walker", "trampoline",
}


def _have_kinetix() -> bool:
    try:
        import jax  # noqa: F401
        import kinetix  # noqa: F401
    except Exception:
        return False
    return True


_needs_kinetix = pytest.mark.skipif(not _have_kinetix(), reason="needs kinetix-env")
_needs_levels = pytest.mark.skipif(not SHARED_LEVELS.is_dir(), reason=SHARED_LEVELS_REASON)


def needs_env(fn):
    """A missing package and missing levels skip with different reasons (only the latter is tolerated)."""
    return _needs_kinetix(_needs_levels(fn))


# ----------------------------------------------------------------------------
# module layout
# ----------------------------------------------------------------------------


def test_import_is_lazy():
    """K-7: importing softrtc and softrtc.kinetix (and its data module) does not import JAX."""
    code = (
        "import sys, softrtc, softrtc.kinetix, softrtc.kinetix.data;"
        "assert 'jax' not in sys.modules, 'jax imported';"
        "assert 'kinetix' not in sys.modules, 'kinetix imported'"
    )
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    r = subprocess.run([sys.executable, "-c", code], cwd=ROOT, env=env, capture_output=True, text=True)
    assert r.returncode == 0, r.stderr


# ----------------------------------------------------------------------------
# levels
# ----------------------------------------------------------------------------


@needs_env
def test_level_names_and_default_dir():
    """K-1, K-2: the 12 level names; default dir is <project root>/../shared/kinetix-levels."""
    from softrtc.kinetix import env as kenv

    assert set(kenv.LEVEL_NAMES) == ALL_LEVELS and len(kenv.LEVEL_NAMES) == 12
    assert kenv.project_root() == ROOT
    assert kenv.default_levels_dir() == SHARED_LEVELS
    assert kenv.resolve_levels_dir() == SHARED_LEVELS
    assert kenv.resolve_levels_dir(str(SHARED_LEVELS)) == SHARED_LEVELS


@needs_env
def test_missing_level_files_are_named(tmp_path):
    """K-3: missing files and the searched directory appear in the error."""
    from softrtc.kinetix import env as kenv

    (tmp_path / "grasp_easy.json").write_text("{}")
    with pytest.raises(FileNotFoundError) as ei:
        kenv.resolve_levels_dir(tmp_path)
    msg = str(ei.value)
    assert str(tmp_path.resolve()) in msg
    assert "catapult.json" in msg and "trampoline.json" in msg and "grasp_easy.json" not in msg
    with pytest.raises(FileNotFoundError, match="mjc_walker.json"):
        kenv.make_env("mjc_walker", levels_dir=tmp_path)
    missing = tmp_path / "nope"
    with pytest.raises(FileNotFoundError) as ei:
        kenv.make_env("grasp_easy", levels_dir=missing)
    assert str(ei.value) == (f"levels_dir must be a directory holding the Kinetix level files (grasp_easy.json); "
                             f"{missing} does not exist")
    with pytest.raises(FileNotFoundError, match=r"^levels_dir must be a directory .* is not a directory$"):
        kenv.resolve_levels_dir(tmp_path / "grasp_easy.json", ("grasp_easy",))


@needs_env
def test_installed_package_has_no_default_levels_dir(tmp_path, monkeypatch):
    """K-2, K-3: outside a source checkout (no pyproject.toml above the package) there is no default
    levels directory; a call without levels_dir says so and asks for levels_dir / --levels-dir."""
    from softrtc.kinetix import env as kenv
    from softrtc.kinetix import levels

    site = tmp_path / "lib" / "python3" / "site-packages" / "softrtc" / "kinetix"
    site.mkdir(parents=True)
    (tmp_path / "lib" / "shared" / "kinetix-levels").mkdir(parents=True)  # the old fallback: never used
    monkeypatch.setattr(levels, "__file__", str(site / "levels.py"))  # where the lookup lives
    assert kenv.project_root() is None and kenv.default_levels_dir() is None
    with pytest.raises(FileNotFoundError, match=r"installed package .* pass levels_dir= \(command line: --levels-dir\)"):
        kenv.resolve_levels_dir(None, ("grasp_easy",))
    assert kenv.resolve_levels_dir(SHARED_LEVELS, ("grasp_easy",)) == SHARED_LEVELS  # an explicit dir still works
    (tmp_path / "pyproject.toml").write_text("")  # a source checkout again
    assert kenv.project_root() == tmp_path


@needs_env
@pytest.mark.slow
def test_all_levels_settings_and_dims():
    """K-1, K-4, K-5: all 12 levels load with the benchmark params, obs 679, action 6."""
    from softrtc.kinetix import env as kenv

    for name in kenv.LEVEL_NAMES:
        task = kenv.make_env(name)
        sp = task.static_env_params
        assert (sp.num_polygons, sp.num_circles, sp.num_joints, sp.num_thrusters) == (12, 4, 6, 2)
        assert (sp.frame_skip, sp.num_motor_bindings, sp.num_thruster_bindings) == (2, 4, 2)
        assert task.env_params.max_timesteps == 256
        assert task.obs_dim == kenv.OBS_DIM == 679
        assert task.action_dim == kenv.ACTION_DIM == 6
        assert task.levels_dir == SHARED_LEVELS


@needs_env
def test_level_file_with_other_params_rejected(tmp_path):
    """K-4: a level file with max_timesteps != 256 or other static sizes is a ValueError."""
    from softrtc.kinetix import env as kenv

    d = json.loads((SHARED_LEVELS / "catapult.json").read_text())
    d["env_params"]["max_timesteps"] = 100
    (tmp_path / "catapult.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="max_timesteps"):
        kenv.make_env("catapult", levels_dir=tmp_path)
    d["env_params"]["max_timesteps"] = 256
    d["static_env_params"]["num_polygons"] = 5
    (tmp_path / "catapult.json").write_text(json.dumps(d))
    with pytest.raises(ValueError, match="num_polygons"):
        kenv.make_env("catapult", levels_dir=tmp_path)


@needs_env
def test_argument_validation(task):
    """K-12: bad names, keys, actions, counts and noise std raise ValueError naming the argument."""
    import jax
    import jax.numpy as jnp

    from softrtc.kinetix import env as kenv

    with pytest.raises(ValueError, match="level_name"):
        kenv.make_env("grasp")
    with pytest.raises(ValueError, match="action_noise_std"):
        kenv.make_env("grasp_easy", action_noise_std=-0.1)
    with pytest.raises(ValueError, match="action_noise_std"):
        kenv.make_env("grasp_easy", action_noise_std=float("nan"))
    with pytest.raises(ValueError, match="levels_dir"):
        kenv.make_env("grasp_easy", levels_dir=3)
    with pytest.raises(ValueError, match="key"):
        task.reset(0)
    with pytest.raises(ValueError, match="key must be a JAX PRNG key"):
        kenv.random_actions(0, (2,))
    with pytest.raises(ValueError, match="shape entry"):
        kenv.random_actions(jax.random.key(0), (2, 0))
    a = kenv.random_actions(jax.random.key(0), (3,))
    assert a.shape == (3, 6) and float(a.min()) >= -1.0 and float(a[:, 4:].min()) >= 0.0
    with pytest.raises(ValueError, match="key"):
        task.reset(jnp.zeros(3, jnp.uint32))
    _, state = task.reset(jax.random.key(0))
    with pytest.raises(ValueError, match="action"):
        task.step(jax.random.key(0), state, jnp.zeros(5))
    with pytest.raises(ValueError, match="action"):
        task.step(jax.random.key(0), state, jnp.zeros(6, jnp.int32))
    with pytest.raises(ValueError, match="n must"):
        task.reset_batch(jax.random.key(0), 0)
    with pytest.raises(ValueError, match="n must"):
        task.reset_batch(jax.random.key(0), 2.0)
    _, bstate = task.reset_batch(jax.random.key(0), 2)
    with pytest.raises(ValueError, match="state"):
        task.step_batch(jax.random.key(0), bstate, jnp.zeros((3, 6)))
    with pytest.raises(ValueError, match="action"):
        task.step_batch(jax.random.key(0), bstate, jnp.zeros(6))
    with pytest.raises(ValueError, match="num_envs"):
        kenv.bench_bare_env("grasp_easy", num_envs=0)
    with pytest.raises(ValueError, match="num_steps"):
        kenv.bench_bare_env("grasp_easy", num_steps=True)
    with pytest.raises(ValueError, match="seed"):
        kenv.bench_bare_env("grasp_easy", seed=-1)
    with pytest.raises(ValueError, match="level_name"):
        kenv.bench_bare_env("nope")


# ----------------------------------------------------------------------------
# stepping (one compiled step shared by the tests)
# ----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def task():
    if not _have_kinetix():
        pytest.skip("needs kinetix-env")
    if not SHARED_LEVELS.is_dir():
        pytest.skip(SHARED_LEVELS_REASON)
    from softrtc.kinetix import env as kenv

    return kenv.make_env("grasp_easy")


@pytest.fixture(scope="module")
def jstep(task):
    import jax

    return jax.jit(task.step)


@pytest.fixture(scope="module")
def jreset(task):
    import jax

    return jax.jit(task.reset)


def _tree_equal(a, b) -> bool:
    import jax

    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    return len(la) == len(lb) and all(np.array_equal(np.asarray(x), np.asarray(y)) for x, y in zip(la, lb))


@needs_env
@pytest.mark.slow
def test_reset_and_step_are_keyed_and_deterministic(task, jreset, jstep):
    """K-7, K-8: same key -> same result; the noise is action + 0.1 * N(0, I) from split(key)[0]."""
    import jax
    import jax.numpy as jnp

    obs, state = jreset(jax.random.key(0))
    assert obs.shape == (679,) and obs.dtype == jnp.float32
    action = jnp.linspace(-0.5, 0.5, 6, dtype=jnp.float32)
    key = jax.random.key(7)
    out1 = jstep(key, state, action)
    out2 = jstep(key, state, action)
    assert _tree_equal(out1, out2)
    noise_key, _ = jax.random.split(key)
    expected = action + 0.1 * jax.random.normal(noise_key, (6,), jnp.float32)
    np.testing.assert_allclose(np.asarray(out1[4]["executed_action"]), np.asarray(expected), rtol=0, atol=1e-7)
    out3 = jstep(jax.random.key(8), state, action)
    assert not np.array_equal(np.asarray(out3[4]["executed_action"]), np.asarray(out1[4]["executed_action"]))
    obs1, state1, reward, done, info = out1
    assert obs1.shape == (679,) and reward.shape == () and done.shape == ()
    assert not bool(done) and not bool(info["solved"]) and int(state1.timestep) == 1


@needs_env
@pytest.mark.slow
def test_timeout_auto_resets_to_level(task, jreset, jstep):
    """K-6, K-9, K-10: the 256th step ends the episode (timeout) and returns the level's initial obs/state."""
    import jax
    import jax.numpy as jnp

    obs0, state0 = jreset(jax.random.key(0))
    late = state0.replace(timestep=255)
    obs, state, reward, done, info = jstep(jax.random.key(3), late, jnp.zeros(6, jnp.float32))
    assert bool(done) and bool(info["timeout"]) and not bool(info["solved"])
    assert int(state.timestep) == 0
    assert _tree_equal(state, state0)
    np.testing.assert_array_equal(np.asarray(obs), np.asarray(obs0))
    # one step earlier the episode continues
    obs, state, reward, done, info = jstep(jax.random.key(3), state0.replace(timestep=254), jnp.zeros(6))
    assert not bool(done) and not bool(info["timeout"]) and int(state.timestep) == 255


@needs_env
@pytest.mark.slow
def test_fail_on_the_last_step_is_a_timeout(task, jreset, jstep):
    """K-10: an episode that fails (NaN state, reward -1) on its 256th step is flagged timeout as well;
    the same fail earlier is no timeout, and neither is solved."""
    import jax
    import jax.numpy as jnp

    _, state0 = jreset(jax.random.key(0))
    nan = state0.replace(polygon=state0.polygon.replace(position=jnp.full_like(state0.polygon.position, jnp.nan)))
    for t, timeout in ((10, False), (255, True)):
        _, state, reward, done, info = jstep(jax.random.key(3), nan.replace(timestep=t), jnp.zeros(6, jnp.float32))
        assert bool(done) and float(reward) == -1.0 and int(state.timestep) == 0, t
        assert bool(info["timeout"]) is timeout and not bool(info["solved"]), t


@needs_env
@pytest.mark.slow
def test_batched_step_matches_single(task, jreset, jstep):
    """K-11: env i of step_batch equals step with jax.random.split(key, n)[i]."""
    import jax

    n = 3
    obs, bstate = task.reset_batch(jax.random.key(1), n)
    assert obs.shape == (n, 679)
    obs0, _ = jreset(jax.random.key(0))
    np.testing.assert_array_equal(np.asarray(obs[1]), np.asarray(obs0))
    actions = jax.random.uniform(jax.random.key(2), (n, 6), minval=-1.0, maxval=1.0)
    key = jax.random.key(5)
    bout = jax.jit(task.step_batch)(key, bstate, actions)
    keys = jax.random.split(key, n)
    for i in range(n):
        state_i = jax.tree.map(lambda x: x[i], bstate)
        sout = jstep(keys[i], state_i, actions[i])
        np.testing.assert_allclose(np.asarray(bout[0][i]), np.asarray(sout[0]), rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(np.asarray(bout[2][i]), np.asarray(sout[2]), rtol=1e-5, atol=1e-5)
        np.testing.assert_array_equal(
            np.asarray(bout[4]["executed_action"][i]), np.asarray(sout[4]["executed_action"])
        )


@needs_env
@pytest.mark.slow
def test_bench_bare_env_reports_throughput():
    """K-13, K-6, K-9: bench reports compile time apart from steps/s; every env times out within 256 steps."""
    from softrtc.kinetix import env as kenv

    out = kenv.bench_bare_env("grasp_easy", num_envs=4, num_steps=260, seed=0)
    assert out["env_steps"] == 4 * 260
    assert out["compile_s"] > 0 and out["run_s"] > 0
    assert out["env_steps_per_s"] == pytest.approx(out["env_steps"] / out["run_s"])
    assert out["episodes_done"] >= 4
    assert 0 <= out["episodes_solved"] <= out["episodes_done"]


# ----------------------------------------------------------------------------
# expert data
# ----------------------------------------------------------------------------


def _fake_release(S=6, E=2, obs_dim=5, A=3, seed=0):
    rng = np.random.default_rng(seed)
    done = np.zeros((S, E), bool)
    done[2, 0] = True
    done[4, 1] = True
    return {
        "obs": rng.standard_normal((S, E, obs_dim)).astype(np.float32),
        "action": rng.uniform(-1, 1, (S, E, A)).astype(np.float32),
        "done": done,
        "solved": (done & (rng.uniform(size=(S, E)) > 0.5)).astype(np.float32),
        "return_": rng.standard_normal((S, E)).astype(np.float32),
        "length": np.full((S, E), 3.0, np.float32),
    }


def test_expert_data_roundtrip(tmp_path):
    """K-14, K-15: a file in the release format (np.savez of the six keys) loads unchanged."""
    arrays = _fake_release()
    p = tmp_path / kdata.expert_data_filename("grasp_easy")
    assert p.name == "worlds_l_grasp_easy.npz"
    np.savez(p, **arrays)
    d = kdata.load_expert_data(p)
    assert (d.num_steps, d.num_envs, d.obs_dim, d.action_dim) == (6, 2, 5, 3)
    for k in kdata.EXPERT_KEYS:
        np.testing.assert_array_equal(getattr(d, k), arrays[k])
    assert d.done.dtype == np.bool_
    assert d.episode_stats()["num_episodes"] == 2
    p2 = kdata.save_expert_data(tmp_path / "again.npz", d)
    d2 = kdata.load_expert_data(p2)
    for k in kdata.EXPERT_KEYS:
        np.testing.assert_array_equal(getattr(d2, k), getattr(d, k))


@pytest.mark.parametrize("key", list(kdata.EXPERT_KEYS))
def test_expert_data_validation_names_key(tmp_path, key):
    """K-15: missing key, wrong rank, mismatched leading dims and non-finite values name the key."""
    base = _fake_release()

    a = dict(base)
    del a[key]
    np.savez(tmp_path / "m.npz", **a)
    with pytest.raises(ValueError, match=f"{key}"):
        kdata.load_expert_data(tmp_path / "m.npz")

    a = dict(base)
    a[key] = a[key][..., None] if a[key].ndim == 2 else a[key][..., 0]
    np.savez(tmp_path / "r.npz", **a)
    with pytest.raises(ValueError, match=f"'{key}'.*rank"):
        kdata.load_expert_data(tmp_path / "r.npz")

    if key != "obs":
        a = dict(base)
        a[key] = a[key][:-1]
        np.savez(tmp_path / "l.npz", **a)
        with pytest.raises(ValueError, match=f"'{key}'.*leading dims"):
            kdata.load_expert_data(tmp_path / "l.npz")

    if key != "done":
        a = dict(base)
        bad = a[key].astype(np.float32).copy()
        bad.flat[3] = np.nan
        a[key] = bad
        np.savez(tmp_path / "n.npz", **a)
        with pytest.raises(ValueError, match=f"'{key}'.*non-finite"):
            kdata.load_expert_data(tmp_path / "n.npz")


def test_expert_data_other_errors(tmp_path):
    """K-15: missing file, bad done values, non-archive files, bad path type."""
    with pytest.raises(FileNotFoundError):
        kdata.load_expert_data(tmp_path / "none.npz")
    with pytest.raises(ValueError, match="path"):
        kdata.load_expert_data(3)
    a = _fake_release()
    a["done"] = a["done"].astype(np.float32) * 2
    np.savez(tmp_path / "d.npz", **a)
    with pytest.raises(ValueError, match="'done'"):
        kdata.load_expert_data(tmp_path / "d.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="path"):
        kdata.load_expert_data(tmp_path / "junk.npz")
    empty = {k: v[:0] for k, v in _fake_release().items()}
    np.savez(tmp_path / "x.npz", **empty)
    with pytest.raises(ValueError, match="'obs'"):
        kdata.load_expert_data(tmp_path / "x.npz")


def _expected_examples(arrays, H, keep_done_action=False):
    """Straight-loop statement of K-16..K-18 (public rule)."""
    S, E = arrays["done"].shape
    obs = [arrays["obs"][s, e] for e in range(E) for s in range(S)]
    act = [arrays["action"][s, e] for e in range(E) for s in range(S)]
    done = [bool(arrays["done"][s, e]) for e in range(E) for s in range(S)]
    out_o, out_c = [], []
    for i in range(E * S - H + 1):
        chunk = []
        ended = False
        for j in range(H):
            if done[i + j] and not keep_done_action:
                ended = True
            chunk.append(np.zeros_like(act[0]) if ended else act[i + j])
            if done[i + j]:
                ended = True
        out_o.append(obs[i])
        out_c.append(np.stack(chunk))
    return np.stack(out_o), np.stack(out_c)


@pytest.mark.parametrize("H", [1, 2, 4])
def test_chunks_follow_public_rule(tmp_path, H):
    """K-16, K-17, K-18, K-19: env-major flattening, all starts, zeros from the first done on."""
    arrays = _fake_release()
    np.savez(tmp_path / "a.npz", **arrays)
    d = kdata.load_expert_data(tmp_path / "a.npz")
    obs, chunks, valid = kdata.make_training_examples(d, H)
    eo, ec = _expected_examples(arrays, H)
    assert obs.shape == (2 * 6 - H + 1, 5) and chunks.shape == (2 * 6 - H + 1, H, 3)
    np.testing.assert_array_equal(obs, eo)
    np.testing.assert_array_equal(chunks, ec)
    assert valid.shape == chunks.shape[:2]
    assert np.all(chunks[~valid] == 0)
    # keep_done_action keeps the action of the step that ended the episode
    _, ck, vk = kdata.make_training_examples(d, H, keep_done_action=True)
    np.testing.assert_array_equal(ck, _expected_examples(arrays, H, keep_done_action=True)[1])
    assert vk.sum() >= valid.sum()
    # a subset of starts gives the same rows
    starts = kdata.chunk_start_indices(d, H)[::3]
    so, sc, sv = kdata.make_chunks(d, starts, H)
    np.testing.assert_array_equal(sc, chunks[starts])
    np.testing.assert_array_equal(so, obs[starts])


def test_chunk_rule_concrete_case():
    """K-16, K-18: done at the chunk's second step zeroes offsets 1.. (the done step's action included)."""
    S, E, A = 4, 1, 1
    arrays = {
        "obs": np.arange(S, dtype=np.float32).reshape(S, E, 1),
        "action": (np.arange(S, dtype=np.float32) + 1).reshape(S, E, A),
        "done": np.array([[False], [True], [False], [False]]),
        "solved": np.zeros((S, E), np.float32),
        "return_": np.zeros((S, E), np.float32),
        "length": np.zeros((S, E), np.float32),
    }
    d = kdata._validate_arrays(arrays)
    _, c, v = kdata.make_training_examples(d, 3)
    np.testing.assert_array_equal(c[..., 0], [[1, 0, 0], [0, 0, 0]])
    _, c, _ = kdata.make_training_examples(d, 3, keep_done_action=True)
    np.testing.assert_array_equal(c[..., 0], [[1, 2, 0], [2, 0, 0]])


def test_cross_env_and_horizon_limits(tmp_path):
    """K-17, K-19: cross_env=False keeps chunks inside one env; too-large H and bad args are ValueErrors."""
    arrays = _fake_release()
    d = kdata._validate_arrays(arrays)
    starts = kdata.chunk_start_indices(d, 4, cross_env=False)
    assert list(starts) == [0, 1, 2, 6, 7, 8]
    assert len(kdata.chunk_start_indices(d, 4)) == 12 - 4 + 1
    with pytest.raises(ValueError, match="horizon"):
        kdata.chunk_start_indices(d, 7, cross_env=False)
    with pytest.raises(ValueError, match="horizon"):
        kdata.make_training_examples(d, 13)
    with pytest.raises(ValueError, match="horizon"):
        kdata.make_training_examples(d, 0)
    with pytest.raises(ValueError, match="horizon"):
        kdata.make_training_examples(d, 2.0)
    with pytest.raises(ValueError, match="cross_env"):
        kdata.chunk_start_indices(d, 2, cross_env=1)
    with pytest.raises(ValueError, match="starts"):
        kdata.make_chunks(d, np.array([11]), 2)
    with pytest.raises(ValueError, match="data"):
        kdata.make_training_examples(arrays, 2)
    with pytest.raises(ValueError, match="level_name"):
        kdata.expert_data_filename("worlds/l/grasp_easy.json")
