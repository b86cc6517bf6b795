"""Diagnosis of a failed rollout request: which requirement the implementation's answer breaks ([CR-9]).

A request whose chunk or executed actions leave the tolerance is compared
with the reference's answers under named deviations, each the plausible
integration mistake that breaks one requirement. The first deviation the
implementation's answer matches within the same tolerance names the
requirement; when none matches, the failure keeps every requirement the
output is checked for.
"""

from __future__ import annotations

import numpy as np

from softrtc.reference import executor as rexec

from .rollout_impls import ReferenceRollout

TOL = {"abs": 1e-4, "rel": 1e-4}


def within(got, want, tol: dict = TOL) -> bool:
    """Whether ``got`` equals ``want`` within ``|got - want| <= abs + rel |want|`` everywhere ([CF-5])."""
    g, w = np.asarray(got, np.float64), np.asarray(want, np.float64)
    return g.shape == w.shape and bool(np.all(np.abs(g - w) <= tol["abs"] + tol["rel"] * np.abs(w)))


def chunk_deviations(args: dict) -> list:
    """``(requirement, description, kwargs of ReferenceRollout, delay)`` for the chunk's deviations."""
    s, d, arrival, method = args["s"], args["d"], args["arrival"], args["method"]
    H = np.shape(args["noise"])[0]
    out = [("X-3", "the prior shifted by s - 1 instead of s", {"prior_shift": -1}, d),
           ("X-3", "the prior shifted by s + 1 instead of s", {"prior_shift": 1}, d),
           ("X-3", "the previous chunk used as the prior without the shift by s", {"prior_shift": -s}, d)]
    if method.startswith("inference_"):
        out.append(("G-3", "the guided pull-back without its Jacobian term (1 - t) (dv/dx)^T err",
                    {"pullback": "no_jacobian"}, d))
    for dd in sorted({arrival, d - 1, d + 1} - {d}):
        if 0 <= dd <= min(s, H - s):
            out.append(("S-6", f"the method's weights for delay {dd} instead of the request's d = {d}", {}, dd))
    if method != "naive":
        out.append(("S-6", "the naive sampler (the prior ignored)", {}, None))
    return out


def diagnose_chunk(field, args: dict, got) -> tuple | None:
    """``(requirement, description)`` of the first deviation the chunk ``got`` matches, else None."""
    if args["prev"] is None:
        return None
    for req, text, kw, dd in chunk_deviations(args):
        ref = ReferenceRollout(**kw)
        try:
            want = ref.chunk(field, args["obs"], args["prev"], args["noise"],
                             "naive" if dd is None else args["method"], args["s"], 0 if dd is None else dd,
                             args["T"], args["window"], args["max_guidance"])
        except ValueError:
            continue
        if within(got, want):
            return req, text
    return None


def diagnose_executed(args: dict, chunk, got) -> tuple | None:
    """``(requirement, description)`` of the first execution deviation ``got`` matches, given the
    implementation's own chunk, else None ([X-4], [R-4])."""
    prev = args["prev"]
    if prev is None:
        return ("X-2", "not the first chunk's tokens 0 .. s - 1") if not within(got, np.asarray(chunk)[:args["s"]]) \
            else None
    prev, chunk = np.asarray(prev, np.float64), np.asarray(chunk, np.float64)
    s, d, a = args["s"], args["d"], args["arrival"]
    e = max(d, a)
    H = prev.shape[0]
    cands = []
    if a > d:
        cands.append(("R-4", f"the chunk arrived late (tick {a} > d = {d}) and was dropped: the previous chunk ran "
                             "on instead of waiting for it", prev[s:2 * s] if 2 * s <= H else None))
        cands.append(("R-4", f"the switch made at the planned delay d = {d} though the chunk arrived at tick {a}",
                      rexec.segment(prev, chunk, s, d)))
    if a < d:
        cands.append(("R-4", f"the switch made at the arrival tick {a} before the planned delay d = {d}",
                      rexec.segment(prev, chunk, s, a)))
    if e > 0:
        cands.append(("X-4", "the new chunk's tokens counted from the switch, not from the request "
                             "(chunk[0 .. s - e - 1] after the switch)", np.concatenate([prev[s:s + e], chunk[:s - e]])))
        cands.append(("X-4", "the committed prefix taken from the new chunk instead of the previous one",
                      chunk[:s]))
    for req, text, want in cands:
        if want is not None and within(got, want):
            return req, text
    return None
