"""JAX-twin checks of rules whose reference side lives in tests/reference/ (chapters D, M, N, S, X):
the same inputs and error messages as the reference, and values worked out by hand."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softrtc.jax import delays as JD
from softrtc.jax import guidance as JG
from softrtc.jax import methods as jmethods
from softrtc.jax import sampler as JS
from softrtc.jax import sampler as jsampler
from softrtc.jax import velocity as jvelocity
from softrtc.reference import metrics as M


def test_jax_cdf_last_entry_is_exactly_one():
    """D-3, D-2: in float32 twelve twelfths sum to 0.99999988, yet the JAX table's last CDF entry is 1
    exactly and u just below 1 draws d_max; decay is checked where the uniform table ignores it."""
    pj = JD.delay_probs("uniform", 0, 11)
    assert float(jnp.cumsum(pj)[-1]) < 1.0 and float(JD.delay_cdf(pj)[-1]) == 1.0
    assert int(JD.sample_delay(pj, 0, jnp.float32(np.nextafter(np.float32(1), np.float32(0))))) == 11
    for bad in (float("nan"), -5.0, 65.0):
        with pytest.raises(ValueError, match="decay"):
            JD.delay_probs("uniform", 0, 3, decay=bad)


def test_undefined_smoothness_metrics_are_nan_in_jax_and_left_out_of_means():
    """M-8: D_k with N <= k and a jump with no switch raise in the reference, are NaN in traced
    JAX, and are left out of the means of the arm study and the Kinetix summary (not counted as 0)."""
    pytest.importorskip("pymunk")
    pytest.importorskip("kinetix")
    import jax

    from softrtc.jax import metrics as JMt

    a = np.arange(6.0).reshape(3, 2)
    with pytest.raises(ValueError, match="chunk switch"):
        M.boundary_jump(a, np.zeros(3, int))
    with pytest.raises(ValueError, match=r"^actions must have more than order=2 steps, got 2$"):
        M.difference_norm(a[:2], 2)
    with pytest.raises(ValueError, match="chunk switch"):
        JMt.boundary_jump(a, np.zeros(3, int))
    traced = jax.jit(JMt.boundary_jump)(a, np.zeros(3, np.int32))
    assert np.isnan(traced)
    assert jax.jit(JMt.boundary_jump)(a, np.array([0, 0, 1], np.int32)) == pytest.approx(M.boundary_jump(
        a, np.array([0, 0, 1])))
    # The one mean of the defined values both simulators use.
    assert M.defined_mean([1.0, float("nan"), 3.0]) == 2.0 and np.isnan(M.defined_mean([float("nan")]))
    assert np.isnan(M.defined_mean([])) and M.defined_mean([np.inf, 4]) == 4.0
    with pytest.raises(ValueError, match=r"^values must be a 1-D array"):
        M.defined_mean(np.zeros((2, 2)))
    with pytest.raises(ValueError, match=r"^values must be"):
        M.defined_mean([True, False])

    # Through the summaries: a NaN jerk (arm: D3) is left out of that metric only.
    from softrtc.arm import study
    from softrtc.kinetix import results as KH

    nan = float("nan")
    rows = [{"method": "naive", "level": "a", "delay": 0, "return": 1.0, "solved": 1.0, "delta": 0.2, "jerk": 0.4},
            {"method": "naive", "level": "a", "delay": 0, "return": 3.0, "solved": 0.0, "delta": 0.4, "jerk": nan}]
    lv = [r for r in KH.summarize(rows, bootstrap_resamples=10)["per_level"] if r["scope"] == "overall"][0]
    assert (lv["jerk"], lv["delta"], lv["return"], lv["solved"]) == (0.4, 0.30000000000000004, 2.0, 0.5)
    trial = {"success": True, "completed": 4, "fault": None, "completion": 1.0, "throughput": 10.0,
             "D1": 0.1, "D2": 0.2, "D3": 0.3, "boundary": 0.5, "latency_ms": 60.0, "hold_ticks": 0}
    row = study.summarize([trial, dict(trial, D3=nan, completion=0.5, throughput=20.0)])
    assert row["D3"] == 0.3 and row["completion"] == 0.75 and row["throughput"] == 15.0


def test_jax_flow_time_arguments_are_range_checked():
    """N-7: the JAX twin's flow times outside [0, 1] and mis-shaped blend times raise naming the argument."""
    with pytest.raises(ValueError, match=r"^t values must lie in \[0\.0, 1\.0\]"):
        jvelocity.time_features(np.array([0.5, 7.0]))
    with pytest.raises(ValueError, match=r"^t values must lie in \[0\.0, 1\.0\]"):
        jsampler.blend_time(np.float32(1.5), np.array([1.0, 0.5, 0.0]))
    with pytest.raises(ValueError, match=r"^t must be a scalar or have the batch shape of weights \[2\]"):
        jsampler.blend_time(np.array([0.5, 0.2, 0.1]), np.zeros((2, 4)))
    # [S-3] by hand: 0.5 + 0.5 * (1, 0.5, 0).
    np.testing.assert_allclose(np.asarray(jsampler.blend_time(0.5, np.array([1.0, 0.5, 0.0]))), [1.0, 0.75, 0.5])


def test_jax_naive_method_rejects_delays_the_executor_cannot_run():
    """X-1, N-7: the JAX naive method ignores d, yet rejects a delay outside [0, min(s, H - s)] or an s outside [1, H]."""
    obs, noise = np.zeros((1, 3), np.float32), np.zeros((1, 8, 2), np.float32)
    calls = {
        "jax": lambda s, d: jmethods.generate_chunk("naive", lambda o, x, t: x, obs, noise, noise, s, d, 2),
        "jax conditioned": lambda s, d: jmethods.generate_chunk_conditioned("naive", None, obs, noise, noise,
                                                                            s, d, 2),
    }
    for name, call in calls.items():
        with pytest.raises(ValueError, match=r"^d must be an integer in \[0, 4\], got 5"):
            call(4, 5)
        with pytest.raises(ValueError, match=r"^s must be an integer in \[1, 8\], got 9"):
            call(9, 0)


def test_jax_velocity_field_output_shape_is_checked():
    """N-7: a field returning the wrong shape is an error in the JAX samplers (not broadcast)."""
    rng = np.random.default_rng(0)
    obs, x, y = rng.standard_normal(3), rng.standard_normal((4, 2)), rng.standard_normal((4, 2))
    w = np.array([1.0, 0.5, 0.0, 0.0])
    bo, bx, by = obs[None], x[None], y[None]
    jbad = lambda o, x, t: x[..., :1]  # noqa: E731
    for call in (lambda: JS.naive_sample(jbad, bo, bx, 2), lambda: JS.rtc_sample(jbad, bo, bx, by, w, 2),
                 lambda: JG.guided_sample(jbad, bo, bx, by, w, 2)):
        with pytest.raises(ValueError, match="velocity_fn must return"):
            call()


def test_jax_delay_table_range():
    """N-12, D-3: the JAX delay draw reaches 4096 and rejects d_min above 4095."""
    p = np.array([0.5, 0.5])
    assert int(JD.sample_delay(p, 4095, 0.9)) == 4096
    with pytest.raises(ValueError, match="d_min must be an integer in \\[0, 4095\\]"):
        JD.sample_delay(p, 4096, 0.9)
