"""Vector cases of the training-time sampler's solver step ([S-10], [S-11]): ``rtc_sample_step`` traces under
Algorithm 1 and the time-consistent step, on the reference fields of the sampler file ([CF-4]).

A separate interface function, not a seventh argument of ``rtc_sample``: an adapter written before steps
existed lacks it and reports these cases unsupported ([CF-9]) instead of failing them.
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import endpoints, executor, methods, sampler
from softrtc.reference.weights import SoftWindow

from .cases_base import TOL_TRACE, _Cases


def _trace(tr: list) -> list:
    return [{k: (float(v) if np.isscalar(v) else np.asarray(v)) for k, v in step.items()} for step in tr]


def gen_sampler_step() -> tuple[_Cases, dict]:
    from .cases_runtime import _field_header, _fields

    c = _Cases()
    rng = np.random.default_rng(53)
    fields = _fields()
    for name, s, T in (("h8a2", 4, 5), ("h10a3", 5, 5)):
        f = fields[name]
        H = f.horizon
        windows = [("train_hard", None), ("train_soft", SoftWindow(endpoints.delay_scaled(2.0, min(5, H)))),
                   ("train_soft", SoftWindow(endpoints.offset(2, H), "exp", "paper", "zeros"))]
        for d in range(min(s, H - s) + 1):
            obs, noise = rng.standard_normal(f.obs_dim), rng.standard_normal((H, f.action_dim))
            prev = sampler.naive_sample(f, obs, rng.standard_normal((H, f.action_dim)), 5)
            prior = executor.shift_prior(prev, s)
            for k, (method, win) in enumerate(windows):
                w = methods.method_weights(method, H, s, d, win)
                binary = bool(np.all((w == 0.0) | (w == 1.0)))
                chunk, tr = sampler.rtc_sample(f, obs, noise, prior, w, T, return_trace=True, step="consistent")
                reqs = ["S-1", "S-3", "S-5", "S-10", "F-1"] + (["S-11"] if binary else [])
                c.add(f"S.rtc_sample_step.{name}.s{s}.d{d}.T{T}.{method}{k}.consistent", "rtc_sample_step", reqs,
                      TOL_TRACE, {"field": name, "obs": obs, "noise": noise, "prior": prior, "weights": w, "T": T,
                                  "step": "consistent"}, {"chunk": chunk, "trace": _trace(tr)})
    # Short and long step counts, and Algorithm 1 by its name (the default of rtc_sample, [S-4]).
    f = fields["h8a2"]
    obs, noise, prior = rng.standard_normal(3), rng.standard_normal((8, 2)), rng.standard_normal((8, 2))
    w = methods.method_weights("train_soft", 8, 4, 2)
    for T, step in ((1, "consistent"), (2, "consistent"), (10, "consistent"), (5, "algorithm1")):
        chunk, tr = sampler.rtc_sample(f, obs, noise, prior, w, T, return_trace=True, step=step)
        reqs = ["S-1", "S-3", "S-5"] + (["S-10"] if step == "consistent" else ["S-4", "S-10"])
        c.add(f"S.rtc_sample_step.h8a2.s4.d2.T{T}.train_soft.{step}", "rtc_sample_step", reqs, TOL_TRACE,
              {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": w, "T": T, "step": step},
              {"chunk": chunk, "trace": _trace(tr)})
    # [S-11] zero weights: the naive sampler's chunk under the consistent step.
    chunk, tr = sampler.rtc_sample(f, obs, noise, prior, np.zeros(8), 5, return_trace=True, step="consistent")
    c.add("S.rtc_sample_step.h8a2.zero-weights.T5.consistent", "rtc_sample_step", ["S-7", "S-11"], TOL_TRACE,
          {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": np.zeros(8), "T": 5,
           "step": "consistent"}, {"chunk": chunk, "trace": _trace(tr)})
    base = {"field": "h8a2", "obs": obs, "noise": noise, "prior": prior, "weights": w, "T": 5}
    for tag, bad in (("unknown-name", "time_consistent"), ("capitalised", "Consistent"), ("empty", ""),
                     ("null", None), ("number", 1)):
        c.error(f"S.rtc_sample_step.reject.step-{tag}", "rtc_sample_step", ["S-10", "N-7"], dict(base, step=bad))
    c.error("S.rtc_sample_step.reject.zero-steps", "rtc_sample_step", ["S-1", "N-7"],
            dict(base, T=0, step="consistent"))
    return c, {"fields": _field_header()}
