"""The time-consistent solver step in JAX ([S-9]..[S-14]): straightforward, conditioned and fast paths.

Expected values: the closed forms of [S-9]/[S-10], the hand-computed worked example [S-13], the NumPy
reference within float32 rounding, and bitwise identities ([S-11]).
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

import softrtc.jax as J  # noqa: E402
from softrtc import reference as R  # noqa: E402
from softrtc.jax import methods as JM  # noqa: E402
from softrtc.jax import sampler as JS  # noqa: E402
from softrtc.jax import velocity as JF  # noqa: E402

F32 = dict(rtol=2e-5, atol=2e-5)


def _oracle(A, eps):
    return lambda obs, x, t: jnp.broadcast_to(A - eps, x.shape)


def _alpha(w, T):
    """[S-9] alpha_T = (w + 1/T)(1 - (1 - w)^T) / w (1 at w = 0)."""
    safe = np.where(w > 0, w, 1.0)
    return np.where(w > 0, (w + 1.0 / T) * (1.0 - (1.0 - w) ** T) / safe, 1.0)


@pytest.mark.parametrize("H,d,e,T,sch,par,unroll", [
    (H, d, e, T, sch, par, unroll) for (H, d, e), T, sch, par, unroll in itertools.product(
        [(8, 2, 6), (10, 0, 10), (6, 1, 4)], [1, 5, 10], ["linear", "exp"], ["rtc", "paper"], [True, False])])
def test_oracle_field(H, d, e, T, sch, par, unroll):
    """S-9, S-10: JAX consistent step returns A on window and free tokens under the oracle field with Y = A,
    Algorithm 1 returns A + (alpha_T - 1)(A - eps), within float32 rounding."""
    rng = np.random.default_rng(H + T)
    A, eps = (rng.standard_normal((2, H, 3)) * 0.5).astype(np.float32)
    w = R.weights.prefix_weights(H, d, e, sch, par)
    obs = jnp.zeros((2, 1))
    AA, EE = jnp.asarray(np.stack([A, A])), jnp.asarray(np.stack([eps, eps]))
    con = JS.rtc_sample(_oracle(AA, EE), obs, EE, AA, w, T, unroll=unroll, step="consistent")
    alg = JS.rtc_sample(_oracle(AA, EE), obs, EE, AA, w, T, unroll=unroll)
    free = w < 1
    np.testing.assert_allclose(np.asarray(con)[0][free], A[free], rtol=0, atol=1e-5)
    np.testing.assert_allclose(np.asarray(alg)[0], A + (_alpha(w, T) - 1.0)[:, None] * (A - eps), rtol=0, atol=1e-5)


def test_worked_example():
    """S-13: v = 1, T = 4, x0 = 0, Y = 5, w = [1, .5, 0] gives [5.25, 5.15625, 1.0] / [5.25, 3.0, 1.0] (exact in
    float32 too: every intermediate is a short binary fraction)."""
    one = lambda obs, x, t: jnp.ones_like(x)  # noqa: E731
    y, w = jnp.full((1, 3, 1), 5.0), jnp.array([1.0, 0.5, 0.0])
    x0, obs = jnp.zeros((1, 3, 1)), jnp.zeros((1, 1))
    assert np.asarray(JS.rtc_sample(one, obs, x0, y, w, 4))[0, :, 0].tolist() == [5.25, 5.15625, 1.0]
    assert np.asarray(JS.rtc_sample(one, obs, x0, y, w, 4, step="consistent"))[0, :, 0].tolist() == [5.25, 3.0, 1.0]


H, A, O, T = 8, 2, 3, 5
RF = R.velocity.ReferenceVelocityField.init(3, H, A, O, hidden=16)
JFIELD = JF.ReferenceVelocityField(RF.params)


def _inputs(seed, B=2):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((B, O)).astype(np.float32), rng.standard_normal((B, H, A)).astype(np.float32),
            rng.standard_normal((B, H, A)).astype(np.float32))


@pytest.mark.parametrize("seed,s,d", [(0, 4, 2), (1, 4, 4), (2, 3, 1)])
def test_matches_reference_and_conditioned(seed, s, d):
    """S-10: straightforward and conditioned JAX paths equal the reference's consistent step within float32."""
    obs, noise, prior = _inputs(seed)
    w = R.methods.method_weights("train_soft", H, s, d)
    got = JS.rtc_sample(JFIELD, obs, noise, prior, w, T, step="consistent")
    cond = JS.rtc_sample_conditioned(JFIELD, obs, noise, prior, w, T, step="consistent")
    for b in range(2):
        want = R.sampler.rtc_sample(RF, obs[b].astype(float), noise[b].astype(float), prior[b].astype(float), w, T,
                                    step="consistent")
        np.testing.assert_allclose(np.asarray(got)[b], want, **F32)
        np.testing.assert_allclose(np.asarray(cond)[b], want, **F32)
    alg = np.asarray(JS.rtc_sample(JFIELD, obs, noise, prior, w, T))
    window = (w > 0) & (w < 1)
    if window.any():  # the steps differ exactly where window tokens are ([S-11])
        assert np.abs(alg - np.asarray(got)).max() > 1e-3
    else:
        assert np.array_equal(alg, np.asarray(got))


@pytest.mark.parametrize("unroll", [True, False])
def test_hard_and_naive_bitwise(unroll):
    """S-11: hard and zero weights give bitwise Algorithm 1's chunk under the consistent step (straightforward
    and conditioned), and zero weights bitwise the naive sampler ([S-7])."""
    obs, noise, prior = _inputs(4)
    for w in (R.weights.hard_weights(H, 3), np.zeros(H)):
        for fn in (lambda **k: JS.rtc_sample(JFIELD, obs, noise, prior, w, T, unroll=unroll, **k),
                   lambda **k: JS.rtc_sample_conditioned(JFIELD, obs, noise, prior, w, T, unroll=unroll, **k)):
            assert np.array_equal(np.asarray(fn()), np.asarray(fn(step="consistent")))
    assert np.array_equal(np.asarray(JS.rtc_sample(JFIELD, obs, noise, prior, np.zeros(H), T, unroll=unroll,
                                                   step="consistent")),
                          np.asarray(JS.naive_sample(JFIELD, obs, noise, T, unroll=unroll)))


CFG = J.PolicyConfig(channel_dim=16, channel_hidden_dim=24, token_hidden_dim=6, num_layers=1, action_chunk_size=8)


@pytest.fixture(scope="module")
def policy():
    pol = J.FlowPolicy(obs_dim=7, action_dim=A, config=CFG, rngs=nnx.Rngs(0))
    rng = np.random.default_rng(0)
    for block in pol.mlp_stack:
        for lin in (block.adaln_1, block.adaln_2):
            lin.kernel[...] = jnp.asarray(0.1 * rng.standard_normal(lin.kernel.shape), jnp.float32)
    return pol


def test_fast_path(policy):
    """S-10, S-11, S-14: FastChunks with step="consistent" gives the straightforward consistent chunk (host and
    traced delays), bitwise Algorithm 1's for train_hard; guided methods reject the step."""
    rng = np.random.default_rng(1)
    obs = jnp.asarray(rng.standard_normal((3, 7)), jnp.float32)
    prior = jnp.asarray(rng.standard_normal((3, H, A)), jnp.float32)
    key = jax.random.key(5)
    noise = jax.random.normal(key, (3, H, A))
    fast = J.FastChunks(policy, "train_soft", 4, T, step="consistent")
    plain = J.FastChunks(policy, "train_soft", 4, T)
    for d in (1, 3):
        want = JM.generate_chunk("train_soft", policy, obs, noise, prior, 4, d, T, step="consistent")
        np.testing.assert_allclose(fast.next(obs, prior, d, key), want, rtol=1e-4, atol=1e-4)
        np.testing.assert_allclose(fast.next(obs, prior, jnp.full((3,), d), key), want, rtol=1e-4, atol=1e-4)
        assert np.abs(np.asarray(plain.next(obs, prior, d, key)) - np.asarray(want)).max() > 1e-4
    hard_c = J.FastChunks(policy, "train_hard", 4, T, step="consistent")
    hard_a = J.FastChunks(policy, "train_hard", 4, T)
    for d in (0, 2, 4):
        assert np.array_equal(np.asarray(hard_c.next(obs, prior, d, key)), np.asarray(hard_a.next(obs, prior, d, key)))
    assert np.array_equal(np.asarray(fast.first(obs, key)), np.asarray(plain.first(obs, key)))
    for m in ("inference_hard", "inference_soft"):
        with pytest.raises(ValueError, match="step must be 'algorithm1' for method"):
            J.FastChunks(policy, m, 4, T, step="consistent")


@pytest.mark.parametrize("bad", ["Consistent", None, 0])
def test_bad_step_rejected(bad):
    """S-10: an unknown step is one ValueError naming step and the allowed names, on every entry point."""
    obs, noise, prior = _inputs(0)
    w = np.zeros(H)
    msg = r"step must be one of \('algorithm1', 'consistent'\)"
    with pytest.raises(ValueError, match=msg):
        JS.rtc_sample(JFIELD, obs, noise, prior, w, T, step=bad)
    with pytest.raises(ValueError, match=msg):
        JS.rtc_sample_conditioned(JFIELD, obs, noise, prior, w, T, step=bad)
    with pytest.raises(ValueError, match=msg):
        JM.generate_chunk("train_soft", JFIELD, obs, noise, prior, 4, 2, T, step=bad)
    with pytest.raises(ValueError, match=msg):
        JM.generate_chunk_conditioned("train_soft", JFIELD, obs, noise, prior, 4, 2, T, step=bad)


def test_bench_row_runs_the_consistent_step():
    """B-1, B-5, S-10: the benchmark's consistent-step row agrees with the straightforward consistent sampler,
    differs from the lam = 2 row of Algorithm 1 where window tokens exist, and is held to the training-time
    target of [B-9]."""
    from softrtc.jax import bench

    cfg = bench.BenchConfig(arch="tiny", calls=2, warmup=1, batch_sizes=(2,), train_calls=0, num_steps=3)
    policy = bench.make_policy(cfg)
    agree = bench.check_agreement(cfg, policy, 2, ("train_soft_lam2_consistent",))
    assert agree["train_soft_lam2_consistent"]["ok"]
    rows = {r.name: r for r in bench.build_rows(cfg, policy, ("train_soft_lam2", "train_soft_lam2_consistent"))
            if r.path == "fast"}
    obs, noise, prior = bench.inputs(cfg, policy, 2, 1)[0]
    d = jnp.asarray(2, jnp.int32)
    a, c = (np.asarray(rows[n].call(obs, noise, prior, d)) for n in ("train_soft_lam2", "train_soft_lam2_consistent"))
    assert np.abs(a - c).max() > 1e-4
    want = JM.generate_chunk("train_soft", policy, obs, noise, prior, cfg.execute_horizon, 2, cfg.num_steps,
                             bench._window((2.0, 5)), step="consistent")
    np.testing.assert_allclose(c, want, rtol=1e-4, atol=1e-4)
    assert "train_soft_lam2_consistent" in bench.TRAIN_ROWS
