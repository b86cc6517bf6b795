"""Mutants that only the margin cases of conformance/cases_margins.py catch ([CF-20], [CF-4]).

Each mutant is a plausible porting mistake: a delay table built without shifting its logits, a draw
with a quantized u, an unknown enumerated name read as a known one, a method window ending at s, a
boundary jump that reads chunk indices as counters, a finite stand-in for c(0) = inf. Each must pass the
vectors generated without the margin cases (so no earlier case caught it) and fail the shipped ones.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from softrtc.conformance import cases_runtime, cases_training, generate, runner
from softrtc.conformance.adapters.reference import ReferenceAdapter, window_from_dict
from softrtc.reference import delays, guidance, methods, metrics, weights
from softrtc.reference.weights import SoftWindow


# ---------------------------------------------------------------- mutated copies

def _exp_table_unshifted(self, dist, d_min, d_max, decay):
    """[D-2] exp(-decay d) normalized, without shifting the logits to start at 0: underflows to 0 / 0 once
    decay * d_min > 745."""
    p = delays.delay_probs(dist, d_min, d_max, decay)
    if dist != "exponential":
        return p
    q = np.exp(-float(decay) * np.arange(d_min, d_max + 1, dtype=np.float64))
    with np.errstate(invalid="ignore"):
        return q / q.sum()


def _sample_delay_u16(self, probs, d_min, u):
    """[D-3] u rounded up to a 16-bit integer k in 0 .. 65535 and drawn at k / 65536 (as a port that draws u as
    a 16-bit integer would)."""
    delays.sample_delay(probs, d_min, u)
    c = delays.delay_cdf(probs)
    return d_min + int(np.sum(c <= min(math.ceil(u * 65536), 65535) / 65536))


def _method_unknown_is_naive(self, method, H, s, d, window):
    return ReferenceAdapter.method_weights(self, method if method in methods.METHODS else "naive", H, s, d, window)


def _parametrization_unknown_is_paper(self, H, d, e, schedule, parametrization):
    return weights.prefix_weights(H, d, e, schedule, "rtc" if parametrization == "rtc" else "paper")


def _overflow_unknown_is_zeros(self, H, d, window, s):
    if isinstance(window, dict) and window.get("overflow", "clip") not in weights.OVERFLOWS:
        window = dict(window, overflow="zeros")
    return ReferenceAdapter.weights(self, H, d, window, s)


def _variant_unknown_is_soft(self, H, s, d, variant):
    return guidance.guidance_prefix_weights(H, s, d, "hard" if variant == "hard" else "soft")


def _inference_window_ends_at_s(self, method, H, s, d, window):
    w = ReferenceAdapter.method_weights(self, method, H, s, d, window)
    if method in ("inference_hard", "inference_soft"):
        return weights.prefix_weights(H, d, s, guidance.GUIDANCE_SCHEDULES[method.split("_", 1)[1]], "rtc")
    return w


def _train_soft_clipped_at_s(self, method, H, s, d, window):
    """[W-6] The training window clipped at s instead of H - s (soft weights for the execute horizon H - s)."""
    w = ReferenceAdapter.method_weights(self, method, H, s, d, window)
    if method != "train_soft" or s == H:
        return w
    win = SoftWindow() if window is None else window_from_dict(window)
    return weights.soft_weights(H, d, win, H - s) if win.overflow == "clip" and d <= H - s else w


def _jump(actions, switches):
    a = np.asarray(actions, dtype=np.float64)
    if switches.size == 0:
        raise ValueError("chunk_index has no chunk switch")
    return float(np.mean(np.linalg.norm(a[switches] - a[switches - 1], axis=-1)))


def _jump_where_index_increases(self, actions, chunk_index):
    metrics.boundary_jump(actions, chunk_index)
    ci = np.asarray(chunk_index)
    return _jump(actions, np.nonzero(ci[1:] > ci[:-1])[0] + 1)


def _jump_at_first_step_of_each_chunk(self, actions, chunk_index):
    metrics.boundary_jump(actions, chunk_index)
    _, first = np.unique(np.asarray(chunk_index), return_index=True)
    return _jump(actions, np.sort(first[first > 0]))


def _lam_finite_c0(self, t, beta):
    """[G-4] c(0) = 1e4 standing in for +inf."""
    guidance.guidance_weight(t, beta)
    c = 1e4 if t == 0 else (1.0 - t) / t
    return min(c * (t * t + (1.0 - t) ** 2) / (1.0 - t) ** 2, beta)


# label -> (interface function, replacement)
MARGIN_MUTANTS = {
    "exponential table without shifted logits (d_min > 1)": ("delay_probs", _exp_table_unshifted),
    "delay drawn at u rounded up to 16 bits": ("sample_delay", _sample_delay_u16),
    "unknown method read as naive": ("method_weights", _method_unknown_is_naive),
    "unknown parametrization read as paper": ("prefix_weights", _parametrization_unknown_is_paper),
    "unknown overflow read as zeros": ("weights", _overflow_unknown_is_zeros),
    "unknown guidance variant read as soft": ("guidance_weights", _variant_unknown_is_soft),
    "inference methods' window ends at s": ("method_weights", _inference_window_ends_at_s),
    "train_soft window clipped at s": ("method_weights", _train_soft_clipped_at_s),
    "boundary jump only where the chunk index increases": ("boundary_jump", _jump_where_index_increases),
    "boundary jump at each chunk's first step": ("boundary_jump", _jump_at_first_step_of_each_chunk),
    "lam with c(0) = 1e4 for +inf": ("guidance_weight", _lam_finite_c0),
}

_MARGIN_HOOKS = ((cases_training, ("margins_endpoints", "margins_weights", "margins_delays", "margins_loss")),
                 (cases_runtime, ("margins_sampler", "margins_guidance", "margins_executor", "margins_metrics")))


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


@pytest.fixture(scope="module")
def vectors_without_margins(tmp_path_factory):
    """The vectors generated with every margins_* call of the case modules turned off: the cases that
    existed before the margin cases."""
    mp = pytest.MonkeyPatch()
    try:
        for module, names in _MARGIN_HOOKS:
            for name in names:
                mp.setattr(module, name, lambda *args: None)
        out = tmp_path_factory.mktemp("vectors-without-margins")
        generate.generate(out)
    finally:
        mp.undo()
    return runner.load_vectors(out)


def _mutant(label):
    fname, func = MARGIN_MUTANTS[label]
    return type("MarginMutant", (ReferenceAdapter,), {"name": f"mutant: {label}", fname: func})(), fname


def test_margin_cases_are_what_the_hooks_add(vector_files, vectors_without_margins):
    """[CF-4] Turning the margin functions off removes cases from each chapter they serve and nothing else:
    every case generated without them is shipped unchanged."""
    def by_file(files):
        return {f["_file"]: {c["id"]: c for c in f["cases"]} for f in files}
    before, now = by_file(vectors_without_margins), by_file(vector_files)
    assert set(before) == set(now)
    grown = {name for name in now if len(now[name]) > len(before[name])}
    assert grown >= {"endpoints.json", "weights.json", "delays.json", "loss.json", "sampler.json", "guidance.json",
                     "executor.json", "metrics.json"}, grown
    for name, cases in before.items():
        for cid, case in cases.items():
            assert now[name].get(cid) == case, f"{name}: {cid} changed"


@pytest.mark.parametrize("label", sorted(MARGIN_MUTANTS))
def test_margin_mutant_killed_only_by_margin_cases(label, vector_files, vectors_without_margins):
    """[CF-20], [CF-4] Each margin mutant (D-2, D-3, N-7, S-6, G-1, W-6, M-3, G-4) passes every case that
    existed without the margin cases and fails at least three cases of the shipped vectors; the reference
    passes both."""
    adapter, fname = _mutant(label)
    before = runner.run(adapter, files=vectors_without_margins, only={fname})
    assert before.ok and before.counts["pass"] > 0, f"mutant '{label}' was already caught"
    now = runner.run(adapter, files=vector_files, only={fname})
    assert not now.ok and now.counts["fail"] >= 3, f"mutant '{label}' failed {now.counts['fail']} cases, not 3"
    base = runner.run(ReferenceAdapter(), files=vector_files, only={fname})
    assert base.ok and base.counts["pass"] == now.counts["pass"] + now.counts["fail"]
