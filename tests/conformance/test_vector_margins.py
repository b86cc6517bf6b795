"""The margins of the shipped vectors ([CF-4], [CF-20]): how many cases hold each requirement, unknown
enumerated names, and the margin cases of conformance/cases_margins.py against hand-computed values.

Expected values here come from closed forms and exact fractions, not from the reference.
"""

from __future__ import annotations

import collections
import math
import re
from fractions import Fraction
from pathlib import Path

import pytest

from softrtc.conformance import runner

ROOT = Path(__file__).resolve().parents[2]
DEF = re.compile(r"^\s*(?:[-*]|\d+\.)\s+\**\[([A-Z]{1,3}-\d+)\]", re.M)
ETA = 1e-8  # [L-2]

# Requirement ids of chapters 1-6 that need not be held by MIN_CASES cases, each with why: the rule concerns
# no function of the adapter interface, is checked elsewhere, or is one worked example. Every other id of
# those chapters, and every id any case cites, is held by at least MIN_CASES cases.
MIN_CASES = 3
NOT_IN_VECTORS = {
    "W-10": "names two complete configurations (a recipe's settings), not a function's result",
    "D-4": "the training loop's draws per example; tested with the trainers (tests/jax, tests/torch)",
    "F-3": "the field's initialization from a seed; the vectors carry the parameters themselves",
    "F-4": "the summation order behind bitwise regeneration ([CF-3]); vectors compare within tolerances",
    "S-9": "the definition of time consistency, a property of a solver step, not a result",
    "S-10": "the time-consistent solver step, an option of rtc_sample; tests/reference/test_reference_step.py "
            "checks it against closed forms",
    "S-11": "the consistent step equals Algorithm 1 bitwise for weights in {0, 1}; "
            "tests/reference/test_reference_step.py",
    "S-12": "the comparison of candidate solver steps (rationale)",
    "S-13": "one worked example of the solver steps (hand-written cases for its T = 5 and T = 4 forms), also run "
            "by the sampler's docstring",
    "S-14": "which sampler and step generate_chunk runs per method; generate_chunk is no interface function",
    "S-15": "bitwise reproducibility on one CPU model, a property of recomputed results, not a function's value",
    "G-7": "an optional restriction of the pull-back with the same chunks, invisible in a trace",
    "X-6": "the closed loop with an environment",
    "X-7": "the alternative first segment, a rollout option",
    "X-8": "which executor the simulators use",
    "M-4": "returns and solve rates of environment episodes",
    "M-7": "names the high delays {3, 4}: a constant of the reports",
    "M-8": "how reports leave undefined values out of a mean; the per-episode error is covered by [M-1], [M-3]",
    "V-2": "the flipped Euler step, run by the flipped adapters on every sampler case (the vectors are in "
           "the spec's time)",
    "V-4": "a dictionary of parameter names in other code",
    "V-5": "batching and dtype of other implementations",
}


@pytest.fixture(scope="module")
def files():
    return runner.load_vectors()


@pytest.fixture(scope="module")
def cases(files):
    return [c for f in files for c in f["cases"]]


def _chapter_ids() -> set:
    ids = set()
    for f in sorted((ROOT / "spec").glob("0[1-6]-*.md")):
        ids |= set(DEF.findall(f.read_text()))
    return ids


def test_every_requirement_held_by_three_cases(cases):
    """[CF-4] Every requirement id of chapters 1-6 and every id a case cites, unless exempted with a reason,
    is cited by at least three cases of the shipped vectors, so no rule rests on a single case."""
    count = collections.Counter(r for c in cases for r in c["requirements"])
    want = (_chapter_ids() | set(count)) - set(NOT_IN_VECTORS)
    thin = {r: count[r] for r in sorted(want) if count[r] < MIN_CASES}
    assert not thin, f"requirement ids held by fewer than {MIN_CASES} cases: {thin}"


def test_exemptions_name_spec_ids():
    """[CF-4] Each exempted id is defined in chapters 1-6 and carries a reason."""
    ids = _chapter_ids()
    assert set(NOT_IN_VECTORS) <= ids, sorted(set(NOT_IN_VECTORS) - ids)
    assert all(len(why) > 20 for why in NOT_IN_VECTORS.values())


# The enumerated string arguments of the interface: (function, path to the argument) -> known names.
ENUMS = {
    ("prefix_weights", ("schedule",)): {"zeros", "ones", "linear", "exp"},
    ("prefix_weights", ("parametrization",)): {"rtc", "paper"},
    ("weights", ("window", "schedule")): {"zeros", "ones", "linear", "exp"},
    ("weights", ("window", "parametrization")): {"rtc", "paper"},
    ("weights", ("window", "overflow")): {"clip", "zeros"},
    ("endpoint", ("rule", "kind")): {"delay_scaled", "offset", "fixed", "hard"},
    ("method_weights", ("method",)): {"naive", "inference_hard", "inference_soft", "train_hard", "train_soft"},
    ("guidance_weights", ("variant",)): {"hard", "soft"},
    ("delay_probs", ("dist",)): {"uniform", "exponential"},
    ("rtc_sample_step", ("step",)): {"algorithm1", "consistent"},
}


def _get(args, path):
    for key in path:
        if not isinstance(args, dict) or key not in args:
            return None, False
        args = args[key]
    return args, True


@pytest.mark.parametrize("fname,path", sorted(ENUMS))
def test_unknown_names_rejected(fname, path, cases):
    """[N-7], [CF-34] Every enumerated string argument has at least three error cases that hold an unknown
    name (a misspelling, another case, an empty name or null) and are valid otherwise; the known names
    all appear in cases with a result."""
    known = ENUMS[(fname, path)]
    unknown, used = set(), set()
    for c in cases:
        if c["function"] != fname:
            continue
        value, present = _get(c["args"], path)
        if not present:
            continue
        if "error" in c["expected"]:
            if value not in known:
                unknown.add(repr(value))
        else:
            used.add(value)
    assert len(unknown) >= MIN_CASES, f"{fname} {'.'.join(path)}: unknown names {sorted(unknown)}"
    assert used == known


# ---------------------------------------------------------------- hand-computed margin cases

def _case(cases, cid):
    hits = [c for c in cases if c["id"] == cid]
    assert len(hits) == 1, cid
    return hits[0]


def test_exponential_table_halving(cases):
    """[D-2] decay = ln 2 on delays 3..5 halves each probability: 4/7, 2/7, 1/7; the table for 12..14 with
    decay 64 is 1 / (1 + e^-64 + e^-128) and its multiples."""
    c = _case(cases, "D.delay_probs.margin.exponential.3-5.decay0.693147")
    assert c["args"]["decay"] == math.log(2.0)
    assert c["expected"]["probs"] == pytest.approx([4 / 7, 2 / 7, 1 / 7], rel=1e-14)
    c = _case(cases, "D.delay_probs.margin.exponential.12-14.decay64")
    z = 1.0 + math.exp(-64.0) + math.exp(-128.0)
    assert c["expected"]["probs"] == pytest.approx([1 / z, math.exp(-64.0) / z, math.exp(-128.0) / z], rel=1e-14)


def test_draws_between_breakpoints(cases):
    """[D-3] Each draw between breakpoints lies strictly inside the bin of the delay it expects: the exact
    cumulative sums (fractions of the float table) bound u, away from either end; d_min > 1 is among them,
    and every breakpoint but the last has a draw just below and just above it."""
    draws = [c for c in cases if c["id"].startswith("D.sample_delay.between.")]
    assert len(draws) >= 100 and any(c["args"]["d_min"] > 1 for c in draws)
    near = 0
    for c in draws:
        p, u, d = c["args"]["probs"], c["args"]["u"], c["expected"]["d"]
        cdf = [sum((Fraction(x) for x in p[:k + 1]), Fraction(0)) for k in range(len(p))]
        cdf[-1] = Fraction(1)
        k = d - c["args"]["d_min"]
        lo, hi = (cdf[k - 1] if k else Fraction(0)), cdf[k]
        assert lo <= Fraction(u) < hi, c["id"]
        near += min(abs(Fraction(u) - lo), abs(hi - Fraction(u))) <= Fraction(3, 1000000)
    assert near >= 40


@pytest.mark.parametrize("tag,value", [("three-tokens", 3.0 / (1.5 + ETA)), ("two-dims", 4.0 / (1.0 + ETA)),
                                       ("noise-target", 4.0 / (2.0 + ETA)), ("all-clamped", 0.0)])
def test_loss_by_hand(tag, value, cases):
    """[L-1], [L-2], [L-4] The small losses computed by hand in the case module's comments."""
    assert _case(cases, f"L.loss.margin.{tag}")["expected"]["loss"] == pytest.approx(value, rel=1e-14, abs=0.0)


def test_boundary_jump_on_labels(cases):
    """[M-3] On indices that are not monotone, every change of label is a switch: the hand case gives
    (2 + 4) / 2 = 3, and each labels case equals the mean over its changes computed here."""
    assert _case(cases, "M.boundary_jump.labels.hand")["expected"]["value"] == 3.0
    labelled = [c for c in cases if c["id"].startswith("M.boundary_jump.labels.")]
    assert len(labelled) >= 5
    for c in labelled:
        a, ci = c["args"]["actions"], c["args"]["chunk_index"]
        steps = [t for t in range(1, len(ci)) if ci[t] != ci[t - 1]]
        assert any(ci[t] < ci[t - 1] for t in steps), c["id"]  # not monotone
        want = sum(math.dist(a[t], a[t - 1]) for t in steps) / len(steps)
        assert c["expected"]["value"] == pytest.approx(want, rel=1e-12)


def test_guidance_weight_large_caps(cases):
    """[G-4] lam(0) is the cap itself however large; near t = 0 it is (t^2 + (1 - t)^2) / (t (1 - t)),
    computed in exact fractions, when that is below the cap."""
    large = [c for c in cases if c["id"].startswith("G.guidance_weight.large-cap.")]
    assert sum(c["args"]["t"] == 0 and c["args"]["max_guidance"] > 1e4 for c in large) >= 3
    for c in large:
        t, beta = Fraction(c["args"]["t"]), c["args"]["max_guidance"]
        want = beta if t == 0 else min(float((t * t + (1 - t) ** 2) / (t * (1 - t))), beta)
        assert c["expected"]["lam"] == pytest.approx(want, rel=1e-12)
    assert _case(cases, "G.guidance_weight.large-cap.t9.53674e-07.beta1e+07")["expected"]["lam"] == \
        pytest.approx(2.0 ** 20 - 1, rel=1e-12)


def _inference_weights(H, s, d, variant):
    """[G-1] By hand: 1 before d, the schedule at x_j = (j - d + 1) / (H - s - d + 1) up to H - s, then 0."""
    out = []
    for j in range(H):
        if j < d:
            out.append(1.0)
        elif j < H - s:
            u = 1.0 - (j - d + 1) / (H - s - d + 1)
            out.append(0.0 if variant == "hard" else u * math.expm1(u) / math.expm1(1.0))
        else:
            out.append(0.0)
    return out


def test_inference_windows_where_h_minus_s_differs_from_s(cases):
    """[S-6], [G-1], [X-1] method_weights of both inference methods at H - s != s end their window at
    H - s; every method has such cases for several geometries, each d in 0..min(s, H - s)."""
    uneven = [c for c in cases if c["function"] == "method_weights" and "error" not in c["expected"]
              and c["args"]["H"] - c["args"]["s"] != c["args"]["s"]]
    per_method = collections.Counter(c["args"]["method"] for c in uneven)
    assert min(per_method.values()) >= 10 and len(per_method) == 5
    geometries = {(c["args"]["H"], c["args"]["s"]) for c in uneven}
    assert {(8, 3), (10, 4), (6, 5)} <= geometries
    for c in uneven:
        a = c["args"]
        if a["method"].startswith("inference_"):
            want = _inference_weights(a["H"], a["s"], a["d"], a["method"].split("_", 1)[1])
            assert c["expected"]["weights"] == pytest.approx(want, abs=1e-15), c["id"]
