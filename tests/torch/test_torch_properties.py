"""softrtc.torch against the NumPy reference on random batches with mixed delays ([PT-3]).

Each batched function is compared, example by example, with the reference function of the same
chapter; the batch mixes delays (and windows, times, noises), so a row computed with another
example's delay, a broadcast over the wrong axis or a shared flow time fails. float64 tensors are
used so that the comparison is tight (1e-12); the conformance vectors cover float32.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

torch = pytest.importorskip("torch")

from softrtc.reference import (corruption as rcorr, endpoints as rend, executor as rexec, guidance as rguid,  # noqa: E402
                               loss as rloss, methods as rmeth, sampler as rsamp, velocity as rvel,
                               weights as rw, delays as rdel)
from softrtc.torch import (corruption, delays, endpoints, executor, guidance, loss, methods, sampler,  # noqa: E402
                           velocity, weights)

F64 = torch.float64
TOL = dict(rtol=1e-12, atol=1e-12)

rules = st.one_of(
    st.builds(rend.delay_scaled, st.sampled_from([0.5, 1.0, 1.1, 1.6, 2.0, 2.2, 3.0]), st.integers(0, 12)),
    st.builds(rend.offset, st.integers(0, 6), st.integers(0, 12)),
    st.builds(rend.fixed, st.integers(0, 12)),
    st.just(rend.hard()))


@st.composite
def window_batch(draw):
    """(H, s, window, delays [B]) with mixed delays in 0 .. H and a window whose bound fits H."""
    H = draw(st.integers(1, 12))
    rule = draw(rules.filter(lambda r: r.kind == "hard" or r.bound() <= H))
    window = rw.SoftWindow(rule, draw(st.sampled_from(rw.SCHEDULES)), draw(st.sampled_from(rw.PARAMETRIZATIONS)),
                           draw(st.sampled_from(rw.OVERFLOWS)))
    s = draw(st.integers(1, H))
    d = draw(st.lists(st.integers(0, H), min_size=1, max_size=9))
    return H, s, window, d


@given(window_batch())
def test_batched_weights_equal_reference_rows(case):
    """[PT-3], [W-7], [W-8], [E-2], [PT-4] soft_weights, hard_weights and endpoint on a delay tensor [B] give,
    row by row, the reference's values for each example's own delay; the weight table's rows are the same."""
    H, s, window, d = case
    dt = torch.tensor(d)
    got = weights.soft_weights(H, dt, window, s, dtype=F64)
    assert got.shape == (len(d), H) and got.dtype == F64
    table = weights.weight_table(H, "soft", window, s, dtype=F64)
    for i, di in enumerate(d):
        want = rw.soft_weights(H, di, window, s)
        np.testing.assert_allclose(got[i].numpy(), want, **TOL)
        np.testing.assert_allclose(table[di].numpy(), want, **TOL)
        np.testing.assert_array_equal(weights.hard_weights(H, dt, dtype=F64)[i].numpy(), rw.hard_weights(H, di))
    assert endpoints.endpoint(window.rule, dt).tolist() == [rend.endpoint(window.rule, di) for di in d]


@given(st.integers(2, 10), st.data())
def test_method_and_guidance_weights_per_example(H, data):
    """[PT-3], [S-6], [G-1], [S-8] method_weights of every method on executable mixed delays [B] equal the
    reference's per example; a delay beyond min(s, H - s) anywhere in the batch is rejected."""
    s = data.draw(st.integers(1, H - 1))
    dmax = min(s, H - s)
    d = data.draw(st.lists(st.integers(0, dmax), min_size=1, max_size=6))
    window = rw.SoftWindow(rend.delay_scaled(2.0, min(5, H)))
    for m in methods.METHODS:
        got = methods.method_weights(m, H, s, torch.tensor(d), window, dtype=F64)
        for i, di in enumerate(d):
            np.testing.assert_allclose(got[i].numpy(), rmeth.method_weights(m, H, s, di, window), **TOL)
    with pytest.raises(ValueError, match="d"):
        methods.method_weights("train_soft", H, s, torch.tensor(d + [dmax + 1]), window)


@given(st.integers(1, 10), st.integers(1, 4), st.integers(1, 6), st.integers(0, 2**31 - 1))
def test_corruption_and_loss_per_example(H, A, B, seed):
    """[PT-3], [C-1], [C-2], [L-1], [L-2], [L-3] corrupt, token_times, loss and batch_loss with per-example
    weights [B, H] and flow times [B] equal the reference example by example; the flipped convention gives
    t' = 1 - t and the same interpolant ([V-1], [V-3])."""
    rng = np.random.default_rng(seed)
    a, n, p = rng.normal(size=(3, B, H, A))
    # alternate hard rows and soft rows (window of two tokens) with each example's own delay
    w = np.stack([rw.hard_weights(H, int(k)) if i % 2 else rw.prefix_weights(H, int(k), min(H, int(k) + 2))
                  for i, k in enumerate(rng.integers(0, H + 1, B))])
    tau = rng.uniform(size=B)
    x, times = corruption.corrupt(torch.tensor(a), torch.tensor(n), torch.tensor(w), torch.tensor(tau))
    xf, tf = corruption.corrupt(torch.tensor(a), torch.tensor(n), torch.tensor(w), torch.tensor(1.0 - tau),
                                convention="noise_at_1")
    per = loss.loss(torch.tensor(p), torch.tensor(a), torch.tensor(n), torch.tensor(w))
    per_f = loss.loss(-torch.tensor(p), torch.tensor(a), torch.tensor(n), torch.tensor(w), convention="noise_at_1")
    for i in range(B):
        wx, wt = rcorr.corrupt(a[i], n[i], w[i], float(tau[i]))
        np.testing.assert_allclose(x[i].numpy(), wx, **TOL)
        np.testing.assert_allclose(times[i].numpy(), wt, **TOL)
        np.testing.assert_allclose(xf[i].numpy(), wx, **TOL)
        np.testing.assert_allclose(tf[i].numpy(), 1.0 - wt, **TOL)
        np.testing.assert_allclose(corruption.token_times(torch.tensor(w), torch.tensor(tau))[i].numpy(),
                                   rcorr.token_times(w[i], float(tau[i])), **TOL)
        want = rloss.flow_matching_loss(p[i], a[i], n[i], w[i])
        assert float(per[i]) == pytest.approx(want, rel=1e-12, abs=1e-12)
        assert float(per_f[i]) == pytest.approx(want, rel=1e-12, abs=1e-12)
    assert float(loss.batch_loss(torch.tensor(p), torch.tensor(a), torch.tensor(n), torch.tensor(w))) == \
        pytest.approx(rloss.batch_loss(p, a, n, w), rel=1e-12)


def _field(seed, H, A, O):
    ref = rvel.ReferenceVelocityField.init(seed, H, A, O, hidden=16)
    return ref, velocity.ReferenceVelocityField(ref.to_dict(), dtype=F64)


@settings(max_examples=15)
@given(st.integers(2, 8), st.integers(1, 3), st.integers(1, 4), st.integers(1, 4), st.integers(0, 2**31 - 1))
def test_samplers_per_example(H, A, B, T, seed):
    """[PT-3], [S-2], [S-3], [S-4], [S-5], [G-2], [G-3], [G-5], [F-1], [F-2] The batched naive, RTC and guided
    samplers on the reference field, with a different delay per example, give each example's reference
    chunk; so does the flipped convention with u = -v(1 - t') ([V-2]); the field's VJP matches [F-2]."""
    rng = np.random.default_rng(seed)
    ref, field = _field(seed % 1000, H, A, 3)
    obs, noise, prior = rng.normal(size=(B, 3)), rng.normal(size=(B, H, A)), rng.normal(size=(B, H, A))
    s = max(1, H // 2)
    d = rng.integers(0, min(s, H - s) + 1, B)
    w_rtc = np.stack([rw.soft_weights(H, int(k), rw.SoftWindow(rend.offset(1, H)), s) for k in d])
    w_g = np.stack([rguid.guidance_prefix_weights(H, s, int(k), "soft") for k in d])
    o, nz, y = torch.tensor(obs), torch.tensor(noise), torch.tensor(prior)
    flipped = lambda ob, xx, tt: -field(ob, xx, 1.0 - tt)  # noqa: E731
    got = {
        "naive": sampler.naive_sample(field, o, nz, T),
        "naive_f": sampler.naive_sample(flipped, o, nz, T, convention="noise_at_1"),
        "rtc": sampler.rtc_sample(field, o, nz, y, torch.tensor(w_rtc), T),
        "rtc_f": sampler.rtc_sample(flipped, o, nz, y, torch.tensor(w_rtc), T, convention="noise_at_1"),
        "guided": guidance.guided_sample(field, o, nz, y, torch.tensor(w_g), T, 5.0),
        "guided_f": guidance.guided_sample(flipped, o, nz, y, torch.tensor(w_g), T, 5.0, convention="noise_at_1"),
    }
    cot = rng.normal(size=(H, A))
    for i in range(B):
        want = {"naive": rsamp.naive_sample(ref, obs[i], noise[i], T),
                "rtc": rsamp.rtc_sample(ref, obs[i], noise[i], prior[i], w_rtc[i], T),
                "guided": rguid.guided_sample(ref, obs[i], noise[i], prior[i], w_g[i], T, 5.0)}
        for k, val in got.items():
            np.testing.assert_allclose(val[i].numpy(), want[k.split("_")[0]], rtol=1e-10, atol=1e-10, err_msg=k)
        t = rng.uniform(size=H)
        np.testing.assert_allclose(
            velocity.velocity_vjp(field, o[i], nz[i], torch.tensor(t), torch.tensor(cot)).numpy(),
            ref.vjp(obs[i], noise[i], t, cot), rtol=1e-10, atol=1e-12)


@given(st.integers(2, 10), st.integers(1, 3), st.integers(1, 5), st.integers(0, 2**31 - 1))
def test_shift_prior_and_delay_draws(H, A, C, seed):
    """[PT-3], [X-3], [X-4], [D-3] shift_prior of a batch of chunks shifts each like the reference;
    execute_chunks matches the reference; inverse-CDF draws of a tensor of uniforms equal the reference's
    draws one by one."""
    rng = np.random.default_rng(seed)
    s = int(rng.integers(1, H))
    chunks = rng.normal(size=(C, H, A))
    got = executor.shift_prior(torch.tensor(chunks), s)
    for c in range(C):
        np.testing.assert_array_equal(got[c].numpy(), rexec.shift_prior(chunks[c], s))
    dl = [0] + [int(k) for k in rng.integers(0, min(s, H - s) + 1, C - 1)]
    ex = executor.execute_chunks(torch.tensor(chunks), torch.tensor(dl), s)
    want = rexec.execute_chunks(chunks, dl, s)
    np.testing.assert_array_equal(ex["actions"].numpy(), want["actions"])
    np.testing.assert_array_equal(ex["chunk_index"].numpy(), want["chunk_index"])
    p = rdel.delay_probs("exponential", 1, 1 + H, 0.7)
    u = rng.uniform(size=20)
    got_d = delays.sample_delay(torch.tensor(p), 1, torch.tensor(u))
    assert got_d.tolist() == [rdel.sample_delay(p, 1, float(x)) for x in u]
