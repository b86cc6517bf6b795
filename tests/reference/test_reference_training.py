"""Delays, corruption and loss of the reference (spec/02-training.md)."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from softrtc.reference import corruption as C
from softrtc.reference import delays as D
from softrtc.reference import loss as L
from softrtc.reference import weights as W
from softrtc.reference.endpoints import delay_scaled

finite = st.floats(-10, 10, allow_nan=False, allow_infinity=False)


@st.composite
def chunks(draw, H=None, A=None):
    H = H or draw(st.integers(1, 12))
    A = A or draw(st.integers(1, 4))
    a = draw(arrays(np.float64, (H, A), elements=finite))
    n = draw(arrays(np.float64, (H, A), elements=finite))
    return a, n


def test_uniform_and_exponential_tables():
    """D-1, D-2: probability tables."""
    np.testing.assert_allclose(D.delay_probs("uniform", 1, 4), [0.25] * 4)
    p = D.delay_probs("exponential", 0, 4, decay=0.5)
    np.testing.assert_allclose(p, np.exp(-0.5 * np.arange(5)) / np.exp(-0.5 * np.arange(5)).sum())
    np.testing.assert_allclose(D.delay_probs("exponential", 2, 5, decay=0.0), D.delay_probs("uniform", 2, 5))
    assert np.all(np.diff(p) < 0)


@given(st.integers(0, 5), st.integers(0, 6), st.floats(0, 3), st.floats(0, 1, exclude_max=True))
def test_inverse_cdf_sampling(d_min, n, decay, u):
    """D-3: d = d_min + #{k: cdf_k <= u}; the draw lies in range and follows the CDF."""
    d_max = d_min + n
    p = D.delay_probs("exponential", d_min, d_max, decay)
    d = D.sample_delay(p, d_min, u)
    assert d_min <= d <= d_max
    c = np.cumsum(p)
    k = d - d_min
    assert (k == 0 or c[k - 1] <= u + 1e-12) and (u < c[k] or k == n)


def test_cdf_last_entry_is_exactly_one():
    """D-3, D-2: the last CDF entry is 1 exactly, so u just below 1 still draws d_max (the plain
    cumulative sum of six sixths ends at 0.9999999999999999 and would draw d_max + 1); decay is
    checked even where the uniform table ignores it."""
    p = D.delay_probs("uniform", 0, 5)
    assert np.cumsum(p)[-1] < 1.0 and D.delay_cdf(p)[-1] == 1.0
    u = float(np.nextafter(1.0, 0.0))
    assert D.sample_delay(p, 0, u) == 5
    for bad in (float("nan"), -5.0, 65.0):
        with pytest.raises(ValueError, match="decay"):
            D.delay_probs("uniform", 0, 3, decay=bad)


def test_sampling_frequencies_match_table():
    """D-3, D-4: many independent draws reproduce the table; same seed, same draws."""
    p = D.delay_probs("exponential", 0, 4, 0.7)
    u = np.random.default_rng(0).random(20000)
    draws = np.array([D.sample_delay(p, 0, x) for x in u])
    np.testing.assert_allclose(np.bincount(draws, minlength=5) / u.size, p, atol=0.015)
    u2 = np.random.default_rng(0).random(20000)
    assert np.array_equal(draws, [D.sample_delay(p, 0, x) for x in u2])


@given(chunks(), st.floats(0, 1), st.data())
def test_corruption_formula(an, tau, data):
    """C-1, C-2: tau_j = w + (1-w) tau and x = tau_j A + (1 - tau_j) eps; w=1 gives A exactly."""
    a, n = an
    H = a.shape[0]
    w = np.array(data.draw(st.lists(st.sampled_from([0.0, 0.25, 0.5, 1.0]), min_size=H, max_size=H)))
    x, tj = C.corrupt(a, n, w, tau)
    np.testing.assert_allclose(tj, w + (1 - w) * tau)
    np.testing.assert_allclose(x, tj[:, None] * a + (1 - tj[:, None]) * n)
    assert np.array_equal(x[w == 1.0], a[w == 1.0])


@given(chunks(), st.floats(0, 1))
def test_zero_weights_is_plain_flow_matching(an, tau):
    """C-3, E-6: w = 0 (or d = 0 under any rule) is bitwise the ordinary interpolant."""
    a, n = an
    H = a.shape[0]
    w0 = W.soft_weights(H, 0, W.SoftWindow(delay_scaled(2, min(5, H))), s=H)
    x, tj = C.corrupt(a, n, w0, tau)
    assert np.array_equal(x, tau * a + (1 - tau) * n)
    assert np.all(tj == tau)


@given(chunks(), st.data())
def test_loss_masks_clamped_tokens(an, data):
    """L-1, L-2: clamped tokens have zero weight; changing their prediction leaves the loss unchanged."""
    a, n = an
    H, A = a.shape
    d = data.draw(st.integers(0, H))
    w = W.hard_weights(H, d)
    pred = data.draw(arrays(np.float64, (H, A), elements=finite))
    other = pred.copy()
    other[:d] += 100.0
    assert L.flow_matching_loss(pred, a, n, w) == L.flow_matching_loss(other, a, n, w)
    l = np.sum((pred - (a - n)) ** 2, axis=-1)
    np.testing.assert_allclose(L.token_errors(pred, a, n), l)
    m = 1 - w
    np.testing.assert_allclose(L.flow_matching_loss(pred, a, n, w), np.sum(m * l) / (np.sum(m) + 1e-8))


def test_loss_all_clamped_is_zero_and_normalizer():
    """L-2: all tokens clamped gives 0; the normalizer divides by sum(1-w) + eta."""
    a = np.ones((4, 2)); n = np.zeros((4, 2)); p = np.zeros((4, 2))
    assert L.flow_matching_loss(p, a, n, np.ones(4)) == 0.0
    w = np.array([1.0, 0.5, 0.0, 0.0])
    assert L.flow_matching_loss(p, a, n, w) == pytest.approx((0.5 * 2 + 2 + 2) / (2.5 + 1e-8), rel=1e-15)


def test_batch_loss_is_mean_of_examples():
    """L-3: the batch loss averages per-example losses."""
    rng = np.random.default_rng(1)
    p, a, n = rng.standard_normal((3, 3, 4, 2))
    w = np.stack([W.hard_weights(4, d) for d in (0, 1, 3)])
    want = np.mean([L.flow_matching_loss(p[i], a[i], n[i], w[i]) for i in range(3)])
    assert L.batch_loss(p, a, n, w) == want


@given(chunks(), st.data())
def test_no_rtc_and_zero_delay_loss_identical(an, data):
    """L-4: w = 0 gives sum(l) / (H + eta), the same for no-RTC and d = 0."""
    a, n = an
    H, A = a.shape
    pred = data.draw(arrays(np.float64, (H, A), elements=finite))
    l0 = L.flow_matching_loss(pred, a, n, np.zeros(H))
    l1 = L.flow_matching_loss(pred, a, n, W.hard_weights(H, 0))
    assert l0 == l1
    assert l0 == pytest.approx(np.sum(L.token_errors(pred, a, n)) / (H + 1e-8), rel=1e-12)
