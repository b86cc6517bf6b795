"""The time-consistent solver step in softrtc.torch ([S-9]..[S-14]) against the reference, closed forms and
bitwise identities; both time conventions ([V-2], [V-3])."""

from __future__ import annotations

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from softrtc.reference import methods as rmeth, sampler as rsamp, velocity as rvel, weights as rw  # noqa: E402
from softrtc.torch import methods, sampler, velocity  # noqa: E402
from softrtc.torch.policy import FlowPolicy, PolicyConfig  # noqa: E402

F64 = torch.float64


def _case(seed, B=3, H=8, A=2, O=3):
    ref = rvel.ReferenceVelocityField.init(seed, H, A, O, hidden=16)
    rng = np.random.default_rng(seed)
    return ref, velocity.ReferenceVelocityField(ref.to_dict(), dtype=F64), rng.normal(size=(B, O)), \
        rng.normal(size=(B, H, A)), rng.normal(size=(B, H, A))


@pytest.mark.parametrize("T", [1, 4, 7])
def test_consistent_equals_reference_both_conventions(T):
    """S-10, V-2, V-3: per example (mixed delays) the consistent step equals the reference's, in data_at_1 and
    natively in noise_at_1 with u = -v(1 - t')."""
    ref, field, obs, noise, prior = _case(T)
    w = np.stack([rw.soft_weights(8, d, rw.SoftWindow(), 4) for d in (1, 2, 3)])
    o, nz, y, wt = torch.tensor(obs), torch.tensor(noise), torch.tensor(prior), torch.tensor(w)
    flipped = lambda ob, xx, tt: -field(ob, xx, 1.0 - tt)  # noqa: E731
    got = sampler.rtc_sample(field, o, nz, y, wt, T, step="consistent")
    got_f = sampler.rtc_sample(flipped, o, nz, y, wt, T, step="consistent", convention="noise_at_1")
    for i in range(3):
        want = rsamp.rtc_sample(ref, obs[i], noise[i], prior[i], w[i], T, step="consistent")
        np.testing.assert_allclose(got[i].numpy(), want, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(got_f[i].numpy(), want, rtol=1e-10, atol=1e-10)


def test_oracle_field_and_worked_example():
    """S-9, S-10, S-13: oracle field v = A - eps with Y = A: consistent returns A on window and free tokens;
    worked example [5.25, 3.0, 1.0] against Algorithm 1's [5.25, 5.15625, 1.0]."""
    rng = np.random.default_rng(0)
    A, eps = torch.tensor(rng.normal(size=(2, 1, 10, 3)))
    w = torch.tensor(rw.prefix_weights(10, 2, 8, "exp", "paper"))
    x = sampler.rtc_sample(lambda o, xx, t: (A - eps).expand_as(xx), torch.zeros(1, 1), eps, A, w, 6,
                           step="consistent")
    free = w < 1
    np.testing.assert_allclose(x[0][free].numpy(), A[0][free].numpy(), rtol=0, atol=1e-13)
    one = lambda o, xx, t: torch.ones_like(xx)  # noqa: E731
    y, ww, x0 = torch.full((1, 3, 1), 5.0), torch.tensor([1.0, 0.5, 0.0]), torch.zeros(1, 3, 1)
    assert sampler.rtc_sample(one, torch.zeros(1, 1), x0, y, ww, 4)[0, :, 0].tolist() == [5.25, 5.15625, 1.0]
    assert sampler.rtc_sample(one, torch.zeros(1, 1), x0, y, ww, 4, step="consistent")[0, :, 0].tolist() == \
        [5.25, 3.0, 1.0]


def _policy():
    cfg = PolicyConfig(horizon=10, width=16, channel_hidden=24, token_hidden=6, num_layers=1)
    model = FlowPolicy(5, 3, cfg, generator=torch.Generator().manual_seed(0)).eval()
    with torch.no_grad():  # random modulation, so that the time matters ([P-6] makes a fresh network ignore it)
        g = torch.Generator().manual_seed(1)
        for name, p in model.named_parameters():
            if "adaln" in name:
                p.copy_(0.1 * torch.randn(p.shape, generator=g))
    return model


def test_conditioned_path_and_bitwise_identities():
    """S-10, S-11, PT-6: the conditioned consistent sampler equals the straightforward one within float32
    rounding; for hard and zero weights the consistent step is bitwise Algorithm 1 on both paths, and zero
    weights bitwise the naive sampler."""
    model = _policy()
    rng = np.random.default_rng(3)
    obs = torch.tensor(rng.normal(size=(2, 5)), dtype=torch.float32)
    x, y = (torch.tensor(rng.normal(size=(2, 10, 3)), dtype=torch.float32) for _ in range(2))
    with torch.no_grad():
        w = torch.tensor(rw.soft_weights(10, 2, rw.SoftWindow(), 5), dtype=torch.float32)
        fast = sampler.rtc_sample_conditioned(model, obs, x, y, w, 5, step="consistent")
        slow = sampler.rtc_sample(model, obs, x, y, w, 5, step="consistent")
        np.testing.assert_allclose(fast.numpy(), slow.numpy(), rtol=1e-5, atol=1e-5)
        assert (fast - sampler.rtc_sample_conditioned(model, obs, x, y, w, 5)).abs().max() > 1e-3
        for ww in (torch.tensor(rw.hard_weights(10, 3), dtype=torch.float32), torch.zeros(10)):
            for fn in (sampler.rtc_sample, sampler.rtc_sample_conditioned):
                assert torch.equal(fn(model, obs, x, y, ww, 5), fn(model, obs, x, y, ww, 5, step="consistent"))
        assert torch.equal(sampler.rtc_sample(model, obs, x, y, torch.zeros(10), 5, step="consistent"),
                           sampler.naive_sample(model, obs, x, 5))


def test_generate_chunk_and_bad_step():
    """S-10, S-14: generate_chunk runs the step for train_soft (the reference's chunk), rejects it for the
    guided methods; an unknown step is one ValueError naming step and the allowed names."""
    ref, field, obs, noise, prior = _case(5, B=1)
    o, nz, y = torch.tensor(obs), torch.tensor(noise), torch.tensor(prior)
    got = methods.generate_chunk("train_soft", field, o, nz, y, 4, 2, 5, step="consistent")
    want = rmeth.generate_chunk("train_soft", ref, obs[0], noise[0], prior[0], 4, 2, 5, step="consistent")
    np.testing.assert_allclose(got[0].numpy(), want, rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="step must be 'algorithm1' for method 'inference_soft'"):
        methods.generate_chunk("inference_soft", field, o, nz, y, 4, 2, 5, step="consistent")
    for call in (lambda: sampler.rtc_sample(field, o, nz, y, torch.zeros(8), 5, step="Consistent"),
                 lambda: methods.generate_chunk("train_hard", field, o, nz, y, 4, 2, 5, step=None)):
        with pytest.raises(ValueError, match=r"step must be one of \('algorithm1', 'consistent'\)"):
            call()
