"""softrtc.torch as a training library: dtypes, autograd, torch.compile, generators, checks ([PT-1]..[PT-7])."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from softrtc.reference import weights as rw  # noqa: E402
from softrtc.torch import (corruption, delays, guidance, loss, methods, sampler, weights)  # noqa: E402
from softrtc.torch.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.torch.training import RTCObjective  # noqa: E402

SMALL = PolicyConfig(horizon=8, width=16, channel_hidden=24, token_hidden=8, num_layers=2)  # adaln, [P-1]
SMALL_TOKEN = PolicyConfig(horizon=8, width=16, channel_hidden=24, token_hidden=8, num_layers=2, time_dim=8,
                           architecture="token_input")
ARCHS = ("adaln", "token_input")


def _policy(seed=0, dtype=None, architecture="adaln"):
    """A small policy; the adaln one with random modulation layers (adaLN-zero would make it ignore time)."""
    cfg = SMALL if architecture == "adaln" else SMALL_TOKEN
    model = FlowPolicy(5, 3, cfg, generator=torch.Generator().manual_seed(seed), dtype=dtype)
    if architecture == "adaln":
        g = torch.Generator().manual_seed(1000 + seed)
        with torch.no_grad():
            for name, p in model.named_parameters():
                if "adaln" in name:
                    p.copy_(0.3 * torch.randn(p.shape, generator=g, dtype=p.dtype))
    return model


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32, torch.bfloat16])
def test_dtype_and_device_follow_the_inputs(dtype):
    """[PT-1] Results keep the inputs' dtype and device: corruption, loss, weights built with dtype=, the
    shifted prior and the RTC sampler; nothing is converted to float32 behind the caller's back."""
    g = torch.Generator().manual_seed(1)
    a = torch.randn(4, 8, 3, generator=g).to(dtype)
    n = torch.randn(4, 8, 3, generator=g).to(dtype)
    w = weights.soft_weights(8, torch.tensor([0, 1, 2, 3]), None, 4, dtype=dtype)
    assert w.dtype == dtype and w.device == a.device
    x, t = corruption.corrupt(a, n, w, torch.rand(4, generator=g).to(dtype))
    assert x.dtype == dtype and t.dtype == dtype and x.device == a.device
    assert loss.loss(x, a, n, w).dtype == dtype
    fn = lambda o, xx, tt: xx * tt[..., None]  # noqa: E731
    out = sampler.rtc_sample(fn, torch.zeros(4, 1, dtype=dtype), n, a, w, 3)
    assert out.dtype == dtype
    # examples 1..3 have d >= 1: token 0 is clamped (x~ = Y, t = 1), so each step gives Y + Y / T
    torch.testing.assert_close(out[1:, :1].double(), a[1:, :1].double() * (1.0 + 1.0 / 3),
                               rtol=1e-2 if dtype == torch.bfloat16 else 1e-6, atol=0)


def test_loss_gradient_flows_only_through_free_tokens():
    """[PT-1], [L-2] The masked loss is differentiable: the gradient in the prediction is
    2 (1 - w_j) (v - (A - eps)) / (sum (1 - w) + eta) / B, zero on clamped tokens, and a policy's
    parameters receive gradients through a training step."""
    g = torch.Generator().manual_seed(2)
    a, n, p = (torch.randn(2, 8, 3, generator=g, dtype=torch.float64) for _ in range(3))
    w = weights.hard_weights(8, torch.tensor([3, 0]), dtype=torch.float64)
    p.requires_grad_(True)
    loss.batch_loss(p, a, n, w).backward()
    m = 1.0 - w
    want = 2.0 * m[..., None] * (p.detach() - (a - n)) / (m.sum(-1) + loss.ETA)[:, None, None] / 2
    torch.testing.assert_close(p.grad, want, rtol=1e-12, atol=1e-15)
    assert torch.all(p.grad[0, :3] == 0) and torch.all(p.grad[1] != 0)
    model = _policy(dtype=torch.float64)
    obj = RTCObjective("soft", 8, 4, d_max=4, dtype=torch.float64)
    b = obj.draw(a, torch.Generator().manual_seed(3))
    obj.loss(model(torch.zeros(2, 5, dtype=torch.float64), b["x"], b["times"]), a, b).backward()
    assert all(q.grad is not None and torch.isfinite(q.grad).all() for q in model.parameters())
    assert model.time_mlp[0].weight.grad.abs().sum() > 0  # the gradient reaches the time path


def test_objective_draws_come_from_the_generator_in_order():
    """[PT-4], [D-4], [C-1], [N-9] draw() takes u [B], tau [B], eps [B, H, A] from the generator in that
    order; delays are the inverse-CDF of u, weights the table rows of those delays, times w + (1 - w) tau
    (flipped (1 - w) tau'); the same seed gives the same batch; a non-generator is rejected."""
    a = torch.randn(6, 8, 2, dtype=torch.float64)
    obj = RTCObjective("soft", 8, 4, delay_dist="exponential", d_min=1, d_max=5, decay=0.5, dtype=torch.float64)
    b = obj.draw(a, torch.Generator().manual_seed(7))
    g = torch.Generator().manual_seed(7)
    u, tau = torch.rand(6, generator=g, dtype=torch.float64), torch.rand(6, generator=g, dtype=torch.float64)
    eps = torch.randn(6, 8, 2, generator=g, dtype=torch.float64)
    cdf = np.cumsum(np.exp(-0.5 * np.arange(5)) / np.exp(-0.5 * np.arange(5)).sum())
    want_d = [1 + int(np.sum(cdf[:-1] <= x)) for x in u.numpy()]
    assert b["delays"].tolist() == want_d
    torch.testing.assert_close(b["tau"], tau)
    torch.testing.assert_close(b["noise"], eps)
    for i, d in enumerate(want_d):
        np.testing.assert_allclose(b["weights"][i].numpy(), rw.soft_weights(8, d, rw.SoftWindow(), 4), atol=1e-15)
    torch.testing.assert_close(b["times"], b["weights"] + (1 - b["weights"]) * tau[:, None])
    flip = RTCObjective("soft", 8, 4, d_min=1, d_max=5, delay_dist="exponential", decay=0.5,
                        convention="noise_at_1", dtype=torch.float64).draw(a, torch.Generator().manual_seed(7))
    torch.testing.assert_close(flip["times"], (1 - b["weights"]) * tau[:, None])
    torch.testing.assert_close(flip["x"], flip["times"][..., None] * eps + (1 - flip["times"][..., None]) * a)
    again = obj.draw(a, torch.Generator().manual_seed(7))
    assert all(torch.equal(b[k], again[k]) for k in b)
    none = RTCObjective("none", 8, 4).draw(a.float(), torch.Generator().manual_seed(7))
    assert torch.all(none["delays"] == 0) and torch.all(none["weights"] == 0)
    with pytest.raises(ValueError, match="generator"):
        obj.draw(a, 7)


@pytest.mark.parametrize("architecture", ARCHS)
def test_training_step_compiles_without_graph_breaks(architecture):
    """[PT-5] prepare + model + loss compile with torch.compile(fullgraph=True) (no graph break: the value
    checks are skipped while compiling) and give the eager loss and gradients; the same holds for the
    conditioned RTC sampler; both architectures of [PT-7]."""
    torch._dynamo.reset()
    model = _policy(4, architecture=architecture)
    obj = RTCObjective("soft", 8, 4, d_max=4)
    a, obs = torch.randn(5, 8, 3), torch.randn(5, 5)
    draws = obj.draw_uniforms(a, torch.Generator().manual_seed(0))

    def step(obs, a, u, tau, eps):
        b = obj.prepare(a, u, tau, eps)
        return obj.loss(model(obs, b["x"], b["times"]), a, b)

    eager = step(obs, a, *draws)
    ge = torch.autograd.grad(eager, list(model.parameters()))
    compiled = torch.compile(step, fullgraph=True, backend="aot_eager")(obs, a, *draws)
    gc = torch.autograd.grad(compiled, list(model.parameters()))
    torch.testing.assert_close(compiled, eager, rtol=1e-5, atol=1e-6)
    for x, y in zip(gc, ge):
        torch.testing.assert_close(x, y, rtol=1e-4, atol=1e-6)
    w = obj.weights(torch.tensor([0, 2, 3, 1, 4]))
    y, n = torch.randn(5, 8, 3), torch.randn(5, 8, 3)
    with torch.no_grad():
        ref = sampler.rtc_sample_conditioned(model, obs, n, y, w, 4)
        comp = torch.compile(sampler.rtc_sample_conditioned, fullgraph=True, backend="aot_eager")(model, obs, n, y,
                                                                                                  w, 4)
    torch.testing.assert_close(comp, ref, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("architecture", ARCHS)
@pytest.mark.parametrize("convention", ["data_at_1", "noise_at_1"])
def test_conditioned_samplers_equal_straightforward(convention, architecture):
    """[PT-6], [S-7] With a precomputed conditioning (one call for all steps, or a per-delay table) the naive
    and RTC samplers give the straightforward samplers' chunks within 1e-5; per-example delays [B] index
    the table; RTC with w = 0 equals naive bitwise on the straightforward path; both architectures."""
    model = _policy(5, architecture=architecture)
    g = torch.Generator().manual_seed(1)
    obs, n, y = torch.randn(4, 5, generator=g), torch.randn(4, 8, 3, generator=g), torch.randn(4, 8, 3, generator=g)
    d = torch.tensor([0, 1, 2, 4])
    table = weights.weight_table(8, "soft", None, 4)
    with torch.no_grad():
        straight = sampler.rtc_sample(model, obs, n, y, table[d], 5, convention=convention)
        fast = sampler.rtc_sample_conditioned(model, obs, n, y, table[d], 5, convention=convention)
        ctab = sampler.conditioning_table(model, table, 5, convention)  # [D, T, 1, H, C]
        rows = [sampler.rtc_sample_conditioned(model, obs[i:i + 1], n[i:i + 1], y[i:i + 1], table[d[i]], 5,
                                               ctab[int(d[i])], convention=convention) for i in range(4)]
        torch.testing.assert_close(fast, straight, rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(torch.cat(rows), straight, rtol=1e-5, atol=1e-5)
        naive = sampler.naive_sample(model, obs, n, 5, convention=convention)
        torch.testing.assert_close(sampler.naive_sample_conditioned(model, obs, n, 5, convention=convention), naive,
                                   rtol=1e-5, atol=1e-5)
        assert torch.equal(sampler.rtc_sample(model, obs, n, y, torch.zeros(8), 5, convention=convention), naive)
        with pytest.raises(ValueError, match="leading axis"):
            sampler.rtc_sample_conditioned(model, obs, n, y, table[d], 4, ctab[0], convention=convention)


def test_generate_chunk_with_per_example_delays():
    """[PT-3], [S-6], [X-2] generate_chunk with a delay per example gives each example's chunk of the same
    method at its own delay; the first chunk (prior None) is naive and needs d = 0."""
    model = _policy(6)
    g = torch.Generator().manual_seed(2)
    obs, n, y = torch.randn(3, 5, generator=g), torch.randn(3, 8, 3, generator=g), torch.randn(3, 8, 3, generator=g)
    d = torch.tensor([0, 2, 4])
    for m in methods.METHODS:
        batch = methods.generate_chunk(m, model, obs, n, y, 4, d, 3)
        for i in range(3):
            one = methods.generate_chunk(m, model, obs[i:i + 1], n[i:i + 1], y[i:i + 1], 4, int(d[i]), 3)
            torch.testing.assert_close(batch[i:i + 1], one, rtol=1e-5, atol=1e-5)
    with pytest.raises(ValueError, match="first chunk"):
        methods.generate_chunk("train_soft", model, obs, n, None, 4, 1, 3)


def test_guidance_weight_conventions_agree():
    """[G-4], [V-1] lam(t) in spec time equals lam(t') of the flipped formula at t' = 1 - t; lam(0) = beta;
    t = 1 (spec) and t' = 0 (flipped) are outside the domain."""
    for t in (0.0, 0.1, 0.25, 0.5, 0.8, 0.95):
        assert guidance.guidance_weight(t, 5.0) == pytest.approx(guidance.guidance_weight(1.0 - t, 5.0, "noise_at_1"),
                                                                 rel=1e-12)
    assert guidance.guidance_weight(0.0, 3.0) == 3.0
    t = 0.8
    assert guidance.guidance_weight(t, 100.0) == pytest.approx((1 - t) / t * (t * t + (1 - t) ** 2) / (1 - t) ** 2)
    for bad, conv in ((1.0, "data_at_1"), (0.0, "noise_at_1")):
        with pytest.raises(ValueError, match="t must"):
            guidance.guidance_weight(bad, 5.0, conv)


@pytest.mark.parametrize("call, match", [
    (lambda: weights.soft_weights(8, True, None, 4), "d must be an integer"),
    (lambda: weights.soft_weights(8, 2.0, None, 4), "d must be an integer"),
    (lambda: weights.soft_weights(8, torch.tensor([1.0, 2.0]), None, 4), "d must hold integers"),
    (lambda: weights.soft_weights(8, torch.tensor([1, 9]), None, 4), r"d values must lie in \[0, 8\]"),
    (lambda: weights.soft_weights(4, 1, None, 2), "bound"),
    (lambda: weights.soft_weights(8, 1, None, None), "s .execute horizon"),
    (lambda: weights.prefix_weights(8, torch.tensor([3, 2]), torch.tensor([4, 1])), "e must be"),
    (lambda: corruption.corrupt(torch.zeros(2, 8, 3), torch.zeros(2, 8, 3), torch.full((2, 8), 1.5), 0.5),
     r"weights values must lie in \[0.0, 1.0\]"),
    (lambda: corruption.corrupt(torch.zeros(2, 8, 3), torch.zeros(2, 8, 3), torch.zeros(3, 8), 0.5),
     r"weights must have shape \[8\] or \[2, 8\]"),
    (lambda: corruption.corrupt(torch.zeros(8, 3), torch.zeros(8, 3), torch.zeros(8), math.nan), "tau must"),
    (lambda: corruption.corrupt(torch.zeros(8, 3), torch.full((8, 3), math.inf), torch.zeros(8), 0.5), "finite"),
    (lambda: corruption.corrupt(torch.zeros(8, 3, dtype=torch.bool), torch.zeros(8, 3), torch.zeros(8), 0.5),
     "real numeric"),
    (lambda: corruption.corrupt(torch.zeros(8, 3), torch.zeros(8, 3), torch.zeros(8), 0.5, "noise_at_0"),
     "convention must be one of"),
    (lambda: loss.batch_loss(torch.zeros(0, 8, 3), torch.zeros(0, 8, 3), torch.zeros(0, 8, 3), torch.zeros(8)),
     "B >= 1"),
    (lambda: delays.sample_delays(delays.delay_probs("uniform", 0, 3), 0, 4, None), "generator must"),
    (lambda: delays.sample_delay(torch.tensor([0.5, 0.6]), 0, 0.1), "sum to 1"),
    (lambda: sampler.rtc_sample(lambda o, x, t: x, torch.zeros(2, 1), torch.zeros(2, 8, 3), torch.zeros(2, 8, 3),
                                torch.zeros(8), 0), r"T must be an integer in \[1, 65536\]"),
    (lambda: sampler.naive_sample(lambda o, x, t: x[..., :1], torch.zeros(2, 1), torch.zeros(2, 8, 3), 2),
     "state's shape"),
    (lambda: sampler.naive_sample(lambda o, x, t: x, torch.zeros(3, 1), torch.zeros(2, 8, 3), 2), "B=2 rows"),
    (lambda: methods.method_weights("train_soft", 8, 4, 5), r"d must be an integer in \[0, 4\]"),
    (lambda: RTCObjective("soft", 8, 4, d_max=9), r"d_max must be an integer in \[0, 8\]"),
    (lambda: FlowPolicy(5, 3, SMALL, generator=None), "generator must"),
    (lambda: _policy()(torch.zeros(2, 5), torch.zeros(2, 8, 3), torch.full((2, 8), 1.5)), r"t values must lie"),
])
def test_invalid_arguments_raise_value_errors_naming_them(call, match):
    """[PT-2], [N-7] Bad arguments raise ValueError naming the argument and its range: booleans and floats
    as delays, out-of-range delays anywhere in a batch, a window too long for H, a missing s, weights above
    1 or of another batch shape, NaN/inf, boolean arrays, an unknown convention, an empty batch, a missing
    generator, an unnormalised table, T = 0, a field output of the wrong shape, obs of another batch."""
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("architecture", ARCHS)
def test_policy_shared_and_per_token_time_and_conditioning(architecture):
    """[PT-7], [PT-6] FlowPolicy: t [B] equals the same time repeated [B, H]; the velocity equals
    apply_conditioned(encode_obs(obs), x, time_conditioning(t)); token j's conditioning (input projection
    or every block's modulation) depends on t_j only (changing t_3 changes time_conditioning at token 3
    alone); the initialisation is a function of the generator's seed; both architectures."""
    model = _policy(8, architecture=architecture)
    g = torch.Generator().manual_seed(3)
    obs, x, t = torch.randn(3, 5, generator=g), torch.randn(3, 8, 3, generator=g), torch.rand(3, generator=g)
    with torch.no_grad():
        shared = model(obs, x, t)
        # The shared time's conditioning [B, 1, F] broadcasts over the tokens: its products have other
        # shapes than the per-token ones, and a CPU's kernels, chosen by shape, may round them differently.
        tol = 1e-5
        torch.testing.assert_close(model(obs, x, t[:, None].expand(3, 8)), shared, rtol=tol, atol=tol)
        tt = torch.rand(3, 8, generator=g)
        torch.testing.assert_close(model(obs, x, tt),
                                   model.apply_conditioned(model.encode_obs(obs), x, model.time_conditioning(tt)))
        t2 = tt.clone()
        t2[:, 3] = 0.5 * tt[:, 3]
        diff = (model.time_conditioning(t2) - model.time_conditioning(tt)).abs().sum(-1)
        assert torch.all(diff[:, 3] > 0) and torch.all(diff[:, [0, 1, 2, 4, 5, 6, 7]] == 0)
    same, other = (FlowPolicy(5, 3, model.config, generator=torch.Generator().manual_seed(k)) for k in (8, 9))
    first = FlowPolicy(5, 3, model.config, generator=torch.Generator().manual_seed(8))
    assert all(torch.equal(p, q) for p, q in zip(first.parameters(), same.parameters()))
    assert any(not torch.equal(p, q) for p, q in zip(first.parameters(), other.parameters()))


def test_overflow_of_results_is_an_error():
    """[N-15] [PT-2] Finite inputs whose loss or metric overflows the tensors' dtype raise ValueError naming the
    input (float32: 1e30 ** 2; float64: 1e300 ** 2), for the loss, the metrics and the bootstrap interval."""
    from softrtc.torch import metrics

    for dtype, big in ((torch.float32, 1e30), (torch.float64, 1e300)):
        z = torch.zeros(2, 2, dtype=dtype)
        p = torch.full((2, 2), big, dtype=dtype)
        cases = [("pred", lambda: loss.token_errors(p, z, z)),
                 ("pred", lambda: loss.token_errors(p, z, z, "noise_at_1")),
                 ("pred", lambda: loss.loss(p, z, z, torch.zeros(2, dtype=dtype))),
                 ("preds", lambda: loss.batch_loss(p[None], z[None], z[None], torch.zeros(1, 2, dtype=dtype))),
                 ("actions", lambda: metrics.action_delta(torch.stack([p[0], -p[0]]))),
                 ("actions", lambda: metrics.action_jerk(torch.stack([z[0], p[0], z[0]]))),
                 ("actions", lambda: metrics.boundary_jump(torch.stack([p[0], -p[0]]), torch.tensor([0, 1]))),
                 # std of (0.9 max, -0.9 max) is 0.9 max * sqrt(2), past the limit however it is summed.
                 ("values", lambda: metrics.standard_error(torch.tensor([0.9, -0.9], dtype=dtype)
                                                           * torch.finfo(dtype).max)),
                 ("values", lambda: metrics.bootstrap_interval(torch.full((2,), torch.finfo(dtype).max, dtype=dtype),
                                                               torch.tensor([[0, 1], [1, 1]])))]
        for name, call in cases:
            with pytest.raises(ValueError, match=rf"^{name} is too large in magnitude: .* overflows {dtype}"):
                call()
    # 2^60 squared, summed over two dimensions, is 2^121: exact in float32.
    x = torch.full((1, 2), 2.0**60)
    assert loss.token_errors(x, torch.zeros(1, 2), torch.zeros(1, 2)).tolist() == [2.0**121]
