"""Vector cases of the solver step ([S-10], [S-11], [S-13]) judge implementations, and an adapter without the
step reports them unsupported ([CF-9])."""

from __future__ import annotations

import pytest

from softrtc.conformance import runner
from softrtc.conformance.adapters.reference import ReferenceAdapter
from softrtc.reference import sampler, velocity


@pytest.fixture(scope="module")
def vector_files():
    return runner.load_vectors()


def _step_cases(res):
    return [c for c in res.cases if c.function == "rtc_sample_step"]


class _IgnoresStep(ReferenceAdapter):
    """Checks the step's name but always runs Algorithm 1."""

    def rtc_sample_step(self, field, obs, noise, prior, w, T, step):
        sampler.check_step(step)
        return sampler.rtc_sample(velocity.ReferenceVelocityField(field), obs, noise, prior, w, T, return_trace=True)


class _ReblendsWindow(ReferenceAdapter):
    """Candidate (c) of [S-12]: the step (1 - w) / T with Algorithm 1's blend before every step."""

    def rtc_sample_step(self, field, obs, noise, prior, w, T, step):
        import numpy as np

        f = velocity.ReferenceVelocityField(field)
        x, w = np.asarray(noise, float), np.asarray(w, float)
        c = np.where(w < 1, 1 - w, 1.0)[:, None] if sampler.check_step(step) == "consistent" else 1.0
        for k in range(T):
            xb = w[:, None] * prior + (1 - w[:, None]) * x
            x = xb + c * f(obs, xb, w + (1 - w) * k / T) / T
        return x, None


class _NoStep(ReferenceAdapter):
    rtc_sample_step = None


def test_step_cases_exist_and_pass_the_reference_port(vector_files):
    """S-10, S-11, S-13: the shipped vectors hold consistent-step cases (generated and hand-written, windows,
    binary and zero weights, bad names); a run through the reference adapter passes them."""
    res = runner.run(ReferenceAdapter(), files=vector_files, only={"rtc_sample_step"})
    cases = _step_cases(res)
    ids = {c.id for c in cases}
    assert len(cases) >= 40 and res.ok and all(c.status == "pass" for c in cases)
    assert "S.rtc_sample_step.hand.constant-field.T5.consistent" in ids
    assert "S.rtc_sample_step.reject.step-unknown-name" in ids
    assert "S.rtc_sample_step.h8a2.zero-weights.T5.consistent" in ids


@pytest.mark.parametrize("cls", [_IgnoresStep, _ReblendsWindow])
def test_wrong_steps_fail(cls, vector_files):
    """S-10, S-12, CF-16: an implementation that runs Algorithm 1 under the consistent name, or re-blends the
    window every step, fails window cases but passes the binary-weight ones ([S-11])."""
    res = runner.run(cls(), files=vector_files, only={"rtc_sample_step"})
    by_id = {c.id: c for c in _step_cases(res)}
    assert not res.ok
    assert by_id["S.rtc_sample_step.hand.constant-field.T5.consistent"].status == "fail"
    assert by_id["S.rtc_sample_step.h8a2.s4.d2.T5.train_soft1.consistent"].status == "fail"
    assert by_id["S.rtc_sample_step.h8a2.s4.d2.T5.train_hard0.consistent"].status == "pass"
    assert by_id["S.rtc_sample_step.h8a2.zero-weights.T5.consistent"].status == "pass"


def test_adapter_without_the_step_reports_unsupported(vector_files):
    """CF-9, S-10: an adapter written before steps existed (no rtc_sample_step) has those cases unsupported,
    none failed, and still passes rtc_sample."""
    res = runner.run(_NoStep(), files=vector_files, only={"rtc_sample_step", "rtc_sample"})
    assert res.counts["fail"] == 0
    assert all(c.status == "unsupported" for c in _step_cases(res)) and _step_cases(res)
    assert all(c.status == "pass" for c in res.cases if c.function == "rtc_sample")
