"""The JAX twin (softrtc.jax) agrees with the NumPy reference (softrtc.reference).

Float32 tolerances ([N-8]): weights, times, corruption and losses within
atol = rtol = 1e-5; whole sampler trajectories (T Euler steps through the
reference field, float32 against float64) within atol = rtol = 1e-4.
Bitwise claims of the spec ([S-7], [G-6], [C-3], [W-8], [L-4]) are checked
with exact equality. Jitted functions are module-level and reused so that
hypothesis examples hit the compilation cache.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softrtc import reference as R
from softrtc.jax import conventions as JV
from softrtc.jax import corruption as JC
from softrtc.jax import delays as JD
from softrtc.jax import endpoints as JE
from softrtc.jax import executor as JX
from softrtc.jax import guidance as JG
from softrtc.jax import loss as JL
from softrtc.jax import methods as JM
from softrtc.jax import metrics as JMt
from softrtc.jax import sampler as JS
from softrtc.jax import velocity as JF
from softrtc.jax import weights as JW

TOL = dict(atol=1e-5, rtol=1e-5)
TRAJ = dict(atol=1e-4, rtol=1e-4)
few = settings(max_examples=15, deadline=None)

# ---------------------------------------------------------------- strategies

# [E-2]: float32 agrees with the exact ceiling for lam with three decimals while lam * d <= 256 (d <= 64 here).
lams = st.one_of(st.integers(0, 16).map(lambda k: k / 4.0), st.integers(0, 4000).map(lambda k: k / 1000.0))


@st.composite
def ref_rules(draw, H=None):
    kind = draw(st.sampled_from(R.endpoints.RULES))
    hi = H if H is not None else 64
    if kind == "delay_scaled":
        return R.delay_scaled(draw(lams), draw(st.integers(0, hi)))
    if kind == "offset":
        return R.offset(draw(st.integers(0, hi)), draw(st.integers(0, hi)))
    if kind == "fixed":
        return R.fixed(draw(st.integers(0, hi)))
    return R.hard()


@st.composite
def ref_windows(draw, H):
    return R.SoftWindow(draw(ref_rules(H)), draw(st.sampled_from(R.weights.SCHEDULES)),
                        draw(st.sampled_from(R.weights.PARAMETRIZATIONS)),
                        draw(st.sampled_from(R.weights.OVERFLOWS)))


def arr(seed, *shape):
    return np.random.default_rng(seed).standard_normal(shape)


# ---------------------------------------------------------------- E, W

_endpoint_all = jax.jit(jax.vmap(JE.endpoint, in_axes=(None, 0)))


@few
@given(ref_rules())
def test_endpoint_rules(rule):
    """E-1, E-2, E-3, E-4, E-5, E-6: endpoints of every rule for d = 0..64, lam with up to three decimals."""
    got = np.asarray(_endpoint_all(JE.from_reference(rule), jnp.arange(65)))
    want = [R.endpoint(rule, d) for d in range(65)]
    assert got.tolist() == want
    assert got[0] == 0


def test_endpoint_exact_ceil_and_constructors():
    """E-1, E-2: lam = 2, d = 3 gives 6; built rules validate their parameters."""
    assert int(JE.endpoint(JE.delay_scaled(2.0, 8), 3)) == 6
    assert int(JE.endpoint(JE.delay_scaled(0.25, 4096), 4095)) == 1024
    # [E-2] delta: the decimal lam's endpoint, although 1.6 and 1.1 are stored slightly above.
    assert [int(JE.endpoint(JE.delay_scaled(1.6, 16), d)) for d in range(6)] == [0, 2, 4, 5, 7, 8]
    assert int(JE.endpoint(JE.delay_scaled(1.1, 100), 10)) == 11
    assert int(JE.endpoint(JE.delay_scaled(0.6, 100), 25)) == 15  # the float32 product is 15.000001
    with pytest.raises(ValueError, match="lam"):
        JE.delay_scaled(-1.0, 5)
    with pytest.raises(ValueError, match="h_max"):
        JE.offset(2, 5000)
    with pytest.raises(ValueError, match="d"):
        JE.endpoint(JE.hard(), -1)


@functools.partial(jax.jit, static_argnames=("H",))
def _soft_table(H, window, s):
    return JW.weight_table(H, window, s)


@few
@given(st.data())
def test_soft_weights_all_variants(data):
    """W-1, W-2, W-3, W-4, W-5, W-6, W-7: soft weights of every rule, schedule,
    parametrization and overflow agree with the reference for every d = 0..H."""
    H = data.draw(st.sampled_from([1, 4, 8, 10]))
    window = data.draw(ref_windows(H))
    s = data.draw(st.integers(1, H))
    got = np.asarray(_soft_table(H, JW.from_reference(window), s))
    for d in range(H + 1):
        want = R.soft_weights(H, d, window, s)
        np.testing.assert_allclose(got[d], want, **TOL)
        np.testing.assert_allclose(np.asarray(JW.soft_weights(H, d, window, s)), want, **TOL)
    assert np.all(got >= 0) and np.all(got <= 1) and np.all(np.diff(got, axis=1) <= 1e-7)


@few
@given(st.data())
def test_prefix_weights_and_endpoints(data):
    """W-1, W-2, W-3, W-4, W-5, W-6: prefix weights, schedules and effective endpoints."""
    H = data.draw(st.integers(1, 12))
    d = data.draw(st.integers(0, H))
    e = data.draw(st.integers(d, H))
    sched = data.draw(st.sampled_from(R.weights.SCHEDULES))
    par = data.draw(st.sampled_from(R.weights.PARAMETRIZATIONS))
    np.testing.assert_allclose(JW.prefix_weights(H, d, e, sched, par), R.prefix_weights(H, d, e, sched, par), **TOL)
    x = np.linspace(0, 1, 7)
    np.testing.assert_allclose(JW.schedule_value(sched, x), R.weights.schedule_value(sched, x), **TOL)
    e2 = data.draw(st.integers(0, H))
    s = data.draw(st.integers(1, H))
    for ov in R.weights.OVERFLOWS:
        assert int(JW.effective_endpoint(H, d, e2, s, ov)) == R.weights.effective_endpoint(H, d, e2, s, ov)


def test_worked_examples_and_hard_identities():
    """W-4, W-5, W-7, W-8, W-9: worked examples; bitwise Hard RTC identities; d = 0 gives w = 0."""
    np.testing.assert_allclose(JW.prefix_weights(10, 2, 6, "linear"), [1, 1, .8, .6, .4, .2, 0, 0, 0, 0], **TOL)
    np.testing.assert_allclose(JW.prefix_weights(10, 2, 6, "linear", "paper"),
                               [1, 1, 1, .75, .5, .25, 0, 0, 0, 0], **TOL)
    np.testing.assert_allclose(_soft_table(8, JW.SoftWindow(), 4)[1:5],
                               [[1, .5, 0, 0, 0, 0, 0, 0], [1, 1, 2 / 3, 1 / 3, 0, 0, 0, 0],
                                [1, 1, 1, .5, 0, 0, 0, 0], [1, 1, 1, 1, 0, 0, 0, 0]], **TOL)
    hard_rules = [JW.SoftWindow(JE.offset(0, 8)), JW.SoftWindow(JE.delay_scaled(1.0, 8)),
                  JW.SoftWindow(JE.hard()), JW.SoftWindow(JE.delay_scaled(2.0, 5), schedule="zeros")]
    for win in hard_rules:
        for par in R.weights.PARAMETRIZATIONS:
            w = JW.SoftWindow(win.rule, win.schedule, par, "zeros")
            t = np.asarray(_soft_table(8, w, 4))
            for d in range(9):
                assert np.array_equal(t[d], np.asarray(JW.hard_weights(8, d)))
    for win in hard_rules:
        assert np.array_equal(np.asarray(_soft_table(8, win, 4))[0], np.zeros(8))


# ---------------------------------------------------------------- D, C, L


_sample_delay = jax.jit(JD.sample_delay)


@few
@given(st.sampled_from(R.delays.DISTRIBUTIONS), st.integers(0, 6), st.sampled_from([0, 2, 4]),
       st.floats(0, 8), st.lists(st.floats(0, 1, exclude_max=True), min_size=1, max_size=20))
def test_delay_tables_and_inverse_cdf(dist, d_min, span, decay, us):
    """D-1, D-2, D-3: probability tables and inverse-CDF draws from the same u."""
    d_max = d_min + span
    p_ref = R.delays.delay_probs(dist, d_min, d_max, decay)
    p = JD.delay_probs(dist, d_min, d_max, decay)
    np.testing.assert_allclose(p, p_ref, **TOL)
    cdf = R.delays.delay_cdf(p_ref)
    # u within float32 rounding of a CDF boundary may legitimately fall either way (module doc).
    # The midpoint of every CDF interval is always among the draws, so each delay with mass is hit.
    edges = np.concatenate([[0.0], cdf])
    mids = [(a + b) / 2 for a, b in zip(edges[:-1], edges[1:]) if b - a > 1e-5]
    us = [u for u in list(us) + mids if np.min(np.abs(cdf - u)) > 1e-6]
    assert mids and us
    got = np.asarray(_sample_delay(p, d_min, np.asarray(us, np.float32)))
    assert got.tolist() == [R.delays.sample_delay(p_ref, d_min, u) for u in us]


def test_keyed_delay_sampler():
    """D-3, D-4, N-9: sample_delays draws u from the key; same key, same delays."""
    p = JD.delay_probs("exponential", 0, 4, 1.0)
    key = jax.random.key(3)
    d = JD.sample_delays(key, p, 0, (1000,))
    assert np.array_equal(d, JD.sample_delays(key, p, 0, (1000,)))
    u = np.asarray(jax.random.uniform(key, (1000,), jnp.float32))
    assert np.array_equal(d, JD.sample_delay(p, 0, u))
    assert int(d.min()) >= 0 and int(d.max()) <= 4 and np.mean(np.asarray(d) == 0) > 0.5


@few
@given(st.integers(0, 10**6), st.floats(0, 1))
def test_corruption(seed, tau):
    """C-1, C-2, C-3: per-token times and the corrupted chunk; w = 0 is bitwise plain flow matching."""
    H, A = 8, 2
    rng = np.random.default_rng(seed)
    a, n, w = rng.standard_normal((H, A)), rng.standard_normal((H, A)), np.sort(rng.random(H))[::-1]
    w[: seed % 4] = 1.0
    x, tj = JC.corrupt(a, n, w, tau)
    xr, tr = R.corruption.corrupt(a, n, w, tau)
    np.testing.assert_allclose(x, xr, **TOL)
    np.testing.assert_allclose(tj, tr, **TOL)
    a32, n32 = jnp.float32(a), jnp.float32(n)
    x0, t0 = JC.corrupt(a32, n32, np.zeros(H), tau)
    assert np.array_equal(x0, jnp.float32(tau) * a32 + (1 - jnp.float32(tau)) * n32)
    # Batched by broadcasting.
    xb, _ = JC.corrupt(np.stack([a, a]), np.stack([n, n]), np.stack([w, np.zeros(H)]), np.array([tau, tau]))
    assert np.array_equal(xb[0], x) and np.array_equal(xb[1], x0)


@few
@given(st.integers(0, 10**6))
def test_loss(seed):
    """L-1, L-2, L-3, L-4: token errors, per-example and batch loss; clamped tokens do not count."""
    B, H, A = 3, 8, 2
    rng = np.random.default_rng(seed)
    p, a, n = (rng.standard_normal((B, H, A)) for _ in range(3))
    w = np.sort(rng.random((B, H)), axis=1)[:, ::-1]
    w[0, : H // 2] = 1.0
    np.testing.assert_allclose(JL.batch_loss(p, a, n, w), R.loss.batch_loss(p, a, n, w), **TOL)
    for i in range(B):
        np.testing.assert_allclose(JL.flow_matching_loss(p[i], a[i], n[i], w[i]),
                                   R.loss.flow_matching_loss(p[i], a[i], n[i], w[i]), **TOL)
        np.testing.assert_allclose(JL.token_errors(p[i], a[i], n[i]), R.loss.token_errors(p[i], a[i], n[i]), **TOL)
    assert float(JL.flow_matching_loss(p[0], a[0], n[0], np.ones(H))) == 0.0
    p2 = p.copy()
    p2[0, : H // 2] += 100.0
    assert float(JL.flow_matching_loss(p2[0], a[0], n[0], w[0])) == float(JL.flow_matching_loss(p[0], a[0], n[0], w[0]))
    l0 = JL.flow_matching_loss(p[0], a[0], n[0], np.zeros(H))
    assert np.array_equal(l0, JL.flow_matching_loss(p[0], a[0], n[0], JW.soft_weights(H, 0, JW.SoftWindow(JE.hard()), 1)))


def test_rtc_loss_matches_parts():
    """C-1, C-2, L-1, L-3: rtc_loss corrupts, evaluates the field at per-token times and averages."""
    rf = R.velocity.ReferenceVelocityField.init(1, 8, 2, 3, hidden=16)
    f = JF.ReferenceVelocityField(rf.params)
    obs, a, n = arr(0, 2, 3), arr(1, 2, 8, 2), arr(2, 2, 8, 2)
    w = np.stack([R.soft_weights(8, d, R.SoftWindow(), 4) for d in (1, 3)])
    tau = np.array([0.3, 0.7])
    want = np.mean([R.loss.flow_matching_loss(rf(obs[i], *R.corruption.corrupt(a[i], n[i], w[i], tau[i])),
                                              a[i], n[i], w[i]) for i in range(2)])
    np.testing.assert_allclose(JL.rtc_loss(f, obs, a, n, w, tau), want, **TRAJ)


# ---------------------------------------------------------------- F, S, G

H, A, O, B = 8, 2, 3, 3
RF = R.velocity.ReferenceVelocityField.init(7, H, A, O, hidden=16)
JFIELD = JF.ReferenceVelocityField(RF.params)


def _inputs(seed):
    return arr(seed, B, O), arr(seed + 1, B, H, A), arr(seed + 2, B, H, A)


@few
@given(st.integers(0, 10**6))
def test_field_and_vjp(seed):
    """F-1, F-2: field values, the hand-written VJP and jax.vjp agree with the reference VJP."""
    obs, x, g = _inputs(seed)
    t = np.random.default_rng(seed).random((B, H))
    v = JFIELD(obs, x, t)
    vj = JFIELD.vjp(obs, x, t, g)
    _, pull = jax.vjp(lambda xx: JFIELD(obs, xx, t), jnp.float32(x))
    for i in range(B):
        np.testing.assert_allclose(v[i], RF(obs[i], x[i], t[i]), **TOL)
        np.testing.assert_allclose(vj[i], RF.vjp(obs[i], x[i], t[i], g[i]), **TOL)
        np.testing.assert_allclose(pull(jnp.float32(g))[0][i], RF.vjp(obs[i], x[i], t[i], g[i]), **TOL)
        np.testing.assert_allclose(JFIELD(obs[i], x[i], t[i]), RF(obs[i], x[i], t[i]), **TOL)
    np.testing.assert_allclose(JFIELD.apply_conditioned(obs, x, JFIELD.time_conditioning(t)), v, **TOL)


_naive = jax.jit(JS.naive_sample, static_argnums=(0, 3))
_rtc = jax.jit(JS.rtc_sample, static_argnums=(0, 5))
_guided = jax.jit(JG.guided_sample, static_argnums=(0, 5))
_naive_c = jax.jit(JS.naive_sample_conditioned, static_argnums=(3,))
_rtc_c = jax.jit(JS.rtc_sample_conditioned, static_argnums=(5,))
_guided_c = jax.jit(JG.guided_sample_conditioned, static_argnums=(5,))
_gen = jax.jit(JM.generate_chunk, static_argnums=(0, 5, 7))
_gen_c = jax.jit(JM.generate_chunk_conditioned, static_argnums=(0, 5, 7))


def _ref_batch(fn, *arrays, **kw):
    return np.stack([fn(RF, *(a[i] for a in arrays), **kw) for i in range(B)])


@few
@given(st.integers(0, 10**6), st.sampled_from([1, 5]), st.integers(0, 4))
def test_sampler_trajectories(seed, T, d):
    """S-1, S-2, S-3, S-4, S-5, G-1, G-2, G-3, G-4, G-5: naive, training-time RTC and guided
    trajectories with the reference field and the same noise, both the straightforward
    and the conditioned path."""
    obs, noise, prior = _inputs(seed)
    naive_ref = _ref_batch(lambda f, o, n: R.sampler.naive_sample(f, o, n, T), obs, noise)
    np.testing.assert_allclose(_naive(JFIELD, obs, noise, T), naive_ref, **TRAJ)
    np.testing.assert_allclose(_naive_c(JFIELD, obs, noise, T), naive_ref, **TRAJ)
    w = R.soft_weights(H, d, R.SoftWindow(), 4)
    rtc_ref = _ref_batch(lambda f, o, n, y: R.sampler.rtc_sample(f, o, n, y, w, T), obs, noise, prior)
    np.testing.assert_allclose(_rtc(JFIELD, obs, noise, prior, w, T), rtc_ref, **TRAJ)
    np.testing.assert_allclose(_rtc_c(JFIELD, obs, noise, prior, w, T), rtc_ref, **TRAJ)
    W = R.guidance.guidance_prefix_weights(H, 4, d, "soft")
    g_ref = _ref_batch(lambda f, o, n, y: R.guidance.guided_sample(f, o, n, y, W, T), obs, noise, prior)
    np.testing.assert_allclose(_guided(JFIELD, obs, noise, prior, W, T), g_ref, **TRAJ)
    np.testing.assert_allclose(_guided_c(JFIELD, obs, noise, prior, W, T), g_ref, **TRAJ)


_guided_split = jax.jit(JG.guided_sample_conditioned, static_argnums=(5,), static_argnames=("guided_tokens",))


@few
@given(st.integers(0, 10**6), st.sampled_from([1, 5]), st.integers(0, 4), st.sampled_from(["hard", "soft"]))
def test_restricted_pull_back_matches_reference(seed, T, d, variant):
    """G-7, G-1, G-3: the pull-back through tokens j < H - s only (guidance weights vanish beyond) gives the
    reference guided trajectory; its velocity comes from the split evaluation of the field."""
    obs, noise, prior = _inputs(seed)
    W = R.guidance.guidance_prefix_weights(H, 4, d, variant)
    g_ref = _ref_batch(lambda f, o, n, y: R.guidance.guided_sample(f, o, n, y, W, T), obs, noise, prior)
    got = _guided_split(JFIELD, obs, noise, prior, W, T, guided_tokens=H - 4)
    np.testing.assert_allclose(got, g_ref, **TRAJ)
    # Per-example weights [B, H] (one delay per example) take the same path.
    Wb = np.stack([R.guidance.guidance_prefix_weights(H, 4, dd, variant) for dd in (0, 2, 4)])
    got_b = _guided_split(JFIELD, obs, noise, prior, Wb, T, guided_tokens=H - 4)
    for i in range(B):
        want = R.guidance.guided_sample(RF, obs[i], noise[i], prior[i], Wb[i], T)
        np.testing.assert_allclose(got_b[i], want, **TRAJ)


def test_restricted_pull_back_validation():
    """G-7, N-7: guided_tokens must be in [1, H - 1], weights beyond it must be zero, the model must split."""
    obs, noise, prior = _inputs(3)
    W = R.guidance.guidance_prefix_weights(H, 4, 2, "soft")
    with pytest.raises(ValueError, match="guided_tokens"):
        JG.guided_sample_conditioned(JFIELD, obs, noise, prior, W, 2, guided_tokens=0)
    with pytest.raises(ValueError, match="guided_tokens"):
        JG.guided_sample_conditioned(JFIELD, obs, noise, prior, W, 2, guided_tokens=H)
    # Weight 1 on token 4 (j >= guided_tokens = 4) would be silently dropped: rejected instead.
    with pytest.raises(ValueError, match=r"weights\[\.\.\., 4:\] to be zero"):
        JG.guided_sample_conditioned(JFIELD, obs, noise, prior, np.ones(H), 2, guided_tokens=4)

    class NoSplit:
        time_conditioning = JFIELD.time_conditioning
        apply_conditioned = JFIELD.apply_conditioned

    with pytest.raises(ValueError, match="apply_conditioned_split"):
        JG.guided_sample_conditioned(NoSplit(), obs, noise, prior, W, 2, guided_tokens=4)
    with pytest.raises(ValueError, match="restrict_guidance must be a bool"):
        JM.generate_chunk_conditioned("inference_soft", JFIELD, obs, noise, prior, 4, 2, 2, restrict_guidance=1)
    with pytest.raises(ValueError, match="head"):
        JFIELD.apply_conditioned_split(obs, noise, JFIELD.time_conditioning(np.zeros((B, H))), H)


@few
@given(st.integers(0, 10**6))
def test_per_example_weights(seed):
    """S-3, S-6, D-4: weights [B, H] (one delay per example) equal per-example runs."""
    obs, noise, prior = _inputs(seed)
    ds = np.array([0, 2, 4])
    w = np.stack([R.soft_weights(H, int(d), R.SoftWindow(), 4) for d in ds])
    got = _rtc(JFIELD, obs, noise, prior, w, 5)
    got_c = _rtc_c(JFIELD, obs, noise, prior, w, 5)
    for i in range(B):
        want = R.sampler.rtc_sample(RF, obs[i], noise[i], prior[i], w[i], 5)
        np.testing.assert_allclose(got[i], want, **TRAJ)
        np.testing.assert_allclose(got_c[i], want, **TRAJ)


@few
@given(st.integers(0, 10**6), st.sampled_from([1, 5]))
def test_zero_weights_are_bitwise_naive(seed, T):
    """S-7, G-6: with w = 0 (d = 0) the RTC sampler and the guided sampler are bitwise naive."""
    obs, noise, prior = _inputs(seed)
    naive = np.asarray(_naive(JFIELD, obs, noise, T))
    w0 = JW.soft_weights(H, 0, JW.SoftWindow(), 4)
    assert np.array_equal(np.asarray(_rtc(JFIELD, obs, noise, prior, w0, T)), naive)
    assert np.array_equal(np.asarray(_guided(JFIELD, obs, noise, prior, np.zeros(H), T)), naive)
    for m in ("train_hard", "train_soft"):
        assert np.array_equal(np.asarray(_gen(m, JFIELD, obs, noise, prior, 4, 0, T)), naive)


def test_guidance_weight():
    """G-4: lam(t) with c = +inf at t = 0 (no NaN under jit), capped at beta."""
    ts = np.array([0.0, 0.2, 0.5, 0.8, 0.95])
    got = np.asarray(jax.jit(JG.guidance_weight)(ts))
    np.testing.assert_allclose(got, [R.guidance.guidance_weight(t) for t in ts], **TOL)
    assert float(jax.jit(JG.guidance_weight)(0.0)) == 5.0
    assert float(JG.guidance_weight(0.5, 1.5)) == 1.5
    with pytest.raises(ValueError, match="t"):
        JG.guidance_weight(1.0)


# ---------------------------------------------------------------- X


_shift = jax.jit(JX.shift_prior)
_segment = jax.jit(JX.segment, static_argnums=2)
_execute = jax.jit(JX.execute_chunks, static_argnums=2)


@few
@given(st.integers(0, 10**6), st.sampled_from([(8, 4), (8, 3), (8, 6), (4, 1), (1, 1)]), st.data())
def test_executor(seed, Hs, data):
    """X-1, X-2, X-3, X-4, X-5: prior shift, segments and the executed sequence with traced delays."""
    Hx, s = Hs
    C = 4
    dmax = min(s, Hx - s)
    delays = [0] + [data.draw(st.integers(0, dmax)) for _ in range(C - 1)]
    chunks = arr(seed, C, Hx, 2)
    np.testing.assert_allclose(_shift(chunks[0], s), R.executor.shift_prior(chunks[0], s), **TOL)
    seg = _segment(chunks[0], chunks[1], s, delays[1])
    np.testing.assert_allclose(seg, R.executor.segment(chunks[0], chunks[1], s, delays[1]), **TOL)
    got = _execute(chunks, np.asarray(delays, np.int32), s)
    want = R.executor.execute_chunks(chunks, delays, s)
    np.testing.assert_allclose(got["actions"], want["actions"], **TOL)
    assert np.array_equal(got["chunk_index"], want["chunk_index"])
    assert np.array_equal(got["token_index"], want["token_index"])
    if dmax < Hx:
        with pytest.raises(ValueError, match="d"):
            JX.check_delay(Hx, s, dmax + 1)


def test_closed_loop():
    """X-2, X-3, X-4, X-6: the scanned closed loop equals the reference's Python loop."""
    Hc, s, C = 8, 4, 4
    delays = [0, 1, 3, 2]

    def gen_ref(obs, prior, d, c):
        if prior is None:
            return R.sampler.naive_sample(RF, np.r_[obs, 0.0, 0.0], arr(c, Hc, A), 3)
        return R.methods.generate_chunk("train_soft", RF, np.r_[obs, 0.0, 0.0], arr(c, Hc, A), prior, s, d, 3)

    noises = jnp.asarray(np.stack([arr(c, Hc, A) for c in range(C)]), jnp.float32)

    def gen_jax(obs, prior, d, c):
        o = jnp.concatenate([obs, jnp.zeros(2)])[None]
        if prior is None:
            return JS.naive_sample(JFIELD, o, noises[c][None], 3)[0]
        return JM.generate_chunk("train_soft", JFIELD, o, noises[c][None], prior[None], s, d, 3)[0]

    ref_state = [np.zeros(1)]

    def env_ref(a):
        ref_state[0] = 0.9 * ref_state[0] + a[:1]
        return ref_state[0].copy()

    def env_jax(state, a):
        state = 0.9 * state + a[:1]
        return state, state

    want = R.executor.closed_loop(gen_ref, env_ref, np.zeros(1), C, Hc, s, delays)
    got = jax.jit(lambda ds: JX.closed_loop(gen_jax, env_jax, jnp.zeros(1), jnp.zeros(1), ds, Hc, s))(
        jnp.asarray(delays, jnp.int32))
    np.testing.assert_allclose(got["actions"], want["actions"], **TRAJ)
    np.testing.assert_allclose(got["chunks"], want["chunks"], **TRAJ)
    np.testing.assert_allclose(got["request_obs"], np.stack(want["request_obs"]), **TRAJ)
    np.testing.assert_allclose(got["priors"][1:], np.stack(want["priors"][1:]), **TRAJ)


# ---------------------------------------------------------------- M, V


_jerk = jax.jit(JMt.action_jerk)
_jump = jax.jit(JMt.boundary_jump)


@few
@given(st.integers(0, 10**6), st.data())
def test_metrics(seed, data):
    """M-1, M-2, M-3, M-4, M-6, M-7: D_k, delta, jerk, boundary jump (also truncated), SEM, high delay."""
    N, Ad = 24, 2
    a = arr(seed, N, Ad)
    for k in (1, 2, 3):
        np.testing.assert_allclose(JMt.difference_norm(a, k), R.metrics.difference_norm(a, k), **TOL)
    np.testing.assert_allclose(JMt.action_delta(a), R.metrics.action_delta(a), **TOL)
    np.testing.assert_allclose(JMt.action_jerk(a), R.metrics.action_jerk(a), **TOL)
    n = data.draw(st.integers(3, N))
    np.testing.assert_allclose(_jerk(a, n), R.metrics.action_jerk(a[:n]), **TOL)
    ramp = np.arange(6.0)[:, None] * np.array([[3.0, 4.0]])
    assert abs(float(JMt.action_jerk(ramp))) < 1e-6 and abs(float(JMt.action_delta(ramp)) - 5.0) < 1e-5
    ci = np.repeat(np.arange(N), data.draw(st.integers(1, 3)))[:N]
    if ci[-1] > 0:
        np.testing.assert_allclose(_jump(a, ci), R.metrics.boundary_jump(a, ci), **TOL)
        assert np.array_equal(np.nonzero(np.asarray(JMt.switch_mask(ci)))[0], R.metrics.switch_steps(ci))
    np.testing.assert_allclose(JMt.standard_error(a[:, 0]), R.metrics.standard_error(a[:, 0]), **TOL)
    solved = a[:, 0] > 0
    np.testing.assert_allclose(JMt.solve_rate(solved), R.metrics.solve_rate(solved), **TOL)
    assert np.asarray(JMt.is_high_delay(np.arange(6))).tolist() == [R.metrics.is_high_delay(d) for d in range(6)]


@few
@given(st.integers(0, 10**6), st.sampled_from([1, 5, 12]), st.sampled_from([0.9, 0.95]))
def test_bootstrap_from_indices(seed, n, conf):
    """M-5: the bootstrap interval from the NumPy index matrix equals the reference's."""
    vals = arr(seed, n)
    idx = R.metrics.bootstrap_indices(n, 500, seed)
    lo, hi = JMt.bootstrap_interval_from_indices(vals, idx, conf)
    want = R.metrics.bootstrap_interval_from_indices(vals, idx, conf)
    np.testing.assert_allclose([lo, hi], want, **TOL)


@few
@given(st.integers(0, 10**6))
def test_conventions(seed):
    """V-1, V-2, V-3: flipped time and velocity; the flipped Euler step is the naive step term by term."""
    rng = np.random.default_rng(seed)
    t, w, u = rng.random(8), rng.random(8), rng.standard_normal((8, 2))
    np.testing.assert_allclose(JV.to_flipped_time(t), R.conventions.to_flipped_time(t), **TOL)
    np.testing.assert_allclose(JV.from_flipped_time(t), R.conventions.from_flipped_time(t), **TOL)
    np.testing.assert_allclose(JV.from_flipped_velocity(u), R.conventions.from_flipped_velocity(u), **TOL)
    np.testing.assert_allclose(JV.flipped_token_times(w, 0.3), R.conventions.flipped_token_times(w, 0.3), **TOL)
    flipped = lambda obs, x, tf: -JFIELD(obs, x, 1.0 - tf)  # u(x, t') = -v(x, 1 - t')
    obs, noise, _ = _inputs(seed)
    np.testing.assert_allclose(JS.naive_sample(JV.flipped_velocity_fn(flipped), obs, noise, 4),
                               JS.naive_sample(JFIELD, obs, noise, 4), **TOL)


# ---------------------------------------------------------------- methods, validation



@pytest.mark.parametrize("method", R.methods.METHODS)
def test_methods(method):
    """S-6, G-1, W-7, W-8, X-2: method weights, tables, and chunks of every method for every
    executable delay, on the straightforward and the table-driven conditioned path."""
    window = R.SoftWindow(R.offset(2, 8), "exp")
    jw = JW.from_reference(window)
    table = np.asarray(JM.method_weight_table(method, H, 4, jw))
    tables = JM.method_tables(method, JFIELD, H, 4, 3, jw)
    obs, noise, prior = _inputs(11)
    for d in range(5):
        w = R.methods.method_weights(method, H, 4, d, window)
        np.testing.assert_allclose(JM.method_weights(method, H, 4, d, window), w, **TOL)
        np.testing.assert_allclose(table[d], w, **TOL)
        want = np.stack([R.methods.generate_chunk(method, RF, obs[i], noise[i], prior[i], 4, d, 3, window)
                         for i in range(B)])
        np.testing.assert_allclose(_gen(method, JFIELD, obs, noise, prior, 4, d, 3, jw), want, **TRAJ)
        np.testing.assert_allclose(_gen_c(method, JFIELD, obs, noise, prior, 4, d, 3, jw, tables=tables),
                                   want, **TRAJ)
    # Per-example delays [B] gather per-example weights and conditioning.
    ds = np.array([0, 2, 4])
    want = np.stack([R.methods.generate_chunk(method, RF, obs[i], noise[i], prior[i], 4, int(ds[i]), 3, window)
                     for i in range(B)])
    np.testing.assert_allclose(_gen_c(method, JFIELD, obs, noise, prior, 4, ds, 3, jw, tables=tables), want, **TRAJ)
    first = _gen(method, JFIELD, obs, noise, None, 4, 0, 3)
    assert np.array_equal(np.asarray(first), np.asarray(_naive(JFIELD, obs, noise, 3)))


def test_validation_errors():
    """N-7, X-1: static arguments, shapes and concrete values are validated with named ValueErrors."""
    obs, noise, prior = _inputs(0)
    cases = [
        (lambda: JW.soft_weights(8, 9, JW.SoftWindow(), 4), "d"),
        (lambda: JW.soft_weights(8, 2.0, JW.SoftWindow(), 4), "d"),
        (lambda: JW.soft_weights(8, True, JW.SoftWindow(), 4), "d"),
        (lambda: JW.soft_weights(4, 1, JW.SoftWindow(), 2), "h_max"),
        (lambda: JW.soft_weights(8, 1, JW.SoftWindow(), None), "s"),
        (lambda: JW.prefix_weights(8, 3, 2), "e"),
        (lambda: JW.SoftWindow(schedule="cosine"), "schedule"),
        (lambda: JW.schedule_value("linear", [1.5]), "x"),
        (lambda: JS.naive_sample(JFIELD, obs, noise, 0), "num_steps"),
        (lambda: JS.rtc_sample(JFIELD, obs, noise, prior[:, :4], np.zeros(H), 2), "prior"),
        (lambda: JS.rtc_sample(JFIELD, obs, noise, prior, np.full(H, 2.0), 2), "weights"),
        (lambda: JS.rtc_sample(JFIELD, obs[:2], noise, prior, np.zeros(H), 2), "obs"),
        (lambda: JS.naive_sample(JFIELD, obs, np.where(np.arange(A) == 0, np.nan, noise), 2), "noise"),
        (lambda: JG.guided_sample(JFIELD, obs, noise, prior, np.zeros(H), 2, max_guidance=0.0), "max_guidance"),
        (lambda: JM.method_weights("train_soft", H, 4, 5), "d"),
        (lambda: JM.method_weights("nope", H, 4, 1), "method"),
        (lambda: JM.generate_chunk("train_hard", JFIELD, obs, noise, None, 4, 1, 2), "d"),
        (lambda: JX.execute_chunks(np.zeros((3, 8, 2)), np.array([1, 0, 0]), 4), "delays"),
        (lambda: JX.execute_chunks(np.zeros((3, 8, 2)), np.array([0, 5, 0]), 4), "delays"),
        (lambda: JD.delay_probs("uniform", 3, 2), "d_max"),
        (lambda: JD.sample_delay(JD.delay_probs("uniform", 0, 3), 0, 1.0), "u"),
        (lambda: JL.flow_matching_loss(noise[0], noise[0], noise[0], np.zeros(H), eta=0.0), "eta"),
        (lambda: JMt.difference_norm(noise[0], 8), "actions"),
        (lambda: JMt.boundary_jump(noise[0], np.zeros(H, int)), "chunk_index"),
    ]
    for fn, name in cases:
        with pytest.raises(ValueError, match=name):
            fn()


def test_policy_fast_path_matches_straightforward():
    """S-3, S-6: with the flow policy, the table-driven conditioned path
    (time_conditioning once, apply_conditioned per step) equals policy(obs, x, t)."""
    import flax.nnx as nnx

    from softrtc.jax.policy import FlowPolicy, PolicyConfig

    cfg = PolicyConfig(channel_dim=8, channel_hidden_dim=16, token_hidden_dim=4, num_layers=1, action_chunk_size=H)
    graphdef, state = nnx.split(FlowPolicy(obs_dim=O, action_dim=A, config=cfg, rngs=nnx.Rngs(0)))
    # adaLN kernels start at zero; perturb every parameter so that time matters.
    leaves, treedef = jax.tree.flatten(state)
    rng = np.random.default_rng(5)
    state = jax.tree.unflatten(treedef, [np.asarray(x) + 0.3 * rng.standard_normal(x.shape).astype(np.float32)
                                         for x in leaves])
    obs, noise, prior = _inputs(21)

    @functools.partial(jax.jit, static_argnums=0)
    def both(method, state, obs, noise, prior, d):
        pol = nnx.merge(graphdef, state)
        tables = JM.method_tables(method, pol, H, 4, 3)
        slow = JM.generate_chunk(method, pol, obs, noise, prior, 4, d, 3)
        fast = JM.generate_chunk_conditioned(method, pol, obs, noise, prior, 4, d, 3, tables=tables)
        return slow, fast

    for d in (0, 3):
        slow, fast = both("train_soft", state, obs, noise, prior, d)
        np.testing.assert_allclose(fast, slow, **TRAJ)


def test_exp_schedule_is_exactly_one_at_zero_in_float32():
    """W-3, W-1: the exp schedule's denominator is expm1(1), so g(0) = 1 exactly and weights stay in [0, 1]."""
    import jax.numpy as jnp

    from softrtc.jax import weights as JW

    assert float(JW.schedule_value("exp", jnp.zeros(1, jnp.float32))[0]) == 1.0
    for H in range(1, 17):
        for d in range(H):
            w = JW.prefix_weights(H, d, H, "exp", "paper")
            assert float(jnp.max(w)) <= 1.0


def test_twin_api_differences_are_the_listed_ones():
    """N-10: window_positions returns all H tokens (the window's entries are the reference's) and rejects e < d
    like the reference; soft_weights defaults to SoftWindow(), the paper's main setting."""
    for p in ("rtc", "paper"):
        for d, e in ((2, 6), (0, 3), (3, 4)):
            full = np.asarray(JW.window_positions(8, d, e, p))
            assert full.shape == (8,)
            np.testing.assert_allclose(full[d:e], R.weights.window_positions(d, e, p), rtol=1e-6)
    for call in (lambda: JW.window_positions(8, 5, 3), lambda: R.weights.window_positions(5, 3)):
        with pytest.raises(ValueError, match="^e must be an integer"):
            call()
    np.testing.assert_allclose(np.asarray(JW.soft_weights(8, 3, s=4)),
                               R.weights.soft_weights(8, 3, R.SoftWindow(), s=4), rtol=1e-6)


def test_twin_rejects_what_jax_would_clamp_wrap_or_broadcast():
    """N-7: concrete inputs that XLA would silently clamp (gathers), wrap (int32) or broadcast are rejected."""
    import flax.nnx as nnx

    from softrtc.jax.policy import FlowPolicy, PolicyConfig

    pol = FlowPolicy(obs_dim=3, action_dim=2, config=PolicyConfig(channel_dim=8, channel_hidden_dim=16,
                     token_hidden_dim=4, num_layers=1, action_chunk_size=8), rngs=nnx.Rngs(0))
    obs, noise = jnp.zeros((2, 3)), jnp.zeros((2, 8, 2))
    table = JS.conditioning_table(pol, JM.method_weight_table("train_soft", 8, 4, None), 3)
    good = JM.method_tables("train_soft", pol, 8, 4, 3)
    cases = [
        (lambda: JS.select_conditioning(table, 5), r"^d must be an integer in \[0, 4\]"),
        (lambda: JS.select_conditioning(table, jnp.array([1, -1])), r"^d entries must be integers in \[0, 4\]"),
        (lambda: JM.generate_chunk_conditioned("train_soft", pol, obs, noise, noise, 4, 2, 3,
                                               tables=JM.method_tables("train_soft", pol, 8, 2, 3)),
         r"^tables\['weights'\] must have shape \[5, 8\]"),
        (lambda: JM.generate_chunk_conditioned("train_soft", pol, obs, noise, noise, 4, 2, 5, tables=good),
         r"^tables\['cond'\] must have leading axes \[5, 5\]"),
        (lambda: JS.naive_sample_conditioned(pol, obs, noise, 2, cond=JS.naive_conditioning(pol, 3)),
         r"^cond must have leading axes \[2\]"),
        (lambda: JX.execute_chunks(np.zeros((2, 8, 1)), np.array([0, 2**32 + 1]), 4), "delays"),
        (lambda: JMt.is_high_delay(np.int64(2**32 + 3)), r"^d entries must be integers"),
        (lambda: JMt.switch_mask(np.array([0, 2**32])), "chunk_index"),
        (lambda: JG.guidance_weight(0.5, max_guidance=1e300), "within float32 range"),
        (lambda: JC.corrupt(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(4), np.zeros(3)), "^tau must have"),
        (lambda: JV.to_flipped_time("0.5"), "real numeric array"),
        (lambda: JV.to_flipped_time(np.array([0.5 + 1j])), "real numeric array"),
        (lambda: JMt.standard_error([True, False]), "real numeric array"),
        (lambda: JE.endpoint(JE.EndpointRule(lam=jnp.float32(np.nan), h_max=jnp.int32(3), length=jnp.int32(0),
                                             kind="delay_scaled"), 1), r"^rule.lam must be"),
        (lambda: JW.soft_weights(8, 1, JW.SoftWindow(JE.EndpointRule(
            lam=jnp.float32(1), h_max=jnp.int32(-5), length=jnp.int32(0), kind="delay_scaled")), 4),
         r"^rule.h_max must be"),
        (lambda: JE.endpoint(JE.EndpointRule(lam=jnp.float32(1), h_max=jnp.int32(3), length=jnp.int32(0),
                                             kind="bogus"), 1), r"^rule.kind must be one of"),
        # E-1: a parameter the rule does not have is an error, not ignored.
        (lambda: JE.endpoint(JE.EndpointRule(lam=jnp.float32(1), h_max=jnp.int32(0), length=jnp.int32(0),
                                             kind="hard"), 1), r"^rule.lam is not a parameter of the 'hard'"),
        (lambda: R.endpoints.EndpointRule("hard", lam=float("nan")), r"^lam is not a parameter"),
        (lambda: R.endpoints.EndpointRule("delay_scaled", lam=2.0, h_max=5, length=-7), r"^length is not"),
    ]
    vf = lambda o, x, t: x  # noqa: E731
    probs = JD.delay_probs("uniform", 0, 4)
    cases += [
        (lambda: JD.sample_delays(5, probs, 0, 2), "^key must be a JAX PRNG key"),
        (lambda: JD.sample_delays(jax.random.key(0), probs, 0, 2.0), "^shape must be"),
        (lambda: JM.generate_chunk("naive", vf, obs, noise, noise, 4, 1, 2, window="bogus"), "^window must be"),
        (lambda: JM.generate_chunk("naive", vf, obs, noise, jnp.full_like(noise, jnp.nan), 4, 1, 2), "^prior"),
        (lambda: JM.generate_chunk("naive", vf, obs, noise, np.zeros(5), 4, 1, 2), r"^prior must have shape"),
        (lambda: JM.generate_chunk("train_soft", vf, obs, noise, noise, 4, jnp.array([1, 1, 1]), 2),
         r"^d must have shape \[2\]"),
    ]
    for call, pattern in cases:
        with pytest.raises(ValueError, match=pattern):
            call()
    # What is valid still runs, also under jit with concrete tables closed over.
    key = jax.random.key(1)
    assert np.array_equal(jax.jit(lambda k: JD.sample_delays(k, probs, 0, 3))(key), JD.sample_delays(key, probs, 0, 3))
    assert JM.generate_chunk_conditioned("train_soft", pol, obs, noise, noise, 4, 2, 3, tables=good).shape == (2, 8, 2)
    assert JC.corrupt(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(4), 0.5)[0].shape == (4, 2)


def test_method_request_checked_whole():
    """S-8: as the reference, the default window is resolved by train_soft only (other methods
    run for H < 5), and a window given to any method, on the first chunk too, must fit H."""
    small = R.SoftWindow(R.delay_scaled(2.0, 3))
    for method in R.methods.METHODS:
        win = small if method == "train_soft" else None
        np.testing.assert_allclose(JM.method_weights(method, 4, 2, 1, win),
                                   R.methods.method_weights(method, 4, 2, 1, win), **TOL)
        with pytest.raises(ValueError, match="h_max or h"):
            JM.method_weights(method, 4, 2, 1, JW.SoftWindow())
    with pytest.raises(ValueError, match="h_max or h"):
        JM.method_weights("train_soft", 4, 2, 1)
    obs, noise, prior = _inputs(2)
    for method in R.methods.METHODS:
        with pytest.raises(ValueError, match="window"):
            JM.generate_chunk(method, JFIELD, obs, noise, None, 4, 0, 2, window="junk")
        with pytest.raises(ValueError, match="window"):
            JM.generate_chunk_conditioned(method, JFIELD, obs, noise, None, 4, 0, 2, window="junk")


def test_shapes_are_not_broadcast():
    """N-7, N-1, S-3, V-3, M-7: the JAX twin rejects shapes XLA would broadcast and empty axes,
    as the reference does, and accepts the documented batch forms."""
    x = np.zeros((4, 2))
    with pytest.raises(ValueError, match="weights must have shape"):
        JS.blend(x, x, np.zeros(1))
    with pytest.raises(ValueError, match="weights must have shape"):
        JS.blend(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros((2, 1)))
    xb = np.ones((3, 4, 2))
    w = np.array([1.0, 0.5, 0.0, 0.0])
    np.testing.assert_allclose(JS.blend(xb, 0 * xb, w), np.broadcast_to((1 - w)[None, :, None], xb.shape))
    np.testing.assert_allclose(JS.blend(xb, 0 * xb, np.tile(w, (3, 1))), JS.blend(xb, 0 * xb, w))
    with pytest.raises(ValueError, match="t_flipped must be a scalar"):
        JV.flipped_token_times(np.zeros(3), np.zeros((2, 3)))
    wb = np.tile(np.array([1.0, 0.5, 0.0]), (2, 1))
    np.testing.assert_allclose(JV.flipped_token_times(wb, np.array([0.2, 0.4])),
                               (1 - wb) * np.array([[0.2], [0.4]]), rtol=1e-6)
    with pytest.raises(ValueError, match="d"):
        JMt.is_high_delay(-1)
    with pytest.raises(ValueError, match="at least one entry"):
        JC.corrupt(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0), 0.5)
    with pytest.raises(ValueError, match="at least one entry"):
        R.corruption.corrupt(np.zeros((3, 0)), np.zeros((3, 0)), np.zeros(3), 0.5)
