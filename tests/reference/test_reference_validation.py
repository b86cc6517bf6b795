"""Input validation and notation of the reference (spec/00-overview.md)."""

import math
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from softrtc.reference import corruption, delays, endpoints, executor, guidance, loss, metrics, sampler, weights
from softrtc.reference.velocity import ReferenceVelocityField

ROOT = Path(__file__).resolve().parents[2]

bad_ints = st.one_of(st.integers(-50, -1), st.just(2.0), st.just(True), st.just(float("nan")),
                     st.just("3"), st.just(None))
bad_reals = st.one_of(st.floats(-50, -1e-3), st.just(float("nan")), st.just(float("inf")), st.just("1"),
                      st.just(None))

F = ReferenceVelocityField.init(0, 4, 2, 3)
OK = dict(obs=np.zeros(3), noise=np.zeros((4, 2)), prior=np.zeros((4, 2)), weights=np.zeros(4))


def _invalid_calls():
    """(argument, strategy of zero-arg callables that must raise ValueError naming it), one per kind of invalid call."""
    return (
        ('H', bad_ints.map(lambda v: lambda: weights.prefix_weights(v, 0, 0))),
        ('d', bad_ints.map(lambda v: lambda: weights.prefix_weights(4, v, 4))),
        ('d', st.integers(5, 40).map(lambda v: lambda: weights.prefix_weights(4, v, 4))),
        ('e', st.integers(0, 1).map(lambda v: lambda: weights.prefix_weights(4, 3, v))),  # e < d
        ('e', st.integers(5, 40).map(lambda v: lambda: weights.prefix_weights(4, 0, v))),  # e > H
        ('schedule', st.text(max_size=5).map(lambda v: lambda: weights.prefix_weights(4, 1, 2, "x" + v))),
        ('d', bad_ints.map(lambda v: lambda: weights.soft_weights(8, v, weights.SoftWindow(), 4))),
        ('s', st.one_of(bad_ints, st.integers(9, 40)).map(lambda v: lambda: weights.soft_weights(8, 1, weights.SoftWindow(), v))),
        ('window', st.integers(9, 30).map(lambda v: lambda: weights.soft_weights(8, 1, weights.SoftWindow(endpoints.offset(1, v)), 4))),
        ('lam', bad_reals.map(lambda v: lambda: endpoints.delay_scaled(v, 5))),
        ('h_max', st.one_of(bad_ints, st.integers(4097, 10**6)).map(lambda v: lambda: endpoints.delay_scaled(2, v))),
        ('length', bad_ints.map(lambda v: lambda: endpoints.offset(v, 5))),
        ('h', bad_ints.map(lambda v: lambda: endpoints.fixed(v))),
        ('d', bad_ints.map(lambda v: lambda: endpoints.endpoint(endpoints.hard(), v))),
        ('d_min', bad_ints.map(lambda v: lambda: delays.delay_probs("uniform", v, 4))),
        ('d_max', st.integers(0, 3).map(lambda v: lambda: delays.delay_probs("uniform", 4, v))),
        ('decay', bad_reals.map(lambda v: lambda: delays.delay_probs("exponential", 0, 4, v))),
        ('u', st.one_of(bad_reals, st.floats(1.0, 5.0)).map(lambda v: lambda: delays.sample_delay([0.5, 0.5], 0, v))),
        ('tau', st.one_of(bad_reals, st.floats(1.001, 5.0)).map(lambda v: lambda: corruption.corrupt(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(4), v))),
        ('noise', st.integers(1, 6).filter(lambda n: n != 4).map(lambda n: lambda: corruption.corrupt(np.zeros((4, 2)), np.zeros((n, 2)), np.zeros(4), 0.5))),
        ('pred', st.sampled_from([np.nan, np.inf, -np.inf]).map(lambda v: lambda: loss.flow_matching_loss(np.full((4, 2), v), np.zeros((4, 2)), np.zeros((4, 2)), np.zeros(4)))),
        ('weights', st.floats(1.001, 3).map(lambda v: lambda: loss.flow_matching_loss(np.zeros((4, 2)), np.zeros((4, 2)), np.zeros((4, 2)), np.full(4, v)))),
        ('num_steps', st.one_of(bad_ints, st.just(0)).map(lambda v: lambda: sampler.naive_sample(F, OK["obs"], OK["noise"], v))),
        ('prior', st.integers(1, 6).filter(lambda n: n != 4).map(lambda n: lambda: sampler.rtc_sample(F, OK["obs"], OK["noise"], np.zeros((n, 2)), OK["weights"], 5))),
        ('noise', st.sampled_from([np.nan, np.inf]).map(lambda v: lambda: sampler.rtc_sample(F, OK["obs"], np.full((4, 2), v), OK["prior"], OK["weights"], 5))),
        ('max_guidance', st.one_of(bad_reals, st.just(0.0)).map(lambda v: lambda: guidance.guided_sample(F, OK["obs"], OK["noise"], OK["prior"], OK["weights"], 5, v))),
        ('t', st.one_of(bad_reals, st.floats(1.0, 3.0)).map(lambda v: lambda: guidance.guidance_weight(v))),
        ('d', st.integers(5, 20).map(lambda v: lambda: guidance.guidance_prefix_weights(8, 4, v, "soft"))),
        ('d', st.one_of(bad_ints, st.integers(5, 20)).map(lambda v: lambda: executor.check_delay(8, 4, v))),
        ('s', st.one_of(bad_ints, st.integers(9, 20)).map(lambda v: lambda: executor.shift_prior(np.zeros((8, 1)), v))),
        ('delays[0]', st.integers(1, 4).map(lambda v: lambda: executor.execute_chunks(np.zeros((2, 8, 1)), [v, 0], 4))),
        ('delays[1]', st.integers(5, 9).map(lambda v: lambda: executor.execute_chunks(np.zeros((2, 8, 1)), [0, v], 4))),
        ('order', st.one_of(bad_ints, st.just(0)).map(lambda v: lambda: metrics.difference_norm(np.zeros((5, 1)), v))),
        ('confidence', st.one_of(bad_reals, st.floats(1.0, 2.0)).map(lambda v: lambda: metrics.bootstrap_interval(np.ones(3), 100, 0, v))),
        ('seed', bad_ints.map(lambda v: lambda: ReferenceVelocityField.init(v, 4, 2, 3))),
        ('horizon', st.one_of(bad_ints, st.just(0)).map(lambda v: lambda: ReferenceVelocityField.init(0, v, 2, 3))),
    )


INVALID = _invalid_calls()


@pytest.mark.parametrize("kind", range(len(INVALID)))
@settings(max_examples=20)
@given(data=st.data())
def test_random_invalid_configurations_raise(kind, data):
    """N-7: every invalid configuration raises ValueError whose message starts with the offending argument (never
    clamps or wraps); each kind is drawn."""
    name, strategy = INVALID[kind]
    call = data.draw(strategy)
    with pytest.raises(ValueError, match=rf"^{re.escape(name)} "):
        call()


def test_error_messages_name_argument_and_range():
    """N-7: messages name the argument and the allowed range."""
    with pytest.raises(ValueError, match=r"d must be an integer in \[0, 8\], got 9"):
        weights.prefix_weights(8, 9, 9)
    with pytest.raises(ValueError, match=r"lam must be a finite real number in \[0.0, 4096.0\]"):
        endpoints.delay_scaled(-1.0, 5)
    with pytest.raises(ValueError, match=r"noise must have shape \[4, 2\]"):
        corruption.corrupt(np.zeros((4, 2)), np.zeros((3, 2)), np.zeros(4), 0.5)
    with pytest.raises(ValueError, match=r"d must be an integer in \[0, 2\], got 3"):
        executor.check_delay(8, 6, 3)
    with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 8\], got 2\.0$"):
        weights.prefix_weights(8, 2.0, 4)


def test_notation_shapes():
    """N-1, N-2, N-3, N-4: chunk shapes [H, A], 1 <= s <= H, d >= 0, the three regions."""
    w = weights.soft_weights(10, 2, weights.SoftWindow(endpoints.offset(3, 10)), 4)
    assert w.shape == (10,)
    assert list(w[:2]) == [1, 1] and np.all((w[2:5] > 0) & (w[2:5] < 1)) and np.all(w[5:] == 0)
    for s in (0, 11):
        with pytest.raises(ValueError, match="s must be"):
            weights.soft_weights(10, 2, weights.SoftWindow(), s)
    with pytest.raises(ValueError, match="d must be"):
        weights.hard_weights(10, -1)


def test_time_convention_and_noise_symbols():
    """N-5, N-6: t = 0 is noise, t = 1 data; the loss constant eta is distinct from noise."""
    a, n = np.ones((2, 1)), np.zeros((2, 1))
    x0, _ = corruption.corrupt(a, n, np.zeros(2), 0.0)
    x1, _ = corruption.corrupt(a, n, np.zeros(2), 1.0)
    assert np.array_equal(x0, n) and np.array_equal(x1, a)
    assert loss.ETA == 1e-8
    # eta is the denominator's constant, not the noise: with l_j = 1 on one free token,
    # L = 1 / (1 + eta), whatever the noise.
    pred, acts, noise = np.zeros((2, 1)), np.ones((2, 1)), np.zeros((2, 1))
    w = np.array([1.0, 0.0])
    assert loss.flow_matching_loss(pred, acts, noise, w, eta=0.25) == 1.0 / 1.25
    assert loss.flow_matching_loss(pred, acts, noise, w) == 1.0 / (1.0 + 1e-8)


def test_float64_and_determinism():
    """N-8, N-9: the reference computes in float64; the same seed gives the same field and bootstrap."""
    w = weights.prefix_weights(8, 2, 5)
    assert w.dtype == np.float64
    a = ReferenceVelocityField.init(7, 4, 2, 3)
    b = ReferenceVelocityField.init(7, 4, 2, 3)
    assert all(np.array_equal(a.params[k], b.params[k]) for k in a.params)
    assert metrics.bootstrap_indices(4, 10, 3).tolist() == metrics.bootstrap_indices(4, 10, 3).tolist()
    # ... and the seed is used: another seed gives another field and other resamples.
    c = ReferenceVelocityField.init(8, 4, 2, 3)
    assert not all(np.array_equal(a.params[k], c.params[k]) for k in a.params)
    assert metrics.bootstrap_indices(4, 10, 3).tolist() != metrics.bootstrap_indices(4, 10, 4).tolist()


def test_reference_imports_only_numpy():
    """The dependency-light reference: importing softrtc.reference loads no third-party module but NumPy."""
    code = ("import sys, softrtc.reference\n"
            "std = set(sys.stdlib_module_names)\n"
            "bad = sorted({m.split('.')[0] for m in sys.modules} - std - {'numpy', 'softrtc', '__main__'})\n"
            "bad = [m for m in bad if not m.startswith('_')]\n"
            "print(','.join(bad))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, check=True)
    assert out.stdout.strip() == "", f"third-party modules imported: {out.stdout}"


def test_flow_time_arguments_are_range_checked():
    """N-7: flow times outside [0, 1], NaN or bool, and mis-shaped flipped times raise naming the argument."""
    from softrtc.reference import conventions, velocity

    w = [1.0, 0.5, 0.0]
    for t in (5.0, -0.1, float("nan"), True):
        with pytest.raises(ValueError, match=r"^t must be .*\[0\.0, 1\.0\]"):
            sampler.blend_time(t, w)
    with pytest.raises(ValueError, match="t_flipped must be a scalar or have the shape of weights"):
        conventions.flipped_token_times(w, np.array([0.1, 0.2]))
    with pytest.raises(ValueError, match=r"^t values must lie in \[0\.0, 1\.0\]"):
        velocity.time_features(np.array([0.5, 7.0]))
    with pytest.raises(ValueError, match=r"^t values must lie"):
        F(np.zeros(3), np.zeros((4, 2)), np.full(4, 1.5))
    # [S-3]'s blend time t + (1 - t) w_j, by hand: 0.5 + 0.5 * (1, 0.5, 0).
    np.testing.assert_allclose(sampler.blend_time(0.5, w), [1.0, 0.75, 0.5])


def test_naive_method_rejects_delays_the_executor_cannot_run():
    """X-1, N-7: naive ignores d, yet a delay outside [0, min(s, H - s)] or an s outside [1, H] is rejected."""
    from softrtc.reference import methods as rmethods

    field = ReferenceVelocityField.init(0, 8, 2, 3)
    obs, noise = np.zeros(3), np.zeros((8, 2))
    call = lambda s, d: rmethods.generate_chunk("naive", field, obs, noise, noise, s, d, 2)  # noqa: E731
    with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 4\], got 5"):
        call(4, 5)
    with pytest.raises(ValueError, match=r"^s must be an integer in \[1, 8\], got 9"):
        call(9, 0)
    assert call(4, 4).shape == (8, 2)


def test_arrays_of_non_real_dtype_rejected():
    """N-7: booleans, strings and complex numbers are not converted to floats."""
    a = np.ones((3, 2))
    for bad in (np.array([True, False, False]), np.array(["1", "0", "0.5"]), np.array([1, 0, 0.5j])):
        with pytest.raises(ValueError, match="weights must be a real numeric array"):
            corruption.corrupt(a, a, bad, 0.5)
    with pytest.raises(ValueError, match="actions must be a real numeric array"):
        corruption.corrupt(a.astype(bool), a, np.zeros(3), 0.5)
    # Integer arrays are real and accepted.
    np.testing.assert_array_equal(corruption.corrupt(a.astype(int), a, np.ones(3), 0.5)[0], a)


def test_velocity_field_output_is_checked():
    """N-7: a field returning the wrong shape or NaN is an error in every reference sampler."""
    rng = np.random.default_rng(0)
    obs, x, y = rng.standard_normal(3), rng.standard_normal((4, 2)), rng.standard_normal((4, 2))
    w = np.array([1.0, 0.5, 0.0, 0.0])
    bad_shape = lambda o, x, t: np.zeros(x.shape[1])  # noqa: E731
    bad_value = lambda o, x, t: np.full(x.shape, np.nan)  # noqa: E731
    for f, match in ((bad_shape, r"^field must return an array of the state's shape \[4, 2\], got \[2\]$"),
                     (bad_value, r"^field returned non-finite values")):
        with pytest.raises(ValueError, match=match):
            sampler.naive_sample(f, obs, x, 2)
        with pytest.raises(ValueError, match=match):
            sampler.rtc_sample(f, obs, x, y, w, 2)

    class BadVJP:
        def __call__(self, o, x, t):
            return np.zeros_like(x)

        def vjp(self, o, x, t, ct):
            return np.zeros(1)

    with pytest.raises(ValueError, match="field.vjp must return"):
        guidance.guided_sample(BadVJP(), obs, x, y, w, 2)


def test_implementation_ranges():
    """N-12, D-3, M-1, M-5: the stated bounds are where inputs become errors, in the reference
    a table cannot draw a delay above 4096."""
    p = np.array([0.5, 0.5])
    assert delays.sample_delay(p, 4095, 0.9) == 4096
    with pytest.raises(ValueError, match="d_min must be an integer in \\[0, 4095\\]"):
        delays.sample_delay(p, 4096, 0.9)
    with pytest.raises(ValueError, match="num_steps"):
        sampler.euler_times(65537)
    assert sampler.euler_times(65536).size == 65536
    assert metrics.difference_norm(np.zeros((20, 1)), 16) == 0.0  # the largest order is allowed
    with pytest.raises(ValueError, match="order"):
        metrics.difference_norm(np.zeros((20, 1)), 17)
    with pytest.raises(ValueError, match="num_resamples"):
        metrics.bootstrap_indices(3, 10**7 + 1, 0)
    # 10^7 resamples are allowed; the bound is checked before any drawing, so probe it with a bad seed.
    with pytest.raises(ValueError, match="seed"):
        metrics.bootstrap_indices(3, 10**7, -1)
    assert endpoints.endpoint(endpoints.hard(), 4096) == 4096
    with pytest.raises(ValueError, match="d must be"):
        endpoints.endpoint(endpoints.hard(), 4097)


def _raises_naming(fn, name):
    """fn() raises ValueError whose message starts with the argument ``name`` ([N-7])."""
    with pytest.raises(ValueError) as info:
        fn()
    assert re.match(rf"{re.escape(name)}(?![\w])", str(info.value)), f"message does not start with {name!r}: {info.value}"


def test_field_results_of_another_kind_are_rejected_not_converted():
    """[N-7] A velocity or VJP the field returns as a complex, boolean or string array is an error, as an input
    of that dtype would be; a real integer array is accepted and read as floats."""
    def field_of(value):
        return lambda obs, x, t: np.full(x.shape, value)

    for value in (1 + 5j, True, "3.5"):
        _raises_naming(lambda: sampler.naive_sample(field_of(value), np.zeros(3), np.zeros((4, 2)), 2), "the result of field")
    out = sampler.naive_sample(field_of(2), np.zeros(3), np.zeros((4, 2)), 2)
    np.testing.assert_array_equal(out, np.full((4, 2), 2.0))


def test_schedule_positions_are_checked_like_arrays():
    """[W-3] [N-7] [N-12] schedule_value's positions x must be a non-empty real array in [0, 1]: booleans,
    strings, complex numbers and empty arrays are rejected, not converted."""
    for bad in ([True, False], ["0.25"], [], True, [0.5, "a"], np.array([0.5 + 1j])):
        _raises_naming(lambda: weights.schedule_value("linear", bad), "x")
    np.testing.assert_allclose(weights.schedule_value("linear", [0.25, 1]), [0.75, 0.0])
    # An empty window (e = d) still gives the prefix and the tail.
    assert weights.prefix_weights(4, 2, 2, "exp").tolist() == [1.0, 1.0, 0.0, 0.0]


def test_horizon_and_delay_bounds():
    """[N-12] H lies in [1, 4096], so every token index, endpoint and delay lies in [0, 4096]: larger values are
    rejected with the argument named, where an unbounded H ran out of memory or accepted a delay of 4500."""
    _raises_naming(lambda: weights.hard_weights(5000, 4500), "H")
    _raises_naming(lambda: weights.hard_weights(10**30, 0), "H")
    _raises_naming(lambda: weights.prefix_weights(4097, 0, 0), "H")
    _raises_naming(lambda: weights.window_positions(0, 10**12), "e")
    _raises_naming(lambda: weights.window_positions(5000, 5001), "d")
    _raises_naming(lambda: executor.check_delay(10000, 5000, 4500), "H")
    _raises_naming(lambda: guidance.guidance_prefix_weights(4097, 1, 0, "soft"), "H")
    _raises_naming(lambda: metrics.is_high_delay(4097), "d")
    _raises_naming(lambda: metrics.is_high_delay(10**30), "d")
    _raises_naming(lambda: metrics.bootstrap_indices(10**30, 1, 0), "num_values")
    _raises_naming(lambda: weights.check_weights("w", np.zeros(2), 2.0), "H")
    _raises_naming(lambda: weights.check_weights("w", np.zeros(2), None), "H")
    assert weights.hard_weights(4096, 4096).sum() == 4096
    assert metrics.is_high_delay(4096) is False and metrics.is_high_delay(3) is True
    # A table longer than the delay range is refused by its length, not by a misleading d_min range.
    _raises_naming(lambda: delays.sample_delay(np.full(5000, 1 / 5000), 0, 0.5), "probs")


def test_reals_too_large_for_a_float_are_value_errors():
    """[N-7] A real argument given as an integer or Fraction beyond the float range raises ValueError naming it,
    not OverflowError."""
    from fractions import Fraction

    _raises_naming(lambda: corruption.token_times([0.0], 10**400), "tau")
    _raises_naming(lambda: endpoints.delay_scaled(Fraction(10**400, 3), 5), "lam")
    _raises_naming(lambda: guidance.guidance_weight(0.5, 10**400), "max_guidance")


def test_velocity_field_arguments():
    """[F-3] [N-7] init's scale is a finite real > 0 (booleans rejected) and the constructor takes a dict."""
    for bad in (True, None, "2", 0.0, -1.0, float("nan"), 10**400, 1 + 1j):
        _raises_naming(lambda: ReferenceVelocityField.init(0, 4, 1, 2, 3, scale=bad), "scale")
    for bad in (None, 3, ["W1"], "W1", {**F.params, "W3": F.params["W1"]}):
        _raises_naming(lambda: ReferenceVelocityField(bad), "params")
    a, b = ReferenceVelocityField.init(0, 4, 1, 2, 3, scale=2.0), ReferenceVelocityField.init(0, 4, 1, 2, 3)
    np.testing.assert_allclose(a.params["W1"], 2.0 * b.params["W1"])


def test_endpoint_rule_stores_numpy_scalars_by_value():
    """[E-1] [E-2] EndpointRule built directly with NumPy scalars stores them as Python numbers, so endpoint()
    reads the value as delay_scaled() does, and returns a Python int."""
    r = endpoints.EndpointRule("delay_scaled", np.float32(1.6), np.int64(16))
    assert type(r.lam) is float and type(r.h_max) is int
    assert r == endpoints.delay_scaled(np.float32(1.6), 16)
    e = endpoints.endpoint(r, 5)
    assert type(e) is int and e == math.ceil(float(np.float32(1.6)) * 5 - 1e-4)
    o = endpoints.EndpointRule("offset", length=np.int64(2), h_max=np.int32(8))
    assert type(o.length) is int and endpoints.endpoint(o, 3) == 5


def test_trace_flag_is_a_bool():
    """[N-7] return_trace is True or False: a truthy string or number is an error, not a request for a trace."""
    f = ReferenceVelocityField.init(0, 4, 2, 3)
    calls = (lambda v: sampler.naive_sample(f, OK["obs"], OK["noise"], 2, return_trace=v),
             lambda v: sampler.rtc_sample(f, OK["obs"], OK["noise"], OK["prior"], OK["weights"], 2, return_trace=v),
             lambda v: guidance.guided_sample(f, OK["obs"], OK["noise"], OK["prior"], OK["weights"], 2,
                                              return_trace=v))
    for call in calls:
        for bad in ("no", 1, None, float("nan")):
            _raises_naming(lambda: call(bad), "return_trace")
        assert isinstance(call(True), tuple) and isinstance(call(np.bool_(False)), np.ndarray)


def test_executor_delay_lists_name_the_bad_entry():
    """[X-5] [N-7] delays must be a sequence with one executable delay per chunk; a bad entry is named by its
    index, and a non-sequence is a ValueError, not a TypeError."""
    chunks = np.zeros((3, 8, 1))
    _raises_naming(lambda: executor.execute_chunks(chunks, [0, 2.0, 1], 4), "delays[1]")
    _raises_naming(lambda: executor.execute_chunks(chunks, [0, 1, 5], 4), "delays[2]")
    for bad in (None, True, 0, 0.5, "012"):
        _raises_naming(lambda: executor.execute_chunks(chunks, bad, 4), "delays")
        _raises_naming(lambda: executor.closed_loop(lambda o, p, d, c: np.zeros((8, 1)), lambda a: 0.0, 0.0, 3, 8,
                                                    4, bad), "delays")
    assert executor.execute_chunks(chunks, (0, 4, 0), 4)["actions"].shape == (12, 1)


def test_metric_and_method_inputs():
    """[M-3] [S-8] [N-7] An empty chunk_index and a ragged noise array raise ValueError naming the argument."""
    from softrtc.reference.methods import generate_chunk

    _raises_naming(lambda: metrics.switch_steps(np.array([], int)), "chunk_index")
    _raises_naming(lambda: generate_chunk("naive", F, np.zeros(3), [[0.0], [0.0, 1.0]], None, 1, 0, 2), "noise")
    assert metrics.switch_steps(np.array([0, 0, 1])).tolist() == [2]


def test_conformance_api_arguments():
    """[CF-13] [CF-5] [N-7] The runner's only is a collection of known function names (a string would match by
    substring, an unknown name would run nothing); paths, JSON text, tolerances and file names are checked."""
    from softrtc.conformance import generate, runner

    _raises_naming(lambda: runner.run("reference", only="batch_loss"), "only")
    _raises_naming(lambda: runner.run("reference", only={"bogus"}), "only names unknown interface functions ['bogus']")
    _raises_naming(lambda: runner.run("reference", only=5), "only")
    _raises_naming(lambda: runner.load_vectors(123), "directory")
    _raises_naming(lambda: runner.parse_json(None), "text")
    _raises_naming(lambda: runner.compare("x", np.zeros(2), [0.0, 0.0], {}), "tol")
    _raises_naming(lambda: generate.render("bogus"), "name")
    _raises_naming(lambda: generate.generate(123), "out_dir")
    res = runner.run("reference", only=["batch_loss"])
    assert res.cases and {c.function for c in res.cases} == {"batch_loss"}


def test_executor_delays_must_be_an_ordered_sequence():
    """[X-5] [N-7] A dict of delays (iterated by its keys) or a set (hash order) is a ValueError naming delays;
    a 2-D array too. The same delays as a list, tuple or 1-D array run, and give the executed order of [X-4]."""
    chunks = np.arange(3 * 8, dtype=float).reshape(3, 8, 1)
    # {0: 1, 1: 2, 2: 3} read by its keys would be the valid delays 0, 1, 2.
    for bad in ({0: 1, 1: 2, 2: 3}, {0, 1, 2}, frozenset({0, 1, 2}), np.zeros((1, 3), int), iter([0, 1, 2])):
        with pytest.raises(ValueError, match=r"^delays must be a sequence of 3 integers"):
            executor.execute_chunks(chunks, bad, 4)
        with pytest.raises(ValueError, match=r"^delays must be a sequence of 3 integers"):
            executor.closed_loop(lambda o, p, d, c: np.zeros((8, 1)), lambda a: 0.0, 0.0, 3, 8, 4, bad)
    for good in ([0, 1, 2], (0, 1, 2), np.array([0, 1, 2])):
        ci = executor.execute_chunks(chunks, good, 4)["chunk_index"].tolist()
        # Chunk 1 takes over after d_1 = 1 step of segment 1, chunk 2 after d_2 = 2 steps of segment 2.
        assert ci == [0, 0, 0, 0, 0, 1, 1, 1, 1, 1, 2, 2]


def test_closed_loop_names_generate_when_a_chunk_changes_width():
    """[X-6] [N-7] A later chunk with another action width than the first is an error naming generate and the
    chunk, not the executor's internal argument new_chunk."""
    gen = lambda obs, prior, d, c: np.zeros((8, 2 if c == 0 else 3))  # noqa: E731
    with pytest.raises(ValueError, match=r"^generate must return chunks of shape \[H=8, A=2\], got \[8, 3\] "
                                         r"for chunk 1$"):
        executor.closed_loop(gen, lambda a: 0.0, 0.0, 3, 8, 4, [0, 1, 1])


def test_samplers_name_noise_and_obs_against_the_fields_sizes():
    """[S-2] [S-3] [G-2] [N-7] A noise or obs that does not fit the field's declared sizes is named by the
    sampler's argument (noise, obs), not by the field's internal x."""
    f = ReferenceVelocityField.init(0, 8, 2, 3)
    obs, noise, w = np.zeros(3), np.zeros((8, 3)), np.zeros(8)
    calls = {"naive": lambda o, n: sampler.naive_sample(f, o, n, 2),
             "rtc": lambda o, n: sampler.rtc_sample(f, o, n, n, np.zeros(n.shape[0]), 2),
             "guided": lambda o, n: guidance.guided_sample(f, o, n, n, np.zeros(n.shape[0]), 2)}
    for name, call in calls.items():
        with pytest.raises(ValueError, match=r"^noise must have the field's shape \[H=8, A=2\], got \[8, 3\]$"):
            call(obs, noise)
        with pytest.raises(ValueError, match=r"^noise must have the field's shape \[H=8, A=2\], got \[6, 2\]$"):
            call(obs, np.zeros((6, 2)))
        with pytest.raises(ValueError, match=r"^obs must have the field's shape \[O=3\], got \[4\]$"):
            call(np.zeros(4), np.zeros((8, 2)))
    assert w.shape == (8,) and sampler.naive_sample(f, obs, np.zeros((8, 2)), 2).shape == (8, 2)


def test_metrics_name_ragged_and_mistyped_arguments():
    """[M-3] [M-4] [M-5] [N-7] Ragged lists and arrays of the wrong kind name the argument: chunk_index and
    indices must be integers, solved booleans."""
    cases = [
        (lambda: metrics.switch_steps([[0], [1, 2]]), r"^chunk_index must be an integer array, got a ragged"),
        (lambda: metrics.switch_steps([0.0, 1.0]), r"^chunk_index must be an integer array, got dtype float64"),
        (lambda: metrics.boundary_jump(np.zeros((3, 2)), [[0], [1, 2]]), r"^chunk_index must be an integer array"),
        (lambda: metrics.solve_rate([[True], [False, True]]), r"^solved must be a boolean array, got a ragged"),
        (lambda: metrics.solve_rate([1, 0]), r"^solved must be a boolean array, got dtype int64"),
        (lambda: metrics.bootstrap_interval_from_indices([1.0, 2.0], [[0, 1], [1]]),
         r"^indices must be an integer array, got a ragged"),
        (lambda: metrics.bootstrap_interval([[1.0], [2.0, 3.0]]), r"^values must be a real numeric array"),
    ]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()
    assert metrics.solve_rate([True, False, False, True]) == 0.5


def test_bootstrap_matrix_size_is_bounded():
    """[N-12] [M-5] B * n is at most 10^8 entries: 10^7 resamples of 10^7 values, each factor within its own
    bound, is a ValueError naming both arguments before any memory is taken, not a MemoryError."""
    with pytest.raises(ValueError, match=r"^num_resamples \* num_values must be at most 100000000 \(\[N-12\]\), "
                                         r"got 10000000 \* 10000000$"):
        metrics.bootstrap_indices(10**7, 10**7, 0)
    with pytest.raises(ValueError, match=r"^num_resamples \* num_values must be at most"):
        metrics.bootstrap_interval(np.ones(10**4 + 1), 10**4, 0)
    # At the bound's edge in one factor: a matrix of 10^7 rows of 2 values is drawn, as [M-5] defines it.
    idx = metrics.bootstrap_indices(2, 5 * 10**6, 0)
    assert idx.shape == (5 * 10**6, 2) and idx.min() == 0 and idx.max() == 1
    np.testing.assert_array_equal(idx[:3], np.random.default_rng(0).integers(0, 2, (3, 2)))


# Inputs every check of [N-7] accepts whose loss or metric overflows float64 (hand-picked: 1e300 ** 2 and
# 1.5e308 - (-1.5e308) exceed the float64 limit of about 1.8e308).
BIG = 1.5e308


def _overflow_calls():
    z = np.zeros((2, 1))
    return [
        ("pred", lambda: loss.token_errors(np.full((2, 1), 1e300), z, z)),
        ("pred", lambda: loss.token_errors(np.full((2, 1), 1e200), np.full((2, 1), -1e200), z)),
        ("pred", lambda: loss.flow_matching_loss(np.full((2, 1), 1e300), z, z, np.zeros(2))),
        # Each l_j = 1.21e308 is finite; their weighted sum is not.
        ("pred", lambda: loss.flow_matching_loss(np.full((2, 1), 1.1e154), z, z, np.zeros(2))),
        ("preds", lambda: loss.batch_loss(np.full((2, 2, 1), 1.1e154), np.zeros((2, 2, 1)), np.zeros((2, 2, 1)),
                                          np.zeros((2, 2)))),
        ("actions", lambda: metrics.action_delta(np.array([[BIG], [-BIG]]))),
        ("actions", lambda: metrics.finite_differences(np.array([[BIG], [-BIG]]), 1)),
        # Differences 1e154 * (1, 1) are finite; the norm's squares are not.
        ("actions", lambda: metrics.action_jerk(np.array([[0.0, 0.0], [1e200, 1e200], [0.0, 0.0]]))),
        ("actions", lambda: metrics.boundary_jump(np.array([[BIG], [-BIG], [-BIG]]), np.array([0, 1, 1]))),
        ("values", lambda: metrics.standard_error(np.array([BIG, -BIG]))),
        ("values", lambda: metrics.defined_mean(np.array([BIG, BIG, np.nan]))),
        ("values", lambda: metrics.bootstrap_interval(np.array([BIG, BIG, BIG]), 10, 0)),
    ]


def test_overflow_from_finite_inputs_is_an_error():
    """[N-15] A loss or metric that overflows float64 from finite inputs raises ValueError naming the input,
    never returns inf or NaN; just below the limit the hand-computed values come back."""
    import warnings

    for name, call in _overflow_calls():
        with warnings.catch_warnings():
            warnings.simplefilter("error")  # the overflow is reported once, as the error, not as a warning
            with pytest.raises(ValueError, match=rf"^{name} is too large in magnitude: .* overflows float64"):
                call()
    z = np.zeros((2, 1))
    # Powers of two keep every hand-computed value exact; 2^1023 is the largest finite power.
    assert loss.token_errors(np.full((2, 1), 2.0**511), z, z).tolist() == [2.0**1022, 2.0**1022]
    assert metrics.action_delta(np.array([[2.0**500], [-(2.0**500)]])) == 2.0**501
    assert metrics.standard_error(np.array([2.0**500, -(2.0**500)])) == pytest.approx(2.0**500)  # sqrt(2^1001) / sqrt 2
    assert metrics.defined_mean(np.array([2.0**1022, 2.0**1022, np.nan])) == 2.0**1022
