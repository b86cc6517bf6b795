"""Executor, metrics and conventions of the reference (spec/04..06)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from softrtc.reference import conventions as V
from softrtc.reference import executor as X
from softrtc.reference import metrics as M
from softrtc.reference import sampler as S
from softrtc.reference import weights as W
from softrtc.reference.velocity import ReferenceVelocityField


@st.composite
def schedules(draw):
    H = draw(st.integers(2, 12))
    s = draw(st.integers(1, H - 1))
    C = draw(st.integers(1, 6))
    dmax = min(s, H - s)
    delays = [0] + [draw(st.integers(0, dmax)) for _ in range(C - 1)]
    A = draw(st.integers(1, 3))
    chunks = np.random.default_rng(draw(st.integers(0, 99))).standard_normal((C, H, A))
    return H, s, delays, chunks


def test_executable_delays():
    """X-1: 0 <= d <= min(s, H - s); anything else is rejected, never clipped."""
    assert X.check_delay(8, 4, 4) == 4
    for H, s, d in ((8, 4, 5), (8, 6, 3), (8, 2, 3), (8, 4, -1), (4, 4, 1)):
        with pytest.raises(ValueError, match="d must be"):
            X.check_delay(H, s, d)


@given(schedules())
def test_segments_execute_committed_prefix_from_previous_chunk(cfg):
    """X-2, X-4, X-5: the first d steps of each segment come from the previous chunk."""
    H, s, delays, chunks = cfg
    out = X.execute_chunks(chunks, delays, s)
    acts, ci, tj = out["actions"], out["chunk_index"], out["token_index"]
    assert acts.shape == (len(delays) * s, chunks.shape[2])
    np.testing.assert_array_equal(acts[:s], chunks[0, :s])  # first chunk, no delay
    for c in range(1, len(delays)):
        d = delays[c]
        seg = slice(c * s, c * s + s)
        np.testing.assert_array_equal(acts[seg][:d], chunks[c - 1, s:s + d])
        np.testing.assert_array_equal(acts[seg][d:], chunks[c, d:s])
        assert list(ci[seg]) == [c - 1] * d + [c] * (s - d)
    for t in range(acts.shape[0]):
        np.testing.assert_array_equal(acts[t], chunks[ci[t], tj[t]])


def test_shift_prior():
    """X-3: Y[j] = P[j + s] for j < H - s and 0 past the overlap."""
    P = np.arange(16.0).reshape(8, 2)
    Y = X.shift_prior(P, 3)
    np.testing.assert_array_equal(Y[:5], P[3:])
    assert np.all(Y[5:] == 0)


def test_closed_loop_observation_timing():
    """X-6: request c sees the observation after c*s actions; prior is the shifted previous chunk."""
    H, s = 8, 4
    field = ReferenceVelocityField.init(0, H, 1, 1)
    count = {"n": 0}

    def env_step(a):
        count["n"] += 1
        return np.array([float(count["n"])])

    seen = []

    def generate(obs, prior, d, c):
        seen.append((float(obs[0]), None if prior is None else prior.copy(), d))
        noise = np.random.default_rng(c).standard_normal((H, 1))
        w = W.soft_weights(H, d, W.SoftWindow(), s)
        return S.naive_sample(field, obs, noise, 5) if prior is None else S.rtc_sample(field, obs, noise, prior, w, 5)

    out = X.closed_loop(generate, env_step, np.array([0.0]), 4, H, s, [0, 1, 2, 3])
    assert [o for o, _, _ in seen] == [0.0, 4.0, 8.0, 12.0]
    assert seen[0][1] is None
    for c in range(1, 4):
        # written out: Y[j] = P[j + s] for j < H - s, 0 beyond.
        want = np.zeros((H, 1))
        want[: H - s] = out["chunks"][c - 1][s:]
        np.testing.assert_array_equal(seen[c][1], want)
    ref = X.execute_chunks(out["chunks"], [0, 1, 2, 3], s)
    np.testing.assert_array_equal(out["actions"], ref["actions"])


def test_metrics_on_known_sequences():
    """M-1, M-2: D_k on ramps and quadratics; a linear ramp has zero jerk."""
    t = np.arange(10.0)[:, None]
    ramp = t * np.array([[3.0, 4.0]])
    assert M.action_delta(ramp) == 5.0
    assert M.action_jerk(ramp) == 0.0
    quad = t ** 2
    assert M.difference_norm(quad, 2) == 2.0
    assert M.difference_norm(quad, 3) == 0.0
    np.testing.assert_array_equal(M.finite_differences(quad, 1)[:, 0], 2 * np.arange(9) + 1)
    with pytest.raises(ValueError, match="more than order"):
        M.difference_norm(np.zeros((2, 1)), 2)


def test_boundary_jump():
    """M-3: mean jump over steps whose source chunk changes."""
    a = np.array([[0.0], [0.0], [3.0], [3.0], [7.0]])
    ci = np.array([0, 0, 1, 1, 2])
    np.testing.assert_array_equal(M.switch_steps(ci), [2, 4])
    assert M.boundary_jump(a, ci) == 3.5
    with pytest.raises(ValueError, match="no chunk switch"):
        M.boundary_jump(a, np.zeros(5, int))


def test_solve_rate_and_standard_error():
    """M-4, M-6: solve rate and standard error of the mean."""
    assert M.solve_rate(np.array([True, False, True, True])) == 0.75
    v = np.array([1.0, 2.0, 3.0, 4.0])
    assert M.standard_error(v) == pytest.approx(np.std(v, ddof=1) / 2)


def test_bootstrap_interval():
    """M-5: the interval is the percentile interval of resampled means from the index matrix."""
    v = np.array([0.2, 0.5, 0.9, 0.4, 0.7])
    idx = M.bootstrap_indices(5, 10000, 0)
    np.testing.assert_array_equal(idx, np.random.default_rng(0).integers(0, 5, size=(10000, 5)))
    lo, hi = M.bootstrap_interval(v)
    means = v[idx].mean(axis=1)
    assert (lo, hi) == tuple(np.quantile(means, [0.025, 0.975]))
    assert lo < v.mean() < hi
    assert M.bootstrap_interval(v, seed=0) == M.bootstrap_interval(v, seed=0)
    assert not np.array_equal(M.bootstrap_indices(5, 100, 0), M.bootstrap_indices(5, 100, 1))  # the seed is used


def test_high_delay():
    """M-7: high delay means d in {3, 4}."""
    assert [M.is_high_delay(d) for d in range(6)] == [False, False, False, True, True, False]


def test_flipped_time_mapping():
    """V-1, V-2, V-3: flipped time t' = 1 - t, u = -v, and the Euler step is the same."""
    field = ReferenceVelocityField.init(1, 4, 2, 3)
    rng = np.random.default_rng(0)
    obs, noise, prior = rng.standard_normal(3), rng.standard_normal((4, 2)), rng.standard_normal((4, 2))
    w = np.array([1.0, 0.5, 0.0, 0.0])

    def flipped_field(o, x, tf):  # a network trained in the flipped convention
        return -field(o, x, 1.0 - tf)

    x = noise.copy()
    T = 5
    for k in range(T):
        tf = 1.0 - k / T
        xb = w[:, None] * prior + (1 - w[:, None]) * x
        x = xb + (-1.0 / T) * flipped_field(obs, xb, V.flipped_token_times(w, tf))
    np.testing.assert_allclose(x, S.rtc_sample(field, obs, noise, prior, w, T), atol=1e-12)
    np.testing.assert_allclose(V.flipped_token_times(w, 0.3), 1 - (w + (1 - w) * 0.7))
    np.testing.assert_array_equal(V.from_flipped_time(V.to_flipped_time(np.array([0.25]))), [0.25])
    np.testing.assert_array_equal(V.from_flipped_velocity(np.array([1.0, -2.0])), [-1.0, 2.0])


def test_naming_and_batch_conventions():
    """V-4, V-5, G-1, W-4: inference_delay = d; the window end (prefix_attention_horizon, and LeRobot's
    execution_horizon) is e, H - s for the guidance weights; execute horizon s; batches per example."""
    from softrtc.reference.guidance import guidance_prefix_weights
    from softrtc.reference.weights import prefix_weights
    H, s, inference_delay = 8, 4, 2
    prefix_attention_horizon = H - s
    w = guidance_prefix_weights(H, s, inference_delay, "hard")
    assert w.sum() == inference_delay and w[prefix_attention_horizon:].sum() == 0
    # A chunk of 50 with window end E = 10 (the end, not the 40 actions executed): 1 on the prefix,
    # (E - j) / (E - d + 1) on the window, 0 after it.
    H, s, d = 50, 40, 5
    E = H - s
    w = prefix_weights(H, d, E, "linear", "rtc")
    np.testing.assert_allclose(w[:d], 1.0)
    np.testing.assert_allclose(w[d:E], (E - np.arange(d, E)) / (E - d + 1))
    assert not w[E:].any()
    # The soft guidance weights on the same window, exp schedule written out: u expm1(u) / expm1(1), u = 1 - x.
    u = 1.0 - (np.arange(d, E) - d + 1) / (E - d + 1)
    soft = guidance_prefix_weights(H, s, d, "soft")
    np.testing.assert_allclose(soft[d:E], u * np.expm1(u) / np.expm1(1.0), rtol=0, atol=1e-15)
    assert np.all(soft[:d] == 1.0) and not soft[E:].any()
    # Reading the execute horizon s as the window end guides a different window.
    assert not np.array_equal(prefix_weights(H, d, s, "exp", "rtc"), guidance_prefix_weights(H, s, d, "soft"))
    from softrtc.reference.loss import batch_loss, flow_matching_loss
    rng = np.random.default_rng(0)
    p, a, n = rng.standard_normal((3, 2, 4, 1))
    ws = np.zeros((2, 4))
    assert batch_loss(p, a, n, ws) == np.mean([flow_matching_loss(p[i], a[i], n[i], ws[i]) for i in range(2)])


def test_undefined_smoothness_metrics_are_left_out():
    """M-8: D_k with N <= k and a jump with no switch raise in the reference."""
    a = np.arange(6.0).reshape(3, 2)
    with pytest.raises(ValueError, match="chunk switch"):
        M.boundary_jump(a, np.zeros(3, int))
    with pytest.raises(ValueError, match="order"):
        M.difference_norm(a[:2], 2)
    # One switch after step 1: the jump is |a_2 - a_1| = |(4, 5) - (2, 3)| = sqrt(8).
    assert M.boundary_jump(a, np.array([0, 0, 1])) == pytest.approx(np.sqrt(8.0))

def test_public_first_segment():
    """X-7: the public loop's first segment is first[:d] then second[d:s], both chunks in the reset frame."""
    first = np.arange(16.0).reshape(8, 2)
    second = 100.0 + np.arange(16.0).reshape(8, 2)
    seg = X.public_first_segment(first, second, 4, 3)
    np.testing.assert_array_equal(seg, [[0, 1], [2, 3], [4, 5], [106, 107]])
    np.testing.assert_array_equal(X.public_first_segment(first, second, 4, 0), second[:4])
    with pytest.raises(ValueError, match="d must be"):
        X.public_first_segment(first, second, 4, 5)
    with pytest.raises(ValueError, match="second_chunk"):
        X.public_first_segment(first, second[:6], 4, 1)
