"""Conformance rollouts in closed loop on the arm (spec/42-rollouts.md): the request, the served field, episodes,
the per-request check, the diagnoses, the paired outcomes, and the implementations that must pass or fail."""

from __future__ import annotations

import math

import numpy as np
import pytest

from softrtc.conformance import rollout
from softrtc.conformance.rollout_field import ArmWorld, ServedField
from softrtc.conformance.rollout_impls import MUTANTS, ReferenceRollout
from softrtc.conformance.rollout_loop import Episode, Settings, request_inputs

ALL = ("naive", "train_hard", "train_soft", "inference_hard", "inference_soft")


@pytest.fixture(scope="module")
def field():
    return ServedField()


class Constant:
    """v(obs, x, t) = 1 everywhere, VJP 0: every sampler then has a closed form."""

    def __call__(self, obs, x, t):
        return np.ones(np.shape(x))

    def vjp(self, obs, x, t, cotangent):
        return np.zeros(np.shape(cotangent))


def _request(prev, d, arrival, method="train_hard", H=4, s=2, T=4):
    return dict(obs=np.zeros(3), prev=prev, noise=np.zeros((H, 1)), method=method, s=s, d=d, arrival=arrival, T=T,
                window=None, max_guidance=5.0)


def test_request_hand_example_first_late_and_early():
    """CR-2, X-2, X-4, R-4 With v = 1 and T = 4 the naive chunk from zero noise is 1 everywhere; with H = 4,
    s = 2 the first request executes chunk[0, 1]; a chunk planned for d = 0 arriving at tick 1 waits for it
    (prev[2], then chunk[1]); one planned for d = 1 arriving at tick 0 still switches at d = 1. train_hard with
    d = 1 keeps token 0 at the prior plus one Euler step (prev[2] + 1/4, [S-3])."""
    ref = ReferenceRollout()
    first = ref.rollout_chunk(Constant(), **_request(None, 0, 0))
    assert first["chunk"].tolist() == [[1.0]] * 4 and first["executed"].tolist() == [[1.0], [1.0]]
    prev = np.array([[10.0], [11.0], [12.0], [13.0]])
    late = ref.rollout_chunk(Constant(), **_request(prev, 0, 1))
    assert late["executed"].tolist() == [[12.0], [1.0]]
    early = ref.rollout_chunk(Constant(), **_request(prev, 1, 0))
    assert early["chunk"][0, 0] == 12.25 and early["executed"].tolist() == [[12.0], [1.0]]


@pytest.mark.parametrize("bad, arg", [(dict(d=3), "d"), (dict(arrival=-1), "arrival"), (dict(s=4), "s"),
                                      (dict(method="soft"), "method"), (dict(max_guidance=0.0), "max_guidance"),
                                      (dict(T=0), "T"), (dict(window="linear"), "window")])
def test_request_rejects_invalid_inputs(bad, arg):
    """CR-2, N-7 Every argument is checked at the door; the error names it."""
    req = _request(np.zeros((4, 1)), 1, 1)
    req.update(bad)
    with pytest.raises(ValueError, match=arg):
        ReferenceRollout().rollout_chunk(Constant(), **req)
    with pytest.raises(ValueError, match="d"):
        ReferenceRollout().rollout_chunk(Constant(), **_request(None, 1, 0))


def test_request_inputs_are_seeded_and_hold_early_and_late_arrivals():
    """CR-5 Request 0 has d = arrival = 0; draws repeat for the same (seed, episode, c) and differ with the seed;
    every arrival is d - 1, d or d + 1 within [0, min(s, H - s)], and both early and late arrivals occur."""
    st = Settings(("naive",), 1, (0, 1, 2, 3, 4, 5), 100, seed=3)
    n0, d0, a0 = request_inputs(st, 0, 0, 10, 4, 5)
    assert (d0, a0) == (0, 0) and n0.shape == (10, 4)
    draws = [request_inputs(st, e, c, 10, 4, 5) for e in range(3) for c in range(1, 40)]
    again = [request_inputs(st, e, c, 10, 4, 5) for e in range(3) for c in range(1, 40)]
    assert all(np.array_equal(a[0], b[0]) and a[1:] == b[1:] for a, b in zip(draws, again))
    other = request_inputs(Settings(("naive",), 1, (1,), 100, seed=4), 0, 1, 10, 4, 5)
    assert not np.array_equal(other[0], draws[0][0])
    assert all(abs(a - d) <= 1 and 0 <= a <= 5 and 0 <= d <= 5 for _, d, a in draws)
    assert any(a > d for _, d, a in draws) and any(a < d for _, d, a in draws)


def test_settings_and_env_are_checked():
    """CR-5, CR-13 Settings reject bad values; an unknown env, or a Kinetix option with the arm, is refused
    with an error naming it before anything loads."""
    for bad in (dict(methods=()), dict(methods=("fast",)), dict(episodes=0), dict(delays=(6,)), dict(max_steps=0)):
        with pytest.raises(ValueError):
            Settings(**bad)
    with pytest.raises(ValueError, match="env must be one of"):
        rollout.run("torch", env="mujoco", in_process=True)
    with pytest.raises(ValueError, match="init_seed is for env 'kinetix' only"):
        rollout.run("torch", init_seed=3, in_process=True)


def test_served_field_conventions_and_vjp(field):
    """CR-3, V-1, F-1 The flipped field is u(x, t') = -v(x, 1 - t'); the VJP agrees with central differences of
    the velocity (an independent formula); the world maps actions to physical units clipped to [A-8]."""
    rng = np.random.default_rng(0)
    obs, x, ct = rng.standard_normal(42), rng.standard_normal((10, 4)), rng.standard_normal((10, 4))
    t = np.linspace(0.1, 0.9, 10)
    flip = field.flipped()
    np.testing.assert_allclose(flip(obs, x, 1.0 - t), -field(obs, x, t), atol=1e-6)
    u = rng.standard_normal((10, 4))
    eps = 1e-2
    fd = np.sum((field(obs, x + eps * u, t) - field(obs, x - eps * u, t)) * ct) / (2 * eps)
    assert abs(fd - np.sum(u * field.vjp(obs, x, t, ct))) <= 2e-2 * max(1.0, abs(fd))
    world = ArmWorld(field, max_steps=10)
    world.reset(0)
    a = world.physical(np.full(4, 1e6))
    assert np.all(a == world.high) and np.all(world.physical(np.full(4, -1e6)) == world.low)


@pytest.mark.parametrize("impl", ["jax", "torch", "torch-flipped"])
def test_libraries_pass_in_closed_loop(impl):
    """CR-1, CR-5, CR-11, CR-12, X-3, X-4, S-6, G-3 The JAX twin and the PyTorch library (both conventions) make
    every chunk of short episodes of all five methods within a tenth of the tolerance (the suite's short check of
    [CR-12]: one episode per method and implementation), and the paired outcomes
    against the reference's episodes are reported per method."""
    out = rollout.run(impl, settings=Settings(ALL, 1, (1, 2, 3, 4, 5), 30), in_process=True)
    res = out["result"]
    assert res.ok, rollout.summary_text(out)
    assert res.counts["pass"] == len(res.cases) >= 2 * 5 * 6
    assert max(c.worst for c in res.cases) < 0.1
    assert set(out["paired"]) == set(ALL)


# The mutant, the method and delays under which its mistake shows, and the requirement its diagnosis names.
MUTANT_CASES = {"mutant-prior-shift": ("train_hard", "X-3"), "mutant-tokens-from-switch": ("naive", "X-4"),
                "mutant-prefix-not-reapplied": ("naive", "X-4"), "mutant-late-dropped": ("naive", "R-4"),
                "mutant-no-jacobian": ("inference_hard", "G-3")}


@pytest.mark.parametrize("mutant", sorted(MUTANTS))
def test_mutants_fail_with_their_diagnosis(mutant):
    """CR-9, CR-11, CR-6 Each integration mutant fails; its failing cases are diagnosed with the requirement its
    mistake breaks, and the episode's first divergence is the first request whose executed actions fail."""
    method, req = MUTANT_CASES[mutant]
    out = rollout.run(mutant, settings=Settings((method,), 1, (1, 2, 3), 60), in_process=True)
    res = out["result"]
    assert not res.ok
    failed = [c for c in res.cases if c.status == "fail"]
    assert failed and all(req in c.requirements for c in failed), [c.requirements for c in failed]
    assert f"diagnosis [{req}]" in failed[0].message
    ep = out["episodes"][0]
    executed = [c for c in failed if c.id.endswith(".executed")]
    assert ep.first_divergence["request"] == int(executed[0].id.split(".r")[1][:3])
    assert res.by_requirement()[req]["status"] == "FAIL"


def test_lerobot_guided_sampler_fails_on_the_jacobian_term():
    """CR-11, CR-9, G-3, CR-2 LeRobot's guided sampler fails in closed loop, diagnosed [G-3]; the training-time
    methods it does not have are unsupported, not failed."""
    pytest.importorskip("torch")
    pytest.importorskip("lerobot")
    out = rollout.run("lerobot", settings=Settings(("train_hard", "inference_hard"), 1, (1, 2, 3), 30),
                      in_process=True)
    res = out["result"]
    by_method = {}
    for c in res.cases:
        by_method.setdefault(c.file, set()).add(c.status)
    assert by_method["rollout_train_hard"] == {"unsupported"}
    failed = [c for c in res.cases if c.status == "fail" and c.id.endswith(".chunk")]
    assert failed and all(c.requirements == ["CR-2", "G-3"] for c in failed)
    assert not res.ok


def test_paired_differences_by_hand():
    """CR-7 The paired difference is the mean of implementation minus reference over episodes; undefined values
    leave their pair out; the reported means are per side."""
    mk = lambda vals: [Episode("naive", i, i, metrics=dict(zip(("success", "completed", "D1", "D2", "D3",  # noqa: E731
                                                                   "boundary"), v))) for i, v in enumerate(vals)]
    ours = mk([(1, 4, 0.1, 0.2, 0.3, 0.5), (0, 2, 0.3, 0.2, 0.1, math.nan), (1, 3, 0.2, 0.2, 0.2, 0.1)])
    refs = mk([(1, 4, 0.1, 0.1, 0.1, 0.4), (1, 3, 0.1, 0.1, 0.1, 0.2), (1, 4, 0.1, 0.1, 0.1, 0.1)])
    p = rollout.paired(ours, refs)
    assert p["success"]["diff"] == pytest.approx(-1 / 3) and p["completed"]["diff"] == pytest.approx(-2 / 3)
    assert p["D2"]["diff"] == pytest.approx(0.1) and p["boundary"]["diff"] == pytest.approx(0.05)
    assert p["boundary"]["n"] == 2 and p["D1"]["impl"] == pytest.approx(0.2)
    assert p["success"]["lo"] <= p["success"]["diff"] <= p["success"]["hi"]
