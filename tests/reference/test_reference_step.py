"""The training-time sampler's solver step: Algorithm 1 and the time-consistent step (spec 3.2.1).

Expected values come from closed forms derived in the spec ([S-9], [S-10]), hand-computed
numbers ([S-13]) or an independent formulation written out here, never from the sampler itself.
"""

import itertools

import numpy as np
import pytest

from softrtc.reference import methods as Mth
from softrtc.reference import sampler as S
from softrtc.reference import weights as W
from softrtc.reference.velocity import ReferenceVelocityField

# (H, d, e) with a window; T; schedules and parametrizations of [W-3]..[W-5].
GRID = [(H, d, e, T, sch, par)
        for (H, d, e), T, sch, par in itertools.product(
            [(8, 2, 6), (10, 0, 10), (5, 1, 4), (12, 3, 9)], [1, 2, 5, 10],
            ["linear", "exp"], ["rtc", "paper"])]


def alpha_algorithm1(w, T):
    """[S-9]: flow time of Algorithm 1's result on the oracle path, alpha_T = (w + 1/T)(1 - (1 - w)^T) / w."""
    w = np.asarray(w, dtype=float)
    safe = np.where(w > 0, w, 1.0)
    return np.where(w > 0, (w + 1.0 / T) * (1.0 - (1.0 - w) ** T) / safe, 1.0)


def oracle(A, eps):
    """The on-path oracle field v = A - eps (constant in x and t)."""
    return lambda obs, x, t: A - eps


def point_mass(A):
    """v = (A - x) / (1 - t) per token; 0 at t = 1 (only a w = 1 token, whose state is then A exactly)."""
    def field(obs, x, t):
        t = np.asarray(t)[:, None]
        return np.where(t < 1.0, (A - x) / np.where(t < 1.0, 1.0 - t, 1.0), 0.0)
    return field


def problem(H, seed, A_dim=3):
    rng = np.random.default_rng(seed)
    return rng.standard_normal((H, A_dim)), rng.standard_normal((H, A_dim))  # A (target), eps (noise)


@pytest.mark.parametrize("H,d,e,T,sch,par", GRID)
def test_oracle_field_consistent_exact_algorithm1_closed_form(H, d, e, T, sch, par):
    """S-9, S-10: under the on-path oracle field with Y = A the consistent step returns A on window and
    free tokens, while Algorithm 1 returns A + (alpha_T - 1)(A - eps) with the closed-form alpha_T on every
    token (1 + 1/T on the prefix); the two differ on window tokens when T >= 2."""
    A, eps = problem(H, 7 * H + d + T)
    w = W.prefix_weights(H, d, e, sch, par)
    obs = np.zeros(1)
    alg = S.rtc_sample(oracle(A, eps), obs, eps, A, w, T)
    con = S.rtc_sample(oracle(A, eps), obs, eps, A, w, T, step="consistent")
    expect = A + (alpha_algorithm1(w, T) - 1.0)[:, None] * (A - eps)
    np.testing.assert_allclose(alg, expect, rtol=1e-12, atol=1e-12)
    free = w < 1.0
    np.testing.assert_allclose(con[free], A[free], rtol=0, atol=1e-13)
    np.testing.assert_allclose(con[~free], A[~free] + (A - eps)[~free] / T, rtol=0, atol=1e-13)  # [S-5]
    window = (w > 0.0) & (w < 1.0)
    if T >= 2 and window.any():
        assert np.all(np.abs(alg[window] - A[window]).max(axis=1) > 1e-3)


def test_oracle_closed_form_values():
    """S-9: alpha_T by hand: w = .5, T = 5 gives 1.4 * 31 / 32 = 1.35625; w = 1 gives 1 + 1/T; w = 0 gives 1.
    And the sampler's window token lands there."""
    assert alpha_algorithm1(0.5, 5) == pytest.approx(1.35625, abs=1e-15)
    assert alpha_algorithm1(1.0, 4) == pytest.approx(1.25, abs=1e-15)
    assert alpha_algorithm1(0.0, 4) == 1.0
    A, eps = np.array([[2.0]]), np.array([[0.0]])
    x = S.rtc_sample(oracle(A, eps), np.zeros(1), eps, A, np.array([0.5]), 5)
    assert x[0, 0] == pytest.approx(2.0 * 1.35625, abs=1e-13)


@pytest.mark.parametrize("H,d,e,T,sch,par", [g for g in GRID if g[3] >= 2])
def test_point_mass_field(H, d, e, T, sch, par):
    """S-9, S-10: under v = (A - x)/(1 - t) with Y = A the consistent step returns A on window and free
    tokens; Algorithm 1 misses by (eps - A) prod_k (1 - w - 1/(T - k)) on those tokens."""
    A, eps = problem(H, 3 * H + e + T)
    w = W.prefix_weights(H, d, e, sch, par)
    obs = np.zeros(1)
    con = S.rtc_sample(point_mass(A), obs, eps, A, w, T, step="consistent")
    alg = S.rtc_sample(point_mass(A), obs, eps, A, w, T)
    free = w < 1.0
    np.testing.assert_allclose(con[free], A[free], rtol=0, atol=1e-12)
    factor = np.prod([1.0 - w - 1.0 / (T - k) for k in range(T)], axis=0)
    np.testing.assert_allclose(alg[free], (A + factor[:, None] * (eps - A))[free], rtol=0, atol=1e-12)


def test_point_mass_algorithm1_value():
    """S-9: w = .25, T = 5: the factor is .55 * .5 * (5/12) * .25 * (-.25) = -0.00716145833..."""
    A, eps = np.array([[1.0]]), np.array([[0.0]])
    x = S.rtc_sample(point_mass(A), np.zeros(1), eps, A, np.array([0.25]), 5)
    assert x[0, 0] - 1.0 == pytest.approx(-0.55 * 0.5 * (5 / 12) * 0.25 * (-0.25), abs=1e-14)


def test_worked_example():
    """S-13: v = 1, T = 4, x0 = 0, Y = 5, w = [1, .5, 0]: Algorithm 1 [5.25, 5.15625, 1.0], consistent
    [5.25, 3.0, 1.0] (by hand: x <- 2.5 + .5 x + .25 four times gives 5.15625; .5 * 5 + .5 * 1 = 3)."""
    one = lambda obs, x, t: np.ones_like(x)
    y, w = np.full((3, 1), 5.0), np.array([1.0, 0.5, 0.0])
    assert S.rtc_sample(one, np.zeros(1), np.zeros((3, 1)), y, w, 4)[:, 0].tolist() == [5.25, 5.15625, 1.0]
    assert S.rtc_sample(one, np.zeros(1), np.zeros((3, 1)), y, w, 4, step="consistent")[:, 0].tolist() == [
        5.25, 3.0, 1.0]


def test_prior_keeps_its_direct_weight():
    """S-12: under a field that ignores its input and a prior Y != A, the consistent step returns
    w Y + (1 - w) A on window tokens (the pull the weights define), not A (candidate (b))."""
    rng = np.random.default_rng(5)
    A, eps, Y = rng.standard_normal((3, 6, 2))
    w = W.prefix_weights(6, 1, 5, "linear")
    x = S.rtc_sample(oracle(A, eps), np.zeros(1), eps, Y, w, 7, step="consistent")
    window = (w > 0) & (w < 1)
    np.testing.assert_allclose(x[window], (w[:, None] * Y + (1 - w[:, None]) * A)[window], atol=1e-13)


@pytest.mark.parametrize("T", [1, 3, 8])
def test_consistent_equals_unblended_formulation(T):
    """S-10: with a token-mixing field the carried state is w Y + (1 - w) u^k, u^{k+1} = u^k + v(w Y +
    (1 - w) u^k, t~) / T (written out here); w = 1 tokens end at Y + v / T."""
    f = ReferenceVelocityField.init(2, 8, 2, 3, hidden=16)
    rng = np.random.default_rng(9)
    obs, eps, Y = rng.standard_normal(3), rng.standard_normal((8, 2)), rng.standard_normal((8, 2))
    w = W.soft_weights(8, 2, W.SoftWindow(), 4)
    wc = w[:, None]
    u = eps.copy()
    for k in range(T):
        z = wc * Y + (1 - wc) * u
        v = f(obs, z, w + (1 - w) * (k / T))
        u = u + v / T
    expect = np.where(wc == 1.0, Y + v / T, wc * Y + (1 - wc) * u)
    got = S.rtc_sample(f, obs, eps, Y, w, T, step="consistent")
    np.testing.assert_allclose(got, expect, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("seed,T,d", [(0, 1, 0), (1, 5, 2), (2, 10, 4), (3, 3, 8)])
def test_hard_and_naive_bitwise_unchanged(seed, T, d):
    """S-11: for weights in {0, 1} (hard, zero) the consistent step is bitwise Algorithm 1, and with w = 0
    bitwise the naive sampler ([S-7])."""
    f = ReferenceVelocityField.init(seed, 8, 2, 3, hidden=16)
    rng = np.random.default_rng(seed)
    obs, eps, Y = rng.standard_normal(3), rng.standard_normal((8, 2)), rng.standard_normal((8, 2))
    for w in (W.hard_weights(8, d), np.zeros(8)):
        a = S.rtc_sample(f, obs, eps, Y, w, T)
        c = S.rtc_sample(f, obs, eps, Y, w, T, step="consistent")
        assert np.array_equal(a, c)
    assert np.array_equal(S.rtc_sample(f, obs, eps, Y, np.zeros(8), T, step="consistent"),
                          S.naive_sample(f, obs, eps, T))


def test_step_multipliers():
    """S-10, S-11: c = 1 - w below 1, 1 at w = 1; Algorithm 1 all ones."""
    w = np.array([1.0, 0.75, 0.5, 0.0])
    assert S.step_multipliers(w, "consistent").tolist() == [1.0, 0.25, 0.5, 1.0]
    assert S.step_multipliers(w).tolist() == [1.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("bad", ["Algorithm1", "", None, 1, "time_consistent"])
def test_bad_step_rejected(bad):
    """S-10: a step that is not one of the two names is an error naming step and the allowed names."""
    one = lambda obs, x, t: np.ones_like(x)
    with pytest.raises(ValueError, match=r"step must be one of \('algorithm1', 'consistent'\)"):
        S.rtc_sample(one, np.zeros(1), np.zeros((2, 1)), np.zeros((2, 1)), np.zeros(2), 2, step=bad)
    with pytest.raises(ValueError, match="step must be one of"):
        S.step_multipliers(np.zeros(2), bad)
    f = ReferenceVelocityField.init(0, 4, 1, 1, hidden=4)
    with pytest.raises(ValueError, match="step must be one of"):
        Mth.generate_chunk("naive", f, np.zeros(1), np.zeros((4, 1)), None, 2, 0, 3, step=bad)


def test_generate_chunk_step():
    """S-14: train_* run the chosen step; naive and the first chunk accept either (bitwise the naive
    sampler); the guided methods reject "consistent" on every chunk."""
    f = ReferenceVelocityField.init(4, 8, 2, 3, hidden=16)
    rng = np.random.default_rng(4)
    obs, eps, Y = rng.standard_normal(3), rng.standard_normal((8, 2)), rng.standard_normal((8, 2))
    w = Mth.method_weights("train_soft", 8, 4, 2)
    got = Mth.generate_chunk("train_soft", f, obs, eps, Y, 4, 2, 5, step="consistent")
    assert np.array_equal(got, S.rtc_sample(f, obs, eps, Y, w, 5, step="consistent"))
    assert not np.allclose(got, Mth.generate_chunk("train_soft", f, obs, eps, Y, 4, 2, 5), atol=1e-6)
    assert np.array_equal(Mth.generate_chunk("train_hard", f, obs, eps, Y, 4, 2, 5, step="consistent"),
                          Mth.generate_chunk("train_hard", f, obs, eps, Y, 4, 2, 5))
    naive = S.naive_sample(f, obs, eps, 5)
    assert np.array_equal(Mth.generate_chunk("naive", f, obs, eps, Y, 4, 2, 5, step="consistent"), naive)
    assert np.array_equal(Mth.generate_chunk("train_soft", f, obs, eps, None, 4, 0, 5, step="consistent"), naive)
    for m in ("inference_hard", "inference_soft"):
        for prior, d in ((Y, 2), (None, 0)):
            with pytest.raises(ValueError, match="step must be 'algorithm1' for method"):
                Mth.generate_chunk(m, f, obs, eps, prior, 4, d, 5, step="consistent")
