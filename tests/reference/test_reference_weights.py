"""Endpoints and token weights of the reference (spec/01-weights.md)."""

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from softrtc.reference import endpoints as E
from softrtc.reference import weights as W

def rules_within(H):
    """Endpoint rules whose bound (h_max or h) is at most H, as [E-1] requires for horizon H."""
    return st.one_of(
        st.builds(E.delay_scaled, st.sampled_from([0.0, 0.5, 1.0, 1.25, 1.5, 2.0, 3.0, 4.0, 1.6]), st.integers(0, H)),
        st.builds(E.offset, st.integers(0, 8), st.integers(0, H)),
        st.builds(E.fixed, st.integers(0, H)),
        st.just(E.hard()),
    )



@st.composite
def configs(draw):
    H = draw(st.integers(1, 16))
    rule = draw(rules_within(H))
    window = W.SoftWindow(rule, draw(st.sampled_from(W.SCHEDULES)), draw(st.sampled_from(W.PARAMETRIZATIONS)),
                          draw(st.sampled_from(W.OVERFLOWS)))
    s = draw(st.integers(1, H))
    d = draw(st.integers(0, H))
    return H, s, d, window


@given(configs())
def test_weight_properties(cfg):
    """W-1, W-7: weights in [0,1], non-increasing, 1 on the committed prefix, 0 on the tail."""
    H, s, d, window = cfg
    w = W.soft_weights(H, d, window, s)
    assert w.shape == (H,)
    assert np.all((w >= 0) & (w <= 1))
    assert np.all(np.diff(w) <= 0)
    assert np.all(w[:d] == 1.0)
    e = E.endpoint(window.rule, d)
    e_star = W.effective_endpoint(H, d, min(e, H), s, window.overflow)
    assert np.all(w[e_star:] == 0.0)


@given(configs(), st.data())
def test_prefix_clamped_when_endpoint_below_delay(cfg, data):
    """W-2: e(d) < d still clamps the committed prefix (e* = max(e, d)), for every rule kind that can fall below d."""
    H, s, d, window = cfg
    d = data.draw(st.integers(1, H))
    low = data.draw(st.integers(0, d - 1))  # an endpoint bound below d
    rule = data.draw(st.sampled_from([E.fixed(low), E.delay_scaled(2.0, low), E.offset(1, low)]))
    window = W.SoftWindow(rule, window.schedule, window.parametrization, window.overflow)
    assert E.endpoint(rule, d) < d
    w = W.soft_weights(H, d, window, s)
    np.testing.assert_array_equal(w, W.hard_weights(H, d))
    assert W.effective_endpoint(H, d, low, s, window.overflow) == d


def test_endpoint_rules_worked_examples():
    """E-1, E-2, E-3, E-4, E-5, E-6: the endpoint rules and e(0) = 0."""
    assert [E.endpoint(E.delay_scaled(2, 5), d) for d in range(6)] == [0, 2, 4, 5, 5, 5]
    assert [E.endpoint(E.delay_scaled(1.5, 8), d) for d in range(5)] == [0, 2, 3, 5, 6]
    assert [E.endpoint(E.offset(2, 8), d) for d in range(8)] == [0, 3, 4, 5, 6, 7, 8, 8]
    assert [E.endpoint(E.fixed(3), d) for d in range(5)] == [0, 3, 3, 3, 3]
    assert [E.endpoint(E.hard(), d) for d in range(5)] == [0, 1, 2, 3, 4]
    for rule in (E.delay_scaled(3.7, 9), E.offset(5, 9), E.fixed(4), E.hard()):
        assert E.endpoint(rule, 0) == 0


def test_delay_scaled_ceil_means_the_decimal_lam():
    """E-2: ceil(lam * d - 1e-4) on the float's exact value gives the endpoint of the decimal lam."""
    # 1.1 is stored as 1.100000000000000088...: its exact binary ceiling at d = 10 is 12, not the 11 meant.
    assert math.ceil(Fraction(1.1) * 10) == 12
    assert E.endpoint(E.delay_scaled(1.1, 100), 10) == 11
    # The float64 product 0.28 * 25 is 7.000000000000001: its ceiling is 8, not the 7 meant.
    assert math.ceil(0.28 * 25) == 8 and E.endpoint(E.delay_scaled(0.28, 100), 25) == 7
    assert math.ceil(Fraction(1.6) * 5) == 9 and E.endpoint(E.delay_scaled(1.6, 100), 5) == 8
    assert E.endpoint(E.delay_scaled(0.7, 100), 10) == 7  # stored below 0.7: the product lies below 7
    assert E.endpoint(E.delay_scaled(2.5, 100), 3) == 8
    assert E.endpoint(E.delay_scaled(1.0001, 100), 2) == 3  # 2.0002 is above 2 by more than delta
    assert E.endpoint(E.delay_scaled(1.00001, 100), 2) == 2  # 2.00002 is within delta of 2
    # Every lam with three decimals gives the decimal ceiling.
    for k in range(0, 4001, 7):
        for d in range(0, 40):
            assert E.endpoint(E.delay_scaled(k / 1000, 4096), d) == -(-(k * d) // 1000), (k, d)


def test_schedules():
    """W-3: schedule values and shape of each schedule."""
    x = np.linspace(0, 1, 11)
    assert np.all(W.schedule_value("zeros", x) == 0)
    assert np.all(W.schedule_value("ones", x) == 1)
    np.testing.assert_allclose(W.schedule_value("linear", x), 1 - x)
    u = 1 - x
    np.testing.assert_allclose(W.schedule_value("exp", x), u * np.expm1(u) / (math.e - 1))
    assert W.schedule_value("exp", np.array([0.0]))[0] == 1.0  # exactly: expm1 in numerator and denominator
    for name in W.SCHEDULES:
        assert np.all(np.diff(W.schedule_value(name, x)) <= 0)
    # Every schedule acts on the window only: `ones` is 1 before the end and 0 from it on.
    for par in W.PARAMETRIZATIONS:
        np.testing.assert_array_equal(W.prefix_weights(10, 2, 6, "ones", par), [1] * 6 + [0] * 4)


def test_parametrizations_worked_example():
    """W-4, W-5: rtc and paper window forms on d=2, e=6, H=10."""
    np.testing.assert_allclose(W.prefix_weights(10, 2, 6, "linear", "rtc"),
                               [1, 1, 0.8, 0.6, 0.4, 0.2, 0, 0, 0, 0])
    np.testing.assert_allclose(W.prefix_weights(10, 2, 6, "linear", "paper"),
                               [1, 1, 1, 0.75, 0.5, 0.25, 0, 0, 0, 0])
    w = W.prefix_weights(16, 3, 11, "linear", "rtc")
    assert np.all((w[3:11] > 0) & (w[3:11] < 1))


@given(st.integers(1, 16), st.integers(0, 15), st.integers(1, 8))
def test_rtc_linear_closed_form(H, d, n):
    """W-4: rtc linear weights equal (e - j) / (e - d + 1) on the window."""
    d = min(d, H - 1)
    e = min(d + n, H)
    w = W.prefix_weights(H, d, e, "linear", "rtc")
    j = np.arange(d, e)
    np.testing.assert_allclose(w[d:e], (e - j) / (e - d + 1), rtol=0, atol=1e-15)


def test_paper_window_of_one_is_hard_with_longer_prefix():
    """W-5: under 'paper', a length-one window is Hard RTC with d+1."""
    w = W.soft_weights(8, 1, W.SoftWindow(E.delay_scaled(2, 5), "linear", "paper"), 4)
    np.testing.assert_array_equal(w, W.hard_weights(8, 2))


def test_overflow_clip_and_zeros():
    """W-6: clip caps the window at o = H - s; zeros lets it run past o."""
    clip = W.SoftWindow(E.delay_scaled(2, 5), overflow="clip")
    zeros = W.SoftWindow(E.delay_scaled(2, 5), overflow="zeros")
    np.testing.assert_allclose(W.soft_weights(8, 3, clip, 4), [1, 1, 1, 0.5, 0, 0, 0, 0])
    np.testing.assert_allclose(W.soft_weights(8, 3, zeros, 4), [1, 1, 1, 2 / 3, 1 / 3, 0, 0, 0])
    np.testing.assert_array_equal(W.soft_weights(8, 4, clip, 4), W.hard_weights(8, 4))
    with pytest.raises(ValueError, match="s "):
        W.soft_weights(8, 3, clip)


def test_default_window_table():
    """W-7: the default window on H=8, s=4 gives the table of the spec."""
    table = [W.soft_weights(8, d, W.SoftWindow(), 4) for d in range(5)]
    np.testing.assert_allclose(table[1], [1, 0.5, 0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(table[2], [1, 1, 2 / 3, 1 / 3, 0, 0, 0, 0])
    np.testing.assert_allclose(table[3], [1, 1, 1, 0.5, 0, 0, 0, 0])
    np.testing.assert_array_equal(table[4], W.hard_weights(8, 4))


@given(configs())
def test_hard_rtc_special_cases_are_bitwise_hard(cfg):
    """W-8, E-3, E-5: zeros schedule, offset L=0, lam=1 and the hard rule are exactly Hard RTC."""
    H, s, d, window = cfg
    hard = W.hard_weights(H, d)
    np.testing.assert_array_equal(hard, (np.arange(H) < d).astype(float))
    for rule in (window.rule, E.offset(0, H), E.delay_scaled(1, H), E.hard()):
        for par in W.PARAMETRIZATIONS:
            for ov in W.OVERFLOWS:
                if rule is window.rule:
                    w = W.soft_weights(H, d, W.SoftWindow(rule, "zeros", par, ov), s)
                else:
                    w = W.soft_weights(H, d, W.SoftWindow(rule, window.schedule, par, ov), s)
                assert np.array_equal(w, hard), (rule, par, ov)


@given(configs())
def test_zero_delay_is_no_rtc(cfg):
    """W-9, E-6: d = 0 gives all-zero weights for every rule and schedule."""
    H, s, _, window = cfg
    assert np.array_equal(W.soft_weights(H, 0, window, s), np.zeros(H))
