"""The invariants of the soft window over every configuration, in the reference and the JAX twin.

Every schedule, parametrization and overflow (the default ``clip`` included)
with rules at and around the Hard RTC identities, every delay and execute
horizon of two horizons: weights in [0, 1], non-increasing, zero at d = 0,
Hard RTC for L = 0 and lam = 1 ([W-8], [W-9]), and the JAX tables equal to the
reference's. The samplers are run on the reference velocity field, whose
output depends on the per-token flow time (checked first), so that a wrong
blended time changes the chunk.
"""

import itertools

import jax
import numpy as np
import pytest

from softrtc import reference as R
from softrtc.jax import endpoints as JE
from softrtc.jax import sampler as JS
from softrtc.jax import velocity as JF
from softrtc.jax import weights as JW

TOL = dict(atol=1e-6, rtol=0)
TRAJ = dict(atol=1e-4, rtol=1e-4)
HORIZONS = (4, 8)
# Execute horizons: every s for H = 4; for H = 8 below, at and above H / 2, and s = H (no overlap).
EXECUTE = {4: (1, 2, 3, 4), 8: (1, 3, 4, 5, 8)}


def rules(H: int) -> dict:
    """Rules that fit H: the Hard RTC identities (L = 0, lam = 1, hard), windows past the overlap, and bounds
    below the delay ([W-2])."""
    return {"offset L=0": R.offset(0, H), "delay_scaled lam=1": R.delay_scaled(1.0, H), "hard": R.hard(),
            "delay_scaled lam=2": R.delay_scaled(2.0, H), "delay_scaled lam=2 h_max=H/2": R.delay_scaled(2.0, H // 2),
            "delay_scaled lam=0.5": R.delay_scaled(0.5, H), "offset L=2": R.offset(2, H), "fixed h=H": R.fixed(H),
            "fixed h=1": R.fixed(1)}


HARD = ("offset L=0", "delay_scaled lam=1", "hard")


def windows(H: int):
    for (name, rule), schedule, par, overflow in itertools.product(
            rules(H).items(), R.weights.SCHEDULES, R.weights.PARAMETRIZATIONS, R.weights.OVERFLOWS):
        yield name, R.SoftWindow(rule, schedule, par, overflow)


@pytest.mark.parametrize("H", HORIZONS)
def test_weights_of_every_window_configuration(H):
    """W-1, W-2, W-6, W-7, W-8, W-9, N-10: for every rule, schedule, parametrization and overflow (clip and zeros),
    execute horizons s below, at and above H / 2 and every d = 0..H, the JAX table equals the reference's weights; both are in [0, 1] and
    non-increasing, zero at d = 0, 1 on the committed prefix, and bitwise Hard RTC for L = 0, lam = 1 and hard."""
    checked = 0
    for name, window in windows(H):
        jwin = JW.from_reference(window)
        for s in EXECUTE[H]:
            table = np.asarray(JW.weight_table(H, jwin, s))  # one compilation per H serves every window
            assert table.shape == (H + 1, H)
            for d in range(H + 1):
                ref = R.soft_weights(H, d, window, s)
                np.testing.assert_allclose(table[d], ref, **TOL, err_msg=f"{name} {window} s={s} d={d}")
                for w in (ref, table[d]):
                    assert np.all((w >= 0) & (w <= 1)) and np.all(np.diff(w) <= 0), (name, window, s, d)
                    assert np.all(w[:d] == 1.0), (name, window, s, d)
                if d == 0:
                    assert np.array_equal(ref, np.zeros(H)) and np.array_equal(table[0], np.zeros(H))
                if name in HARD:
                    hard = (np.arange(H) < d).astype(float)  # [W-8] written out
                    assert np.array_equal(ref, hard) and np.array_equal(table[d], hard), (name, window, s, d)
                checked += 1
    # 9 rules x 4 schedules x 2 parametrizations x 2 overflows, each s and d.
    assert checked == 9 * 4 * 2 * 2 * len(EXECUTE[H]) * (H + 1)


def test_clip_and_zeros_differ_only_past_the_overlap():
    """W-6, W-7: the default clip overflow and zero padding give the same weights while the window ends within
    the overlap H - s, and clip's are 0 past it where zero padding's are not (the paper's main window at
    H = 8, s = 4, d = 3: e = 6 > 4)."""
    clip, zeros = R.SoftWindow(), R.SoftWindow(overflow="zeros")
    for d in range(5):
        c, z = R.soft_weights(8, d, clip, 4), R.soft_weights(8, d, zeros, 4)
        np.testing.assert_array_equal(np.asarray(JW.soft_weights(8, d, JW.from_reference(clip), 4)) > 0, c > 0)
        e = R.endpoint(clip.rule, d)
        if e <= 4:
            np.testing.assert_array_equal(c, z)
        else:
            assert np.all(c[4:] == 0) and np.any(z[4:] > 0), d
    np.testing.assert_allclose(R.soft_weights(8, 3, clip, 4), [1, 1, 1, 0.5, 0, 0, 0, 0])
    np.testing.assert_allclose(R.soft_weights(8, 3, zeros, 4), [1, 1, 1, 2 / 3, 1 / 3, 0, 0, 0])


# ----------------------------------------------------------------------------- samplers on a time-dependent field

H, A, O, B, T = 8, 2, 3, 2, 3
RF = R.velocity.ReferenceVelocityField.init(11, H, A, O, hidden=16)
JFIELD = JF.ReferenceVelocityField(RF.params)
_naive = jax.jit(JS.naive_sample, static_argnums=(0, 3))
_rtc = jax.jit(JS.rtc_sample, static_argnums=(0, 5))
_rtc_c = jax.jit(JS.rtc_sample_conditioned, static_argnums=(5,))


def _inputs(seed):
    rng = np.random.default_rng(seed)
    return (rng.standard_normal((B, O)), rng.standard_normal((B, H, A)), rng.standard_normal((B, H, A)))


def test_the_field_depends_on_each_tokens_flow_time():
    """F-1, S-3: the premise of the sampler tests below: changing one token's flow time changes the velocity,
    so a wrong blended time of [S-3] changes the chunk."""
    obs, x, _ = _inputs(0)
    t = np.full(H, 0.5)
    t2 = t.copy()
    t2[5] = 0.75
    assert np.max(np.abs(RF(obs[0], x[0], t2) - RF(obs[0], x[0], t))) > 1e-3
    assert float(np.max(np.abs(JFIELD(obs[:1], x[:1], t2[None]) - JFIELD(obs[:1], x[:1], t[None])))) > 1e-3


@pytest.mark.parametrize("overflow", ["clip", "zeros"])
@pytest.mark.parametrize("parametrization", ["rtc", "paper"])
def test_samplers_over_every_window_configuration(overflow, parametrization):
    """S-3, S-4, S-7, W-6, W-8, W-9, N-8: for every schedule and rule under this overflow and parametrization, and
    every executable d (H = 8, s = 4), the JAX training-time sampler (straightforward and conditioned) equals the
    reference's; d = 0 is bitwise the naive sampler and L = 0, lam = 1 bitwise Hard RTC, in both."""
    obs, noise, prior = _inputs(1)
    s = 4
    naive_j = np.asarray(_naive(JFIELD, obs, noise, T))
    naive_r = np.stack([R.sampler.naive_sample(RF, obs[i], noise[i], T) for i in range(B)])
    hard_j = {d: np.asarray(_rtc(JFIELD, obs, noise, prior, JW.hard_weights(H, d), T)) for d in range(s + 1)}
    hard_r = {d: np.stack([R.sampler.rtc_sample(RF, obs[i], noise[i], prior[i], R.hard_weights(H, d), T)
                           for i in range(B)]) for d in range(s + 1)}
    for name, rule in rules(H).items():
        for schedule in R.weights.SCHEDULES:
            window = R.SoftWindow(rule, schedule, parametrization, overflow)
            for d in range(s + 1):
                w_r = R.soft_weights(H, d, window, s)
                w_j = JW.soft_weights(H, d, JW.from_reference(window), s)
                got = np.asarray(_rtc(JFIELD, obs, noise, prior, w_j, T))
                got_c = np.asarray(_rtc_c(JFIELD, obs, noise, prior, w_j, T))
                want = np.stack([R.sampler.rtc_sample(RF, obs[i], noise[i], prior[i], w_r, T) for i in range(B)])
                np.testing.assert_allclose(got, want, **TRAJ, err_msg=f"{name} {window} d={d}")
                np.testing.assert_allclose(got_c, want, **TRAJ, err_msg=f"{name} {window} d={d}")
                if d == 0:
                    assert np.array_equal(got, naive_j) and np.array_equal(want, naive_r), (name, window)
                if name in HARD:
                    assert np.array_equal(got, hard_j[d]) and np.array_equal(want, hard_r[d]), (name, window, d)
    # The windows differ from Hard RTC somewhere, so the identities above are not vacuous.
    soft = R.SoftWindow(R.delay_scaled(2.0, H), "linear", parametrization, overflow)
    assert not np.array_equal(np.stack([R.sampler.rtc_sample(RF, obs[i], noise[i], prior[i],
                                                             R.soft_weights(H, 2, soft, s), T) for i in range(B)]),
                              hard_r[2])
