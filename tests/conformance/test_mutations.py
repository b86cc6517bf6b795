"""Mutation tests of the conformance suite ([CF-20]): every deliberate bug in a copy of the
reference must make the runner fail.

Each mutant is the reference adapter with one function replaced by a subtly wrong
copy; the runner is restricted to that function's cases to stay fast.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapters.reference import ReferenceAdapter, window_from_dict
from softrtc.reference import corruption, delays, endpoints, executor, guidance, loss, metrics, weights
from softrtc.reference.velocity import ReferenceVelocityField


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


# ---------------------------------------------------------------- mutated copies

def _prefix_end_plus_one(self, H, d, e, schedule, parametrization):
    return weights.prefix_weights(H, d, min(e + 1, H) if e > d else e, schedule, parametrization)


def _prefix_exp_is_linear(self, H, d, e, schedule, parametrization):
    return weights.prefix_weights(H, d, e, "linear" if schedule == "exp" else schedule, parametrization)


def _prefix_paper_rtc_swapped(self, H, d, e, schedule, parametrization):
    return weights.prefix_weights(H, d, e, schedule, {"rtc": "paper", "paper": "rtc"}[parametrization])


def _weights_end_wins(self, H, d, window, s):
    # Public RTC code: start = min(start, end), so e < d un-clamps committed actions.
    win = window_from_dict(window)
    e = min(endpoints.endpoint(win.rule, d), H)
    if win.overflow == "clip":
        e = min(e, H - s)
    d_eff = min(d, e)
    return weights.prefix_weights(H, d_eff, max(e, d_eff), win.schedule, win.parametrization)


def _weights_clip_ignored(self, H, d, window, s):
    return weights.soft_weights(H, d, window_from_dict(dict(window, overflow="zeros")), None)


def _endpoint_floor(self, rule, d):
    r = ReferenceAdapter.endpoint(self, rule, d)
    if rule.get("kind") == "delay_scaled" and d > 0:
        return min(math.floor(rule["lam"] * d), rule["h_max"])
    return r


def _endpoint_float_ceil(self, rule, d):
    r = ReferenceAdapter.endpoint(self, rule, d)
    if rule.get("kind") == "delay_scaled" and d > 0:
        return min(math.ceil(rule["lam"] * d), rule["h_max"])  # float64 product, no delta ([E-2])
    return r


def _loss_no_normalizer(self, pred, actions, noise, w):
    m = 1.0 - np.asarray(w)
    return float(np.sum(m * loss.token_errors(pred, actions, noise)))


def _loss_no_eta(self, pred, actions, noise, w):
    m = 1.0 - np.asarray(w)
    with np.errstate(invalid="ignore", divide="ignore"):
        return float(np.sum(m * loss.token_errors(pred, actions, noise)) / np.sum(m))


def _loss_mean_over_actions(self, pred, actions, noise, w):
    l = np.mean((np.asarray(pred) - (np.asarray(actions) - np.asarray(noise))) ** 2, axis=-1)
    m = 1.0 - np.asarray(w)
    return float(np.sum(m * l) / (np.sum(m) + loss.ETA))


def _corrupt_global_tau(self, actions, noise, w, tau):
    tj = corruption.token_times(w, tau)
    return tau * np.asarray(actions) + (1.0 - tau) * np.asarray(noise), tj


def _rtc(field, obs, noise, prior, w, T, time_fn=None, final_blend=False):
    """A copy of the reference RTC sampler with hooks for the mutations below."""
    f = ReferenceVelocityField(field)
    x, y, w = np.asarray(noise), np.asarray(prior), np.asarray(w)
    trace = []
    for k in range(T):
        t = k / T
        xb = w[:, None] * y + (1.0 - w[:, None]) * x
        tb = time_fn(w, t) if time_fn else w + (1.0 - w) * t
        v = f(obs, xb, tb)
        nxt = xb + v / T
        trace.append({"state": x, "blended_state": xb, "time": tb, "velocity": v, "next_state": nxt})
        x = nxt
    if final_blend:
        x = w[:, None] * y + (1.0 - w[:, None]) * x
    return x, trace


def _rtc_final_blend(self, field, obs, noise, prior, w, T):
    return _rtc(field, obs, noise, prior, w, T, final_blend=True)


def _rtc_time_not_blended(self, field, obs, noise, prior, w, T):
    return _rtc(field, obs, noise, prior, w, T, time_fn=lambda w, t: np.full_like(w, t))


def _guided(field, obs, noise, prior, W, T, beta, sign=1.0, with_vjp=True):
    """A copy of the reference guided sampler with hooks for the mutations below."""
    f = ReferenceVelocityField(field)
    x, y, W = np.asarray(noise), np.asarray(prior), np.asarray(W)[:, None]
    trace = []
    for k in range(T):
        t = k / T
        tv = np.full(x.shape[0], t)
        v = f(obs, x, tv)
        x1 = x + (1.0 - t) * v
        err = sign * W * (y - x1)
        g = err + ((1.0 - t) * f.vjp(obs, x, tv, err) if with_vjp else 0.0)
        lam = guidance.guidance_weight(t, beta)
        vg = v + lam * g
        nxt = x + vg / T
        trace.append({"state": x, "time": tv, "velocity": v, "denoised": x1, "error": err, "vjp": g,
                      "guidance_weight": lam, "guided_velocity": vg, "next_state": nxt})
        x = nxt
    return x, trace


def _guided_sign_flip(self, field, obs, noise, prior, w, T, beta):
    return _guided(field, obs, noise, prior, w, T, beta, sign=-1.0)


def _guided_no_vjp(self, field, obs, noise, prior, w, T, beta):
    return _guided(field, obs, noise, prior, w, T, beta, with_vjp=False)


def _guidance_weight_uncapped(self, t, beta):
    c = math.inf if t == 0 else (1.0 - t) / t
    return c * (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2


def _naive_time_ahead(self, field, obs, noise, T):
    f = ReferenceVelocityField(field)
    x = np.asarray(noise)
    trace = []
    for k in range(T):
        tv = np.full(x.shape[0], (k + 1) / T)
        v = f(obs, x, tv)
        trace.append({"state": x, "time": tv, "velocity": v, "next_state": x + v / T})
        x = x + v / T
    return x, trace


def _shift_by_s_minus_one(self, prev, s):
    prev = np.asarray(prev)
    y = np.zeros_like(prev)
    y[: prev.shape[0] - s] = prev[s - 1: prev.shape[0] - 1]
    return y


def _execute_new_prefix(self, chunks, ds, s):
    out = executor.execute_chunks(chunks, ds, s)
    ch = np.asarray(chunks)
    acts = [ch[0, :s]] + [ch[c, :s] for c in range(1, len(ds))]  # the new chunk from token 0
    out["actions"] = np.concatenate(acts)
    return out


def _sample_delay_strict(self, probs, d_min, u):
    c = delays.delay_cdf(probs)
    return d_min + int(np.sum(c < u))


def _jerk_first_difference(self, actions):
    return metrics.difference_norm(actions, 1)


def _boundary_jump_every_step(self, actions, chunk_index):
    return metrics.action_delta(actions)


def _uniform_off_by_one(self, dist, d_min, d_max, decay):
    p = delays.delay_probs(dist, d_min, d_max, decay)
    if dist == "uniform":
        return np.full(p.size, 1.0 / (d_max - d_min)) if d_max > d_min else p
    return p


MUTANTS = {
    "window end off by one": ("prefix_weights", _prefix_end_plus_one),
    "exp schedule replaced by linear": ("prefix_weights", _prefix_exp_is_linear),
    "paper and rtc parametrization swapped": ("prefix_weights", _prefix_paper_rtc_swapped),
    "prefix not clamped when e < d": ("weights", _weights_end_wins),
    "overflow clip ignored": ("weights", _weights_clip_ignored),
    "endpoint floor instead of ceil": ("endpoint", _endpoint_floor),
    "endpoint ceil of the float product": ("endpoint", _endpoint_float_ceil),
    "loss without normalizer": ("loss", _loss_no_normalizer),
    "loss without eta": ("loss", _loss_no_eta),
    "loss mean instead of sum over action dim": ("loss", _loss_mean_over_actions),
    "corruption with tau instead of tau_j": ("corrupt", _corrupt_global_tau),
    "final blend added": ("rtc_sample", _rtc_final_blend),
    "time blend missing": ("rtc_sample", _rtc_time_not_blended),
    "guidance sign flipped": ("guided_sample", _guided_sign_flip),
    "guidance without the VJP term": ("guided_sample", _guided_no_vjp),
    "guidance weight without cap": ("guidance_weight", _guidance_weight_uncapped),
    "naive sampler evaluates at t_{k+1}": ("naive_sample", _naive_time_ahead),
    "prior shifted by s - 1": ("shift_prior", _shift_by_s_minus_one),
    "executor executes the new chunk's prefix": ("execute_chunks", _execute_new_prefix),
    "delay CDF off by one (< instead of <=)": ("sample_delay", _sample_delay_strict),
    "uniform delay table off by one": ("delay_probs", _uniform_off_by_one),
    "jerk using the first difference": ("action_jerk", _jerk_first_difference),
    "boundary jump over every step": ("boundary_jump", _boundary_jump_every_step),
}


def make_mutant(label: str):
    fname, func = MUTANTS[label]
    cls = type("Mutant", (ReferenceAdapter,), {"name": f"mutant: {label}", fname: func})
    return cls(), fname


def test_more_than_fifteen_mutants():
    """[CF-20] The mutation set holds more than 15 distinct deliberate bugs, each in its own function."""
    assert len(MUTANTS) > 15
    assert len({id(func) for _, func in MUTANTS.values()}) == len(MUTANTS)


@pytest.mark.parametrize("label", sorted(MUTANTS))
def test_runner_fails_mutant(label, vector_files):
    """[CF-20], [CF-13], [CF-16] The runner fails every mutant of the reference; the unmutated
    reference passes the same cases. Mutated rules: W-1, W-2, W-3, W-4, W-5, W-6, E-2, L-1, L-2,
    C-2, S-2, S-3, S-5, G-3, G-4, X-3, X-4, D-1, D-3, M-2, M-3."""
    adapter, fname = make_mutant(label)
    res = runner.run(adapter, files=vector_files, only={fname})
    assert not res.ok, f"mutant '{label}' passed the conformance suite"
    assert res.counts["fail"] > 0
    assert all("\n" not in c.message for c in res.cases)
    base = runner.run(ReferenceAdapter(), files=vector_files, only={fname})
    assert base.ok and base.counts["pass"] == res.counts["pass"] + res.counts["fail"]
