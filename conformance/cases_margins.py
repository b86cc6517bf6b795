"""Vector cases at the margins of the rules ([CF-4], [CF-20]): inputs that tell a rule from a near miss.

Each ``margins_<chapter>`` function adds its cases to the chapter's collector and is called by the
chapter's ``gen_<chapter>``. The categories:

* delay tables whose lower bound is above 1, and draws strictly between, just below and just above each
  CDF breakpoint ([D-2], [D-3]);
* unknown names for every enumerated string argument (schedule, parametrization, overflow, rule kind,
  method, variant, distribution), each an error ([N-7]);
* the inference and training methods' windows where ``H - s != s``, so a window ending at ``s`` is told
  from one ending at ``H - s`` ([S-6], [G-1], [W-6]);
* the boundary jump on a chunk index that is not monotone ([M-3]);
* the guidance weight's cap far above the default, at ``t = 0`` and near it ([G-4]);
* at least three cases for each boundary a single case held before (range checks, the table-sum rule,
  the last CDF entry, ``W = 0`` of [G-6], ``max_guidance`` other than the default, the loss on small
  numbers).

Values are computed by the reference like every generated case; the small ones are also checked against
hand-computed numbers in tests/conformance/test_vector_margins.py.
"""

from __future__ import annotations

import math

import numpy as np

from softrtc.reference import delays, endpoints, executor, guidance, loss, methods, metrics, sampler, weights
from softrtc.reference.weights import SoftWindow

from .cases_base import TOL_ARITH, TOL_EXACT, TOL_TRACE, TOL_WEIGHTS, _Cases

# How far below and above a CDF breakpoint the draws of [D-3] sit: far beyond the rounding of a float32
# table's cumulative sums and of u (a few 2^-24 for the tables here), so every port agrees, yet inside one
# step of a 16-bit grid of u (2^-16), so a draw whose u is quantized is caught.
BREAKPOINT_DELTA = 2e-6

# Delay tables of [D-1], [D-2] whose draws are sampled between the breakpoints. Those with d_min > 1 tell
# (d - d_min) from d or (d - 1) in the exponent; at 12 * 64, 20 * 40 and 100 * 8 the unshifted
# exp(-decay d) underflows to 0 for every delay, so only logits shifted to start at 0 give a table ([D-2]).
# decay = ln 2 halves each probability: 4/7, 2/7, 1/7.
MARGIN_TABLES = (("uniform", 0, 4, 1.0), ("uniform", 2, 11, 1.0), ("exponential", 0, 4, 0.5),
                 ("exponential", 1, 6, 0.75), ("exponential", 2, 6, 0.5), ("exponential", 3, 5, math.log(2.0)),
                 ("exponential", 3, 9, 0.3), ("exponential", 12, 14, 64.0), ("exponential", 20, 27, 40.0),
                 ("exponential", 100, 102, 8.0))

# Geometries with H - s != s ([S-6], [G-1], [W-6], [X-1]).
UNEVEN = ((8, 3), (10, 4), (6, 5), (8, 2))


def _table_tag(dist, lo, hi, decay) -> str:
    return f"{dist}.{lo}-{hi}" + (f".decay{decay:.6g}" if dist == "exponential" else "")


def between_breakpoints(cdf: np.ndarray) -> list:
    """Draws of [D-3] for a CDF: 1/4 and 3/4 of the way through each bin, and BREAKPOINT_DELTA below and
    above each breakpoint but the last (which is 1), kept inside [0, 1)."""
    lo = np.r_[0.0, cdf[:-1]]
    us = [float(a + f * (b - a)) for a, b in zip(lo, cdf) for f in (0.25, 0.75)]
    for c in cdf[:-1]:
        us += [float(c) - BREAKPOINT_DELTA, float(c) + BREAKPOINT_DELTA]
    return sorted({u for u in us if 0.0 <= u < 1.0})


# ---------------------------------------------------------------- chapter E / W

def margins_endpoints(c: _Cases) -> None:
    """Rule kinds are exact names; lam and h_max ranges on both sides, three cases each ([E-1], [N-12])."""
    for tag, rule in (("Hard", {"kind": "Hard"}), ("delay-scaled", {"kind": "delay-scaled", "lam": 2.0, "h_max": 5}),
                      ("offset-space", {"kind": "offset ", "length": 2, "h_max": 8})):
        c.error(f"E.endpoint.reject.kind-{tag}", "endpoint", ["E-1", "CF-34", "N-7"], {"rule": rule, "d": 1})
    for tag, rule in (("lam-4097", {"kind": "delay_scaled", "lam": 4097.0, "h_max": 5}),
                      ("lam-4096.25", {"kind": "delay_scaled", "lam": 4096.25, "h_max": 4096}),
                      ("float-h_max-offset", {"kind": "offset", "length": 3, "h_max": 8.0}),
                      ("float-h_max-4096", {"kind": "delay_scaled", "lam": 1.0, "h_max": 4096.0})):
        c.error(f"E.endpoint.reject.{tag}", "endpoint", ["E-1", "N-12", "N-7"], {"rule": rule, "d": 1})


def margins_weights(c: _Cases) -> None:
    """Unknown schedule, parametrization and overflow names are errors ([W-3], [W-4], [W-5], [W-6],
    [N-7]); s = 0 is an error under clip for every window ([W-6])."""
    base = {"H": 8, "d": 2, "e": 5}
    for tag, sched, par in (("schedule-cosine", "cosine", "rtc"), ("schedule-Linear", "Linear", "rtc"),
                            ("schedule-empty", "", "rtc"), ("schedule-null", None, "rtc"),
                            ("parametrization-RTC", "linear", "RTC"), ("parametrization-openpi", "linear", "openpi"),
                            ("parametrization-null", "exp", None)):
        c.error(f"W.prefix_weights.reject.{tag}", "prefix_weights", ["W-3" if tag.startswith("schedule") else "W-4", "N-7"],
                dict(base, schedule=sched, parametrization=par))
    default = SoftWindow().to_dict()
    for tag, key, value in (("overflow-wrap", "overflow", "wrap"), ("overflow-Clip", "overflow", "Clip"),
                            ("overflow-none", "overflow", "none"), ("parametrization-Paper", "parametrization", "Paper"),
                            ("parametrization-pi0", "parametrization", "pi0"),
                            ("parametrization-empty", "parametrization", ""), ("schedule-Exp", "schedule", "Exp"),
                            ("schedule-null", "schedule", None), ("schedule-linear-space", "schedule", "linear ")):
        for s in (4, None):
            window = dict(default, overflow="clip" if s else "zeros")  # valid but for the one unknown name
            window[key] = value
            c.error(f"W.weights.reject.{tag}.s{s}", "weights", ["W-6", "W-7", "N-7"],
                    {"H": 8, "d": 2, "window": window, "s": s})
    c.error("W.weights.reject.rule-kind-Offset", "weights", ["W-7", "E-1", "N-7"],
            {"H": 8, "d": 2, "window": dict(default, rule={"kind": "Offset", "length": 2, "h_max": 8}), "s": 4})
    for d, rule in ((0, endpoints.offset(2, 8)), (4, endpoints.fixed(3))):
        c.error(f"W.weights.reject.s-zero-under-clip.{rule.kind}.d{d}", "weights", ["W-6", "N-7"],
                {"H": 8, "d": d, "window": SoftWindow(rule).to_dict(), "s": 0})


# ---------------------------------------------------------------- chapter D / L

def margins_delays(c: _Cases) -> None:
    """Tables with d_min > 1, draws between breakpoints, both sides of every range ([D-1]..[D-3])."""
    for dist, lo, hi, decay in MARGIN_TABLES:
        p = delays.delay_probs(dist, lo, hi, decay)
        tag = _table_tag(dist, lo, hi, decay)
        if lo > 1:
            c.add(f"D.delay_probs.margin.{tag}", "delay_probs", ["D-1" if dist == "uniform" else "D-2"],
                  TOL_WEIGHTS, {"dist": dist, "d_min": lo, "d_max": hi, "decay": decay}, {"probs": p})
        for i, u in enumerate(between_breakpoints(delays.delay_cdf(p))):
            c.add(f"D.sample_delay.between.{tag}.u{i}", "sample_delay", ["D-3"], TOL_EXACT,
                  {"probs": p, "d_min": lo, "u": u}, {"d": delays.sample_delay(p, lo, u)})
    # [D-3] The last CDF entry is exactly 1: tables whose float64 cumulative sum ends below 1 (uniform on
    # ten delays ends at 1 - 2^-53, the exponential table at 1 - 2^-52) draw their last delay at the
    # largest u below 1.
    for dist, lo, hi, decay in (("uniform", 1, 10, 1.0), ("exponential", 3, 9, 0.3)):
        p = delays.delay_probs(dist, lo, hi, decay)
        c.add(f"D.sample_delay.last-entry.{_table_tag(dist, lo, hi, decay)}.u1-2^-53", "sample_delay", ["D-3"],
              TOL_EXACT, {"probs": p, "d_min": lo, "u": 1.0 - 2.0 ** -53}, {"d": hi})
    # [D-2], [N-12] decay in [0, 64] for both distributions.
    for tag, dist, decay in (("decay-65", "exponential", 65.0), ("decay-64.000001", "exponential", 64.000001),
                             ("uniform-decay-64.5", "uniform", 64.5)):
        c.error(f"D.delay_probs.reject.{tag}", "delay_probs", ["D-2", "N-12", "N-7"],
                {"dist": dist, "d_min": 2, "d_max": 5, "decay": decay})
    for name in ("exp", "Exponential", ""):
        c.error(f"D.delay_probs.reject.dist-{name or 'empty'}", "delay_probs", ["D-1", "D-2", "CF-34", "N-7"],
                {"dist": name, "d_min": 2, "d_max": 4, "decay": 1.0})
    # [D-3] The table's sum within 1e-6 of 1, on both sides: sums off by 2e-6, 5e-6, 1e-4 and 9e-4 are
    # errors (a tolerance of 1e-3 would renormalize them), 1 + 8e-7 is a table.
    for tag, p in (("sum-1-2e-6", [0.5, 0.499998]), ("sum-1+5e-6", [0.5, 0.500005]),
                   ("sum-1-1e-4", [0.25, 0.25, 0.25, 0.2499]), ("sum-1+9e-4", [0.3009, 0.7])):
        c.error(f"D.sample_delay.reject.{tag}", "sample_delay", ["D-3", "N-7"], {"probs": p, "d_min": 2, "u": 0.4})
    c.add("D.sample_delay.sum-1+8e-7", "sample_delay", ["D-3"], TOL_EXACT,
          {"probs": [0.5000008, 0.5], "d_min": 7, "u": 0.5}, {"d": 7})


def margins_loss(c: _Cases) -> None:
    """Losses on small numbers, checkable by hand ([L-1], [L-2], [L-4]): the mask 1 - w, the sum over the
    action dimension, the normalizer sum(1 - w) + eta with eta = 1e-8."""
    cases = {
        # e = || pred - (a - n) ||^2 per token: [1, 4, 9]; m = 1 - w = [1, 0.5, 0]: (1 + 2) / (1.5 + eta).
        "three-tokens": ([[1.0], [2.0], [3.0]], [[0.0], [0.0], [0.0]], [[0.0], [0.0], [0.0]], [0.0, 0.5, 1.0]),
        # Two action dims: e = [1 + 4, 0 + 1] = [5, 1]; m = [0.75, 0.25]: (3.75 + 0.25) / (1 + eta).
        "two-dims": ([[1.0, 2.0], [0.0, 1.0]], [[0.0, 0.0], [0.0, 0.0]], [[0.0, 0.0], [0.0, 0.0]], [0.25, 0.75]),
        # [L-4] w = 0. The target is a - n = [2, 2]: e = [(2 - 2)^2, (0 - 2)^2] = [0, 4]; m = [1, 1]: 4 / (2 + eta).
        "noise-target": ([[2.0], [0.0]], [[1.0], [3.0]], [[-1.0], [1.0]], [0.0, 0.0]),
        # Every token clamped: 0 / (0 + eta) = 0, eta guarding the division ([L-2]).
        "all-clamped": ([[5.0], [-3.0]], [[0.0], [0.0]], [[1.0], [1.0]], [1.0, 1.0]),
    }
    for tag, (pred, acts, noise, w) in cases.items():
        reqs = ["L-1", "L-2"] + (["L-4"] if max(w) == 0.0 else [])
        c.add(f"L.loss.margin.{tag}", "loss", reqs, TOL_ARITH,
              {"pred": pred, "actions": acts, "noise": noise, "weights": w},
              {"loss": loss.flow_matching_loss(pred, acts, noise, w)})


# ---------------------------------------------------------------- chapter S / G

def margins_sampler(c: _Cases) -> None:
    """Every method's weights where H - s != s ([S-6], [G-1], [W-6], [X-1]); unknown method names are
    errors ([S-6], [N-7])."""
    for H, s in UNEVEN:
        win = SoftWindow(endpoints.delay_scaled(2.0, min(5, H)))
        for d in range(min(s, H - s) + 1):
            for m in methods.METHODS:
                wd = win.to_dict() if m == "train_soft" else None
                c.add(f"S.method_weights.uneven.H{H}.s{s}.d{d}.{m}", "method_weights",
                      ["S-6"] + (["G-1"] if m.startswith("inference") else ["W-6", "W-7"] if m == "train_soft" else []),
                      TOL_WEIGHTS, {"method": m, "H": H, "s": s, "d": d, "window": wd},
                      {"weights": methods.method_weights(m, H, s, d, None if wd is None else win)})
    for name in ("rtc", "Naive", "inference", "train_soft ", "soft", "", None):
        tag = "null" if name is None else (name.strip() + ("-space" if name.endswith(" ") else "")) or "empty"
        c.error(f"S.method_weights.reject.method-{tag}", "method_weights", ["S-6", "N-7"],
                {"method": name, "H": 8, "s": 3, "d": 2, "window": None})
    c.error("S.method_weights.reject.window-overflow-wrap", "method_weights", ["S-8", "W-6", "N-7"],
            {"method": "train_soft", "H": 8, "s": 3, "d": 2, "window": dict(SoftWindow().to_dict(), overflow="wrap")})


def _guided_case(c: _Cases, fields: dict, rng, name: str, s: int, d: int, T: int, variant: str, beta: float,
                 guidance_dict) -> None:
    f = fields[name]
    H = f.horizon
    obs, noise = rng.standard_normal(f.obs_dim), rng.standard_normal((H, f.action_dim))
    prev = sampler.naive_sample(f, obs, rng.standard_normal((H, f.action_dim)), 5)
    prior = executor.shift_prior(prev, s)
    W = guidance.guidance_prefix_weights(H, s, d, variant)
    chunk, tr = guidance.guided_sample(f, obs, noise, prior, W, T, beta, return_trace=True)
    trace = [{k: (float(v) if np.isscalar(v) else np.asarray(v)) for k, v in step.items()} for step in tr]
    reqs = ["G-1", "G-2", "G-3", "G-4", "G-5", "F-2"] + (["G-6"] if not W.any() else [])
    c.add(f"G.guided_sample.margin.{name}.s{s}.d{d}.T{T}.{variant}.beta{beta:g}", "guided_sample", reqs, TOL_TRACE,
          {"field": name, "obs": obs, "noise": noise, "prior": prior, "weights": W, "T": T, "max_guidance": beta,
           "guidance": guidance_dict(H, s, d, variant, beta)}, {"chunk": chunk, "trace": trace})


def margins_guidance(c: _Cases, fields: dict, guidance_dict) -> None:
    """Guided traces with caps other than the default and windows where H - s != s; W = 0 ([G-6]); the
    cap far above the default ([G-4]); unknown variants are errors ([G-1], [N-7])."""
    rng = np.random.default_rng(61)
    for name, s, d, T, variant, beta in (("h8a2", 3, 2, 4, "soft", 2.0), ("h10a3", 4, 1, 3, "hard", 1.0),
                                         ("h8a2", 5, 0, 3, "hard", 2.0), ("h10a3", 6, 3, 4, "soft", 10.0),
                                         ("h8a2", 2, 1, 3, "soft", 0.5), ("h10a3", 3, 0, 2, "hard", 3.0)):
        _guided_case(c, fields, rng, name, s, d, T, variant, beta, guidance_dict)
    # [G-4] lam(0) is the cap exactly, however large: a finite stand-in for c(0) = inf (1e4, 1e8) caps it
    # below beta. The caps are exact in float32 (2^100, not 1e30), so lam(0) = beta holds for every port.
    # Near t = 0, c / r^2 = (t^2 + (1 - t)^2) / (t (1 - t)) ~ 1 / t lies below a large cap: at t = 2^-20 it
    # is 2^20 - 1 + 1 / (2^20 - 1).
    for t, beta in ((0.0, 1e5), (0.0, 2.5e8), (0.0, 2.0 ** 100), (2.0 ** -20, 1e7), (2.0 ** -20, 1e5), (1e-3, 1e9)):
        c.add(f"G.guidance_weight.large-cap.t{t:g}.beta{beta:g}", "guidance_weight", ["G-4", "N-12"], TOL_ARITH,
              {"t": t, "max_guidance": beta}, {"lam": guidance.guidance_weight(t, beta)})
    for t, beta in ((0.0, 0.0), (0.25, -1.0), (0.5, -5.0)):
        c.error(f"G.guidance_weight.reject.max-guidance{beta:g}.t{t:g}", "guidance_weight", ["G-4", "N-12", "N-7"],
                {"t": t, "max_guidance": beta})
    for variant in ("exp", "Soft", "zeros", "", None):
        c.error(f"G.guidance_weights.reject.variant-{variant or ('null' if variant is None else 'empty')}",
                "guidance_weights", ["G-1", "N-7"], {"H": 8, "s": 3, "d": 2, "variant": variant})


# ---------------------------------------------------------------- chapter X / M

def margins_executor(c: _Cases) -> None:
    """The first chunk's delay is 0 ([X-2]): three more plans that break it."""
    rng = np.random.default_rng(71)
    for tag, H, s, ds in (("first-2", 8, 4, [2, 0, 0]), ("first-4", 8, 4, [4, 4]), ("first-1-s3", 10, 3, [1, 2, 3])):
        c.error(f"X.execute_chunks.reject.{tag}", "execute_chunks", ["X-1", "X-2", "N-7"],
                {"chunks": rng.standard_normal((len(ds), H, 2)), "delays": ds, "s": s})


def margins_metrics(c: _Cases) -> None:
    """Boundary jumps on chunk indices that are labels, not counters ([M-3]); orders beyond 16 ([M-1])."""
    rng = np.random.default_rng(81)
    for tag, ci in (("back-and-forth", [0, 0, 1, 1, 0, 0, 2, 2]), ("descending", [3, 3, 3, 2, 2, 1, 1, 0]),
                    ("ring-slots", [0, 1, 0, 1, 0, 1, 0, 1]), ("revisit", [5, 5, 2, 2, 2, 5, 5, 9]),
                    ("negative", [-1, -1, 4, 4, -1, -1, -1, 0])):
        a = rng.standard_normal((len(ci), 2))
        c.add(f"M.boundary_jump.labels.{tag}", "boundary_jump", ["M-3"], TOL_ARITH,
              {"actions": a, "chunk_index": ci}, {"value": metrics.boundary_jump(a, ci)})
    # Hand-checkable: switches at t = 2 (|3 - 1|) and t = 4 (|10 - 6|, back to chunk 0): (2 + 4) / 2 = 3.
    c.add("M.boundary_jump.labels.hand", "boundary_jump", ["M-3"], TOL_ARITH,
          {"actions": [[0.0], [1.0], [3.0], [6.0], [10.0], [15.0]], "chunk_index": [0, 0, 1, 1, 0, 0]},
          {"value": metrics.boundary_jump([[0.0], [1.0], [3.0], [6.0], [10.0], [15.0]], [0, 0, 1, 1, 0, 0])})
    for n, k in ((18, 17), (40, 17), (200, 100)):
        c.error(f"M.difference_norm.reject.order{k}.n{n}", "difference_norm", ["M-1", "N-12", "N-7"],
                {"actions": rng.standard_normal((n, 2)), "order": k})
