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
    """[CF-20], [CF-13], [CF-16], [CF-4] The runner fails every mutant of the reference, on at least three
    cases; the unmutated reference passes the same cases. Mutated rules: W-1, W-2, W-3, W-4, W-5, W-6, E-2,
    L-1, L-2, C-2, S-2, S-3, S-5, G-3, G-4, X-3, X-4, D-1, D-3, M-2, M-3."""
    adapter, fname = make_mutant(label)
    res = runner.run(adapter, files=vector_files, only={fname})
    assert not res.ok, f"mutant '{label}' passed the conformance suite"
    assert res.counts["fail"] >= 3  # [CF-4] no rule rests on a single case
    assert all("\n" not in c.message for c in res.cases)
    base = runner.run(ReferenceAdapter(), files=vector_files, only={fname})
    assert base.ok and base.counts["pass"] == res.counts["pass"] + res.counts["fail"]


# ---------------------------------------------------------------- mutants of the exact rules and boundaries
# Each is a plausible porting mistake, caught by the exact entries ([CF-32]), the cases on both sides of a
# boundary, the hand-written file ([CF-33]) or the window form of guided cases ([CF-27]).

def _prefix(H, d, e, schedule, parametrization, g=None, pos=None):
    """prefix_weights with a replaceable schedule g(x) and position rule pos(j, d, e)."""
    w = np.zeros(H)
    w[:d] = 1.0
    for j in range(d, e):
        x = pos(j, d, e) if pos else ((j - d + 1) / (e - d + 1) if parametrization == "rtc" else (j - d) / (e - d))
        w[j] = g(x) if g and schedule == "exp" else weights.schedule_value(schedule, np.array([x]))[0]
    return w


def _prefix_exp_over_float32_e_minus_1(self, H, d, e, schedule, parametrization):
    weights.prefix_weights(H, d, e, schedule, parametrization)  # same checks
    e_minus_1 = float(np.float32(math.e) - np.float32(1.0))  # a constant written in float32: g(0) = 1 + 5e-8
    return _prefix(H, d, e, schedule, parametrization, g=lambda x: (1 - x) * math.expm1(1 - x) / e_minus_1)


def _prefix_rtc_over_e_minus_d(self, H, d, e, schedule, parametrization):
    weights.prefix_weights(H, d, e, schedule, parametrization)
    if parametrization != "rtc":
        return weights.prefix_weights(H, d, e, schedule, parametrization)
    return _prefix(H, d, e, schedule, parametrization, pos=lambda j, d, e: min((j - d + 1) / (e - d), 1.0))


def _endpoint_margin(delta):
    def endpoint(self, rule, d):
        e = ReferenceAdapter.endpoint(self, rule, d)
        if rule.get("kind") == "delay_scaled" and d > 0:
            from fractions import Fraction
            return min(math.ceil(Fraction(rule["lam"]) * d - delta), rule["h_max"])
        return e
    return endpoint


def _endpoint_offset_at_zero(self, rule, d):
    if rule.get("kind") == "offset" and d == 0:
        return min(rule["length"], rule["h_max"])
    return ReferenceAdapter.endpoint(self, rule, d)


def _endpoint_fixed_at_zero(self, rule, d):
    if rule.get("kind") == "fixed" and d == 0:
        return rule["length"]
    return ReferenceAdapter.endpoint(self, rule, d)


def _endpoint_lam_range_4097(self, rule, d):
    if rule.get("kind") == "delay_scaled" and isinstance(rule.get("lam"), float) and 4096 < rule["lam"] <= 4097:
        return ReferenceAdapter.endpoint(self, dict(rule, lam=4096.0), d)
    return ReferenceAdapter.endpoint(self, rule, d)


def _endpoint_float_h_max(self, rule, d):
    if isinstance(rule.get("h_max"), float) and rule["h_max"].is_integer():
        rule = dict(rule, h_max=int(rule["h_max"]))
    return ReferenceAdapter.endpoint(self, rule, d)


def _weights_clip_unclamped(self, H, d, window, s):
    win = window_from_dict(window)
    if win.overflow != "clip" or s is None:
        return ReferenceAdapter.weights(self, H, d, window, s)
    e = max(endpoints.endpoint(win.rule, d), d)
    e_star = min(e, H - s)  # the window end wins over the prefix
    d_eff = min(d, e_star)
    return weights.prefix_weights(H, d_eff, e_star, win.schedule, win.parametrization)


def _weights_s_unchecked_under_zeros(self, H, d, window, s):
    if window.get("overflow") == "zeros":
        s = None
    return ReferenceAdapter.weights(self, H, d, window, s)


def _weights_clip_accepts_s_zero(self, H, d, window, s):
    if s == 0:
        return ReferenceAdapter.weights(self, H, d, dict(window, overflow="zeros"), None)
    return ReferenceAdapter.weights(self, H, d, window, s)


def _hard_weights_inclusive(self, H, d):
    weights.hard_weights(H, d)
    return (np.arange(H) <= d).astype(float)


def _guidance_weights_end_at_s(self, H, s, d, variant):
    guidance.guidance_prefix_weights(H, s, d, variant)
    return weights.prefix_weights(H, min(d, s), s, guidance.GUIDANCE_SCHEDULES[variant], "rtc")


def _guided_window_end_at_s(self, field, obs, noise, prior, g, T):
    W = weights.prefix_weights(g["H"], min(g["d"], g["s"]), g["s"], g["schedule"], "rtc")
    return guidance.guided_sample(ReferenceVelocityField(field), obs, noise, prior, W, T, g["max_guidance"],
                                  return_trace=True)


def _lam_c_one_over_t(self, t, beta):
    guidance.guidance_weight(t, beta)
    c = math.inf if t == 0 else 1.0 / t
    return min(c * (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2, beta)


def _lam_zero_cap_accepted(self, t, beta):
    return guidance.guidance_weight(t, beta if beta > 0 else 1e-300)


def _token_times_max(self, w, t):
    corruption.token_times(w, t)
    return np.maximum(np.asarray(w), t)


def _corrupt_swapped(self, actions, noise, w, tau):
    x, tj = corruption.corrupt(actions, noise, w, tau)
    return tj[:, None] * np.asarray(noise) + (1.0 - tj[:, None]) * np.asarray(actions), tj


def _shift_pad_last(self, prev, s):
    y = executor.shift_prior(prev, s)
    y[np.asarray(prev).shape[0] - s:] = np.asarray(prev)[-1]
    return y


def _execute_prefix_from_start(self, chunks, ds, s):
    out = executor.execute_chunks(chunks, ds, s)
    ch, acts, k = np.asarray(chunks), out["actions"].copy(), s
    for c in range(1, len(ds)):
        acts[k:k + ds[c]] = ch[c - 1, :ds[c]]
        k += s
    out["actions"] = acts
    return out


def _execute_token_index_new_frame(self, chunks, ds, s):
    out = executor.execute_chunks(chunks, ds, s)
    ti, ci = out["token_index"].copy(), out["chunk_index"]
    for i in range(1, len(ti)):
        if ci[i] != i // s:  # an action of the previous chunk: numbered from 0 instead of s
            ti[i] -= s
    out["token_index"] = ti
    return out


def _execute_first_delay_unchecked(self, chunks, ds, s):
    return executor.execute_chunks(chunks, [0] + list(np.asarray(ds)[1:]), s)


def _rtc_step_from_unblended(self, field, obs, noise, prior, w, T):
    f = ReferenceVelocityField(field)
    x, y, w = np.asarray(noise), np.asarray(prior), np.asarray(w)
    for k in range(T):
        xb = w[:, None] * y + (1.0 - w[:, None]) * x
        x = x + f(obs, xb, w + (1.0 - w) * k / T) / T
    return x, None


def _rtc_velocity_at_unblended(self, field, obs, noise, prior, w, T):
    f = ReferenceVelocityField(field)
    x, y, w = np.asarray(noise), np.asarray(prior), np.asarray(w)
    for k in range(T):
        xb = w[:, None] * y + (1.0 - w[:, None]) * x
        x = xb + f(obs, x, w + (1.0 - w) * k / T) / T
    return x, None


def _guided_denoiser_t_v(self, field, obs, noise, prior, W, T, beta):
    f = ReferenceVelocityField(field)
    x, y, W = np.asarray(noise), np.asarray(prior), np.asarray(W)[:, None]
    for k in range(T):
        t = k / T
        tv = np.full(x.shape[0], t)
        v = f(obs, x, tv)
        err = W * (y - (x + t * v))
        x = x + (v + guidance.guidance_weight(t, beta) * (err + (1 - t) * f.vjp(obs, x, tv, err))) / T
    return x, None


def _sample_delay_summed_cdf(self, probs, d_min, u):
    delays.sample_delay(probs, d_min, u)
    return d_min + int(np.sum(np.cumsum(probs) <= u))


def _sample_delay_sum_within_1e3(self, probs, d_min, u):
    p = np.asarray(probs, dtype=float)
    if p.size and abs(p.sum() - 1.0) <= 1e-3:
        p = p / p.sum()
    return delays.sample_delay(p, d_min, u)


def _decay_up_to_65(self, dist, d_min, d_max, decay):
    if isinstance(decay, float) and 64 < decay <= 65:
        decay = 64.0
    return delays.delay_probs(dist, d_min, d_max, decay)


def _order_up_to_17(self, actions, order):
    if order == 17:
        a = np.asarray(actions)
        return float(np.mean(np.linalg.norm(np.diff(a, n=17, axis=0), axis=-1)))
    return metrics.difference_norm(actions, order)


def _standard_error_ddof0(self, values):
    metrics.standard_error(values)
    v = np.asarray(values)
    return float(np.std(v) / np.sqrt(v.size))


def _velocity_cos_sin_swapped(self, field, obs, x, t):
    p = {k: np.asarray(v) for k, v in field.items()}
    t = np.asarray(t)
    phi = np.stack([t, np.cos(np.pi * t), np.sin(np.pi * t)], axis=-1).reshape(-1)
    h = np.tanh(np.asarray(x).reshape(-1) @ p["W1"] + phi @ p["Wt"] + np.asarray(obs) @ p["Wo"] + p["b1"])
    return (h @ p["W2"] + p["b2"]).reshape(np.shape(x))


def _vjp_without_tanh_derivative(self, field, obs, x, t, cot):
    p = {k: np.asarray(v) for k, v in field.items()}
    return ((np.asarray(cot).reshape(-1) @ p["W2"].T) @ p["W1"].T).reshape(np.shape(x))


def _loss_over_H(self, pred, actions, noise, w):
    m = 1.0 - np.asarray(w)
    return float(np.sum(m * loss.token_errors(pred, actions, noise)) / (m.size + loss.ETA))


# label -> (interface function, {adapter attribute: replacement}); None removes a form.
STRICT_MUTANTS = {
    "exp schedule divided by a float32 e - 1 (g(0) not exactly 1)": ("prefix_weights",
                                                                      {"prefix_weights": _prefix_exp_over_float32_e_minus_1}),
    "rtc positions over e - d": ("prefix_weights", {"prefix_weights": _prefix_rtc_over_e_minus_d}),
    "endpoint margin 1e-3": ("endpoint", {"endpoint": _endpoint_margin(__import__("fractions").Fraction(1, 1000))}),
    "endpoint margin 1e-5": ("endpoint", {"endpoint": _endpoint_margin(__import__("fractions").Fraction(1, 100000))}),
    "offset rule without e(0) = 0": ("endpoint", {"endpoint": _endpoint_offset_at_zero}),
    "fixed rule without e(0) = 0": ("endpoint", {"endpoint": _endpoint_fixed_at_zero}),
    "lam accepted up to 4097": ("endpoint", {"endpoint": _endpoint_lam_range_4097}),
    "h_max written as a float accepted": ("endpoint", {"endpoint": _endpoint_float_h_max}),
    "clip lets the window end win over the prefix": ("weights", {"weights": _weights_clip_unclamped}),
    "s unchecked under zeros": ("weights", {"weights": _weights_s_unchecked_under_zeros}),
    "clip accepts s = 0": ("weights", {"weights": _weights_clip_accepts_s_zero}),
    "hard weights 1[j <= d]": ("hard_weights", {"hard_weights": _hard_weights_inclusive}),
    "guidance window ends at s, not H - s": ("guidance_weights", {"guidance_weights": _guidance_weights_end_at_s}),
    "window form of the guided sampler ends at s": ("guided_sample", {"guided_sample": None,
                                                                     "guided_sample_window": _guided_window_end_at_s}),
    "lam with c = 1 / t": ("guidance_weight", {"guidance_weight": _lam_c_one_over_t}),
    "max_guidance 0 accepted": ("guidance_weight", {"guidance_weight": _lam_zero_cap_accepted}),
    "token time max(w, t)": ("token_times", {"token_times": _token_times_max}),
    "corruption with action and noise swapped": ("corrupt", {"corrupt": _corrupt_swapped}),
    "prior padded with the last action": ("shift_prior", {"shift_prior": _shift_pad_last}),
    "committed prefix from the previous chunk's start": ("execute_chunks", {"execute_chunks": _execute_prefix_from_start}),
    "committed tokens numbered in the new chunk's frame": ("execute_chunks",
                                                          {"execute_chunks": _execute_token_index_new_frame}),
    "first delay not checked": ("execute_chunks", {"execute_chunks": _execute_first_delay_unchecked}),
    "RTC step from the unblended state": ("rtc_sample", {"rtc_sample": _rtc_step_from_unblended}),
    "RTC velocity at the unblended state": ("rtc_sample", {"rtc_sample": _rtc_velocity_at_unblended}),
    "guided denoiser x + t v": ("guided_sample", {"guided_sample": _guided_denoiser_t_v}),
    "delay CDF summed, last entry not set to 1": ("sample_delay", {"sample_delay": _sample_delay_summed_cdf}),
    "table sum checked to 1e-3": ("sample_delay", {"sample_delay": _sample_delay_sum_within_1e3}),
    "decay accepted up to 65": ("delay_probs", {"delay_probs": _decay_up_to_65}),
    "difference order 17 accepted": ("difference_norm", {"difference_norm": _order_up_to_17}),
    "standard error with ddof 0": ("standard_error", {"standard_error": _standard_error_ddof0}),
    "velocity features cos and sin swapped": ("velocity", {"velocity": _velocity_cos_sin_swapped}),
    "VJP without the tanh derivative": ("velocity_vjp", {"velocity_vjp": _vjp_without_tanh_derivative}),
    "loss normalized by H": ("loss", {"loss": _loss_over_H}),
}


def test_at_least_twenty_strict_mutants():
    """[CF-20], [CF-32] Beside the first set, at least 20 further deliberate bugs, each its own function and
    none repeating a mutant of the first set."""
    assert len(STRICT_MUTANTS) >= 20 and not set(STRICT_MUTANTS) & set(MUTANTS)
    funcs = [f for _, repl in STRICT_MUTANTS.values() for f in repl.values() if f is not None]
    assert len({id(f) for f in funcs}) == len(funcs)


@pytest.mark.parametrize("label", sorted(STRICT_MUTANTS))
def test_runner_fails_strict_mutant(label, vector_files):
    """[CF-20], [CF-32], [CF-33], [CF-27], [CF-4] The runner fails every mutant of the exact rules and
    boundaries (E-2, E-1, E-6, W-2, W-3, W-4, W-6, W-8, G-1, G-4, C-1, C-2, X-1, X-2, X-3, X-4, S-3, S-4, G-3,
    D-2, D-3, M-1, M-6, F-1, F-2, L-2, N-12), each on at least three cases; the unmutated reference passes the
    same cases."""
    fname, repl = STRICT_MUTANTS[label]
    cls = type("StrictMutant", (ReferenceAdapter,), {"name": f"mutant: {label}", **repl})
    res = runner.run(cls(), files=vector_files, only={fname})
    assert not res.ok and res.counts["fail"] >= 3, f"mutant '{label}' failed {res.counts['fail']} cases, not 3"
    assert res.counts["unsupported"] == 0
    base = runner.run(ReferenceAdapter(), files=vector_files, only={fname})
    assert base.ok and base.counts["pass"] == res.counts["pass"] + res.counts["fail"]
