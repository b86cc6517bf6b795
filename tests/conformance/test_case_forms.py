"""Per-case unsupported ([CF-26]) and the window form of guided cases ([CF-27])."""

from __future__ import annotations

import numpy as np
import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapters.reference import ReferenceAdapter
from softrtc.reference import guidance, velocity
from softrtc.reference.weights import prefix_weights


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


class _Only:
    name = "partial"

    def __init__(self, **fns):
        for k, v in fns.items():
            setattr(self, k, v)


REF = ReferenceAdapter()


def _rtc_only(H, d, e, schedule, parametrization):
    """prefix_weights for the rtc parametrization only; the paper parametrization is declined."""
    if parametrization == "paper":
        raise NotImplementedError("only the rtc parametrization")
    return REF.prefix_weights(H, d, e, schedule, parametrization)


def test_not_implemented_is_unsupported_per_case(vector_files):
    """[CF-26], [CF-14], [CF-16] A case whose call raises NotImplementedError is unsupported, never passed or
    failed; the summary lists such cases per requirement id ([W-4] keeps passing, [W-5] is all unsupported),
    and the run passes (exit 0) on the cases the implementation took."""
    res = runner.run(_Only(prefix_weights=_rtc_only), files=vector_files, only={"prefix_weights"})
    par = {c["id"]: c["args"]["parametrization"] for f in vector_files for c in f["cases"]
           if c["function"] == "prefix_weights"}
    paper = [c for c in res.cases if par[c.id] == "paper"]
    rtc = [c for c in res.cases if par[c.id] != "paper"]
    assert paper and all(c.status == "unsupported" for c in paper)
    assert all("NotImplementedError: only the rtc parametrization" in c.message for c in paper)
    assert rtc and all(c.status == "pass" for c in rtc)
    assert res.ok and res.counts["unsupported"] == len(paper)
    reqs = res.by_requirement()
    assert reqs["W-5"]["status"] == "UNSUPPORTED" and reqs["W-5"]["pass"] == 0
    assert reqs["W-4"]["status"] == "PASS" and reqs["W-4"]["unsupported"] == 0
    text = runner.format_summary(res)
    line = next(ln for ln in text.splitlines() if ln.startswith("unsupported cases"))
    n_paper = sum(1 for c in paper if "W-5" in c.requirements)
    assert f"W-5 ({n_paper})" in line and "W-4 (" not in line
    assert "adapter lacks the function" not in text


def test_not_implemented_on_an_invalid_input_is_not_a_pass(vector_files):
    """[CF-26], [N-7] NotImplementedError on a case that expects ValueError is unsupported, not a pass."""
    def declines(H, d):
        raise NotImplementedError
    res = runner.run(_Only(hard_weights=declines), files=vector_files, only={"hard_weights"})
    assert res.counts["pass"] == 0 and res.counts["unsupported"] == len(res.cases) > 0
    assert not res.ok and "no supported case ran" in runner.format_summary(res)


def test_guided_cases_carry_the_window_that_defines_w(vector_files):
    """[CF-27], [G-1] Every guided case carries, beside W, the parameters H, s, d, variant, schedule,
    window end and cap that define it: W equals prefix_weights(H, d, end, schedule, "rtc") computed here,
    end = H - s, and the cap is the case's max_guidance."""
    cases = [c for f in vector_files for c in f["cases"] if c["function"] == "guided_sample"]
    assert len(cases) > 10
    for c in cases:
        g, a = c["args"]["guidance"], c["args"]
        assert g["end"] == g["H"] - g["s"] and g["max_guidance"] == a["max_guidance"]
        assert g["schedule"] == {"hard": "zeros", "soft": "exp"}[g["variant"]]
        assert len(a["weights"]) == g["H"] == len(a["noise"])
        # the hand-written cases compute u = 2/3 where the reference has 1 - 1/3: equal to the last bit or two
        np.testing.assert_allclose(a["weights"], prefix_weights(g["H"], g["d"], g["end"], g["schedule"], "rtc"),
                                   rtol=1e-14, atol=0)
    assert {c["args"]["guidance"]["variant"] for c in cases} == {"hard", "soft"}
    assert {5.0, 2.0} <= {c["args"]["max_guidance"] for c in cases}
    assert sum(c["args"]["max_guidance"] != 5.0 for c in cases) >= 3  # a cap other than the default, thrice


def test_window_form_runs_guided_cases(vector_files):
    """[CF-27], [CF-9] An adapter offering only guided_sample_window(field, obs, noise, prior, guidance, T)
    runs every guided case from the window parameters and passes; a wrong window (end off by one) fails."""
    res = runner.run(_Only(guided_sample_window=REF.guided_sample_window), files=vector_files,
                     only={"guided_sample"})
    assert res.ok and res.counts["unsupported"] == 0 and res.counts["pass"] == len(res.cases) > 10

    def end_off_by_one(field, obs, noise, prior, g, T):
        W = prefix_weights(g["H"], g["d"], min(g["end"] + 1, g["H"]), g["schedule"], "rtc")
        return guidance.guided_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, W, T,
                                      g["max_guidance"], return_trace=True)
    bad = runner.run(_Only(guided_sample_window=end_off_by_one), files=vector_files, only={"guided_sample"})
    assert not bad.ok and bad.counts["fail"] > 0


def test_window_form_is_tried_when_the_weight_form_declines(vector_files):
    """[CF-27], [CF-26] With both forms, guided_sample is tried first; a NotImplementedError from it passes
    the case to guided_sample_window. A case without 'guidance' cannot go through the window form: it is
    unsupported for an adapter with that form only."""
    calls = []

    def weight_form(field, obs, noise, prior, w, T, beta):
        calls.append("weights")
        raise NotImplementedError("weights given directly")

    def window_form(field, obs, noise, prior, g, T):
        calls.append("window")
        return REF.guided_sample_window(field, obs, noise, prior, g, T)
    res = runner.run(_Only(guided_sample=weight_form, guided_sample_window=window_form), files=vector_files,
                     only={"guided_sample"})
    assert res.ok and res.counts["pass"] == len(res.cases)
    assert calls.count("weights") == calls.count("window") == len(res.cases) == len(calls) // 2
    stripped = [dict(f, cases=[dict(c, args={k: v for k, v in c["args"].items() if k != "guidance"})
                               for c in f["cases"]]) for f in vector_files]
    res = runner.run(_Only(guided_sample_window=window_form), files=stripped, only={"guided_sample"})
    assert res.counts["unsupported"] == len(res.cases) > 0
    assert all("needs the case's 'guidance'" in c.message for c in res.cases)


def test_malformed_guidance_is_a_vector_error(tmp_path):
    """[CF-27], [CF-24] A guided case whose 'guidance' lacks a key or holds a float end stops loading."""
    import json
    files = runner.load_vectors()
    case = next(c for f in files for c in f["cases"] if c["function"] == "guided_sample")
    fields = next(f["fields"] for f in files if any(c is case for c in f["cases"]))
    for change, needle in ((lambda g: g.pop("end"), "exactly the keys"), (lambda g: g.update(end=4.0), "integers")):
        bad = json.loads(json.dumps(case))
        change(bad["args"]["guidance"])
        (tmp_path / "g.json").write_text(json.dumps({"format_version": "1.1", "fields": fields, "cases": [bad]}))
        with pytest.raises(runner.VectorError, match=needle):
            runner.load_vectors(tmp_path)


def _rejects_partial_window(H, d, window, s):
    if set(window) != {"rule", "schedule", "parametrization", "overflow"}:
        raise ValueError("window must have all four keys")
    return REF.weights(H, d, window, s)


def _window_extra_keys_ignored(H, d, window, s):
    return REF.weights(H, d, {k: v for k, v in window.items() if k != "shedule"}, s)


def _monotonic_only(actions, noise, w, tau):
    if np.any(np.diff(np.asarray(w)) > 0):
        raise ValueError("weights must be non-increasing")
    return REF.corrupt(actions, noise, w, tau)


def _any_dist_name(dist, d_min, d_max, decay):
    return REF.delay_probs(dist.lower() if dist.lower() in ("uniform", "exponential") else "uniform", d_min, d_max,
                           decay)


def _velocity_clips_times(field, obs, x, t):
    return REF.velocity(field, obs, x, np.clip(t, 0.0, 1.0))


def _token_times_per_token(w, t):
    return np.asarray(w) + (1.0 - np.asarray(w)) * np.asarray(t)


def _indices_any_columns(values, indices, confidence):
    v, idx = np.asarray(values), np.asarray(indices)
    if idx.ndim != 2 or idx.min() < 0 or idx.max() >= v.size or not 0 < confidence < 1:
        raise ValueError("indices or confidence")
    lo, hi = np.quantile(v[idx].mean(axis=1), [(1 - confidence) / 2, (1 + confidence) / 2])
    return np.array([lo, hi])


@pytest.mark.parametrize("function,impl", [
    ("weights", _rejects_partial_window),
    ("weights", _window_extra_keys_ignored),
    ("corrupt", _monotonic_only),
    ("delay_probs", _any_dist_name),
    ("velocity", _velocity_clips_times),
    ("token_times", _token_times_per_token),
    ("bootstrap_interval", _indices_any_columns),
])
def test_other_readings_of_the_interface_fail(vector_files, function, impl):
    """[CF-34] Each point of the interface a port could read another way has cases that tell the readings
    apart: an implementation taking the other reading fails a CF-34 case, and the reference passes them all."""
    res = runner.run(_Only(**{function: impl}), files=vector_files, only={function})
    failed = [c for c in res.cases if c.status == "fail"]
    assert failed and all("CF-34" in c.requirements for c in failed), [c.id for c in failed][:5]
    ref = runner.run(REF, files=vector_files, only={function})
    assert ref.ok and ref.by_requirement()["CF-34"]["status"] == "PASS"


def test_hand_written_vectors_are_indexed_and_pass(vector_files):
    """[CF-33], [CF-25] The hand-written file is not produced by the generator, is listed in index.json with
    chapter HAND and its digest, covers every chapter's worked examples, and the reference passes all of it."""
    import json

    from softrtc.conformance import generate, vectors_dir
    hand = next(f for f in vector_files if f["_file"] == "worked_examples.json")
    assert "worked_examples" not in generate.FILES and hand["generator"].startswith("written by hand")
    entry = json.loads((vectors_dir() / "index.json").read_text())["files"]["worked_examples.json"]
    assert entry["chapter"] == "HAND" and entry["cases"] == len(hand["cases"]) >= 40
    assert {c["id"][0] for c in hand["cases"]} == set("EWGSDCLFXM")
    res = runner.run(REF, files=[hand])
    assert res.ok and res.counts["pass"] == len(hand["cases"])
