"""Vector cases of chapters F, S, G, X, M and V: the reference field, samplers, guidance, execution,
metrics and the flipped convention ([CF-4]).
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import conventions, executor, guidance, methods, metrics, sampler, velocity
from softrtc.reference.weights import SoftWindow
from softrtc.reference import endpoints

from .cases_base import TOL_ARITH, TOL_COPY, TOL_TRACE, TOL_WEIGHTS, _Cases
from .cases_margins import margins_executor, margins_guidance, margins_metrics, margins_sampler
from .cases_training import _training_weights

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
    # [CF-34] Flow times are checked: a per-token time outside [0, 1] is an error for the field and its VJP.
    f = _fields()["h8a2"]
    obs, x = rng.standard_normal(f.obs_dim), rng.standard_normal((8, 2))
    for tag, bad in (("t-above-one", 1.5), ("t-below-zero", -0.25)):
        t = np.full(8, 0.5)
        t[3] = bad
        c.error(f"F.velocity.reject.{tag}", "velocity", ["F-1", "CF-34", "N-7"], {"field": "h8a2", "obs": obs,
                                                                                   "x": x, "t": t})
        c.error(f"F.velocity_vjp.reject.{tag}", "velocity_vjp", ["F-2", "CF-34", "N-7"],
                {"field": "h8a2", "obs": obs, "x": x, "t": t, "cotangent": x})
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
    c.error("S.naive_sample.reject.steps-above-65536", "naive_sample", ["S-1", "N-12", "N-7"],
            {"field": "h8a2", "obs": obs, "noise": noise, "T": 65537})
    c.error("S.method_weights.reject.d-above-overlap", "method_weights", ["S-6", "X-1", "N-7"],
            {"method": "train_hard", "H": 8, "s": 6, "d": 3, "window": None})
    # also bounds d by s for the inference methods, though guidance_weights(8, 2, 3) is defined ([G-1]).
    c.error("S.method_weights.reject.inference-d-above-s", "method_weights", ["S-6", "S-8", "X-1", "G-1", "N-7"],
            {"method": "inference_hard", "H": 8, "s": 2, "d": 3, "window": None})
    c.error("S.method_weights.reject.window-too-long", "method_weights", ["S-8", "E-1", "N-7"],
            {"method": "naive", "H": 4, "s": 2, "d": 1, "window": SoftWindow().to_dict()})
    c.add("S.method_weights.h4.default-window-unused", "method_weights", ["S-6", "S-8"], TOL_WEIGHTS,
          {"method": "train_hard", "H": 4, "s": 2, "d": 1, "window": None},
          {"weights": methods.method_weights("train_hard", 4, 2, 1)})
    margins_sampler(c)
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
    # [G-4], [N-12] Both sides of t in [0, 1) and of max_guidance > 0; lam(0) is the cap exactly.
    for t, beta in ((0.0, 2.0 ** -20), (0.0, 0.25), (1.0 - 2.0 ** -10, 5.0), (0.5, 1.5)):
        c.add(f"G.guidance_weight.edge.t{t}.beta{beta}", "guidance_weight", ["G-4", "N-12"], TOL_ARITH,
              {"t": t, "max_guidance": beta}, {"lam": guidance.guidance_weight(t, beta)})
    c.error("G.guidance_weight.reject.negative-t", "guidance_weight", ["G-4", "N-7"],
            {"t": -1e-12, "max_guidance": 5.0})
    # [CF-34] t of guidance_weight is one scalar (reals may be written as integers); an array is an error.
    c.add("G.guidance_weight.integer-args", "guidance_weight", ["G-4", "CF-34"], TOL_ARITH,
          {"t": 0, "max_guidance": 5}, {"lam": 5.0})
    c.error("G.guidance_weight.reject.array-t", "guidance_weight", ["G-4", "CF-34", "N-7"],
            {"t": [0.25, 0.5], "max_guidance": 5.0})
    c.error("G.guidance_weight.reject.zero-max-guidance", "guidance_weight", ["G-4", "N-12", "N-7"],
            {"t": 0.5, "max_guidance": 0.0})
    margins_guidance(c, fields, _guidance)
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
    margins_executor(c)
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
    # [M-1], [N-12] Both sides of the order range 1 <= k <= 16.
    a = rng.standard_normal((17, 2))
    c.add("M.difference_norm.order16", "difference_norm", ["M-1", "N-12"], TOL_ARITH, {"actions": a, "order": 16},
          {"value": metrics.difference_norm(a, 16)})
    for k in (0, 17):
        c.error(f"M.difference_norm.reject.order{k}", "difference_norm", ["M-1", "N-12", "N-7"],
                {"actions": rng.standard_normal((20, 2)), "order": k})
    vals = [0.1, 0.5, 0.9]
    for conf in (0.0, 1.0):
        c.error(f"M.bootstrap_interval.reject.confidence{conf}", "bootstrap_interval", ["M-5", "N-7"],
                {"values": vals, "indices": [[0, 1, 2]], "confidence": conf})
    # [CF-34] The index matrix has exactly len(values) columns (one resample of n values per row), B >= 1 rows.
    c.add("M.bootstrap_interval.one-row", "bootstrap_interval", ["M-5", "CF-34"], TOL_ARITH,
          {"values": vals, "indices": [[2, 2, 0]], "confidence": 0.9},
          {"interval": list(metrics.bootstrap_interval_from_indices(vals, [[2, 2, 0]], 0.9))})
    for tag, idx in (("columns-n-1", [[0, 1], [1, 2]]), ("columns-n+1", [[0, 1, 2, 0], [1, 2, 0, 1]]),
                     ("index-n", [[0, 1, 3]])):
        c.error(f"M.bootstrap_interval.reject.{tag}", "bootstrap_interval", ["M-5", "CF-34", "N-7"],
                {"values": vals, "indices": idx, "confidence": 0.9})
    margins_metrics(c)
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
    # [CF-34] token_times takes one scalar flow time t (the example's tau); per-token times are its output.
    c.error("V.token_times.reject.array-t", "token_times", ["C-1", "CF-34", "N-7"],
            {"weights": [0.0, 0.5], "t": [0.2, 0.4]})
    return c
