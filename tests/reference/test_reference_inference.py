"""Velocity field, samplers and guidance of the reference (spec/03-inference.md)."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from softrtc.reference import guidance as G
from softrtc.reference import methods as Mth
from softrtc.reference import sampler as S
from softrtc.reference import weights as W
from softrtc.reference.executor import shift_prior
from softrtc.reference.velocity import ReferenceVelocityField, time_features


def make(seed=0, H=8, A=2, O=3):
    f = ReferenceVelocityField.init(seed, H, A, O, hidden=16)
    rng = np.random.default_rng(seed + 100)
    return f, rng.standard_normal(O), rng.standard_normal((H, A)), rng.standard_normal((H, A))


def test_field_formula():
    """F-1, F-3: the field computes the spec formula from the stored weights; init is seeded."""
    f, obs, x, _ = make()
    t = np.linspace(0, 1, 8)
    p = f.params
    h = np.tanh(x.reshape(-1) @ p["W1"] + time_features(t).reshape(-1) @ p["Wt"] + obs @ p["Wo"] + p["b1"])
    np.testing.assert_allclose(f(obs, x, t), (h @ p["W2"] + p["b2"]).reshape(8, 2))
    g = ReferenceVelocityField.init(0, 8, 2, 3, hidden=16)
    assert all(np.array_equal(f.params[k], g.params[k]) for k in f.params)
    assert not np.array_equal(f.params["W1"], ReferenceVelocityField.init(1, 8, 2, 3, hidden=16).params["W1"])
    assert np.array_equal(ReferenceVelocityField(f.params)(obs, x, t), f(obs, x, t))


def test_products_summed_in_index_order():
    """F-4: the field and its VJP are, bit for bit, the products summed over the vector's index in order
    (written out here with Python floats), and vecmat checks its arguments."""
    from softrtc.reference.velocity import vecmat

    def ordered(v, M):  # sum_i v_i M_i, left to right, one rounding per operation
        out = []
        for k in range(len(M[0])):
            acc = float(v[0]) * float(M[0][k])
            for i in range(1, len(v)):
                acc = acc + float(v[i]) * float(M[i][k])
            out.append(acc)
        return np.array(out)

    f, obs, x, g = make(3, H=4, A=3, O=5)
    t = np.random.default_rng(3).random(4)
    p = f.params
    pre = (ordered(x.reshape(-1), p["W1"]) + ordered(time_features(t).reshape(-1), p["Wt"])
           + ordered(obs, p["Wo"]) + p["b1"])
    h = np.tanh(pre)
    assert np.array_equal(f(obs, x, t), (ordered(h, p["W2"]) + p["b2"]).reshape(4, 3))
    dh = ordered(g.reshape(-1), p["W2"].T) * (1.0 - h * h)
    assert np.array_equal(f.vjp(obs, x, t, g), ordered(dh, p["W1"].T).reshape(4, 3))
    # A summation order BLAS may take (pairs first) rounds differently for some inputs; the order matters.
    v, M = np.array([1.0, 1e16, -1e16]), np.ones((3, 1))
    assert vecmat(v, M)[0] == 0.0 and v[0] + (v[1] + v[2]) == 1.0
    with pytest.raises(ValueError, match="M must have shape"):
        vecmat(np.ones(3), np.ones((2, 4)))
    with pytest.raises(ValueError, match="v must have 1 dimensions"):
        vecmat(np.ones((3, 1)), np.ones((3, 4)))
    with pytest.raises(ValueError, match="v must contain only finite"):
        vecmat(np.array([np.nan, 1.0]), np.ones((2, 2)))


@given(st.integers(0, 50))
def test_vjp_matches_finite_differences(seed):
    """F-2: the hand-written VJP equals J^T g (central differences)."""
    f, obs, x, g = make(seed, H=4, A=2)
    t = np.random.default_rng(seed).random(4)
    eps = 1e-6
    J = np.zeros((8, 8))
    for i in range(8):
        dx = np.zeros(8); dx[i] = eps
        J[:, i] = ((f(obs, x + dx.reshape(4, 2), t) - f(obs, x - dx.reshape(4, 2), t)) / (2 * eps)).reshape(-1)
    np.testing.assert_allclose(f.vjp(obs, x, t, g).reshape(-1), J.T @ g.reshape(-1), atol=1e-7)


def test_euler_times():
    """S-1: t_k = k / T."""
    np.testing.assert_array_equal(S.euler_times(5), [0, 0.2, 0.4, 0.6, 0.8])


def test_naive_sampler_steps():
    """S-1, S-2: x_{k+1} = x_k + v(obs, x_k, t_k) / T from the noise."""
    f, obs, noise, _ = make()
    out, trace = S.naive_sample(f, obs, noise, 4, return_trace=True)
    x = noise
    for k in range(4):
        x = x + f(obs, x, np.full(8, k / 4)) / 4
        np.testing.assert_array_equal(trace[k]["next_state"], x)
    np.testing.assert_array_equal(out, x)


@given(st.integers(0, 8), st.integers(1, 6), st.integers(0, 30))
def test_rtc_sampler_blend(d, T, seed):
    """S-3, S-4, S-5: blended state and time; w=1 tokens equal the prior exactly; no final blend."""
    f, obs, noise, prior = make(seed)
    w = W.soft_weights(8, min(d, 4), W.SoftWindow(), 4)
    out, trace = S.rtc_sample(f, obs, noise, prior, w, T, return_trace=True)
    x = noise
    for k, st_ in enumerate(trace):
        xb = w[:, None] * prior + (1 - w[:, None]) * x
        np.testing.assert_array_equal(st_["blended_state"], xb)
        np.testing.assert_array_equal(st_["time"], w + (1 - w) * (k / T))
        assert np.array_equal(st_["blended_state"][w == 1], prior[w == 1])
        x = xb + f(obs, xb, st_["time"]) / T
        np.testing.assert_array_equal(st_["next_state"], x)
    np.testing.assert_array_equal(out, x)
    # [S-5]: the committed prefix of the result is the prior plus one velocity step, not the prior.
    last = trace[-1]
    np.testing.assert_array_equal(out[w == 1], prior[w == 1] + last["velocity"][w == 1] / T)
    np.testing.assert_array_equal(S.blend(noise, prior, w), w[:, None] * prior + (1 - w[:, None]) * noise)
    np.testing.assert_array_equal(S.blend_time(0.4, w), w + (1 - w) * 0.4)


@given(st.integers(0, 40), st.integers(1, 6))
def test_zero_delay_rtc_equals_naive_bitwise(seed, T):
    """S-7, S-6, G-1: d = 0 gives identical chunks for naive, train hard/soft and inference hard.

    Inference soft RTC still guides the whole overlap at d = 0 ([G-1]), so it differs.
    """
    f, obs, noise, prior = make(seed)
    naive = S.naive_sample(f, obs, noise, T)
    for method in ("naive", "train_hard", "train_soft", "inference_hard"):
        out = Mth.generate_chunk(method, f, obs, noise, prior, 4, 0, T)
        assert np.array_equal(out, naive), method
    assert not np.array_equal(Mth.generate_chunk("inference_soft", f, obs, noise, prior, 4, 0, T), naive)


def test_method_weights_table():
    """S-6, G-1, W-7: methods map to the spec's weights, written out by hand (H = 8, s = 4)."""
    np.testing.assert_array_equal(Mth.method_weights("naive", 8, 4, 3), np.zeros(8))
    np.testing.assert_array_equal(Mth.method_weights("train_hard", 8, 4, 3), [1, 1, 1, 0, 0, 0, 0, 0])
    # The default window at d = 2: e = 4, rtc positions 1/3, 2/3, linear schedule (the README's table).
    np.testing.assert_allclose(Mth.method_weights("train_soft", 8, 4, 2), [1, 1, 2 / 3, 1 / 3, 0, 0, 0, 0],
                               rtol=0, atol=1e-15)
    # [G-1]: the guided window ends at H - s = 4; zeros schedule for hard, exp for soft.
    np.testing.assert_array_equal(Mth.method_weights("inference_hard", 8, 4, 2), [1, 1, 0, 0, 0, 0, 0, 0])
    g = [u * math.expm1(u) / math.expm1(1.0) for u in (2 / 3, 1 / 3)]  # u = 1 - x at x = 1/3, 2/3
    np.testing.assert_allclose(Mth.method_weights("inference_soft", 8, 4, 2), [1, 1, *g, 0, 0, 0, 0],
                               rtol=0, atol=1e-15)
    f, obs, noise, prior = make()
    for method in Mth.METHODS:  # every method's first chunk is the naive sampler, d = 0
        assert np.array_equal(Mth.generate_chunk(method, f, obs, noise, None, 4, 0, 5),
                              S.naive_sample(f, obs, noise, 5)), method
        with pytest.raises(ValueError, match="d must be"):
            Mth.generate_chunk(method, f, obs, noise, None, 4, 2, 5)


def test_guidance_weight_values():
    """G-4: lam(t) = min(c inv_r2, beta), lam(0) = beta."""
    assert G.guidance_weight(0.0) == 5.0
    t = 0.6
    assert G.guidance_weight(t) == pytest.approx((1 - t) / t * (t * t + (1 - t) ** 2) / (1 - t) ** 2)
    assert G.guidance_weight(0.9) == 5.0
    assert G.guidance_weight(0.2, max_guidance=2.0) == 2.0


@given(st.integers(0, 30), st.integers(1, 5), st.integers(0, 4), st.sampled_from(["hard", "soft"]))
def test_guided_sampler_steps(seed, T, d, variant):
    """G-1, G-2, G-3, G-5: denoised estimate, weighted error, VJP pull-back and the step."""
    f, obs, noise, prev = make(seed)
    prior = shift_prior(prev, 4)
    w = G.guidance_prefix_weights(8, 4, d, variant)
    out, trace = G.guided_sample(f, obs, noise, prior, w, T, return_trace=True)
    x = noise
    for k, st_ in enumerate(trace):
        t = k / T
        tv = np.full(8, t)
        v = f(obs, x, tv)
        x1 = x + (1 - t) * v
        err = w[:, None] * (prior - x1)
        g = err + (1 - t) * f.vjp(obs, x, tv, err)
        np.testing.assert_allclose(st_["denoised"], x1)
        np.testing.assert_allclose(st_["vjp"], g)
        x = x + (v + G.guidance_weight(t) * g) / T
        np.testing.assert_allclose(st_["next_state"], x)
    np.testing.assert_allclose(out, x)


def test_guidance_pulls_prefix_toward_prior():
    """G-5: with guidance the committed prefix ends closer to the prior than without."""
    f, obs, noise, prev = make(3)
    prior = shift_prior(prev, 4)
    w = G.guidance_prefix_weights(8, 4, 3, "hard")
    guided = G.guided_sample(f, obs, noise, prior, w, 5)
    naive = S.naive_sample(f, obs, noise, 5)
    assert np.linalg.norm(guided[:3] - prior[:3]) < np.linalg.norm(naive[:3] - prior[:3])


@given(st.integers(0, 40), st.integers(1, 6))
def test_guided_with_zero_weights_equals_naive(seed, T):
    """G-6: all-zero guidance weights give exactly the naive sampler."""
    f, obs, noise, prior = make(seed)
    assert np.array_equal(G.guided_sample(f, obs, noise, prior, np.zeros(8), T), S.naive_sample(f, obs, noise, T))


def test_method_request_checked_whole():
    """S-8: the default window is resolved by train_soft only, so every other method runs
    for H < 5; arguments a method ignores (a window, naive's prior) are checked all the same."""
    f, obs, noise, prior = make(3, H=4)
    for method in ("naive", "inference_hard", "inference_soft", "train_hard"):
        assert Mth.method_weights(method, 4, 2, 1).shape == (4,)
        assert Mth.generate_chunk(method, f, obs, noise, prior, 2, 1, 3).shape == (4, 2)
    np.testing.assert_array_equal(Mth.method_weights("train_hard", 4, 2, 1), [1, 0, 0, 0])
    with pytest.raises(ValueError, match="h_max or h"):
        Mth.method_weights("train_soft", 4, 2, 1)
    small = W.SoftWindow(W.delay_scaled(2.0, 3))
    assert Mth.method_weights("train_soft", 4, 2, 1, small).tolist() == [1.0, 0.5, 0.0, 0.0]
    for method in Mth.METHODS:
        with pytest.raises(ValueError, match="h_max or h"):  # a given window must fit H, used or not
            Mth.method_weights(method, 4, 2, 1, W.SoftWindow())
        with pytest.raises(ValueError, match="window must be a SoftWindow"):
            Mth.generate_chunk(method, f, obs, noise, None, 2, 0, 3, window="junk")
    with pytest.raises(ValueError, match="prior must have shape"):
        Mth.generate_chunk("naive", f, obs, noise, prior[:3], 2, 1, 3)
    with pytest.raises(ValueError, match="prior must be a numeric array|prior must be a real"):
        Mth.generate_chunk("naive", f, obs, noise, "foo", 2, 1, 3)
