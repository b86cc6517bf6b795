"""Behaviours of ``softrtc.jax`` pinned down one each: the guidance cap on every guided path, the training
delay draw at a CDF entry, the keys and epoch order of the training loop, the first chunk of the executor
under a traced delay, and the truncation of the boundary-jump metric.

Sizes are tiny and every random quantity comes from an explicit seed or key.
"""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

from softrtc import reference as R  # noqa: E402
from softrtc.jax import executor as JX  # noqa: E402
from softrtc.jax import guidance as JG  # noqa: E402
from softrtc.jax import metrics as JMt  # noqa: E402
from softrtc.jax import velocity as JF  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.jax.training import TrainConfig, make_train_step, train  # noqa: E402

TRAJ = dict(atol=1e-4, rtol=1e-4)  # float32 sampler trajectories against the float64 reference ([N-8])

# ----------------------------------------------------------------------------- G: guidance weight cap

GH, GA, GO, GB = 8, 2, 3, 3
RF = R.velocity.ReferenceVelocityField.init(7, GH, GA, GO, hidden=16)
JFIELD = JF.ReferenceVelocityField(RF.params)


def test_guided_samplers_use_the_given_max_guidance():
    """G-4, G-5, G-7: the guided step x += (v + lam(t_k) g) / T uses lam capped at the caller's beta
    (``max_guidance``), on the straightforward path, the conditioned path and the restricted pull-back;
    beta = 1 gives the reference chunk for beta = 1, not the one of the default beta = 5."""
    rng = np.random.default_rng(5)
    obs, noise, prior = (rng.standard_normal(s) for s in ((GB, GO), (GB, GH, GA), (GB, GH, GA)))
    W = R.guidance.guidance_prefix_weights(GH, 4, 2, "soft")
    T, beta = 3, 1.0
    want = np.stack([R.guidance.guided_sample(RF, obs[i], noise[i], prior[i], W, T, max_guidance=beta)
                     for i in range(GB)])
    default = np.stack([R.guidance.guided_sample(RF, obs[i], noise[i], prior[i], W, T) for i in range(GB)])
    assert not np.allclose(want, default, **TRAJ)  # beta matters for these inputs (lam(0) = beta)
    got = {
        "straightforward": JG.guided_sample(JFIELD, obs, noise, prior, W, T, max_guidance=beta),
        "conditioned": JG.guided_sample_conditioned(JFIELD, obs, noise, prior, W, T, max_guidance=beta),
        "restricted": JG.guided_sample_conditioned(JFIELD, obs, noise, prior, W, T, max_guidance=beta,
                                                   guided_tokens=GH - 4),
    }
    for name, chunk in got.items():
        np.testing.assert_allclose(np.asarray(chunk), want, err_msg=name, **TRAJ)


# ----------------------------------------------------------------------------- T: training draws and loop

TH, TOBS, TACT = 6, 3, 2
TCFG = PolicyConfig(channel_dim=8, channel_hidden_dim=8, token_hidden_dim=4, num_layers=1, action_chunk_size=TH)


def _policy(seed: int = 0) -> FlowPolicy:
    return FlowPolicy(obs_dim=TOBS, action_dim=TACT, config=TCFG, rngs=nnx.Rngs(seed))


def _data(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((n, TOBS)).astype(np.float32),
            rng.standard_normal((n, TH, TACT)).astype(np.float32))


# Keys whose u_i = uniform(k_d, [64])_i ([T-2]) lands exactly on an entry of the CDF [0.25, 0.5, 0.75, 1]
# of a uniform table over 4 delays (asserted below, so a change of the generator fails loudly).
EDGE_KEYS = ((20229, 38, 0.5), (89970, 1, 0.75))


def test_training_delay_draw_counts_cdf_entries_equal_to_u():
    """T-2, D-3: d_i = d_min + #{k : cdf_k <= u_i}; a u_i equal to a CDF entry counts that entry, so it
    draws the next delay (the float32 CDF of a uniform table over 4 delays is exact)."""
    cfg = TrainConfig(method="hard", execute_horizon=None, delay_dist="uniform", d_min=1, d_max=4, batch_size=64)
    step = make_train_step(_policy(0), cfg)
    probs = R.delays.delay_probs("uniform", 1, 4)
    for seed, i, edge in EDGE_KEYS:
        key = jax.random.key(seed)
        u = np.asarray(jax.random.uniform(jax.random.split(key, 3)[0], (64,), jnp.float32))
        assert u[i] == edge  # the draw sits on a CDF entry
        d = np.asarray(step.draw(key, 64)["delay"])
        want = [R.delays.sample_delay(probs, 1, float(x)) for x in u]
        assert d[i] == 1 + int(round(edge * 4))  # e.g. u = 0.5 counts 0.25 and 0.5: d = d_min + 2
        assert d.tolist() == want


def test_train_step_keys_are_fold_in_of_the_step_index():
    """T-8, T-9: with an iterable of batches, step i of ``train`` is the train step with key
    fold_in(k_steps, i), k_data, k_steps = split(key): the loss history and the parameters equal
    those of the steps run by hand (bitwise, same compiled step)."""
    cfg = TrainConfig(method="soft", execute_horizon=3, d_min=0, d_max=3, batch_size=4, learning_rate=1e-2)
    obs, actions = _data(12, seed=1)
    batches = [(obs[i:i + 4], actions[i:i + 4]) for i in range(0, 12, 4)]
    key = jax.random.key(17)
    trained, losses = train(_policy(2), iter(batches), cfg, key, 3, progress=False)

    step = make_train_step(_policy(2), cfg)
    state = step.init_state()
    _, k_steps = jax.random.split(key)
    want = []
    for i, batch in enumerate(batches):
        state, metrics = step(state, batch, jax.random.fold_in(k_steps, i))
        want.append(float(metrics["loss"]))
    np.testing.assert_array_equal(losses, np.asarray(want, np.float32))
    for a, b in zip(jax.tree.leaves(nnx.state(trained, nnx.Param)), jax.tree.leaves(state.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_train_reshuffles_array_data_every_epoch():
    """T-8, T-9: array data is drawn epoch by epoch without replacement, epoch e in the order
    permutation(fold_in(k_data, e), N); steps use fold_in(k_steps, i). Two epochs of two batches
    each, replayed by hand, give the same loss history and parameters."""
    cfg = TrainConfig(method="soft", execute_horizon=3, d_min=0, d_max=3, batch_size=4, learning_rate=1e-2)
    obs, actions = _data(8, seed=3)
    key = jax.random.key(23)
    trained, losses = train(_policy(4), (obs, actions), cfg, key, 4, progress=False)

    step = make_train_step(_policy(4), cfg)
    state = step.init_state()
    k_data, k_steps = jax.random.split(key)
    orders = [np.asarray(jax.random.permutation(jax.random.fold_in(k_data, e), 8)) for e in range(2)]
    assert not np.array_equal(orders[0], orders[1])  # the epochs really are shuffled differently
    want = []
    for i in range(4):
        idx = orders[i // 2][(i % 2) * 4:(i % 2 + 1) * 4]
        state, metrics = step(state, (obs[idx], actions[idx]), jax.random.fold_in(k_steps, i))
        want.append(float(metrics["loss"]))
    np.testing.assert_array_equal(losses, np.asarray(want, np.float32))
    for a, b in zip(jax.tree.leaves(nnx.state(trained, nnx.Param)), jax.tree.leaves(state.params)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


# ----------------------------------------------------------------------------- X: executor, M: metrics


def test_first_chunk_never_takes_from_a_previous_chunk_even_with_traced_d0():
    """X-2, X-4, X-5: the first chunk executes its own tokens 0 .. s-1 whatever a traced d_0 holds (only a
    concrete d_0 can be rejected); later segments follow [X-4] as in the reference."""
    C, H, s = 4, 8, 4
    chunks = np.random.default_rng(9).standard_normal((C, H, 2))
    run = jax.jit(JX.execute_chunks, static_argnums=2)
    got = run(chunks, jnp.asarray([2, 2, 0, 1], jnp.int32), s)
    np.testing.assert_array_equal(np.asarray(got["chunk_index"][:s]), 0)
    np.testing.assert_array_equal(np.asarray(got["token_index"][:s]), np.arange(s))
    want = R.executor.execute_chunks(chunks, [0, 2, 0, 1], s)
    np.testing.assert_allclose(np.asarray(got["actions"]), want["actions"], atol=1e-6)
    np.testing.assert_array_equal(np.asarray(got["chunk_index"]), want["chunk_index"])
    np.testing.assert_array_equal(np.asarray(got["token_index"]), want["token_index"])


def test_boundary_jump_truncated_at_length_excludes_step_length():
    """M-3, M-4: with ``length`` only steps t < length count, so a chunk switch at t = length is left out;
    the result equals the reference jump of the truncated episode, concrete and under jit."""
    rng = np.random.default_rng(11)
    N, s = 16, 4
    a = rng.standard_normal((N, 2))
    a[8] += 50.0  # a large jump at the switch step t = 8: counting it would show
    ci = np.repeat(np.arange(N // s), s)  # switches at t = 4, 8, 12
    jitted = jax.jit(JMt.boundary_jump)
    for length in (8, 9, 12, 13, 16):
        want = R.metrics.boundary_jump(a[:length], ci[:length])
        np.testing.assert_allclose(float(JMt.boundary_jump(a, ci, length)), want, rtol=1e-5)
        np.testing.assert_allclose(float(jitted(a, ci, jnp.int32(length))), want, rtol=1e-5)
