"""Vector cases of chapters E, W, D, C and L: endpoints, weights, delays, corruption, loss ([CF-4]).

Each ``gen_<chapter>`` function returns the cases of one vector file, computed by the NumPy reference
from fixed inputs and fixed seeds ([CF-1]).
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import corruption, delays, endpoints, loss, weights
from softrtc.reference.weights import SoftWindow

from .cases_base import TOL_ARITH, TOL_EXACT, TOL_WEIGHTS, _Cases, _rule_id
from .cases_margins import margins_delays, margins_endpoints, margins_loss, margins_weights

HORIZONS = (4, 8, 10, 16, 50)
LAMS = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0)
OFFSETS = tuple(range(7))
FIXED = (3, 5)
# h_max of the delay-scaled rules per horizon (H = 8 gives the paper's h_max = 5).
H_MAX = {4: 4, 8: 5, 10: 6, 16: 10, 50: 25}
# Execute horizons used with overflow = "clip" per horizon.
CLIP_S = {4: (1, 2), 8: (2, 4), 10: (3, 5), 16: (8,), 50: (25,)}

def _rules_for(H: int) -> list:
    rules = [endpoints.delay_scaled(lam, H_MAX[H]) for lam in LAMS]
    rules += [endpoints.offset(L, H) for L in OFFSETS]
    rules += [endpoints.fixed(h) for h in FIXED if h <= H]
    rules.append(endpoints.hard())
    return rules


# ---------------------------------------------------------------- chapter E / W

def gen_endpoints() -> _Cases:
    c = _Cases()
    rules = [endpoints.delay_scaled(lam, hm) for lam in LAMS for hm in (5, 8)]
    rules += [endpoints.offset(L, 8) for L in OFFSETS] + [endpoints.fixed(h) for h in FIXED] + [endpoints.hard()]
    for rule in rules:
        rd = rule.to_dict()
        reqs = {"delay_scaled": ["E-1", "E-2"], "offset": ["E-1", "E-3"], "fixed": ["E-1", "E-4"],
                "hard": ["E-1", "E-5"]}[rule.kind]
        for d in range(13):
            c.add(f"E.endpoint.{_rule_id(rd)}.d{d}", "endpoint", reqs + (["E-6"] if d == 0 else []), TOL_EXACT,
                  {"rule": rd, "d": d}, {"e": endpoints.endpoint(rule, d)})
    # [E-2] ceil(lam * d - 1e-4) on the exact value of lam: binary-exact lam (0.25 * 4 = 1, 1.75 * 4 = 7) and
    # decimal lam stored slightly above (1.1, 1.6, 2.2) or below (0.7, 0.3) the number written, where the exact
    # binary ceiling is off; 0.28 * 25 and 0.56 * 25 (float64 product above the integer), 0.6 * 25 and 1.2 * 25
    # (float32 product above it), where the ceiling of a float product without delta is off.
    for lam, d in ((0.25, 4), (1.75, 4), (2.5, 3), (3.75, 7), (1.1, 10), (1.6, 5), (2.2, 5), (0.7, 10), (0.3, 3),
                   (1.6, 3), (1.001, 3), (0.28, 25), (0.56, 25), (0.6, 25), (1.2, 25)):
        rule = endpoints.delay_scaled(lam, 64)
        c.add(f"E.endpoint.exact-ceil.lam{lam}.d{d}", "endpoint", ["E-2"], TOL_EXACT,
              {"rule": rule.to_dict(), "d": d}, {"e": endpoints.endpoint(rule, d)})
    c.error("E.endpoint.reject.negative-d", "endpoint", ["E-1", "N-7"],
            {"rule": endpoints.hard().to_dict(), "d": -1})
    c.error("E.endpoint.reject.float-d", "endpoint", ["E-1", "N-7"],
            {"rule": endpoints.hard().to_dict(), "d": 2.0})
    c.error("E.endpoint.reject.lam-too-large", "endpoint", ["E-1", "N-7"],
            {"rule": {"kind": "delay_scaled", "lam": 5000.0, "h_max": 5}, "d": 1})
    c.error("E.endpoint.reject.unknown-kind", "endpoint", ["E-1", "N-7"], {"rule": {"kind": "quadratic"}, "d": 1})
    c.error("E.endpoint.reject.unused-parameter", "endpoint", ["E-1", "N-7"],
            {"rule": {"kind": "hard", "lam": 2.0}, "d": 1})
    c.error("E.endpoint.reject.d-above-range", "endpoint", ["E-1", "N-12", "N-7"],
            {"rule": endpoints.hard().to_dict(), "d": 4097})
    # [E-2] Both sides of the margin delta = 1/10000: lam * d just above an integer by 2e-4 (ceiling k + 1)
    # or by 5e-5, 2e-5 or 6e-5 (ceiling k); a margin of 1e-3 or 1e-5 reads some of them differently, and
    # float32 arithmetic agrees on all of them (lam * d <= 4).
    for lam, d in ((3.0002, 1), (3.00005, 1), (1.5001, 2), (1.50001, 2), (0.0002, 1), (0.00005, 1), (1.00002, 5),
                   (1.00005, 4), (0.50003, 2), (2.56, 100)):
        rule = endpoints.delay_scaled(lam, 4096)
        c.add(f"E.endpoint.margin.lam{lam}.d{d}", "endpoint", ["E-2"], TOL_EXACT, {"rule": rule.to_dict(), "d": d},
              {"e": endpoints.endpoint(rule, d)})
    # [E-1], [N-12] Both sides of the ranges: lam, h_max, L, h and d up to 4096.
    c.add("E.endpoint.range.lam4096.d1", "endpoint", ["E-1", "E-2", "N-12"], TOL_EXACT,
          {"rule": {"kind": "delay_scaled", "lam": 4096.0, "h_max": 4096}, "d": 1}, {"e": 4096})
    c.add("E.endpoint.range.hard.d4096", "endpoint", ["E-1", "E-5", "N-12"], TOL_EXACT,
          {"rule": {"kind": "hard"}, "d": 4096}, {"e": 4096})
    c.add("E.endpoint.range.offset-L4096", "endpoint", ["E-1", "E-3", "N-12"], TOL_EXACT,
          {"rule": {"kind": "offset", "length": 4096, "h_max": 4096}, "d": 1}, {"e": 4096})
    for tag, rule in (("lam-above-4096", {"kind": "delay_scaled", "lam": 4096.5, "h_max": 5}),
                      ("h_max-above-4096", {"kind": "delay_scaled", "lam": 2.0, "h_max": 4097}),
                      ("L-above-4096", {"kind": "offset", "length": 4097, "h_max": 8}),
                      ("h-above-4096", {"kind": "fixed", "length": 4097}),
                      ("negative-lam", {"kind": "delay_scaled", "lam": -0.5, "h_max": 5}),
                      ("float-h_max", {"kind": "delay_scaled", "lam": 2.0, "h_max": 5.0})):
        c.error(f"E.endpoint.reject.{tag}", "endpoint", ["E-1", "N-12", "N-7"], {"rule": rule, "d": 1})
    # An integer-written lam is the same real ([CF-23]); offset and fixed rules give e(0) = 0 ([E-6]).
    c.add("E.endpoint.integer-lam", "endpoint", ["E-2"], TOL_EXACT,
          {"rule": {"kind": "delay_scaled", "lam": 2, "h_max": 5}, "d": 2}, {"e": 4})
    for rule in (endpoints.offset(3, 8), endpoints.fixed(5)):
        c.add(f"E.endpoint.{rule.kind}.d0", "endpoint", ["E-3" if rule.kind == "offset" else "E-4", "E-6"],
              TOL_EXACT, {"rule": rule.to_dict(), "d": 0}, {"e": 0})
    margins_endpoints(c)
    return c


def gen_weights() -> _Cases:
    c = _Cases()
    # prefix_weights on every (d, e) pair for small H, every schedule and parametrization.
    for H in (4, 8, 10):
        for sched in weights.SCHEDULES:
            for par in weights.PARAMETRIZATIONS:
                for d in range(H + 1):
                    for e in range(d, H + 1):
                        reqs = ["W-1", "W-3", "W-4" if par == "rtc" else "W-5"]
                        c.add(f"W.prefix_weights.H{H}.d{d}.e{e}.{sched}.{par}", "prefix_weights", reqs, TOL_WEIGHTS,
                              {"H": H, "d": d, "e": e, "schedule": sched, "parametrization": par},
                              {"weights": weights.prefix_weights(H, d, e, sched, par)})
    for H in HORIZONS:
        for d in range(H + 1):
            c.add(f"W.hard_weights.H{H}.d{d}", "hard_weights", ["W-8"] + (["W-9"] if d == 0 else []), TOL_WEIGHTS,
                  {"H": H, "d": d}, {"weights": weights.hard_weights(H, d)})
    # Soft weights: every rule with the default schedule, the default rule with every
    # schedule and parametrization, each under overflow "zeros" and "clip" with some s.
    for H in HORIZONS:
        default_rule = endpoints.delay_scaled(2.0, H_MAX[H])
        windows = [SoftWindow(rule, "linear", "rtc", "clip") for rule in _rules_for(H)]
        windows += [SoftWindow(default_rule, sched, par, "clip") for sched in weights.SCHEDULES
                    for par in weights.PARAMETRIZATIONS if (sched, par) != ("linear", "rtc")]
        for base in windows:
            variants = [(SoftWindow(base.rule, base.schedule, base.parametrization, "zeros"), None)]
            variants += [(base, s) for s in CLIP_S[H]]
            if H > 10:
                # Long horizons: rules under clip only, schedule variants under zeros only (file size).
                variants = variants[1:] if (base.schedule, base.parametrization) == ("linear", "rtc") else variants[:1]
            for win, s in variants:
                wd = win.to_dict()
                for d in range(H + 1):
                    w = weights.soft_weights(H, d, win, s)
                    reqs = {"W-1", "W-2", "W-3", "W-6", "W-7", "E-1",
                            "W-4" if win.parametrization == "rtc" else "W-5"}
                    if d == 0:
                        reqs |= {"W-9", "E-6"}
                    if win.schedule == "zeros" or win.rule.kind == "hard" or \
                            (win.rule.kind == "offset" and win.rule.length == 0) or \
                            (win.rule.kind == "delay_scaled" and win.rule.lam == 1.0):
                        reqs.add("W-8")
                    tag = f"{_rule_id(wd['rule'])}.{win.schedule}.{win.parametrization}.{win.overflow}"
                    c.add(f"W.weights.H{H}.{tag}.s{s}.d{d}", "weights", reqs, TOL_WEIGHTS,
                          {"H": H, "d": d, "window": wd, "s": s}, {"weights": w})
    default = SoftWindow().to_dict()
    c.error("W.weights.reject.d-above-H", "weights", ["W-1", "N-7"], {"H": 8, "d": 9, "window": default, "s": 4})
    c.error("W.weights.reject.clip-without-s", "weights", ["W-6", "N-7"], {"H": 8, "d": 2, "window": default, "s": None})
    c.error("W.weights.reject.h_max-above-H", "weights", ["E-1", "N-7"],
            {"H": 4, "d": 2, "window": SoftWindow(endpoints.delay_scaled(2.0, 5)).to_dict(), "s": 2})
    c.error("W.weights.reject.unknown-schedule", "weights", ["W-3", "N-7"],
            {"H": 8, "d": 2, "window": dict(default, schedule="cosine"), "s": 4})
    c.error("W.prefix_weights.reject.e-below-d", "prefix_weights", ["W-1", "N-7"],
            {"H": 8, "d": 3, "e": 2, "schedule": "linear", "parametrization": "rtc"})
    c.error("W.prefix_weights.reject.e-above-H", "prefix_weights", ["W-1", "N-7"],
            {"H": 8, "d": 3, "e": 9, "schedule": "linear", "parametrization": "rtc"})
    # [N-12] The chunk length is bounded: 4096 is the largest H, so every token index and delay is <= 4096.
    c.error("W.hard_weights.reject.H-above-range", "hard_weights", ["W-8", "N-12", "N-7"], {"H": 4097, "d": 0})
    c.error("W.prefix_weights.reject.H-above-range", "prefix_weights", ["W-1", "N-12", "N-7"],
            {"H": 4097, "d": 0, "e": 0, "schedule": "linear", "parametrization": "rtc"})
    zeros = dict(default, overflow="zeros")
    c.error("W.weights.reject.s-above-H-under-zeros", "weights", ["W-6", "N-7"],
            {"H": 8, "d": 2, "window": zeros, "s": 9})
    # [W-6], [N-12] Both sides of the ranges: s = H under clip leaves no overlap (e* = d), s = 0 is an error;
    # H = 4096 is the largest chunk.
    for d in (0, 3):
        c.add(f"W.weights.clip-s-equals-H.d{d}", "weights", ["W-6", "W-7"], TOL_WEIGHTS,
              {"H": 8, "d": d, "window": default, "s": 8}, {"weights": weights.soft_weights(8, d, SoftWindow(), 8)})
    c.error("W.weights.reject.s-zero-under-clip", "weights", ["W-6", "N-7"], {"H": 8, "d": 2, "window": default, "s": 0})
    # [CF-34] Readings of the window argument: absent keys take the defaults of [W-7] (at d = 3, s = 4 the
    # default clip differs from zeros, and a rule-only window equals the default one); the rule is required,
    # an unknown key (a misspelt "schedule") and window None are errors; s is checked under zeros too.
    rule_only = {"rule": endpoints.delay_scaled(2.0, 5).to_dict()}
    c.add("W.weights.window-defaults.rule-only.d3", "weights", ["W-7", "CF-34"], TOL_WEIGHTS,
          {"H": 8, "d": 3, "window": rule_only, "s": 4}, {"weights": weights.soft_weights(8, 3, SoftWindow(), 4)})
    c.add("W.weights.window-defaults.zeros-only.d3", "weights", ["W-6", "W-7", "CF-34"], TOL_WEIGHTS,
          {"H": 8, "d": 3, "window": dict(rule_only, overflow="zeros"), "s": None},
          {"weights": weights.soft_weights(8, 3, SoftWindow(overflow="zeros"))})
    c.error("W.weights.reject.window-unknown-key", "weights", ["W-7", "CF-34", "N-7"],
            {"H": 8, "d": 2, "window": dict(rule_only, shedule="exp"), "s": 4})
    c.error("W.weights.reject.window-none", "weights", ["W-7", "CF-34", "N-7"], {"H": 8, "d": 2, "window": None, "s": 4})
    c.error("W.weights.reject.window-without-rule", "weights", ["W-7", "CF-34", "N-7"],
            {"H": 8, "d": 2, "window": {"schedule": "linear"}, "s": 4})
    c.error("W.weights.reject.s-zero-under-zeros", "weights", ["W-6", "CF-34", "N-7"],
            {"H": 8, "d": 2, "window": zeros, "s": 0})
    c.add("W.hard_weights.H4096.d4096", "hard_weights", ["W-8", "N-12"], TOL_WEIGHTS, {"H": 4096, "d": 4096},
          {"weights": weights.hard_weights(4096, 4096)})
    c.add("W.prefix_weights.H4096.d4093.e4096.exp.paper", "prefix_weights", ["W-1", "W-3", "W-5", "N-12"],
          TOL_WEIGHTS, {"H": 4096, "d": 4093, "e": 4096, "schedule": "exp", "parametrization": "paper"},
          {"weights": weights.prefix_weights(4096, 4093, 4096, "exp", "paper")})
    margins_weights(c)
    return c


# ---------------------------------------------------------------- chapter D / C / L

def gen_delays() -> _Cases:
    c = _Cases()
    tables = [("uniform", lo, hi, 1.0) for lo, hi in ((0, 0), (0, 4), (1, 5), (2, 2), (0, 7))]
    tables += [("exponential", 0, 4, k) for k in (0.0, 0.5, 1.0, 2.0, 64.0)] + [("exponential", 1, 6, 0.75)]
    for dist, lo, hi, decay in tables:
        p = delays.delay_probs(dist, lo, hi, decay)
        tag = f"{dist}.{lo}-{hi}" + (f".decay{decay}" if dist == "exponential" else "")
        c.add(f"D.delay_probs.{tag}", "delay_probs", ["D-1" if dist == "uniform" else "D-2"], TOL_WEIGHTS,
              {"dist": dist, "d_min": lo, "d_max": hi, "decay": decay}, {"probs": p})
        cdf = delays.delay_cdf(p)
        # u exactly on every cdf value catches `<` versus `<=` ([D-3]).
        us = [0.0, 0.999999] + [float(v) for v in cdf[:-1]] + [float(v) for v in (np.r_[0.0, cdf[:-1]] + cdf) / 2]
        for i, u in enumerate(sorted(u for u in set(us) if u < 1.0)):
            c.add(f"D.sample_delay.{tag}.u{i}", "sample_delay", ["D-3"], TOL_EXACT,
                  {"probs": p, "d_min": lo, "u": u}, {"d": delays.sample_delay(p, lo, u)})
    c.error("D.delay_probs.reject.dmax-below-dmin", "delay_probs", ["D-1", "N-7"],
            {"dist": "uniform", "d_min": 3, "d_max": 2, "decay": 1.0})
    c.error("D.delay_probs.reject.negative-decay", "delay_probs", ["D-2", "N-7"],
            {"dist": "exponential", "d_min": 0, "d_max": 2, "decay": -1.0})
    c.error("D.sample_delay.reject.u-one", "sample_delay", ["D-3", "N-7"],
            {"probs": [0.5, 0.5], "d_min": 0, "u": 1.0})
    c.error("D.sample_delay.reject.sum-not-one", "sample_delay", ["D-3", "N-7"],
            {"probs": [0.5, 0.49], "d_min": 0, "u": 0.3})
    c.error("D.sample_delay.reject.negative-entry", "sample_delay", ["D-3", "N-7"],
            {"probs": [1.5, -0.5], "d_min": 0, "u": 0.3})
    c.error("D.sample_delay.reject.beyond-range", "sample_delay", ["D-3", "N-12", "N-7"],
            {"probs": [0.5, 0.5], "d_min": 4096, "u": 0.3})
    c.error("D.delay_probs.reject.bad-decay-uniform", "delay_probs", ["D-2", "N-7"],
            {"dist": "uniform", "d_min": 0, "d_max": 2, "decay": -1.0})
    # [D-3] The last CDF entry is exactly 1: the largest u below 1 (1 - 2^-53, and 1 - 1e-12) draws the last
    # delay of tables whose float64 cumulative sum ends below 1; u = 1 and u < 0 are errors.
    for dist, lo, hi, decay in (("uniform", 0, 6, 1.0), ("uniform", 2, 11, 1.0), ("exponential", 0, 4, 0.5)):
        p = delays.delay_probs(dist, lo, hi, decay)
        for name, u in (("1-2^-53", 1.0 - 2.0 ** -53), ("1-1e-12", 1.0 - 1e-12)):
            c.add(f"D.sample_delay.last-entry.{dist}.{lo}-{hi}.u{name}", "sample_delay", ["D-3"], TOL_EXACT,
                  {"probs": p, "d_min": lo, "u": u}, {"d": delays.sample_delay(p, lo, u)})
    c.error("D.sample_delay.reject.negative-u", "sample_delay", ["D-3", "N-7"],
            {"probs": [0.5, 0.5], "d_min": 0, "u": -1e-12})
    # [D-3] Both sides of the 1e-6 rule on the table's sum: 1 - 8e-7 is a table, 1 - 1.5e-6 is not.
    c.add("D.sample_delay.sum-within-1e-6", "sample_delay", ["D-3"], TOL_EXACT,
          {"probs": [0.5, 0.4999992], "d_min": 3, "u": 0.75}, {"d": delays.sample_delay([0.5, 0.4999992], 3, 0.75)})
    c.error("D.sample_delay.reject.sum-beyond-1e-6", "sample_delay", ["D-3", "N-7"],
            {"probs": [0.5, 0.4999985], "d_min": 3, "u": 0.75})
    # [D-2], [N-12] Both sides of decay <= 64 and of the delay range 4096 (d_min + n - 1 <= 4096).
    c.error("D.delay_probs.reject.decay-above-64", "delay_probs", ["D-2", "N-12", "N-7"],
            {"dist": "exponential", "d_min": 0, "d_max": 2, "decay": 64.5})
    c.add("D.delay_probs.uniform.4096-4096", "delay_probs", ["D-1", "N-12"], TOL_WEIGHTS,
          {"dist": "uniform", "d_min": 4096, "d_max": 4096, "decay": 1.0}, {"probs": [1.0]})
    c.error("D.delay_probs.reject.d_max-above-4096", "delay_probs", ["D-1", "N-12", "N-7"],
            {"dist": "uniform", "d_min": 4095, "d_max": 4097, "decay": 1.0})
    c.add("D.sample_delay.range.d_min4095", "sample_delay", ["D-3", "N-12"], TOL_EXACT,
          {"probs": [0.5, 0.5], "d_min": 4095, "u": 0.75}, {"d": 4096})
    # [CF-34] The distributions are named "uniform" and "exponential", exactly; a real may be written as an
    # integer (u = 0, decay = 1) ([CF-23]).
    for name in ("geometric", "Uniform"):
        c.error(f"D.delay_probs.reject.dist-{name}", "delay_probs", ["D-1", "CF-34", "N-7"],
                {"dist": name, "d_min": 0, "d_max": 2, "decay": 1.0})
    c.add("D.sample_delay.integer-u", "sample_delay", ["D-3", "CF-34"], TOL_EXACT,
          {"probs": [0.5, 0.5], "d_min": 2, "u": 0}, {"d": 2})
    c.add("D.delay_probs.integer-decay", "delay_probs", ["D-2", "CF-34"], TOL_WEIGHTS,
          {"dist": "exponential", "d_min": 0, "d_max": 3, "decay": 1},
          {"probs": delays.delay_probs("exponential", 0, 3, 1.0)})
    margins_delays(c)
    return c


def _training_weights(H: int):
    """A spread of weight vectors for H: none, hard, soft (clip and zeros), all clamped."""
    s = H // 2
    out = [("none", np.zeros(H)), ("hard-d2", weights.hard_weights(H, 2)),
           ("soft-d2", weights.soft_weights(H, 2, SoftWindow(endpoints.delay_scaled(2.0, H_MAX[H])), s)),
           ("soft-zeros-d3", weights.soft_weights(H, 3, SoftWindow(endpoints.offset(3, H), overflow="zeros"))),
           ("soft-exp-paper-d1", weights.soft_weights(H, 1, SoftWindow(endpoints.fixed(3), "exp", "paper"), s)),
           ("all-clamped", np.ones(H))]
    return out


def gen_corruption() -> _Cases:
    c = _Cases()
    rng = np.random.default_rng(20)
    for H, A in ((4, 1), (8, 2), (10, 3), (16, 2)):
        acts, noise = rng.standard_normal((H, A)), rng.standard_normal((H, A))
        for wname, w in _training_weights(H):
            for tau in (0.0, 0.3, 0.999, float(rng.uniform())):
                x, tj = corruption.corrupt(acts, noise, w, tau)
                reqs = ["C-1", "C-2"] + (["C-3"] if not w.any() else [])
                c.add(f"C.corrupt.H{H}A{A}.{wname}.tau{tau:.6f}", "corrupt", reqs, TOL_ARITH,
                      {"actions": acts, "noise": noise, "weights": w, "tau": tau}, {"x": x, "times": tj})
    c.error("C.corrupt.reject.weights-above-one", "corrupt", ["C-1", "N-7"],
            {"actions": [[0.0]], "noise": [[0.0]], "weights": [1.5], "tau": 0.5})
    c.error("C.corrupt.reject.shape-mismatch", "corrupt", ["C-2", "N-7"],
            {"actions": [[0.0], [1.0]], "noise": [[0.0]], "weights": [0.0, 0.0], "tau": 0.5})
    # [CF-34] Weights passed in are checked for shape and [0, 1] only, not for [W-1]'s monotonicity; tau may
    # be written as an integer.
    acts, noise, w = rng.standard_normal((4, 2)), rng.standard_normal((4, 2)), np.array([0.0, 1.0, 0.5, 0.25])
    for tau in (0.3, 0):
        x, tj = corruption.corrupt(acts, noise, w, tau)
        c.add(f"C.corrupt.non-monotonic-weights.tau{tau}", "corrupt", ["C-1", "C-2", "CF-34"], TOL_ARITH,
              {"actions": acts, "noise": noise, "weights": w, "tau": tau}, {"x": x, "times": tj})
    return c


def gen_loss() -> _Cases:
    c = _Cases()
    rng = np.random.default_rng(30)
    for H, A in ((4, 1), (8, 2), (10, 3), (16, 2)):
        acts, noise, pred = (rng.standard_normal((H, A)) for _ in range(3))
        for wname, w in _training_weights(H):
            reqs = ["L-1", "L-2"] + (["L-4"] if not w.any() else [])
            c.add(f"L.loss.H{H}A{A}.{wname}", "loss", reqs, TOL_ARITH,
                  {"pred": pred, "actions": acts, "noise": noise, "weights": w},
                  {"loss": loss.flow_matching_loss(pred, acts, noise, w)})
        B = 3
        preds, acts_b, noise_b = (rng.standard_normal((B, H, A)) for _ in range(3))
        wb = np.stack([w for _, w in _training_weights(H)[1:1 + B]])
        c.add(f"L.batch_loss.H{H}A{A}.B{B}", "batch_loss", ["L-1", "L-2", "L-3"], TOL_ARITH,
              {"preds": preds, "actions": acts_b, "noise": noise_b, "weights": wb},
              {"loss": loss.batch_loss(preds, acts_b, noise_b, wb)})
    c.error("L.loss.reject.weights-above-one", "loss", ["L-1", "N-7"],
            {"pred": [[0.0]], "actions": [[0.0]], "noise": [[0.0]], "weights": [2.0]})
    acts, noise, pred = (rng.standard_normal((4, 2)) for _ in range(3))
    w = np.array([0.5, 0.0, 1.0, 0.25])  # [CF-34] not monotonic: accepted
    c.add("L.loss.non-monotonic-weights", "loss", ["L-2", "CF-34"], TOL_ARITH,
          {"pred": pred, "actions": acts, "noise": noise, "weights": w},
          {"loss": loss.flow_matching_loss(pred, acts, noise, w)})
    margins_loss(c)
    return c
