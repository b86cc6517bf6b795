"""The chapter-P network in PyTorch: equal to the JAX FlowPolicy given the same weights ([PT-7], [P-1]..[P-6])."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")
jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")

from softrtc.jax.policy import FlowPolicy as JaxFlowPolicy  # noqa: E402
from softrtc.jax.policy import PolicyConfig as JaxPolicyConfig  # noqa: E402
from softrtc.torch import sampler, weights  # noqa: E402
from softrtc.torch.policy import FlowPolicy, PolicyConfig  # noqa: E402

# Angles of the time embedding reach 1571 rad, where a float32 step is 1.2e-4 ([P-3]); the two frameworks'
# sin, cos, pow and matrix products round differently, so outputs of order 1 agree to about 1e-5.
RTOL = ATOL = 1e-4


def _random_jax_policy(seed: int, H=8, C=16, obs_dim=5, action_dim=3, layers=2):
    """A small JAX FlowPolicy with every parameter random (the adaLN layers too, which start at zero)."""
    cfg = JaxPolicyConfig(channel_dim=C, channel_hidden_dim=24, token_hidden_dim=6, num_layers=layers,
                          action_chunk_size=H)
    pol = JaxFlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=cfg, rngs=nnx.Rngs(seed))
    rng = np.random.default_rng(seed)

    def rand(tree):
        return {k: rand(v) if isinstance(v, dict) else (0.4 * rng.standard_normal(np.shape(v))).astype(np.float32)
                for k, v in tree.items()}

    state = rand(nnx.state(pol).to_pure_dict())
    nnx.update(pol, state)
    torch_cfg = PolicyConfig(horizon=H, width=C, channel_hidden=24, token_hidden=6, num_layers=layers)
    return pol, state, torch_cfg


def _copy(state, cfg, obs_dim=5, action_dim=3) -> FlowPolicy:
    model = FlowPolicy(obs_dim, action_dim, cfg, generator=torch.Generator().manual_seed(0))
    model.load_chapter_p_state(state)
    return model.eval()


def test_adaln_equals_the_jax_flow_policy_given_its_weights():
    """[PT-7], [P-2]..[P-5], [P-9] Two implementations, one set of weights: a random JAX FlowPolicy's parameter
    tree copied into the PyTorch adaln network gives the JAX velocity within float32 rounding (rtol = atol =
    1e-4 on outputs of order 1) for per-token times [B, H], shared times [B], times 0 and 1, and through the
    precomputed-conditioning path; the output depends on the time (the check is not vacuous)."""
    jp, state, cfg = _random_jax_policy(3)
    model = _copy(state, cfg)
    rng = np.random.default_rng(7)
    obs = rng.standard_normal((6, 5)).astype(np.float32)
    x = rng.standard_normal((6, 8, 3)).astype(np.float32)
    t = rng.random((6, 8)).astype(np.float32)
    t[0] = 0.0
    t[1] = 1.0
    with torch.no_grad():
        for tt in (t, t[:, 2]):
            want = np.asarray(jp(obs, x, tt))
            got = model(torch.as_tensor(obs), torch.as_tensor(x), torch.as_tensor(tt)).numpy()
            np.testing.assert_allclose(got, want, rtol=RTOL, atol=ATOL)
        cond = model.time_conditioning(torch.as_tensor(t))
        fast = model.apply_conditioned(model.encode_obs(torch.as_tensor(obs)), torch.as_tensor(x), cond).numpy()
    np.testing.assert_allclose(fast, np.asarray(jp(obs, x, t)), rtol=RTOL, atol=ATOL)
    assert np.abs(np.asarray(jp(obs, x, t)) - np.asarray(jp(obs, x, 1.0 - t))).max() > 0.1
    # the JAX time conditioning's leaves, concatenated in the documented order, are the PyTorch one's
    jc = jp.time_conditioning(t)
    leaves = [np.asarray(m[k]) for m in jc["mlp_stack"] for k in ("adaln_1", "adaln_2")]
    leaves.append(np.asarray(jc["final_adaln"]))
    np.testing.assert_allclose(cond.numpy(), np.concatenate(leaves, -1), rtol=RTOL, atol=ATOL)


def test_adaln_equals_the_shipped_jax_arm_policy():
    """[PT-7], [PT-9], [A-17] The shipped JAX Train Soft arm checkpoint, copied into the PyTorch network of
    ``softrtc.torch.arm.ARM_POLICY`` (the JAX arm policy's sizes), gives its velocity within float32 rounding
    on random inputs, and the RTC sampler on the copy gives the JAX RTC chunk for the same noise."""
    pytest.importorskip("pymunk")
    from softrtc.arm.checkpoints import CKPT_FILES, default_checkpoint_dir, load_arm_checkpoint
    from softrtc.arm.policy_config import ArmPolicyConfig
    from softrtc.jax import sampler as jsampler
    from softrtc.torch.arm import ARM_POLICY

    acfg = ArmPolicyConfig()
    assert (ARM_POLICY.horizon, ARM_POLICY.width, ARM_POLICY.channel_hidden, ARM_POLICY.token_hidden,
            ARM_POLICY.num_layers, ARM_POLICY.architecture) == (acfg.horizon, acfg.channel_dim,
                                                                acfg.channel_hidden_dim, acfg.token_hidden_dim,
                                                                acfg.num_layers, "adaln")
    jp = load_arm_checkpoint(default_checkpoint_dir() / CKPT_FILES["train_soft"]).model
    model = _copy(nnx.state(jp).to_pure_dict(), ARM_POLICY, jp.obs_dim, jp.action_dim)
    rng = np.random.default_rng(11)
    obs = rng.standard_normal((5, jp.obs_dim)).astype(np.float32)
    x = rng.standard_normal((5, 10, 4)).astype(np.float32)
    t = rng.random((5, 10)).astype(np.float32)
    with torch.no_grad():
        got = model(torch.as_tensor(obs), torch.as_tensor(x), torch.as_tensor(t)).numpy()
    np.testing.assert_allclose(got, np.asarray(jp(obs, x, t)), rtol=RTOL, atol=ATOL)
    w = weights.soft_weights(10, 3, None, 5, dtype=torch.float32)
    prior = rng.standard_normal((5, 10, 4)).astype(np.float32)
    want = np.asarray(jsampler.rtc_sample(lambda o, xx, tt: jp(o, xx, tt), obs, x, prior, np.asarray(w), 5))
    with torch.no_grad():
        chunk = sampler.rtc_sample_conditioned(model, torch.as_tensor(obs), torch.as_tensor(x),
                                               torch.as_tensor(prior), w, 5).numpy()
    np.testing.assert_allclose(chunk, want, rtol=RTOL, atol=ATOL)


def test_adaln_initialisation_is_adaln_zero_and_lecun_normal():
    """[PT-7], [P-6] Fresh adaln network: every adaln_1, adaln_2 and final_adaln kernel and bias is zero, so
    the velocity does not depend on t; the other kernels are truncated normals at two standard deviations
    with variance 1 / fan_in (flax's LeCun normal), biases zero; parameters are a function of the seed."""
    cfg = PolicyConfig(horizon=8, width=64, channel_hidden=128, token_hidden=16, num_layers=2)
    model = FlowPolicy(40, 4, cfg, generator=torch.Generator().manual_seed(2))
    for name, p in model.state_dict().items():
        if "adaln" in name or name.endswith("bias"):
            assert torch.count_nonzero(p) == 0, name
        else:
            fan_in = p.shape[1]
            std = math.sqrt(1.0 / fan_in)
            assert float(p.abs().max()) <= 2 * std / 0.87962566103423978 + 1e-6, name
            if p.numel() >= 2000:  # enough entries for the variance to be within 10 %
                assert abs(float(p.var()) / std ** 2 - 1.0) < 0.1, name
    g = torch.Generator().manual_seed(5)
    obs, x = torch.randn(3, 40, generator=g), torch.randn(3, 8, 4, generator=g)
    with torch.no_grad():
        torch.testing.assert_close(model(obs, x, torch.zeros(3, 8)), model(obs, x, torch.rand(3, 8, generator=g)),
                                   rtol=0, atol=0)
    again = FlowPolicy(40, 4, cfg, generator=torch.Generator().manual_seed(2))
    assert all(torch.equal(p, q) for p, q in zip(model.parameters(), again.parameters()))
    assert model.cond_features == 2 * 6 * 64 + 2 * 64


@pytest.mark.parametrize("call, match", [
    (lambda: PolicyConfig(architecture="film"), "architecture must be one of"),
    (lambda: PolicyConfig(width=16, time_dim=8), r"time_dim must be None or width=16"),
    (lambda: PolicyConfig(width=15), "width must be even"),
    (lambda: PolicyConfig(num_layers=0), r"num_layers must be an integer in \[1, 1024\]"),
    (lambda: PolicyConfig(architecture="token_input", time_dim=7), "time_dim must be even"),
    (lambda: FlowPolicy(5, 3, PolicyConfig(horizon=8, width=16), generator=torch.Generator()).apply_conditioned(
        torch.zeros(2, 16), torch.zeros(2, 8, 3), torch.zeros(2, 8, 16)), r"cond must have shape \[b, h, 224\]"),
    (lambda: FlowPolicy(5, 3, PolicyConfig(horizon=8, width=16, architecture="token_input"),
                        generator=torch.Generator()).load_chapter_p_state({}), "needs architecture 'adaln'"),
    (lambda: FlowPolicy(5, 3, PolicyConfig(horizon=8, width=16), generator=torch.Generator()).load_chapter_p_state(
        {"in_proj": {}}), "state must be the pure dict"),
    (lambda: FlowPolicy(5, 3, PolicyConfig(horizon=8, width=16, channel_hidden=24, token_hidden=6),
                        generator=torch.Generator()).load_chapter_p_state(_random_jax_policy(0, C=8)[1]),
     "does not fit a layer"),
])
def test_invalid_policy_arguments_raise_value_errors(call, match):
    """[PT-2], [PT-7], [N-7] An unknown architecture, a time embedding size other than the width for adaln,
    an odd width, zero adaln blocks, an odd token-input embedding, a conditioning of the wrong size, and a
    parameter tree of another network or other sizes raise ValueError naming the argument."""
    with pytest.raises(ValueError, match=match):
        call()
