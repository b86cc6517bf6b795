"""Input validation of softrtc.kinetix ([N-7], [N-12], [K-12], [K-15], [K-17], [KE-*]).

Each test checks that a bad input raises ``ValueError`` naming the argument,
and makes one valid call. Only abstract tracing (``eval_shape``) is used for
the env; no rollout is compiled.
"""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import flax.nnx as nnx  # noqa: E402
import jax  # noqa: E402

from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.kinetix import data as kdata  # noqa: E402
from softrtc.kinetix import env as kenv  # noqa: E402
from softrtc.kinetix import finetune as kft  # noqa: E402
from softrtc.kinetix.evaluation import episode_metrics, evaluate  # noqa: E402
from softrtc.kinetix.methods import MethodSpec, parse_method  # noqa: E402
from softrtc.kinetix.protocol import EvalConfig  # noqa: E402
from softrtc.kinetix.results import main_table, summarize, write_results  # noqa: E402
from softrtc.kinetix.rollout import make_rollout  # noqa: E402
from tests.conftest import SHARED_LEVELS_REASON  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()
needs_levels = pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)


def _arrays(S=4, E=2, obs_dim=3, A=2):
    rng = np.random.default_rng(0)
    done = np.zeros((S, E), bool)
    done[1, 0] = True
    return {"obs": rng.normal(size=(S, E, obs_dim)).astype(np.float32),
            "action": rng.normal(size=(S, E, A)).astype(np.float32),
            "done": done, "solved": np.zeros((S, E), np.float32),
            "return_": np.zeros((S, E), np.float32), "length": np.ones((S, E), np.float32)}


@pytest.fixture(scope="module")
def task():
    if not LEVELS_DIR.is_dir():
        pytest.skip(SHARED_LEVELS_REASON)
    return kenv.make_env("grasp_easy", LEVELS_DIR)


def test_expert_data_dtypes(tmp_path):
    """[K-15], [N-7]: bool/timedelta obs or action and complex done are rejected, not converted."""
    for key, bad in (("obs", np.zeros((4, 2, 3), bool)), ("action", np.zeros((4, 2, 2), "m8[s]")),
                     ("done", np.zeros((4, 2), complex)), ("return_", np.zeros((4, 2), str))):
        a = _arrays() | {key: bad}
        with pytest.raises(ValueError, match=repr(key)):
            kdata.save_expert_data(tmp_path / "x.npz", a)
        with pytest.raises(ValueError, match=repr(key)):
            kdata.ExpertData(**a)
    with pytest.raises(ValueError, match="'done'"):
        kdata.ExpertData(**(_arrays() | {"done": np.full((4, 2), 2)}))
    # valid: 0/1 integer done becomes bool; a round trip keeps the arrays
    ed = kdata.ExpertData(**(_arrays() | {"done": np.zeros((4, 2), np.int64)}))
    assert ed.done.dtype == np.bool_
    p = kdata.save_expert_data(tmp_path / "ok.npz", _arrays())
    np.testing.assert_array_equal(kdata.load_expert_data(p).obs, _arrays()["obs"])


def test_expert_data_constructor_and_chunks():
    """[K-15], [K-17], [N-12]: ExpertData checks shapes; empty starts and H > E*S are errors."""
    with pytest.raises(ValueError, match="'obs'"):
        kdata.ExpertData(np.zeros((6, 2)), np.zeros(3), None, None, None, None)
    with pytest.raises(ValueError, match="'solved'"):
        kdata.ExpertData(**(_arrays() | {"solved": None}))
    ed = kdata.ExpertData(**_arrays())
    with pytest.raises(ValueError, match="starts"):
        kdata.make_chunks(ed, np.array([], int), 2)
    with pytest.raises(ValueError, match="horizon"):
        kdata.make_chunks(ed, np.array([0]), 99)
    obs, chunks, valid = kdata.make_chunks(ed, np.array([0, 1]), 2)
    assert chunks.shape == (2, 2, 2) and valid.shape == (2, 2)
    assert len(kdata.chunk_start_indices(ed, 2)) == 4 * 2 - 2 + 1


def test_save_expert_data_paths(tmp_path):
    """[N-7], [N-11]: save_expert_data checks its output path before writing."""
    (tmp_path / "d.npz").mkdir()
    with pytest.raises(ValueError, match="path"):
        kdata.save_expert_data(tmp_path / "d.npz", _arrays())
    with pytest.raises(ValueError, match="path"):
        kdata.save_expert_data(tmp_path / "d", _arrays())  # np.savez would add .npz
    with pytest.raises(ValueError, match="path"):
        kdata.save_expert_data(tmp_path / "missing" / "x.npz", _arrays())
    assert kdata.save_expert_data(tmp_path / "y", _arrays()).name == "y.npz"


def test_episode_metrics_dtypes():
    """[N-7], [KE-7]: episode_metrics rejects string, complex and bool arrays."""
    for bad in (np.array([["a", "b"], ["c", "d"]]), np.ones((3, 2), complex), np.ones((3, 2), bool), None):
        with pytest.raises(ValueError, match="actions"):
            episode_metrics(bad, 2)
    m = episode_metrics(np.arange(8.0).reshape(4, 2), 4)
    assert m["delta"] == pytest.approx(2 * np.sqrt(2))  # |(2, 2)| per step


def test_method_spec_label():
    """[KE-2], [KE-8]: a label that parses as a method string must match the spec's method and window."""
    with pytest.raises(ValueError, match="label"):
        MethodSpec("naive", label="train_soft:delay_scaled:2")
    with pytest.raises(ValueError, match="label"):
        MethodSpec("train_hard", label="naive")
    spec = parse_method("train_soft:delay_scaled:1")
    assert MethodSpec("train_soft", spec.window, label="train_soft:delay_scaled:1.0") is not None
    assert MethodSpec("naive", label="my baseline").display == "my baseline"
    assert parse_method("train_soft").label == "train_soft"


def test_eval_config_entries():
    """[KE-1], [N-7]: unhashable levels/delays entries are a ValueError naming the field."""
    with pytest.raises(ValueError, match="levels"):
        EvalConfig(levels=[["a"]])
    with pytest.raises(ValueError, match="delays"):
        EvalConfig(delays=[[0]])
    with pytest.raises(ValueError, match="delays"):
        EvalConfig(delays=3)
    assert EvalConfig(levels=["grasp_easy"], delays=[0, 1]).delays == (0, 1)


def _row(**kw):
    r = {"method": "naive", "level": "grasp_easy", "delay": 0, "return": 1.0, "solved": True,
         "delta": 0.1, "jerk": 0.1}
    return r | kw


def test_summarize_and_main_table(tmp_path):
    """[KE-7], [KE-8], [N-7]: bad rows or summaries raise ValueError naming the argument or key."""
    with pytest.raises(ValueError, match="rows"):
        summarize(5)
    for kw in ({"return": None}, {"return": 1j}, {"method": ["a"]}, {"jerk": "x"}):
        with pytest.raises(ValueError, match="rows\\[0\\]"):
            summarize([_row(**kw)])
    with pytest.raises(ValueError, match="pooled"):
        main_table({"pooled": [{}]})
    with pytest.raises(ValueError, match="pooled"):
        main_table({"pooled": 5})
    # write_results: bad rows create nothing; a file as out_dir is rejected up front
    out = tmp_path / "new"
    with pytest.raises(ValueError, match="rows"):
        write_results({"episodes": [_row(**{"return": None})]}, out, bootstrap_resamples=10)
    assert not out.exists()
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(ValueError, match="out_dir"):
        write_results({"episodes": [_row()]}, f, bootstrap_resamples=10)
    with pytest.raises(ValueError, match="out_dir"):
        write_results({"episodes": [_row()]}, f / "sub", bootstrap_resamples=10)
    summary = summarize([_row(), _row(delay=3)], bootstrap_resamples=10)
    assert "| Naive |" in main_table(summary) or "Naive" in main_table(summary)
    paths = write_results({"episodes": [_row()]}, out, bootstrap_resamples=10)
    assert Path(paths["table"]).is_file()


def test_evaluate_has_no_log_parameter():
    """[KE-1], [N-7]: evaluate takes no unused ``log`` argument; a bad config names ``config``."""
    import inspect

    assert "log" not in inspect.signature(evaluate).parameters
    with pytest.raises(ValueError, match="config"):
        evaluate(None, None)
    with pytest.raises(ValueError, match="progress"):
        evaluate(EvalConfig(levels=["grasp_easy"]), None, progress=1)


def test_release_policy_files(tmp_path):
    """[KE-10], [K-3], [N-7]: unreadable policy files are a ValueError naming the file; missing stays FileNotFoundError."""
    txt = tmp_path / "t.pkl"
    txt.write_text("not a pickle")
    empty = tmp_path / "e.pkl"
    empty.write_bytes(b"")
    for f in (txt, empty):
        for fn in (kft.bc_policy_shape, kft.load_bc_policy):
            with pytest.raises(ValueError, match="path"):
                fn(f)
    for bad in (5, None):
        with pytest.raises(ValueError, match="path"):
            kft.bc_policy_shape(bad)
    with pytest.raises(FileNotFoundError):
        kft.bc_policy_shape(tmp_path / "missing.pkl")
    k2 = np.zeros((2, 2))
    pure = {"in_proj": {"kernel": np.zeros((5, 4))}, "out_proj": {"kernel": np.zeros((4, 2))},
            "mlp_stack": {0: {"token_mix_in": {"kernel": np.zeros((8, 3))},
                              "channel_mix_in": {"kernel": np.zeros((4, 6))}}}}
    bad = pure | {"out_proj": {"kernel": np.zeros(4)}}
    with pytest.raises(ValueError, match="out_proj/kernel"):
        kft.infer_policy_shape(bad)
    ok = tmp_path / "ok.pkl"
    ok.write_bytes(pickle.dumps(pure))
    obs_dim, action_dim, cfg = kft.bc_policy_shape(ok)
    assert (obs_dim, action_dim, cfg.action_chunk_size, k2.ndim) == (3, 2, 8, 2)


@needs_levels
def test_levels_dir_and_level_files(tmp_path):
    """[K-3], [K-12], [N-12]: names must be a level name or a non-empty sequence of them; malformed files name the field."""
    for bad in ([], None, 5):
        with pytest.raises(ValueError, match="names"):
            kenv.resolve_levels_dir(LEVELS_DIR, bad)
    with pytest.raises(ValueError, match="level_name"):
        kenv.resolve_levels_dir(LEVELS_DIR, ["nope"])
    assert kenv.resolve_levels_dir(LEVELS_DIR, "grasp_easy") == LEVELS_DIR
    assert kenv.resolve_levels_dir(LEVELS_DIR, ("grasp_easy",)) == LEVELS_DIR
    for content in ('{"static_env_params": {}, "env_params": []}', '{"static_env_params": 5, "env_params": {}}'):
        (tmp_path / "grasp_easy.json").write_text(content)
        with pytest.raises(ValueError, match="grasp_easy.json.*(env_params|static_env_params)"):
            kenv.load_level("grasp_easy", tmp_path)


@needs_levels
def test_env_counts_and_floats(task):
    """[K-12], [N-12], [N-7]: counts are bounded; a huge noise std is a ValueError, not OverflowError."""
    k = jax.random.key(0)
    with pytest.raises(ValueError, match="n must"):
        task.reset_batch(k, 10**30)
    with pytest.raises(ValueError, match="shape"):
        kenv.random_actions(k, (10**30,))
    with pytest.raises(ValueError, match="num_envs"):
        kenv.bench_bare_env("grasp_easy", num_envs=10**30)
    with pytest.raises(ValueError, match="task"):
        kenv.make_random_rollout(None, 1, 1)
    with pytest.raises(ValueError, match="num_envs"):
        kenv.make_random_rollout(task, 10**30, 1)
    with pytest.raises(ValueError, match="action_noise_std"):
        kenv.make_env("grasp_easy", LEVELS_DIR, 10**400)
    assert kenv.random_actions(k, (3,)).shape == (3, kenv.ACTION_DIM)
    assert callable(kenv.make_random_rollout(task, 2, 2))


@needs_levels
def test_task_step_and_constructor(task):
    """[K-12], [N-7]: step validates state and action before reaching JAX; KinetixTask checks its fields."""
    k = jax.random.key(0)
    with pytest.raises(ValueError, match="state"):
        task.step(k, None, np.zeros(6, np.float32))
    with pytest.raises(ValueError, match="action"):
        task.step(k, None, "abcdef")
    with pytest.raises(ValueError, match="action"):
        task.step(k, None, None)
    state = jax.eval_shape(task.reset, k)[1]
    out = jax.eval_shape(task.step, k, state, jax.ShapeDtypeStruct((6,), np.float32))
    assert out[0].shape == (task.obs_dim,)
    with pytest.raises(ValueError, match="state"):
        jax.eval_shape(task.step_batch, k, state, jax.ShapeDtypeStruct((2, 6), np.float32))
    with pytest.raises(ValueError, match="level_name"):
        kenv.KinetixTask(*[None] * 8)
    import dataclasses

    with pytest.raises(ValueError, match="obs_dim"):
        dataclasses.replace(task, obs_dim=0)
    assert dataclasses.replace(task, action_noise_std=0).action_noise_std == 0.0


@needs_levels
def test_rollout_delays_and_devices(task):
    """[KE-4], [X-1], [N-7]: bad delays and devices raise ValueError naming them (no compile)."""
    pol = FlowPolicy(obs_dim=task.obs_dim, action_dim=task.action_dim,
                     config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1,
                                         action_chunk_size=8), rngs=nnx.Rngs(0))
    for bad in (5, ["cpu"], "cpu"):
        with pytest.raises(ValueError, match="devices"):
            make_rollout(task, pol, "rtc", 2, episode_steps=8, devices=bad)
    ro = make_rollout(task, pol, "rtc", 2, episode_steps=8, devices=jax.devices()[:1])
    keys = jax.random.split(jax.random.key(0), 2)
    for d in (3, None, np.array(2), np.array([0, 9]), np.array([0.0, 1.0])):
        with pytest.raises(ValueError, match="delays"):
            ro(pol, MethodSpec("naive"), "grasp_easy", keys, d)
        with pytest.raises(ValueError, match="delays"):
            ro.compile(pol, MethodSpec("naive"), "grasp_easy", keys, d)
    args = ro._args(pol, MethodSpec("naive"), "grasp_easy", keys, np.array([0, 1]))
    assert args[-1].shape == (2,)


def test_finetune_output_folder_is_checked_before_any_input(tmp_path):
    """[KE-10], [N-7], [N-11]: finetune_level rejects an out_dir that is a file, lies under a file, or holds a
    folder where the level's checkpoint would go, before it reads data or release files (the data and bc
    folders given here do not exist, so reaching them would raise FileNotFoundError instead)."""
    f = tmp_path / "afile"
    f.write_text("x")
    (tmp_path / "out" / "grasp_easy.npz").mkdir(parents=True)
    missing = tmp_path / "no-such-folder"
    for out, word in ((f, "is a file"), (f / "sub", "cannot be created"), (tmp_path / "out", "grasp_easy.npz")):
        with pytest.raises(ValueError, match="out_dir") as info:
            kft.finetune_level(missing, missing, "grasp_easy", "hard", out)
        assert word in str(info.value), info.value
    # A valid out_dir passes its check and the call goes on to the (missing) data folder.
    with pytest.raises((FileNotFoundError, ValueError), match="data_dir"):
        kft.finetune_level(missing, missing, "grasp_easy", "hard", tmp_path / "new")
    assert not (tmp_path / "new").exists()
