"""Tests of the Kinetix evaluation protocol, release-asset fine-tuning and the CLI ([KE-1]..[KE-12]).

One rollout configuration per sampler family (training-time and guided, a
small freshly initialised policy, 10 envs, 24 steps) is compiled once per
module and reused by every rollout test and by the end-to-end evaluation.
"""

from __future__ import annotations

import csv
import pickle
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import flax.nnx as nnx  # noqa: E402
import jax  # noqa: E402

from softrtc.jax import checkpoint as jckpt  # noqa: E402
from softrtc.jax.params import load_pure_dict, state_pure_dict  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.kinetix import data as kdata  # noqa: E402
from softrtc.reference import executor as ref_executor  # noqa: E402
from softrtc.reference import metrics as ref_metrics  # noqa: E402
from softrtc.reference import methods as ref_methods  # noqa: E402
from tests.conftest import SHARED_LEVELS_REASON  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()
needs_levels = pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)

from softrtc.kinetix import evaluation as kevaluation  # noqa: E402
from softrtc.kinetix.bench import bench_harness  # noqa: E402
from softrtc.kinetix.evaluation import episode_metrics, evaluate  # noqa: E402
from softrtc.kinetix.limits import EPISODES_MAX, NUM_ENVS_MAX, REPEATS_MAX  # noqa: E402
from softrtc.kinetix.methods import MethodSpec, method_family, parse_method, rollout_weight_table  # noqa: E402
from softrtc.kinetix.protocol import EvalConfig  # noqa: E402
from softrtc.kinetix.results import main_table, summarize, write_results  # noqa: E402
from softrtc.kinetix.rollout import episode_keys, make_rollout  # noqa: E402

S = 4
EPISODES = 2
DELAYS = (0, 1, 2, 3, 4)
STEPS = 24
SMALL = PolicyConfig(channel_dim=16, channel_hidden_dim=16, token_hidden_dim=8, num_layers=1, action_chunk_size=8)


@pytest.fixture(scope="module")
def setup():
    from softrtc.kinetix import env as kenv

    task = kenv.make_env("grasp_easy", LEVELS_DIR)
    pol = FlowPolicy(obs_dim=task.obs_dim, action_dim=task.action_dim, config=SMALL, rngs=nnx.Rngs(0))
    # adaLN-zero init ([P-6]) closes every gate, so a fresh policy acts on each token alone and
    # Hard RTC could not change an executed action; random modulation kernels open the gates.
    rng = np.random.default_rng(0)
    pure = jax.tree_util.tree_map_with_path(
        lambda path, a: np.asarray(a) + 0.3 * rng.standard_normal(np.shape(a)).astype(np.float32)
        if "adaln" in jax.tree_util.keystr(path) else np.asarray(a), state_pure_dict(pol))
    load_pure_dict(pol, pure)
    n = EPISODES * len(DELAYS)
    ro = make_rollout(task, pol, "rtc", n, episode_steps=STEPS)
    keys = jax.numpy.tile(episode_keys(0, "grasp_easy", EPISODES), len(DELAYS))
    delays = np.repeat(np.asarray(DELAYS), EPISODES)
    outs = {m: ro(pol, parse_method(m), "grasp_easy", keys, delays)
            for m in ("naive", "train_hard", "train_soft", "train_soft:offset:0")}
    guided = make_rollout(task, pol, "guided", n, episode_steps=STEPS)
    outs |= {m: guided(pol, parse_method(m), "grasp_easy", keys, delays)
             for m in ("inference_hard", "inference_soft")}
    return {"task": task, "policy": pol, "rollout": ro, "guided": guided, "keys": keys, "delays": delays,
            "outs": outs}


# ----------------------------------------------------------------------------- cheap checks


def test_parse_method_and_tables():
    """KE-2, KE-3, S-6, G-1, W-7, W-8, X-2: method strings, families and per-delay weight tables."""
    assert parse_method("naive").method == "naive"
    soft = parse_method("train_soft")
    assert soft.window.rule.kind == "delay_scaled" and soft.window.rule.lam == 2.0 and soft.window.rule.h_max == 5
    off = parse_method("train_soft:offset:1")
    assert off.window.rule.kind == "offset" and off.window.rule.length == 1 and off.window.rule.h_max == 8
    assert parse_method("train_soft:delay_scaled:2:5:zeros").window.overflow == "zeros"
    zeros = parse_method("train_soft:zeros").window  # the main window, zero-padded ([KE-2] grammar)
    assert zeros.overflow == "zeros" and zeros.rule == soft.window.rule
    assert parse_method("train_soft:delay_scaled:1").display == "Train Soft RTC (delay_scaled:1)"
    for bad in ("", "fancy", "naive:offset:1", "train_soft:offset", "train_soft:offset:x", "train_soft:wide:3",
                "train_soft:delay_scaled:1_0", "train_soft:fixed:\uff13"):
        with pytest.raises(ValueError, match="method"):
            parse_method(bad)
    assert [method_family(m) for m in ref_methods.METHODS] == ["rtc", "guided", "guided", "rtc", "rtc"]
    for m in ("naive", "inference_hard", "inference_soft", "train_hard", "train_soft"):
        spec = parse_method(m)
        t = rollout_weight_table(spec, 8, S)
        assert t.shape == (5, 8)  # one row per delay 0 .. min(s, H - s)
        for d in range(5):
            np.testing.assert_allclose(t[d], ref_methods.method_weights(m, 8, S, d, spec.window), atol=1e-6)
    np.testing.assert_array_equal(rollout_weight_table(parse_method("train_soft:offset:0"), 8, S),
                                  rollout_weight_table(parse_method("train_hard"), 8, S))


def test_episode_metrics_truncate():
    """M-1, M-2, M-4, KE-7: delta and jerk on the executed actions up to the episode's end."""
    a = np.zeros((10, 2))
    a[:4, 0] = [0.0, 1.0, 3.0, 6.0]
    a[4:] = 100.0  # after the episode's end: must not count
    m = episode_metrics(a, 4)
    assert m["delta"] == pytest.approx(ref_metrics.action_delta(a[:4]))
    assert m["jerk"] == pytest.approx(1.0)
    assert np.isnan(episode_metrics(a, 2)["jerk"]) and np.isnan(episode_metrics(a, 1)["delta"])
    with pytest.raises(ValueError, match="length"):
        episode_metrics(a, 11)


def test_summarize_pools_levels_and_delays():
    """M-4, M-5, M-7, KE-7, KE-8: per-level means weight delays equally; pooled = mean over levels + bootstrap."""
    rows = []
    rng = np.random.default_rng(0)
    for lv in ("grasp_easy", "catapult", "trampoline"):
        for d in DELAYS:
            for e in range(2 if d else 4):  # unequal counts: delays still weigh equally
                rows.append({"method": "naive", "level": lv, "delay": d, "episode": e, "return": rng.normal(),
                             "solved": bool(rng.integers(2)), "length": 10, "delta": rng.random(),
                             "jerk": rng.random()})
    summ = summarize(rows, bootstrap_resamples=500)
    per = {(r["level"], r["scope"]): r for r in summ["per_level"]}
    for lv in ("grasp_easy", "catapult", "trampoline"):
        want = np.mean([np.mean([r["return"] for r in rows if r["level"] == lv and r["delay"] == d]) for d in DELAYS])
        assert per[(lv, "overall")]["return"] == pytest.approx(want)
        want_hi = np.mean([np.mean([r["jerk"] for r in rows if r["level"] == lv and r["delay"] == d]) for d in (3, 4)])
        assert per[(lv, "high")]["jerk"] == pytest.approx(want_hi)
    pooled = {r["scope"]: r for r in summ["pooled"]}
    vals = np.array([per[(lv, "overall")]["solved"] for lv in ("grasp_easy", "catapult", "trampoline")])
    assert pooled["overall"]["solved"] == pytest.approx(vals.mean())
    lo, hi = ref_metrics.bootstrap_interval(vals, 500, 0)
    assert (pooled["overall"]["solved_lo"], pooled["overall"]["solved_hi"]) == pytest.approx((lo, hi))
    table = main_table(summ)
    assert table.splitlines()[0].startswith("| Method | Overall Return | Overall Solve | High-delay Solve | High-delay Jerk")
    assert "| Base Naive |" in table
    with pytest.raises(ValueError, match="rows"):
        summarize([])
    with pytest.raises(ValueError, match=r"^rows\[0\]\['delay'\] must be an integer"):
        summarize([dict(rows[0], delay=-7)])
    with pytest.raises(ValueError, match=r"^rows\[1\] must be a mapping with keys"):
        summarize([rows[0], {"method": "naive"}])


def test_config_and_input_validation():
    """N-7, X-1, KE-1, KE-9: bad protocol and bench values raise ValueError naming the argument."""
    assert EvalConfig().episodes == 32 and EvalConfig().delays == (0, 1, 2, 3, 4)
    assert EvalConfig().execute_horizon == 4 and EvalConfig().num_flow_steps == 5
    for kw, name in (({"levels": ("nope",)}, "levels"), ({"episodes": 0}, "episodes"),
                     ({"delays": (0, 5)}, "delays"), ({"methods": ("naive", "naive")}, "methods"),
                     ({"episodes": 2.0}, "episodes"), ({"seed": -1}, "seed"),
                     ({"delays": 3}, "delays"), ({"levels": 5}, "levels"), ({"methods": 5}, "methods"),
                     ({"delays": "01"}, "delays"), ({"levels": None}, "levels"),
                     ({"episodes": EPISODES_MAX + 1}, "episodes"), ({"episode_steps": 0}, "episode_steps")):
        with pytest.raises(ValueError, match=f"^{name}"):
            EvalConfig(**kw)
    # A bare level or method string is a one-entry sequence; a NumPy array of delays is a sequence.
    assert EvalConfig(levels="catapult", methods="naive", delays=np.arange(3)).delays == (0, 1, 2)
    with pytest.raises(ValueError, match="level"):
        episode_keys(0, "nope", 2)
    with pytest.raises(ValueError, match="window"):
        MethodSpec("train_hard", window=parse_method("train_soft").window)
    with pytest.raises(ValueError, match="level"):
        bench_harness("nope")
    with pytest.raises(ValueError, match=r"^repeats must be an integer in \[1, 100\]"):
        bench_harness(repeats=REPEATS_MAX + 1)


def test_cli_ranges_are_the_librarys():
    """KE-1, KE-9, KE-12, N-11: each option accepts exactly the range of the library value it sets."""
    from softrtc.cli import build_parser
    from softrtc.kinetix import limits

    assert (EPISODES_MAX, REPEATS_MAX, NUM_ENVS_MAX) == (limits.EPISODES_MAX, limits.REPEATS_MAX,
                                                               limits.NUM_ENVS_MAX)
    parser = build_parser()
    ev = ["kinetix", "eval", "--out", "x"]
    assert parser.parse_args(ev + ["--episodes", str(limits.EPISODES_MAX)]).episodes == limits.EPISODES_MAX
    assert EvalConfig(episodes=limits.EPISODES_MAX).episodes == limits.EPISODES_MAX
    assert parser.parse_args(["kinetix", "bench", "--repeats", str(limits.REPEATS_MAX)]).repeats == limits.REPEATS_MAX
    assert parser.parse_args(["kinetix", "bench", "--num-envs", str(limits.NUM_ENVS_MAX)]).num_envs == \
        limits.NUM_ENVS_MAX
    for argv in (ev + ["--episodes", str(limits.EPISODES_MAX + 1)],
                 ["kinetix", "bench", "--repeats", str(limits.REPEATS_MAX + 1)],
                 ["kinetix", "bench", "--num-envs", str(limits.NUM_ENVS_MAX + 1)]):
        with pytest.raises(SystemExit):
            parser.parse_args(argv)
    # make_rollout and EvalConfig share the episode_steps range ([KE-1]).
    assert limits.EPISODE_STEPS_MIN == 1
    assert EvalConfig(episode_steps=limits.EPISODE_STEPS_MIN).episode_steps == 1
    with pytest.raises(ValueError, match="episode_steps"):
        EvalConfig(episode_steps=limits.EPISODE_STEPS_MAX + 1)


# ----------------------------------------------------------------------------- rollouts


@pytest.mark.slow
@needs_levels
def test_zero_delay_identical_for_training_samplers(setup):
    """S-7, X-2, W-9, KE-3: at d = 0 no-RTC, hard and soft training-time samplers execute identical actions."""
    outs, d0 = setup["outs"], setup["delays"] == 0
    for m in ("train_hard", "train_soft"):
        np.testing.assert_array_equal(outs[m]["actions"][d0], outs["naive"]["actions"][d0])
        np.testing.assert_array_equal(outs[m]["chunks"][d0], outs["naive"]["chunks"][d0])
    # The first chunk of every episode is the naive sampler whatever the method and delay ([X-2]).
    np.testing.assert_array_equal(outs["train_soft"]["chunks"][:, 0], outs["naive"]["chunks"][:, 0])
    # With a delay the methods do differ (the test is not vacuous).
    assert not np.array_equal(outs["train_hard"]["actions"][~d0], outs["naive"]["actions"][~d0])


@pytest.mark.slow
@needs_levels
def test_guided_rollout_inference_methods(setup):
    """KE-3, G-1, G-6, X-2, X-3, S-6, P-14: the guided family runs inference-time RTC in closed loop.

    The first chunk of every episode is the naive sampler: bitwise the guided program's own naive chunk
    (inference_hard at d = 0, W = 0, [G-6]) for every method and delay, and the training-time family's
    naive chunk within [P-14] (another compiled program). inference_hard at d = 0 executes the naive
    actions; guidance toward the previous chunk changes the executed actions at every d > 0."""
    outs, delays = setup["outs"], setup["delays"]
    naive, d0 = outs["naive"], delays == 0
    tol = {"rtol": 1e-4, "atol": 1e-4}  # [P-14]
    assert setup["guided"].family == "guided"
    # Envs are ordered delay-major with the same episode keys at every delay.
    own_naive = np.tile(outs["inference_hard"]["chunks"][d0][:, 0], (len(DELAYS), 1, 1))
    for m in ("inference_hard", "inference_soft"):
        np.testing.assert_array_equal(outs[m]["chunks"][:, 0], own_naive, err_msg=m)
        np.testing.assert_allclose(outs[m]["chunks"][:, 0], naive["chunks"][:, 0], err_msg=m, **tol)
        np.testing.assert_allclose(outs[m]["actions"][:, :S], naive["actions"][:, :S], err_msg=m, **tol)
        for d in range(1, 5):  # far beyond rounding: guidance acts
            assert np.abs(outs[m]["actions"][delays == d] - naive["actions"][delays == d]).max() > 1e-2, (m, d)
    np.testing.assert_allclose(outs["inference_hard"]["actions"][d0], naive["actions"][d0], **tol)
    np.testing.assert_allclose(outs["inference_hard"]["chunks"][d0], naive["chunks"][d0], **tol)
    # Soft inpainting guides the whole overlap even at d = 0 ([G-1]): not naive after the first chunk.
    assert np.abs(outs["inference_soft"]["chunks"][d0][:, 1:] - naive["chunks"][d0][:, 1:]).max() > 1e-2

    # Guidance pulls the new chunk's committed prefix toward the previous chunk shifted by s ([X-3]):
    # far closer than naive chunks, which ignore it (measured: about 0.01 against about 1).
    def prefix_gap(chunks):
        gaps = [np.abs(chunks[e, c, :d] - chunks[e, c - 1, S:S + d]).mean()
                for e, d in enumerate(delays) if d > 0 for c in range(1, chunks.shape[1])]
        return float(np.mean(gaps))

    assert prefix_gap(outs["inference_hard"]["chunks"]) < 0.1 * prefix_gap(naive["chunks"])


@pytest.mark.slow
@needs_levels
def test_offset_zero_equals_hard(setup):
    """E-3, W-8: train_soft with the offset rule L = 0 is exactly Hard RTC in closed loop."""
    outs = setup["outs"]
    np.testing.assert_array_equal(outs["train_soft:offset:0"]["actions"], outs["train_hard"]["actions"])
    np.testing.assert_array_equal(outs["train_soft:offset:0"]["chunks"], outs["train_hard"]["chunks"])


@pytest.mark.slow
@needs_levels
def test_chunk_switch_executes_committed_prefix(setup):
    """X-3, X-4, KE-6: each segment runs prev[s : s + d] then new[d : s]."""
    for m, out in setup["outs"].items():
        acts, chunks = out["actions"], out["chunks"]
        C = chunks.shape[1]
        assert acts.shape == (len(setup["delays"]), C * S, 6)
        for e, d in enumerate(setup["delays"]):
            np.testing.assert_array_equal(acts[e, :S], chunks[e, 0, :S])
            for c in range(1, C):
                seg = acts[e, c * S:(c + 1) * S]
                np.testing.assert_array_equal(seg[:d], chunks[e, c - 1, S:S + d], err_msg=f"{m} env {e} chunk {c}")
                np.testing.assert_array_equal(seg[d:], chunks[e, c, d:S], err_msg=f"{m} env {e} chunk {c}")


@pytest.mark.slow
@needs_levels
def test_matches_reference_executor(setup):
    """X-2, X-5, KE-6: the executed sequence equals softrtc.reference.executor.execute_chunks on the chunks generated."""
    for out in setup["outs"].values():
        C = out["chunks"].shape[1]
        for e, d in enumerate(setup["delays"]):
            ref = ref_executor.execute_chunks(out["chunks"][e].astype(np.float64), [0] + [int(d)] * (C - 1), S)
            np.testing.assert_array_equal(out["actions"][e], ref["actions"].astype(np.float32))


@pytest.mark.slow
@needs_levels
def test_same_seed_same_rollout(setup):
    """N-9, KE-5: the same keys give the same rollout; other keys give another."""
    ro, pol, keys, delays = setup["rollout"], setup["policy"], setup["keys"], setup["delays"]
    again = ro(pol, parse_method("naive"), "grasp_easy", keys, delays)
    for k in ("actions", "chunks", "return", "length", "solved"):
        np.testing.assert_array_equal(again[k], setup["outs"]["naive"][k])
    other = jax.numpy.tile(episode_keys(1, "grasp_easy", EPISODES), len(DELAYS))
    assert not np.array_equal(ro(pol, parse_method("naive"), "grasp_easy", other, delays)["actions"],
                              again["actions"])
    with pytest.raises(ValueError, match="delays"):
        ro(pol, parse_method("naive"), "grasp_easy", keys, np.full(len(delays), 5))
    with pytest.raises(ValueError, match="family"):
        ro(pol, parse_method("inference_hard"), "grasp_easy", keys, delays)


@pytest.mark.slow
@needs_levels
def test_rollout_mesh_over_env_axis(setup):
    """KE-4: the env axis is sharded over a 1-D mesh of every device (one CPU device here)."""
    ro = setup["rollout"]
    assert ro.mesh.axis_names == ("env",) and ro.num_devices == len(jax.devices())
    assert ro.padded % ro.num_devices == 0 and ro.padded >= ro.num_envs


@pytest.mark.slow
@needs_levels
def test_evaluate_end_to_end(setup, tmp_path):
    """KE-1, KE-7, KE-8, M-4, X-6: evaluate two levels, write CSV and the Markdown table (reuses the compile)."""
    methods = ("naive", "inference_hard", "inference_soft", "train_hard", "train_soft")
    cfg = EvalConfig(levels=("grasp_easy", "cartpole_thrust"), methods=methods,
                       episodes=EPISODES, episode_steps=STEPS, levels_dir=str(LEVELS_DIR))
    res = evaluate(cfg, setup["policy"], progress=False)
    rows = res["episodes"]
    assert len(rows) == len(methods) * 2 * len(DELAYS) * EPISODES
    assert set(res["compile_s"]) == {"rtc", "guided"}
    assert all(1 <= r["length"] <= STEPS for r in rows)
    g = {(r["method"], r["level"], r["delay"], r["episode"]): r for r in rows}
    # Same keys for every method: at d = 0 the training-time samplers reproduce naive exactly ([S-7]).
    for lv in cfg.levels:
        for e in range(EPISODES):
            for m in ("train_hard", "train_soft"):  # [S-7]: the same program, bitwise
                assert g[(m, lv, 0, e)]["return"] == g[("naive", lv, 0, e)]["return"]
            # [G-6] in the guided program: naive within [P-14] of the training-time one.
            assert g[("inference_hard", lv, 0, e)]["return"] == pytest.approx(g[("naive", lv, 0, e)]["return"],
                                                                              rel=1e-4, abs=1e-4)
    # With a delay the inference rows are guided runs, not naive ones.
    assert max(abs(g[(m, lv, d, e)]["return"] - g[("naive", lv, d, e)]["return"]) for m in ("inference_hard",
               "inference_soft") for lv in cfg.levels for d in DELAYS[1:] for e in range(EPISODES)) > 1e-3
    # grasp_easy rows reproduce the fixture's direct rollouts, guided family included.
    for m in ("naive", "inference_hard", "inference_soft"):
        out = setup["outs"][m]
        for i, d in enumerate(setup["delays"]):
            assert g[(m, "grasp_easy", int(d), i % EPISODES)]["return"] == pytest.approx(float(out["return"][i]))
    paths = write_results(res, tmp_path, bootstrap_resamples=200)
    with open(paths["pooled"]) as f:
        pooled = list(csv.DictReader(f))
    assert {(r["method"], r["scope"]) for r in pooled} == {(m, s) for m in methods for s in ("overall", "high")}
    table = Path(paths["table"]).read_text()
    for row in ("Inference Hard RTC", "Inference Soft RTC", "Train Hard RTC", "Train Soft RTC"):
        assert f"| {row} |" in table


@needs_levels
def test_evaluate_checks_every_policy_before_the_first_rollout(monkeypatch):
    """KE-11, X-1, KE-1: evaluate resolves and checks every (method, level) policy before any rollout runs."""
    from softrtc.kinetix import env as kenv

    def no_rollout(*args, **kwargs):
        raise AssertionError("a rollout was built before every policy was checked")

    pol = FlowPolicy(obs_dim=kenv.OBS_DIM, action_dim=kenv.ACTION_DIM, config=SMALL, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match=r"^episode_steps must be an integer in \[1, 65536\]"):  # EvalConfig's range
        make_rollout(kenv.make_env("grasp_easy", LEVELS_DIR), pol, "rtc", 1, episode_steps=0)
    monkeypatch.setattr(kevaluation, "make_rollout", no_rollout)
    cfg = EvalConfig(levels=("grasp_easy", "catapult"), methods=("naive", "train_hard"), episodes=1,
                       levels_dir=str(LEVELS_DIR))
    calls = []

    def policies(spec, level):  # the last (method, level) has no policy
        calls.append((spec.label, level))
        return None if (spec.label, level) == ("train_hard", "catapult") else pol

    with pytest.raises(ValueError, match="'train_hard' and level 'catapult'"):
        evaluate(cfg, policies, progress=False)
    assert calls == [(m, lv) for m in ("naive", "train_hard") for lv in ("grasp_easy", "catapult")]
    # H = 6 with s = 4 holds delays up to min(4, 2) = 2 only ([X-1]).
    short = FlowPolicy(obs_dim=kenv.OBS_DIM, action_dim=kenv.ACTION_DIM,
                       config=PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1,
                                           action_chunk_size=6), rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match=r"^delays must lie in \[0, 2\].*'train_hard' and level 'catapult'"):
        evaluate(cfg, lambda spec, level: short if spec.label == "train_hard" and level == "catapult" else pol,
                   progress=False)
    wrong = FlowPolicy(obs_dim=5, action_dim=kenv.ACTION_DIM, config=SMALL, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="obs_dim=679"):
        evaluate(cfg, {"grasp_easy": pol, "catapult": wrong}, progress=False)


# ----------------------------------------------------------------------------- release assets


def _write_release(tmp_path, obs_dim=5, action_dim=2, chunks=(("grasp_easy", 8),)):
    """Tiny files in exactly the release formats: expert .npz ([K-14]) and a pickled pure dict ([P-8]),
    one pair per (level, chunk size H) of ``chunks``; returns the first level's policy."""
    bc = tmp_path / "bc" / "24" / "policies"
    bc.mkdir(parents=True)
    data = tmp_path / "data"
    data.mkdir()
    pols = []
    for level, h in chunks:
        cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=h)
        pols.append(FlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=cfg, rngs=nnx.Rngs(3)))
        with open(bc / f"worlds_l_{level}.pkl", "wb") as f:
            pickle.dump(jax.tree.map(np.asarray, state_pure_dict(pols[-1])), f)
        rng = np.random.default_rng(0)
        S_, E_ = 24, 2
        done = np.zeros((S_, E_), bool)
        done[10, 0] = True
        arrays = {"obs": rng.normal(size=(S_, E_, obs_dim)).astype(np.float32),
                  "action": rng.uniform(-1, 1, size=(S_, E_, action_dim)).astype(np.float32),
                  "done": done, "solved": done.astype(np.float32), "return_": np.zeros((S_, E_), np.float32),
                  "length": np.zeros((S_, E_), np.float32)}
        np.savez(data / kdata.expert_data_filename(level), **arrays)
    return pols[0], tmp_path / "bc", data


def test_release_policy_loader(tmp_path):
    """P-7, P-8, KE-10, KE-11: a pickled release pure dict loads with its architecture inferred."""
    from softrtc.kinetix import finetune as ft

    pol, bc, _ = _write_release(tmp_path)
    assert ft.find_bc_file(bc, "grasp_easy").name == "worlds_l_grasp_easy.pkl"
    loaded = ft.load_level_policy(bc, "grasp_easy")
    assert (loaded.obs_dim, loaded.action_dim, loaded.config) == (pol.obs_dim, pol.action_dim, pol.config)
    for a, b in zip(jax.tree.leaves(state_pure_dict(loaded)), jax.tree.leaves(state_pure_dict(pol))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    with pytest.raises(FileNotFoundError, match="catapult"):
        ft.find_bc_file(bc, "catapult")
    with pytest.raises(ValueError, match="level"):
        ft.find_bc_file(bc, "nope")


@pytest.mark.slow
def test_finetune_soft_and_cli_hard(tmp_path, capsys):
    """KE-10, KE-11, KE-12, T-3, K-16: one epoch of soft (API) and hard (CLI) RTC on release-format files."""
    from softrtc.cli import main
    from softrtc.kinetix import finetune as ft

    pol, bc, data = _write_release(tmp_path)
    meta = ft.finetune_level(data, bc, "grasp_easy", "soft", tmp_path / "soft", batch_size=8, progress=False)
    assert meta["steps"] == (2 * 24 - 8 + 1) // 8 and meta["method"] == "soft"
    tuned, header_meta = jckpt.load_checkpoint(meta["path"])
    assert header_meta["train_config"]["method"] == "soft" and header_meta["level"] == "grasp_easy"
    assert tuned.config == pol.config
    changed = [not np.array_equal(np.asarray(a), np.asarray(b))
               for a, b in zip(jax.tree.leaves(state_pure_dict(tuned)), jax.tree.leaves(state_pure_dict(pol)))]
    assert any(changed)
    again = ft.load_level_policy(tmp_path / "soft", "grasp_easy")
    for a, b in zip(jax.tree.leaves(state_pure_dict(again)), jax.tree.leaves(state_pure_dict(tuned))):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    rc = main(["kinetix", "finetune", "--data", str(data), "--bc", str(bc), "--method", "hard",
               "--batch-size", "8", "--out", str(tmp_path / "hard"), "--no-progress"])
    assert rc == 0 and (tmp_path / "hard" / "grasp_easy.npz").is_file()
    assert "grasp_easy: 5 steps" in capsys.readouterr().out
    with pytest.raises(ValueError, match="method"):
        ft.finetune_level(data, bc, "grasp_easy", "none", tmp_path / "x")


def test_cli_errors_are_one_line(tmp_path, capsys):
    """KE-12, N-7: bad arguments and missing directories print one clear error line, exit status 2,
    before any work starts (argparse rejects malformed options, the command the rest)."""
    from softrtc.cli import main

    def status(argv):
        try:
            return main(argv)
        except SystemExit as exc:  # argparse: usage line, then the error line
            return exc.code

    (tmp_path / "afile").write_text("x")
    cases = [
        (["kinetix", "eval", "--levels", "grasp_easy,nope", "--out", str(tmp_path)], "--levels entries"),
        (["kinetix", "eval", "--delays", "0,5", "--out", str(tmp_path)], "--delays entries must be an integer in [0, 4]"),
        (["kinetix", "eval", "--methods", "naive,fancy", "--out", str(tmp_path)], "--methods entry"),
        (["kinetix", "eval", "--episodes", "65537", "--out", str(tmp_path)], "--episodes"),
        (["kinetix", "eval", "--levels", "grasp_easy", "--levels-dir", str(tmp_path / "none"),
          "--out", str(tmp_path)], "--levels-dir"),
        (["kinetix", "eval", "--methods", "train_soft:wide", "--out", str(tmp_path)], "method"),
        (["kinetix", "eval", "--delays", "0,x", "--out", str(tmp_path)], "--delays"),
        (["kinetix", "eval", "--delays", "1,,2", "--out", str(tmp_path)], "--delays"),
        (["kinetix", "eval", "--levels", "", "--out", str(tmp_path)], "--levels"),
        (["kinetix", "eval", "--out", str(tmp_path / "afile")], "--out"),
        (["kinetix", "eval", "--init-seed", "99999999999999999999", "--out", str(tmp_path)], "--init-seed"),
        (["kinetix", "finetune", "--data", str(tmp_path / "none"), "--bc", str(tmp_path), "--method", "soft",
          "--out", str(tmp_path)], "--data"),
        (["kinetix", "finetune", "--data", str(tmp_path), "--bc", str(tmp_path), "--method", "hard",
          "--levels", "grasp_easy,catapult", "--out", str(tmp_path / "ft")], "grasp_easy"),
        (["kinetix", "finetune", "--data", str(tmp_path), "--bc", str(tmp_path), "--method", "hard",
          "--levels", ",", "--out", str(tmp_path / "ft")], "--levels"),
        (["kinetix", "finetune", "--data", str(tmp_path), "--bc", str(tmp_path), "--method", "soft",
          "--window", "bogus", "--out", str(tmp_path / "ft")], "--window 'bogus' is not a soft window"),
        (["kinetix", "finetune", "--data", str(tmp_path), "--bc", str(tmp_path), "--method", "soft",
          "--lr", "0", "--out", str(tmp_path / "ft")], "--lr"),
        (["kinetix", "bench", "--level", "nope"], "--level must be one of"),
        (["kinetix", "bench", "--method", "fancy"], "--method must start with one of"),
        (["kinetix", "bench", "--repeats", "101"], "--repeats"),
        (["kinetix", "bench", "--out", str(tmp_path)], "--out"),
    ]
    for argv, word in cases:
        assert status(argv) == 2, argv
        err = capsys.readouterr().err
        last = err.strip().splitlines()[-1]
        assert last.startswith("softrtc kinetix ") and word in last and "Traceback" not in err, err
    assert not (tmp_path / "ft").exists()  # nothing trained before the missing inputs were found


def _cli_status(main, argv):
    try:
        return main(argv)
    except SystemExit as exc:  # argparse: usage line, then the error line
        return exc.code


@needs_levels
def test_cli_eval_checks_every_policy_folder_first(tmp_path, capsys, monkeypatch):
    """KE-11, KE-12, N-11: every --method-policy and every (folder, level) policy is checked before the
    evaluation starts; an error is one line naming the option, exit status 2."""
    from softrtc.cli import main

    def no_eval(*args, **kwargs):
        raise AssertionError("the evaluation started before every policy folder was checked")

    monkeypatch.setattr(kevaluation, "evaluate", no_eval)
    _, bc, _ = _write_release(tmp_path)  # grasp_easy only
    empty = tmp_path / "empty"
    empty.mkdir()
    broken = tmp_path / "broken"
    broken.mkdir()
    (broken / "grasp_easy.npz").write_bytes(b"not a checkpoint")
    base = ["kinetix", "eval", "--levels-dir", str(LEVELS_DIR), "--levels", "grasp_easy", "--episodes", "1",
            "--out", str(tmp_path / "out"), "--no-progress", "--policy-dir", str(bc)]
    two = ["--methods", "naive,train_hard"]
    cases = [
        (base[:5] + ["grasp_easy,catapult"] + base[6:] + ["--methods", "naive"],
         f"--policy-dir {bc} has no policy for level 'catapult'"),
        (base + two + ["--method-policy", f"train_hard={tmp_path / 'none'}"], "--method-policy train_hard="),
        (base + two + ["--method-policy", f"train_hard={empty}"],
         f"--method-policy train_hard={empty} has no policy for level 'grasp_easy'"),
        (base + two + ["--method-policy", f"train_hard={broken}"],
         f"--method-policy train_hard={broken}: the policy of level 'grasp_easy' does not load"),
        (base + two + ["--method-policy", f"train_soft={empty}"], "--method-policy method 'train_soft' is not among"),
        (base + two + ["--method-policy", f"train_hard={bc}", "--method-policy", f"train_hard={bc}"],
         "--method-policy gives method 'train_hard' twice"),
        (base + two + ["--method-policy", str(bc)], "--method-policy must be METHOD=DIR"),
    ]
    for argv, words in cases:
        assert _cli_status(main, argv) == 2, argv
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("softrtc kinetix eval: error: "), err
        assert words in err, err
    assert not (tmp_path / "out").exists()


@needs_levels
def test_cli_eval_policy_sources(tmp_path, capsys, monkeypatch):
    """KE-11: --policy-dir serves every method without --method-policy (base policies for naive and the
    inference rows), each --method-policy its own method, as in the README's evaluation command."""
    from softrtc.cli import main

    pol, bc, _ = _write_release(tmp_path)
    tuned = FlowPolicy(obs_dim=pol.obs_dim, action_dim=pol.action_dim, config=pol.config, rngs=nnx.Rngs(9))
    (tmp_path / "hard").mkdir()
    jckpt.save_checkpoint(tmp_path / "hard" / "grasp_easy.npz", tuned, {"level": "grasp_easy", "method": "hard"})
    seen = {}

    def fake_evaluate(config, policies, progress=True):
        rows = []
        for spec in config.methods:
            for level in config.levels:
                seen[spec.label] = policies(spec, level)
                rows += [{"method": spec.label, "level": level, "delay": d, "episode": 0, "return": 0.0,
                          "solved": False, "length": 3, "delta": 0.0, "jerk": 0.0} for d in config.delays]
        return {"episodes": rows, "compile_s": {}, "config": config}

    monkeypatch.setattr(kevaluation, "evaluate", fake_evaluate)
    argv = ["kinetix", "eval", "--levels-dir", str(LEVELS_DIR), "--levels", "grasp_easy", "--episodes", "1",
            "--methods", "naive,inference_soft,train_hard", "--policy-dir", str(bc),
            "--method-policy", f"train_hard={tmp_path / 'hard'}", "--out", str(tmp_path / "out"), "--no-progress"]
    assert _cli_status(main, argv) == 0, capsys.readouterr().err
    assert "| Inference Soft RTC |" in capsys.readouterr().out

    def same(a, b):
        return all(np.array_equal(np.asarray(x), np.asarray(y))
                   for x, y in zip(jax.tree.leaves(state_pure_dict(a)), jax.tree.leaves(state_pure_dict(b))))

    assert seen["naive"] is seen["inference_soft"] and same(seen["naive"], pol)
    assert same(seen["train_hard"], tuned) and not same(seen["train_hard"], pol)


def test_cli_finetune_checks_d_max_first(tmp_path, capsys):
    """KE-10, KE-12, D-4: --d-max above the release policy's chunk size H stops finetune before any work."""
    from softrtc.cli import main

    # grasp_easy (trained first) holds --d-max 9, catapult's policy does not.
    _, bc, data = _write_release(tmp_path, chunks=(("grasp_easy", 16), ("catapult", 8)))
    argv = ["kinetix", "finetune", "--data", str(data), "--bc", str(bc), "--method", "hard", "--d-max", "9",
            "--out", str(tmp_path / "ft"), "--no-progress"]
    assert _cli_status(main, argv) == 2
    err = capsys.readouterr().err
    assert err.strip() == ("softrtc kinetix finetune: error: --d-max must be an integer in [0, 8] "
                           "(the chunk size H of worlds_l_catapult.pkl), got 9"), err
    assert not (tmp_path / "ft").exists()
    from softrtc.kinetix import finetune as ft

    with pytest.raises(ValueError, match=r"^d_max must be an integer in \[0, 8\]"):  # the library checks too
        ft.finetune_level(data, bc, "catapult", "hard", tmp_path / "ft", d_max=9)
    assert not (tmp_path / "ft").exists()


def _save_level_checkpoint(folder, level, meta, seed=0):
    """A tiny policy built directly (no training) saved as ``<folder>/<level>.npz`` with ``meta``."""
    folder.mkdir(parents=True, exist_ok=True)
    cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=8)
    pol = FlowPolicy(obs_dim=5, action_dim=2, config=cfg, rngs=nnx.Rngs(seed))
    jckpt.save_checkpoint(folder / f"{level}.npz", pol, meta)
    return pol


def test_level_policy_loader_checks_level_and_role(tmp_path):
    """KE-11: a checkpoint whose metadata names another level is refused under this level's name; with a
    method, the file must play its role (base for naive and inference-time methods, a hard or soft
    fine-tune of the method's window for train_hard / train_soft); a release file is a base."""
    from softrtc.kinetix import finetune as ft
    from softrtc.jax.training import TrainConfig
    from softrtc.reference.endpoints import delay_scaled
    from softrtc.reference.weights import SoftWindow

    _save_level_checkpoint(tmp_path / "other", "grasp_easy", {"level": "car_launch", "method": "hard"})
    with pytest.raises(ValueError) as info:
        ft.load_level_policy(tmp_path / "other", "grasp_easy")
    assert str(info.value) == (f"checkpoint {str(tmp_path / 'other' / 'grasp_easy.npz')!r} holds the policy of "
                               f"level 'car_launch' (its metadata), not of level 'grasp_easy'")
    _save_level_checkpoint(tmp_path / "none", "grasp_easy", {})
    with pytest.raises(ValueError, match="holds the policy of level None"):
        ft.load_level_policy(tmp_path / "none", "grasp_easy")

    hard = tmp_path / "hard"
    _save_level_checkpoint(hard, "grasp_easy", {"level": "grasp_easy", "method": "hard"})
    ft.load_level_policy(hard, "grasp_easy", "train_hard")
    for method, need in (("train_soft", "a soft fine-tune"), ("naive", "a base policy"),
                         ("inference_soft", "a base policy")):
        with pytest.raises(ValueError, match=rf"grasp_easy\.npz' is a hard fine-tune, but method '{method}' "
                                             rf"runs {need}$"):
            ft.load_level_policy(hard, "grasp_easy", method)
    base = tmp_path / "base"
    _save_level_checkpoint(base, "grasp_easy", {"level": "grasp_easy"})
    ft.load_level_policy(base, "grasp_easy", "inference_hard")
    with pytest.raises(ValueError, match="is a base policy, but method 'train_hard' runs a hard fine-tune$"):
        ft.load_level_policy(base, "grasp_easy", "train_hard")
    _, bc, _ = _write_release(tmp_path / "release")
    ft.load_level_policy(bc, "grasp_easy", "naive")
    with pytest.raises(ValueError, match=r"worlds_l_grasp_easy\.pkl' is a base policy, but method 'train_soft'"):
        ft.load_level_policy(bc, "grasp_easy", "train_soft")

    # A soft fine-tune serves train_soft only with the window it was trained with ([W-7]).
    soft = tmp_path / "soft"
    lam1 = TrainConfig(method="soft", window=SoftWindow(delay_scaled(1.0, 5)), execute_horizon=4, d_max=4)
    _save_level_checkpoint(soft, "grasp_easy", {"level": "grasp_easy", "method": "soft", "train_config": lam1.to_dict()})
    policy, about = ft.read_level_policy(soft, "grasp_easy")
    assert about["role"] == "soft" and about["window"] == SoftWindow(delay_scaled(1.0, 5))
    ft.check_level_role(about, "train_soft", SoftWindow(delay_scaled(1.0, 5)))
    with pytest.raises(ValueError, match="was fine-tuned with window .* but method 'train_soft' runs window"):
        ft.check_level_role(about, "train_soft", SoftWindow())
    with pytest.raises(ValueError, match="^method must be one of"):
        ft.load_level_policy(soft, "grasp_easy", "train_sofft")


@needs_levels
def test_cli_eval_checks_each_methods_role(tmp_path, capsys, monkeypatch):
    """KE-11 KE-12: `kinetix eval` refuses, before any rollout, a --method-policy folder whose checkpoint plays
    another role or level than the method and level it would serve, naming the option, level and file."""
    from softrtc.cli import main

    def no_eval(*args, **kwargs):
        raise AssertionError("the evaluation started before the roles were checked")

    monkeypatch.setattr(kevaluation, "evaluate", no_eval)
    _, bc, _ = _write_release(tmp_path)
    soft = tmp_path / "soft"
    from softrtc.jax.training import TrainConfig

    _save_level_checkpoint(soft, "grasp_easy", {"level": "grasp_easy", "method": "soft",
                                                "train_config": TrainConfig(method="soft").to_dict()})
    moved = tmp_path / "moved"
    _save_level_checkpoint(moved, "grasp_easy", {"level": "car_launch", "method": "hard"})
    base = ["kinetix", "eval", "--levels-dir", str(LEVELS_DIR), "--levels", "grasp_easy", "--episodes", "1",
            "--out", str(tmp_path / "out"), "--no-progress", "--policy-dir", str(bc), "--methods", "naive,train_hard"]
    cases = [
        (base + ["--method-policy", f"train_hard={soft}"],
         f"--method-policy train_hard={soft}: level 'grasp_easy': {str(soft / 'grasp_easy.npz')!r} is a soft "
         f"fine-tune, but method 'train_hard' runs a hard fine-tune"),
        (base + ["--method-policy", f"train_hard={moved}"], "holds the policy of level 'car_launch'"),
        (base, f"--policy-dir {bc}: level 'grasp_easy': "
               f"{str(bc / '24' / 'policies' / 'worlds_l_grasp_easy.pkl')!r} is a base policy, but method "
               f"'train_hard' runs a hard fine-tune"),
    ]
    for argv, words in cases:
        assert _cli_status(main, argv) == 2, argv
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and err.startswith("softrtc kinetix eval: error: "), err
        assert words in err, err
    assert not (tmp_path / "out").exists()
