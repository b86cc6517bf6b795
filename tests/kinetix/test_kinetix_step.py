"""The time-consistent solver step in the Kinetix evaluation ([KE-13], [S-10], [S-11], [S-14]).

Method strings with the ``:consistent`` suffix, their labels and rows; the rollout's sampler against the
NumPy reference's consistent sampler on the same field and noise; and closed-loop rollouts of the
training-time family, where weights in {0, 1} give Algorithm 1's episodes bit for bit. The rollout uses
the configuration of ``test_kinetix_harness.py`` (policy size, 10 envs, 24 steps), so within one test
process the two modules share one compiled program.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("jax")
pytest.importorskip("kinetix")

import flax.nnx as nnx  # noqa: E402
import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402

from softrtc.jax.params import load_pure_dict, state_pure_dict  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.kinetix.methods import MethodSpec, parse_method, rollout_weight_table  # noqa: E402
from softrtc.kinetix.protocol import EvalConfig  # noqa: E402
from softrtc.kinetix.results import main_table, summarize  # noqa: E402
from softrtc.kinetix.rollout import episode_keys, make_rollout, rollout_sampler  # noqa: E402
from softrtc.reference import methods as ref_methods  # noqa: E402
from softrtc.reference import sampler as ref_sampler  # noqa: E402
from softrtc.reference.weights import SoftWindow  # noqa: E402
from tests.conftest import SHARED_LEVELS_REASON  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
LEVELS_DIR = (ROOT.parent / "shared" / "kinetix-levels").resolve()
needs_levels = pytest.mark.skipif(not LEVELS_DIR.is_dir(), reason=SHARED_LEVELS_REASON)

S, T = 4, 5
EPISODES = 2
DELAYS = (0, 1, 2, 3, 4)
STEPS = 24
SMALL = PolicyConfig(channel_dim=16, channel_hidden_dim=16, token_hidden_dim=8, num_layers=1, action_chunk_size=8)


def _policy(obs_dim: int, action_dim: int) -> FlowPolicy:
    """A small policy whose adaLN gates are opened by random kernels, so tokens interact ([P-6])."""
    pol = FlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=SMALL, rngs=nnx.Rngs(0))
    rng = np.random.default_rng(0)
    pure = jax.tree_util.tree_map_with_path(
        lambda path, a: np.asarray(a) + 0.3 * rng.standard_normal(np.shape(a)).astype(np.float32)
        if "adaln" in jax.tree_util.keystr(path) else np.asarray(a), state_pure_dict(pol))
    load_pure_dict(pol, pure)
    return pol


# ----------------------------------------------------------------------------- method strings


@pytest.mark.parametrize("text,method,step,display", [
    ("train_soft:delay_scaled:2:consistent", "train_soft", "consistent",
     "Train Soft RTC (delay_scaled:2, consistent step)"),
    ("train_soft:zeros:consistent", "train_soft", "consistent", "Train Soft RTC (zeros, consistent step)"),
    ("train_soft:consistent", "train_soft", "consistent", "Train Soft RTC (consistent step)"),
    ("train_soft:offset:1:8:zeros:consistent", "train_soft", "consistent",
     "Train Soft RTC (offset:1:8:zeros, consistent step)"),
    ("train_hard:consistent", "train_hard", "consistent", "Train Hard RTC (consistent step)"),
    ("naive:consistent", "naive", "consistent", "Base Naive (consistent step)"),
    ("train_soft:delay_scaled:1", "train_soft", "algorithm1", "Train Soft RTC (delay_scaled:1)"),
])
def test_parse_label_round_trip(text, method, step, display):
    """KE-2, KE-13: the suffix selects the step; the label keeps it, parses back to the same spec, and the
    display name says "consistent step"."""
    spec = parse_method(text)
    assert (spec.method, spec.step, spec.label, spec.display) == (method, step, text, display)
    assert parse_method(spec.label) == spec
    # A spec built without a label gets the shortest method string of its method and step.
    bare = MethodSpec(method, step=step)
    assert bare.label == method + (":consistent" if step == "consistent" else "")
    assert parse_method(bare.label) == bare


def test_suffix_window_is_the_plain_strings():
    """KE-13: ':consistent' changes the step only; the window is the one of the string without it."""
    for plain in ("train_soft", "train_soft:zeros", "train_soft:delay_scaled:2:5", "train_soft:hard",
                  "train_soft:fixed:3:zeros"):
        a, b = parse_method(plain), parse_method(plain + ":consistent")
        assert b.window == a.window and (a.step, b.step) == ("algorithm1", "consistent")
        np.testing.assert_array_equal(rollout_weight_table(a, 8, S), rollout_weight_table(b, 8, S))
    assert parse_method("train_soft:zeros:consistent").window == SoftWindow(overflow="zeros")


@pytest.mark.parametrize("bad,match", [
    ("inference_soft:consistent", "guided method 'inference_soft' has no blended step"),
    ("inference_hard:consistent", "guided method 'inference_hard' has no blended step"),
    ("train_soft:consistent:zeros", r"':zeros', then optionally ':consistent'"),
    ("train_soft:consistent:consistent", "not a valid soft window"),
    ("train_hard:zeros:consistent", "takes no window parameters"),
    ("naive:Consistent", "takes no window parameters"),
])
def test_bad_suffixes_refused(bad, match):
    """KE-13, S-14: the guided methods refuse the step; the suffix comes last, after ':zeros'."""
    with pytest.raises(ValueError, match=match):
        parse_method(bad)


def test_spec_step_checked():
    """KE-13, S-10, S-14: MethodSpec.step is one of the two steps, and not "consistent" for the guided methods;
    a label that reads as a method string must carry the spec's own step."""
    with pytest.raises(ValueError, match=r"step must be one of \('algorithm1', 'consistent'\)"):
        MethodSpec("train_soft", step="exact")
    with pytest.raises(ValueError, match="step must be 'algorithm1' for method 'inference_soft'"):
        MethodSpec("inference_soft", step="consistent")
    with pytest.raises(ValueError, match="label 'train_soft:consistent' parses as"):
        MethodSpec("train_soft", label="train_soft:consistent")
    with pytest.raises(ValueError, match="label 'train_hard' parses as"):
        MethodSpec("train_hard", label="train_hard", step="consistent")
    assert MethodSpec("train_soft", label="my row", step="consistent").display == "my row"


def test_eval_config_and_table_rows_keep_the_suffix():
    """KE-2, KE-8, KE-13: the two steps of one method are two rows, whose names keep the suffix; two spellings
    of one method, window and step are one."""
    cfg = EvalConfig(levels=("grasp_easy",), methods=("train_soft", "train_soft:consistent", "train_hard",
                                                      "train_hard:consistent"))
    assert [m.label for m in cfg.methods] == ["train_soft", "train_soft:consistent", "train_hard",
                                              "train_hard:consistent"]
    with pytest.raises(ValueError, match="same method and window, with the same solver step"):
        EvalConfig(levels=("grasp_easy",), methods=("train_soft:consistent", "train_soft:delay_scaled:2:5:consistent"))
    rows = [{"method": m, "level": "grasp_easy", "delay": d, "episode": 0, "return": r, "solved": True, "length": 5,
             "delta": 0.1, "jerk": 0.2} for m, r in (("train_soft", 1.0), ("train_soft:consistent", 2.0))
            for d in (0, 3)]
    summary = summarize(rows, bootstrap_resamples=10)
    assert {r["method"] for r in summary["pooled"]} == {"train_soft", "train_soft:consistent"}
    table = main_table(summary)
    assert "| Train Soft RTC | 1.000" in table and "| Train Soft RTC (consistent step) | 2.000" in table


# ----------------------------------------------------------------------------- the rollout's sampler


def test_rollout_sampler_matches_reference():
    """KE-13, S-10, KE-3: one chunk of the rollout's sampler (traced step flag, per-env delays and keys) equals
    the NumPy reference's consistent sampler on the same field, noise, prior and weights within float32
    rounding, and with the flag off Algorithm 1's; the two steps differ on window tokens."""
    O, A, B = 5, 3, 3
    pol = _policy(O, A)
    H = SMALL.action_chunk_size
    spec = parse_method("train_soft:delay_scaled:2:consistent")
    table = jnp.asarray(rollout_weight_table(spec, H, S))
    rng = np.random.default_rng(7)
    obs = rng.standard_normal((B, O)).astype(np.float32)
    prior = rng.standard_normal((B, H, A)).astype(np.float32)
    delays = np.array([1, 2, 3], np.int32)
    keys = jax.vmap(lambda e: jax.random.fold_in(jax.random.key(3), e))(jnp.arange(B, dtype=jnp.uint32))

    @jax.jit
    def request(flag):
        return rollout_sampler(pol, "rtc", S, T, table, flag)[1](obs, prior, delays, keys)

    def field(o, x, t):  # the policy as the reference's field(obs, x, t [H]) -> [H, A]
        v = pol(jnp.asarray(o[None], jnp.float32), jnp.asarray(x[None], jnp.float32), jnp.asarray(t[None], jnp.float32))
        return np.asarray(v[0], np.float64)

    noise = np.asarray(jax.vmap(lambda k: jax.random.normal(k, (H, A), jnp.float32))(keys))
    got = {step: np.asarray(request(jnp.asarray(step == "consistent"))) for step in ("algorithm1", "consistent")}
    for b, d in enumerate(delays):
        w = ref_methods.method_weights("train_soft", H, S, int(d), spec.window)
        assert ((w > 0) & (w < 1)).any()  # a soft window: the steps differ
        for step in ("algorithm1", "consistent"):
            want = ref_sampler.rtc_sample(field, obs[b].astype(np.float64), noise[b].astype(np.float64),
                                          prior[b].astype(np.float64), w, T, step=step)
            np.testing.assert_allclose(got[step][b], want, rtol=1e-4, atol=1e-4, err_msg=f"{step} d={d}")
        assert np.abs(got["consistent"][b] - got["algorithm1"][b]).max() > 1e-2
    with pytest.raises(ValueError, match="consistent must be False for the 'guided' family"):
        rollout_sampler(pol, "guided", S, T, table, True)
    with pytest.raises(ValueError, match="consistent must be a bool"):
        rollout_sampler(pol, "rtc", S, T, table, 1)


# ----------------------------------------------------------------------------- closed-loop rollouts


@pytest.fixture(scope="module")
def outs():
    from softrtc.kinetix import env as kenv

    task = kenv.make_env("grasp_easy", LEVELS_DIR)
    pol = _policy(task.obs_dim, task.action_dim)
    ro = make_rollout(task, pol, "rtc", EPISODES * len(DELAYS), episode_steps=STEPS)
    keys = jnp.tile(episode_keys(0, "grasp_easy", EPISODES), len(DELAYS))
    delays = np.repeat(np.asarray(DELAYS), EPISODES)
    methods = ("naive", "naive:consistent", "train_hard", "train_hard:consistent", "train_soft:hard:consistent",
               "train_soft", "train_soft:consistent")
    return {"delays": delays, **{m: ro(pol, parse_method(m), "grasp_easy", keys, delays) for m in methods}}


@pytest.mark.slow
@needs_levels
def test_consistent_rows_with_weights_0_1_are_algorithm1(outs):
    """S-11, KE-13: with weights in {0, 1} the consistent rows are Algorithm 1's bit for bit in closed loop:
    train_soft:hard and train_hard with either step equal train_hard, naive:consistent equals naive."""
    assert np.array_equal(rollout_weight_table(parse_method("train_soft:hard"), 8, S),
                          rollout_weight_table(parse_method("train_hard"), 8, S))
    for m, ref in (("train_soft:hard:consistent", "train_hard"), ("train_hard:consistent", "train_hard"),
                   ("naive:consistent", "naive")):
        for k in ("actions", "chunks", "return", "length", "solved"):
            np.testing.assert_array_equal(outs[m][k], outs[ref][k], err_msg=f"{m} {k}")
    assert not np.array_equal(outs["train_hard"]["actions"], outs["naive"]["actions"])  # not vacuous


@pytest.mark.slow
@needs_levels
def test_consistent_soft_row_differs_only_where_windows_are(outs):
    """S-7, S-10, S-11, X-2, KE-13: train_soft:consistent is naive bit for bit at d = 0 (w = 0) and in every
    episode's first chunk; at a delay whose weights have window tokens (0 < w < 1) it is another closed loop
    than train_soft's Algorithm 1, at a delay whose weights lie in {0, 1} (d = 4 here: the window ends at
    h_max = 5 and adds no token with 0 < w < 1, [W-7]) the same one bit for bit."""
    delays, soft, cons = outs["delays"], outs["train_soft"], outs["train_soft:consistent"]
    d0 = delays == 0
    np.testing.assert_array_equal(cons["actions"][d0], outs["naive"]["actions"][d0])
    np.testing.assert_array_equal(cons["chunks"][:, 0], soft["chunks"][:, 0])
    table = rollout_weight_table(parse_method("train_soft"), 8, S)
    windowed = [d for d in DELAYS if ((table[d] > 0) & (table[d] < 1)).any()]
    assert windowed == [1, 2, 3]  # lam = 2, h_max = 5 at H = 8, s = 4
    for d in DELAYS:
        if d in windowed:
            # Chunk 1 is made from the same observation and prior by both rows; window tokens differ.
            assert np.abs(cons["chunks"][delays == d, 1] - soft["chunks"][delays == d, 1]).max() > 1e-2, d
        else:
            np.testing.assert_array_equal(cons["actions"][delays == d], soft["actions"][delays == d])
            np.testing.assert_array_equal(cons["chunks"][delays == d], soft["chunks"][delays == d])
