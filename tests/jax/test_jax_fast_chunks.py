"""The fast-chunk object and the public JAX API ([B-13], [S-6], [X-2])."""

from __future__ import annotations

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

import softrtc.jax as J  # noqa: E402
from softrtc.jax import methods as JM  # noqa: E402

CFG = J.PolicyConfig(channel_dim=16, channel_hidden_dim=24, token_hidden_dim=6, num_layers=1, action_chunk_size=8)
B, O, A, H, S, T = 3, 7, 2, 8, 4, 3
TOL = dict(rtol=1e-4, atol=1e-4)  # [B-5]


@pytest.fixture(scope="module")
def policy():
    pol = J.FlowPolicy(obs_dim=O, action_dim=A, config=CFG, rngs=nnx.Rngs(0))
    # adaLN-zero makes a fresh network ignore time ([P-6]); random modulation makes every delay differ.
    rng = np.random.default_rng(0)
    for block in pol.mlp_stack:
        for lin in (block.adaln_1, block.adaln_2):
            lin.kernel[...] = jnp.asarray(0.1 * rng.standard_normal(lin.kernel.shape), jnp.float32)
    return pol


def _inputs(seed=1):
    rng = np.random.default_rng(seed)
    return (jnp.asarray(rng.standard_normal((B, O)), jnp.float32),
            jnp.asarray(rng.standard_normal((B, H, A)), jnp.float32))


def _straightforward(policy, method, obs, noise, prior, d):
    vel = policy if method.startswith("train_") else (lambda o, x, t: policy(o, x, t[:, 0]))
    return JM.generate_chunk(method, vel, obs, noise, prior, S, d, T)


@pytest.mark.parametrize("method", JM.METHODS)
def test_first_and_next_are_the_methods_chunks(policy, method):
    """B-13, X-2, S-6, B-5: first is the naive sampler and next the method's sampler at delay d, from noise
    drawn from the key; within float32 rounding of the straightforward path."""
    obs, prior = _inputs()
    key = jax.random.key(5)
    noise = jax.random.normal(key, (B, H, A))
    fast = J.FastChunks(policy, method, S, T)
    np.testing.assert_allclose(fast.first(obs, key), _straightforward(policy, "naive", obs, noise, None, 0), **TOL)
    for d in (0, 2, 4):
        want = _straightforward(policy, method, obs, noise, prior, d)
        np.testing.assert_allclose(fast.next(obs, prior, d, key), want, **TOL)
        np.testing.assert_allclose(fast.chunk(obs, noise, prior, d), want, **TOL)
    if method != "naive":  # the delay matters, so a row mix-up would show
        assert np.abs(np.asarray(fast.next(obs, prior, 0, key) - fast.next(obs, prior, 4, key))).max() > 1e-4


def test_per_entry_delays_and_keys(policy):
    """B-13, X-8, N-9: one delay per batch entry (traced or not) gives each entry its own delay's chunk; one
    key per entry draws each entry's own noise."""
    obs, prior = _inputs(2)
    fast = J.FastChunks(policy, "train_soft", S, T)
    keys = jax.random.split(jax.random.key(3), B)
    ds = np.array([0, 3, 1])
    batched = np.asarray(fast.next(obs, prior, ds, keys))
    traced = np.asarray(jax.jit(lambda d: fast.next(obs, prior, d, keys))(jnp.asarray(ds, jnp.int32)))
    np.testing.assert_allclose(traced, batched, **TOL)
    for e, d in enumerate(ds):
        one = fast.next(obs[e:e + 1], prior[e:e + 1], int(d), keys[e:e + 1])
        np.testing.assert_allclose(batched[e], np.asarray(one)[0], **TOL)
        noise = jax.random.normal(keys[e], (H, A))[None]
        np.testing.assert_allclose(batched[e], np.asarray(fast.chunk(obs[e:e + 1], noise, prior[e:e + 1], int(d)))[0],
                                   **TOL)


def test_one_compilation_serves_every_delay_and_object(policy):
    """B-13, B-7: host delays pick a row of fixed shape; a second object of the same kind compiles nothing."""
    obs, prior = _inputs(3)
    noise = prior + 1.0
    fast = J.FastChunks(policy, "train_hard", S, T)
    before = fast.compilations()
    for d in range(5):
        fast.chunk(obs, noise, prior, d)
    again = J.FastChunks(policy, "train_hard", S, T)
    again.chunk(obs, noise, prior, 2)
    assert fast.compilations() - before <= 1 and again.compilations() == fast.compilations()


def test_weights_replace_the_methods_table(policy):
    """B-13, KE-3: weights= gives the sampler of the method with another table (here train_hard's sampler
    with train_soft's weights equals train_soft)."""
    obs, prior = _inputs(4)
    key = jax.random.key(9)
    table = JM.method_weight_table("train_soft", H, S)
    a = J.FastChunks(policy, "train_hard", S, T, weights=table).next(obs, prior, 3, key)
    b = J.FastChunks(policy, "train_soft", S, T).next(obs, prior, 3, key)
    np.testing.assert_allclose(a, b, **TOL)


def test_arguments_are_checked_at_construction_and_per_call(policy):
    """B-13, N-7, X-1, X-2: every argument is checked, naming it."""
    with pytest.raises(ValueError, match="^policy must be"):
        J.FastChunks(object(), "naive", S, T)
    with pytest.raises(ValueError, match="^method must be one of"):
        J.FastChunks(policy, "fancy", S, T)
    with pytest.raises(ValueError, match=r"^execute_horizon must be an integer in \[1, 8\]"):
        J.FastChunks(policy, "naive", 9, T)
    with pytest.raises(ValueError, match="^num_steps must be an integer"):
        J.FastChunks(policy, "naive", S, 0)
    with pytest.raises(ValueError, match=r"^guided_tokens must be an integer in \[1, 7\]"):
        J.FastChunks(policy, "inference_soft", S, T, guided_tokens=8)
    with pytest.raises(ValueError, match=r"^weights must have shape \[5, 8\]"):
        J.FastChunks(policy, "train_hard", S, T, weights=np.zeros((4, 8)))
    fast = J.FastChunks(policy, "inference_hard", S, T)
    obs, prior = _inputs(5)
    with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 4\]"):
        fast.next(obs, prior, 5, jax.random.key(0))
    with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 0\]"):
        fast.chunk(obs, prior, None, 1)
    with pytest.raises(ValueError, match="^key must be"):
        fast.first(obs, 0)
    with pytest.raises(ValueError, match=r"^key must be one typed PRNG key or one per batch entry"):
        fast.first(obs, jax.random.split(jax.random.key(0), B + 1))
    assert fast.next(obs, prior, 4, jax.random.key(0)).shape == (B, H, A)


def test_public_api_names_and_protocols(policy):
    """B-13, S-2, P-11: softrtc.jax exports what users call; the flow policy is a velocity field and a
    conditioned model, a plain function only a velocity field."""
    for name in ("FastChunks", "FlowPolicy", "PolicyConfig", "shift_prior", "execute_chunks", "generate_chunk",
                 "TrainConfig", "train", "VelocityField", "ConditionedModel", "save_checkpoint", "load_pure_dict"):
        assert name in J.__all__ and getattr(J, name) is not None
    with pytest.raises(AttributeError):
        J.no_such_name  # noqa: B018
    assert isinstance(policy, J.VelocityField) and isinstance(policy, J.ConditionedModel)

    def field(obs, x, t):
        return -x

    assert isinstance(field, J.VelocityField) and not isinstance(field, J.ConditionedModel)
