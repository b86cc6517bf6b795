"""Generate the conformance vectors of conformance/vectors/ from the NumPy reference ([CF-1]..[CF-6]).

The cases of each chapter, and so the coverage of [CF-4], are built by the ``gen_<chapter>`` functions below.

    python -m softrtc.conformance.generate [--out DIR]
    softrtc conformance generate [--out DIR]

Every random input comes from ``numpy.random.default_rng`` with a fixed seed and
every number is written with Python's shortest round-trip ``repr``, keys sorted,
so two runs on one machine give byte-identical files ([CF-3]); on another
machine they agree within :data:`REGEN_TOL` (:func:`compare`,
``softrtc conformance generate --check``).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
import tempfile
from pathlib import Path

import numpy as np

from softrtc.reference import (conventions, corruption, delays, endpoints, executor, guidance, loss, methods,
                               metrics, sampler, velocity, weights)
from softrtc.reference.weights import SoftWindow

from .._cli_util import command_error, output_dir
from . import FORMAT_VERSION, SPEC_VERSION, vectors_dir
from .vectors_io import parse_json


# Tolerances (absolute, relative) per kind of quantity, loose enough for float32
# ports ([CF-5]); integers and indices are compared exactly.
TOL_EXACT = {"abs": 0.0, "rel": 0.0}
TOL_WEIGHTS = {"abs": 1e-5, "rel": 1e-5}
TOL_ARITH = {"abs": 1e-5, "rel": 1e-5}
TOL_TRACE = {"abs": 1e-4, "rel": 1e-4}
TOL_COPY = {"abs": 1e-6, "rel": 1e-6}
# How far two regenerations may differ ([CF-3]): float64 rounding of NumPy's
# CPU-dependent transcendental kernels, far inside every tolerance above.
REGEN_TOL = {"abs": 1e-12, "rel": 1e-12}

HORIZONS = (4, 8, 10, 16, 50)
LAMS = (0.5, 1.0, 1.5, 2.0, 3.0, 4.0)
OFFSETS = tuple(range(7))
FIXED = (3, 5)
# h_max of the delay-scaled rules per horizon (H = 8 gives the paper's h_max = 5).
H_MAX = {4: 4, 8: 5, 10: 6, 16: 10, 50: 25}
# Execute horizons used with overflow = "clip" per horizon.
CLIP_S = {4: (1, 2), 8: (2, 4), 10: (3, 5), 16: (8,), 50: (25,)}


class _Cases:
    """Collects cases of one vector file, checking ids are unique."""

    def __init__(self):
        self.cases: list[dict] = []
        self._ids: set[str] = set()

    def add(self, cid: str, function: str, requirements, tolerance: dict, args: dict, expected: dict):
        if cid in self._ids:
            raise RuntimeError(f"duplicate case id {cid}")
        self._ids.add(cid)
        self.cases.append({"id": cid, "function": function, "requirements": sorted(requirements),
                           "tolerance": dict(tolerance), "args": _plain(args), "expected": _plain(expected)})

    def error(self, cid: str, function: str, requirements, args: dict):
        """A case whose call MUST raise ValueError ([N-7])."""
        self.add(cid, function, requirements, TOL_EXACT, args, {"error": "ValueError"})


def _plain(obj):
    """NumPy values to plain Python (float, int, list) so json writes them with repr."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _plain(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        v = float(obj)
        if not math.isfinite(v):
            raise RuntimeError("vector files hold only finite numbers")
        return v + 0.0  # -0.0 -> 0.0, so the sign of zero never differs between runs
    return obj


def _rule_id(rule: dict) -> str:
    return "-".join(f"{k}{rule[k]}" if k != "kind" else rule[k] for k in sorted(rule, key=lambda k: k != "kind"))


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
    # An integer-written lam is the same real ([CF-23]); offset and fixed rules give e(0) = 0 ([E-6]).
    c.add("E.endpoint.integer-lam", "endpoint", ["E-2"], TOL_EXACT,
          {"rule": {"kind": "delay_scaled", "lam": 2, "h_max": 5}, "d": 2}, {"e": 4})
    for rule in (endpoints.offset(3, 8), endpoints.fixed(5)):
        c.add(f"E.endpoint.{rule.kind}.d0", "endpoint", ["E-3" if rule.kind == "offset" else "E-4", "E-6"],
              TOL_EXACT, {"rule": rule.to_dict(), "d": 0}, {"e": 0})
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
    return c


# ---------------------------------------------------------------- chapter F / S / G

FIELDS = {"h8a2": (101, 8, 2, 3, 16), "h10a3": (102, 10, 3, 4, 12)}


def _fields() -> dict:
    return {name: velocity.ReferenceVelocityField.init(seed, H, A, O, K) for name, (seed, H, A, O, K) in FIELDS.items()}


def _field_header() -> dict:
    return {name: {"params": f.to_dict(), "horizon": f.horizon, "action_dim": f.action_dim, "obs_dim": f.obs_dim,
                   "hidden": f.hidden} for name, f in _fields().items()}


def gen_velocity() -> tuple[_Cases, dict]:
    c = _Cases()
    rng = np.random.default_rng(40)
    for name, f in _fields().items():
        H, A, O = f.horizon, f.action_dim, f.obs_dim
        for i in range(4):
            obs, x, cot = rng.standard_normal(O), rng.standard_normal((H, A)), rng.standard_normal((H, A))
            t = rng.uniform(size=H) if i else np.linspace(0.0, 1.0, H)
            c.add(f"F.velocity.{name}.{i}", "velocity", ["F-1"], TOL_ARITH,
                  {"field": name, "obs": obs, "x": x, "t": t}, {"velocity": f(obs, x, t)})
            c.add(f"F.velocity_vjp.{name}.{i}", "velocity_vjp", ["F-2"], TOL_ARITH,
                  {"field": name, "obs": obs, "x": x, "t": t, "cotangent": cot}, {"vjp": f.vjp(obs, x, t, cot)})
    return c, {"fields": _field_header()}


def _trace(tr: list) -> list:
    return [{k: (float(v) if np.isscalar(v) else np.asarray(v)) for k, v in step.items()} for step in tr]


def _prior(f, rng, obs, s: int) -> np.ndarray:
    """A realistic prior: the naive chunk for other noise, shifted by s ([X-3])."""
    prev = sampler.naive_sample(f, obs, rng.standard_normal((f.horizon, f.action_dim)), 5)
    return executor.shift_prior(prev, s)


def gen_sampler() -> tuple[_Cases, dict]:
    c = _Cases()
    rng = np.random.default_rng(50)
    fields = _fields()
    setups = [("h8a2", 4, 5), ("h10a3", 5, 5)]
    for name, s, T in setups:
        f = fields[name]
        H = f.horizon
        for d in range(min(s, H - s) + 1):
            obs, noise = rng.standard_normal(f.obs_dim), rng.standard_normal((H, f.action_dim))
            prior = _prior(f, rng, obs, s)
            chunk, tr = sampler.naive_sample(f, obs, noise, T, return_trace=True)
            base = {"field": name, "obs": obs, "noise": noise}
            c.add(f"S.naive_sample.{name}.s{s}.d{d}.T{T}", "naive_sample", ["S-1", "S-2", "F-1"], TOL_TRACE,
                  dict(base, T=T), {"chunk": chunk, "trace": _trace(tr)})
            windows = [("train_hard", None), ("train_soft", SoftWindow(endpoints.delay_scaled(2.0, min(5, H)))),
                       ("train_soft", SoftWindow(endpoints.offset(2, H), "exp", "paper", "zeros"))]
            for k, (method, win) in enumerate(windows):
                w = methods.method_weights(method, H, s, d, win)
                chunk, tr = sampler.rtc_sample(f, obs, noise, prior, w, T, return_trace=True)
                reqs = ["S-1", "S-3", "S-4", "S-5", "S-6", "F-1"] + (["S-7"] if d == 0 else [])
                c.add(f"S.rtc_sample.{name}.s{s}.d{d}.T{T}.{method}{k}", "rtc_sample", reqs, TOL_TRACE,
                      dict(base, prior=prior, weights=w, T=T), {"chunk": chunk, "trace": _trace(tr)})
                if method == "train_soft" or d == 0:
                    c.add(f"S.method_weights.{name}.s{s}.d{d}.{method}{k}", "method_weights", ["S-6", "W-7"],
                          TOL_WEIGHTS, {"method": method, "H": H, "s": s, "d": d,
                                        "window": None if win is None else win.to_dict()}, {"weights": w})
    f = fields["h8a2"]
    obs, noise = rng.standard_normal(f.obs_dim), rng.standard_normal((8, 2))
    prior = _prior(f, rng, obs, 4)
    for T in (1, 2):
        w = methods.method_weights("train_soft", 8, 4, 2)
        chunk, tr = sampler.rtc_sample(f, obs, noise, prior, w, T, return_trace=True)
        c.add(f"S.rtc_sample.h8a2.s4.d2.T{T}.train_soft", "rtc_sample", ["S-1", "S-3", "S-4", "S-5"], TOL_TRACE,
              {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": w, "T": T},
              {"chunk": chunk, "trace": _trace(tr)})
    for m in ("naive", "inference_hard", "inference_soft"):
        c.add(f"S.method_weights.h8a2.s4.d2.{m}", "method_weights", ["S-6", "G-1"], TOL_WEIGHTS,
              {"method": m, "H": 8, "s": 4, "d": 2, "window": None}, {"weights": methods.method_weights(m, 8, 4, 2)})
    c.error("S.rtc_sample.reject.zero-steps", "rtc_sample", ["S-1", "N-7"],
            {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": np.zeros(8), "T": 0})
    c.error("S.method_weights.reject.d-above-overlap", "method_weights", ["S-6", "X-1", "N-7"],
            {"method": "train_hard", "H": 8, "s": 6, "d": 3, "window": None})
    # [X-1] also bounds d by s for the inference methods, though guidance_weights(8, 2, 3) is defined ([G-1]).
    c.error("S.method_weights.reject.inference-d-above-s", "method_weights", ["S-6", "S-8", "X-1", "G-1", "N-7"],
            {"method": "inference_hard", "H": 8, "s": 2, "d": 3, "window": None})
    c.error("S.method_weights.reject.window-too-long", "method_weights", ["S-8", "E-1", "N-7"],
            {"method": "naive", "H": 4, "s": 2, "d": 1, "window": SoftWindow().to_dict()})
    c.add("S.method_weights.h4.default-window-unused", "method_weights", ["S-6", "S-8"], TOL_WEIGHTS,
          {"method": "train_hard", "H": 4, "s": 2, "d": 1, "window": None},
          {"weights": methods.method_weights("train_hard", 4, 2, 1)})
    return c, {"fields": _field_header()}


def _guidance(H: int, s: int, d: int, variant: str, max_guidance: float) -> dict:
    """The parameters that define a guided case's weights, beside them ([CF-27], [G-1]): the guided window
    runs from d to end = H - s with the variant's schedule; max_guidance is the cap of [G-4]."""
    return {"H": H, "s": s, "d": d, "variant": variant, "schedule": guidance.GUIDANCE_SCHEDULES[variant],
            "end": H - s, "max_guidance": max_guidance}


def gen_guidance() -> tuple[_Cases, dict]:
    c = _Cases()
    rng = np.random.default_rng(60)
    fields = _fields()
    for H, s in ((8, 4), (8, 2), (10, 5), (50, 25)):
        for d in range(H - s + 1):
            for variant in ("hard", "soft"):
                c.add(f"G.guidance_weights.H{H}.s{s}.d{d}.{variant}", "guidance_weights", ["G-1", "W-3", "W-4"],
                      TOL_WEIGHTS, {"H": H, "s": s, "d": d, "variant": variant},
                      {"weights": guidance.guidance_prefix_weights(H, s, d, variant)})
    for T in (1, 2, 3, 5, 7):
        for k in range(T):
            t = k / T
            for beta in (5.0, 2.0):
                c.add(f"G.guidance_weight.T{T}.k{k}.beta{beta}", "guidance_weight", ["G-4"], TOL_ARITH,
                      {"t": t, "max_guidance": beta}, {"lam": guidance.guidance_weight(t, beta)})
    for name, s, T in (("h8a2", 4, 5), ("h10a3", 3, 4)):
        f = fields[name]
        H = f.horizon
        for d in range(min(s, H - s) + 1):
            obs, noise = rng.standard_normal(f.obs_dim), rng.standard_normal((H, f.action_dim))
            prior = _prior(f, rng, obs, s)
            for variant in ("hard", "soft"):
                W = guidance.guidance_prefix_weights(H, s, d, variant)
                chunk, tr = guidance.guided_sample(f, obs, noise, prior, W, T, 5.0, return_trace=True)
                c.add(f"G.guided_sample.{name}.s{s}.d{d}.T{T}.{variant}", "guided_sample",
                      ["G-1", "G-2", "G-3", "G-4", "G-5", "F-2", "S-6"] + (["G-6"] if not W.any() else []),
                      TOL_TRACE, {"field": name, "obs": obs, "noise": noise, "prior": prior, "weights": W, "T": T,
                                  "max_guidance": 5.0, "guidance": _guidance(H, s, d, variant, 5.0)},
                      {"chunk": chunk, "trace": _trace(tr)})
    f = fields["h8a2"]
    obs, noise = rng.standard_normal(3), rng.standard_normal((8, 2))
    prior = _prior(f, rng, obs, 4)
    W = guidance.guidance_prefix_weights(8, 4, 2, "soft")
    chunk, tr = guidance.guided_sample(f, obs, noise, prior, W, 4, 2.0, return_trace=True)
    c.add("G.guided_sample.h8a2.s4.d2.T4.soft.beta2", "guided_sample", ["G-3", "G-4", "G-5"], TOL_TRACE,
          {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": W, "T": 4, "max_guidance": 2.0,
           "guidance": _guidance(8, 4, 2, "soft", 2.0)},
          {"chunk": chunk, "trace": _trace(tr)})
    c.error("G.guidance_weights.reject.d-above-overlap", "guidance_weights", ["G-1", "N-7"],
            {"H": 8, "s": 4, "d": 5, "variant": "soft"})
    c.error("G.guidance_weight.reject.t-one", "guidance_weight", ["G-4", "N-7"], {"t": 1.0, "max_guidance": 5.0})
    return c, {"fields": _field_header()}


# ---------------------------------------------------------------- chapter X / M / V

def gen_executor() -> _Cases:
    c = _Cases()
    rng = np.random.default_rng(70)
    for H, A in ((4, 1), (8, 2), (10, 3)):
        prev = rng.standard_normal((H, A))
        for s in range(1, H + 1):
            c.add(f"X.shift_prior.H{H}.s{s}", "shift_prior", ["X-3"], TOL_COPY, {"prev": prev, "s": s},
                  {"prior": executor.shift_prior(prev, s)})
    plans = [(8, 4, [0, d, d, d]) for d in range(5)] + [(8, 4, [0, 1, 3, 2, 4, 0]), (8, 2, [0, 2, 1, 0]),
                                                         (10, 5, [0, 5, 3]), (10, 3, [0, 3, 1, 2]), (4, 2, [0, 2])]
    for H, s, ds in plans:
        chunks = rng.standard_normal((len(ds), H, 2))
        out = executor.execute_chunks(chunks, ds, s)
        c.add(f"X.execute_chunks.H{H}.s{s}.d{'-'.join(map(str, ds))}", "execute_chunks",
              ["X-1", "X-2", "X-4", "X-5"], TOL_COPY, {"chunks": chunks, "delays": ds, "s": s}, out)
    chunks = rng.standard_normal((3, 8, 1))
    for tag, ds, s in (("d-above-overlap", [0, 3, 3], 6), ("d-above-s", [0, 3, 1], 2), ("first-nonzero", [1, 1, 1], 4),
                       ("negative", [0, -1, 0], 4), ("float-d", [0, 2.0, 1], 4)):
        c.error(f"X.execute_chunks.reject.{tag}", "execute_chunks", ["X-1", "N-7"] + (["X-2"] if tag == "first-nonzero"
                                                                                      else []),
                {"chunks": chunks, "delays": ds, "s": s})
    return c


def gen_metrics() -> _Cases:
    c = _Cases()
    rng = np.random.default_rng(80)
    seqs = {"random": rng.standard_normal((24, 2)), "walk": np.cumsum(rng.standard_normal((40, 3)), axis=0),
            "ramp": np.arange(10.0)[:, None] * np.array([[3.0, 4.0]]), "short": rng.standard_normal((4, 1))}
    for name, a in seqs.items():
        for k in (1, 2, 3):
            c.add(f"M.difference_norm.{name}.k{k}", "difference_norm", ["M-1"], TOL_ARITH, {"actions": a, "order": k},
                  {"value": metrics.difference_norm(a, k)})
        c.add(f"M.action_delta.{name}", "action_delta", ["M-2"], TOL_ARITH, {"actions": a},
              {"value": metrics.action_delta(a)})
        c.add(f"M.action_jerk.{name}", "action_jerk", ["M-2"], TOL_ARITH, {"actions": a},
              {"value": metrics.action_jerk(a)})
    for H, s, ds in ((8, 4, [0, 2, 2, 2, 2]), (8, 4, [0, 1, 3, 0]), (10, 3, [0, 3, 1, 2])):
        out = executor.execute_chunks(rng.standard_normal((len(ds), H, 2)), ds, s)
        c.add(f"M.boundary_jump.H{H}.s{s}.d{'-'.join(map(str, ds))}", "boundary_jump", ["M-3"], TOL_ARITH,
              {"actions": out["actions"], "chunk_index": out["chunk_index"]},
              {"value": metrics.boundary_jump(out["actions"], out["chunk_index"])})
    vals = rng.uniform(0.3, 0.9, size=12)
    idx = metrics.bootstrap_indices(12, 400, 0)
    for conf in (0.95, 0.9):
        c.add(f"M.bootstrap_interval.n12.B400.conf{conf}", "bootstrap_interval", ["M-5"], TOL_ARITH,
              {"values": vals, "indices": idx, "confidence": conf},
              {"interval": list(metrics.bootstrap_interval_from_indices(vals, idx, conf))})
    for n in (2, 5, 12):
        v = rng.standard_normal(n)
        c.add(f"M.standard_error.n{n}", "standard_error", ["M-6"], TOL_ARITH, {"values": v},
              {"value": metrics.standard_error(v)})
    c.error("M.difference_norm.reject.too-short", "difference_norm", ["M-1", "N-7"],
            {"actions": [[0.0], [1.0]], "order": 2})
    c.error("M.boundary_jump.reject.no-switch", "boundary_jump", ["M-3", "N-7"],
            {"actions": [[0.0], [1.0]], "chunk_index": [0, 0]})
    c.error("M.boundary_jump.reject.float-chunk-index", "boundary_jump", ["M-3", "N-7"],
            {"actions": [[0.0], [1.0]], "chunk_index": [0.0, 1.5]})
    c.error("M.standard_error.reject.one-value", "standard_error", ["M-6", "N-7"], {"values": [1.0]})
    vals = [0.1, 0.5, 0.9]
    for conf in (0.0, 1.0):
        c.error(f"M.bootstrap_interval.reject.confidence{conf}", "bootstrap_interval", ["M-5", "N-7"],
                {"values": vals, "indices": [[0, 1, 2]], "confidence": conf})
    return c


def gen_conventions() -> _Cases:
    c = _Cases()
    for H in (4, 8, 10):
        for wname, w in _training_weights(H):
            for t in (0.0, 0.2, 0.6, 0.8):
                tf = float(conventions.to_flipped_time(t))
                # Stored in spec time; a flipped adapter receives t' and returns t~' = (1 - w) t' ([V-3]).
                c.add(f"V.token_times.H{H}.{wname}.t{t}", "token_times", ["V-1", "V-3", "C-1", "S-3"], TOL_ARITH,
                      {"weights": w, "t": t}, {"times": 1.0 - conventions.flipped_token_times(w, tf)})
    return c


# ---------------------------------------------------------------- files

FILES = {
    "endpoints": ("E", "Endpoint rules e(d) (spec/01-weights.md 1.1)", gen_endpoints),
    "weights": ("W", "Token weights, schedules, parametrizations, overflow (spec/01-weights.md 1.2)", gen_weights),
    "delays": ("D", "Training delay distributions and inverse-CDF draws (spec/02-training.md 2.1)", gen_delays),
    "corruption": ("C", "Weighted corruption and per-token times (spec/02-training.md 2.2)", gen_corruption),
    "loss": ("L", "Weighted flow-matching loss (spec/02-training.md 2.3)", gen_loss),
    "velocity": ("F", "Reference velocity field and its VJP (spec/03-inference.md 3.1)", gen_velocity),
    "sampler": ("S", "Naive and training-time RTC sampler traces (spec/03-inference.md 3.2)", gen_sampler),
    "guidance": ("G", "Inference-time RTC guidance weights and guided-sampler traces (spec/03-inference.md 3.3)",
                 gen_guidance),
    "executor": ("X", "Prior shift and asynchronous execution (spec/04-execution.md)", gen_executor),
    "metrics": ("M", "Metrics on executed sequences (spec/05-metrics.md)", gen_metrics),
    "conventions": ("V", "Per-token times through the flipped-time mapping (spec/06-conventions.md)",
                    gen_conventions),
}


def _dumps(obj) -> str:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)


def render(name: str) -> str:
    """Text of one vector file: header keys sorted, then one case per line ([CF-3])."""
    if not isinstance(name, str) or name not in FILES:
        raise ValueError(f"name must be one of the vector files {sorted(FILES)}, got {name!r}")
    chapter, title, fn = FILES[name]
    res = fn()
    cases, extra = (res if isinstance(res, tuple) else (res, {}))
    header = {"format_version": FORMAT_VERSION, "spec_version": SPEC_VERSION, "chapter": chapter, "title": title,
              "generator": "softrtc.conformance.generate", "reference": "softrtc.reference"}
    header.update(_plain(extra))
    lines = ["{"]
    lines += [f"{_dumps(k)}:{_dumps(header[k])}," for k in sorted(header)]
    lines.append('"cases":[')
    lines.append(",\n".join(_dumps(case) for case in cases.cases))
    lines.append("]}")
    return "\n".join(lines) + "\n"


def generate(out_dir=None) -> dict:
    """Write every vector file and index.json into ``out_dir`` ([CF-1]); return {file: size in bytes}."""
    if out_dir is not None and not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a path (str or os.PathLike), got {type(out_dir).__name__}")
    out = Path(out_dir) if out_dir is not None else vectors_dir()
    if out.exists() and not out.is_dir():
        raise ValueError(f"out_dir must be a directory, got the file {out}")
    out.mkdir(parents=True, exist_ok=True)
    sizes, index = {}, {}
    for name in FILES:
        text = render(name)
        (out / f"{name}.json").write_text(text, encoding="ascii")
        sizes[f"{name}.json"] = len(text)
        index[f"{name}.json"] = {"chapter": FILES[name][0], "cases": text.count('"id":'),
                                 "sha256": hashlib.sha256(text.encode("ascii")).hexdigest()}
    idx = _dumps({"format_version": FORMAT_VERSION, "spec_version": SPEC_VERSION, "files": index}) + "\n"
    (out / "index.json").write_text(idx, encoding="ascii")
    sizes["index.json"] = len(idx)
    return sizes


def _walk_diff(a, b, where: str, worst: list) -> None:
    """Raises ValueError where ``a`` and ``b`` differ other than in the value of a real number; collects
    (|a - b|, excess over REGEN_TOL) of the reals in ``worst``."""
    if isinstance(a, dict) and isinstance(b, dict):
        if list(a) != list(b):
            raise ValueError(f"{where}: keys differ ({sorted(a)} against {sorted(b)})")
        for k in a:
            _walk_diff(a[k], b[k], f"{where}/{k}", worst)
    elif isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            raise ValueError(f"{where}: lengths differ ({len(a)} against {len(b)})")
        for i, (x, y) in enumerate(zip(a, b)):
            _walk_diff(x, y, f"{where}[{i}]", worst)
    elif type(a) is float and type(b) is float:
        diff = abs(a - b)
        worst.append((diff, diff / (REGEN_TOL["abs"] + REGEN_TOL["rel"] * abs(b)), where))
    elif type(a) is not type(b) or a != b:
        raise ValueError(f"{where}: {a!r} against {b!r}")


def compare(got_dir, want_dir) -> dict:
    """Compare two vector directories file by file ([CF-3]).

    Returns ``{file: {"identical": bool, "max_abs_diff": float, "within": bool, "worst": str | None}}``
    for every ``*.json`` of ``want_dir`` except ``index.json`` (whose digests follow the bytes):
    ``identical`` when the bytes agree; otherwise the files must have the same
    structure, strings, booleans and integers ([CF-23]), and ``within`` tells
    whether every real agrees within :data:`REGEN_TOL`. Raises ValueError when
    a file is missing or differs in anything but the value of a real.
    """
    dirs = []
    for name, d in (("got_dir", got_dir), ("want_dir", want_dir)):
        if not isinstance(d, (str, os.PathLike)) or not Path(d).is_dir():
            raise ValueError(f"{name} must be an existing directory, got {d!r}")
        dirs.append(Path(d))
    got, want = dirs
    names = sorted(p.name for p in want.glob("*.json") if p.name != "index.json")
    if not names:
        raise ValueError(f"want_dir {want} holds no vector files")
    out = {}
    for name in names:
        if not (got / name).is_file():
            raise ValueError(f"{name} is missing from {got}")
        a, b = (got / name).read_bytes(), (want / name).read_bytes()
        if a == b:
            out[name] = {"identical": True, "max_abs_diff": 0.0, "within": True, "worst": None}
            continue
        worst: list = []
        _walk_diff(parse_json(a), parse_json(b), name, worst)  # [CF-23] ints stay ints
        top = max(worst, key=lambda w: w[1], default=(0.0, 0.0, None))
        out[name] = {"identical": False, "max_abs_diff": max((w[0] for w in worst), default=0.0),
                     "within": top[1] <= 1.0, "worst": top[2]}
    return out


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--out", type=output_dir(), default=None, help="output directory (default: the vectors shipped with softrtc, conformance/vectors/ in a source "
                             "checkout)")
    parser.add_argument("--check", action="store_true",
                        help="regenerate into a temporary directory and compare with --out (default: the shipped "
                             "vectors) instead of writing; exit 1 unless every number agrees within "
                             f"{REGEN_TOL['abs']:g} + {REGEN_TOL['rel']:g} |x|")


def _check(prog: str, out_dir) -> int:
    want = Path(out_dir) if out_dir is not None else vectors_dir()
    if not want.is_dir():
        raise ValueError(f"--out must be an existing directory of vector files with --check, got {want}")
    with tempfile.TemporaryDirectory() as tmp:
        generate(tmp)
        try:
            res = compare(tmp, want)
        except ValueError as exc:
            print(f"{prog}: the regenerated vectors differ from {want} beyond rounding: {exc}", file=sys.stderr)
            return 1
    for name, r in res.items():
        status = ("byte-identical" if r["identical"] else
                  f"max |diff| {r['max_abs_diff']:.2e} ({'within' if r['within'] else 'BEYOND'} rounding)")
        print(f"{name:20s} {status}")
    ok = all(r["within"] for r in res.values())
    print("regeneration agrees" if ok else "regeneration differs beyond rounding", f"with {want}")
    return 0 if ok else 1


def run_from_args(args) -> int:
    prog = getattr(args, "_prog", "softrtc conformance generate")
    try:
        if getattr(args, "check", False):
            return _check(prog, args.out)
        sizes = generate(args.out)
    except (ValueError, OSError) as exc:
        return command_error(prog, exc)
    for name, size in sizes.items():
        print(f"{name:20s} {size:>9d} bytes")
    print(f"total {sum(sizes.values())} bytes in {Path(args.out) if args.out else vectors_dir()}")
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.generate",
                                     description="Generate the softrtc conformance vectors from the NumPy reference.")
    add_arguments(parser)
    parser.set_defaults(_prog=parser.prog)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
