"""Validation of the JAX twin's samplers, methods and their helpers ([N-7], [N-10], [N-12], [S-8]).

Each bad call raises ``ValueError`` naming the offending argument, and the
matching good call still works. Traced arguments are checked for shape and
dtype only ([N-10]); the tests that jit a function check that a valid traced
call still compiles and runs. Tiny shapes keep the file fast.
"""

import re
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from softrtc import reference as R
from softrtc.jax import corruption as JC
from softrtc.jax import delays as JD
from softrtc.jax import endpoints as JE
from softrtc.jax import guidance as JG
from softrtc.jax import loss as JL
from softrtc.jax import methods as JM
from softrtc.jax import sampler as JS
from softrtc.jax import velocity as JF
from softrtc.jax import weights as JW

H, A, O, K, B = 4, 2, 3, 5, 2
RF = R.velocity.ReferenceVelocityField.init(0, H, A, O, K)
F = JF.ReferenceVelocityField.from_reference(RF)
OBS = jnp.zeros((B, O))
X = jnp.ones((B, H, A))
PRIOR = jnp.full((B, H, A), 0.5)
W = jnp.array([1.0, 0.5, 0.0, 0.0])
WIN = JW.SoftWindow(JE.delay_scaled(2.0, 2))  # a window that fits H = 4 ([S-8])


def _raises(fn, name):
    """fn() raises ValueError whose message names ``name`` ([N-7])."""
    with pytest.raises(ValueError) as info:
        fn()
    assert re.match(rf"{re.escape(name)}(?![\w])", str(info.value)), f"message does not start with {name!r}: {info.value}"
    return str(info.value)


def _ok(out, shape=(B, H, A)):
    out = np.asarray(out)
    assert out.shape == shape and np.all(np.isfinite(out))
    return out


def test_apply_conditioned_checks_cond():
    """[N-7] [F-1] [S-2] [N-10] cond of apply_conditioned / apply_conditioned_split is [K] or [b, K] with
    b in {1, B}, real and finite: a [B, 1], [1], scalar, [3, K], NaN, bool, complex or None cond raises
    naming cond (also through the conditioned samplers and under jit) instead of broadcasting."""
    bad = [jnp.zeros((B, 1)), jnp.zeros(1), jnp.zeros(()), jnp.zeros((3, K)), jnp.full(K, jnp.nan),
           np.zeros(K, bool), np.zeros(K, np.complex64), None, "abc"]
    for c in bad:
        _raises(lambda: F.apply_conditioned(OBS, X, c), "cond")
        _raises(lambda: F.apply_conditioned_split(OBS, X, c, 2), "cond")
    _raises(lambda: F.apply_conditioned(OBS[0], X[0], jnp.zeros((B, K))), "cond")  # one example: b = 1
    _raises(lambda: JS.naive_sample_conditioned(F, OBS, X, 2, cond=jnp.zeros((2, 2, 1))), "cond")
    _raises(lambda: jax.jit(lambda c: F.apply_conditioned(OBS, X, c))(jnp.zeros((B, 1))), "cond")
    _raises(lambda: jax.jit(lambda c: F.apply_conditioned(OBS, X, c))(jnp.zeros((B, K), jnp.complex64)), "cond")
    t = jnp.full((B, H), 0.25)
    want = np.asarray(F(OBS, X, t))
    for c in (F.time_conditioning(t), F.time_conditioning(t[:1]), F.time_conditioning(t[0])):
        np.testing.assert_allclose(F.apply_conditioned(OBS, X, c), want, atol=1e-6)
        head, tail = F.apply_conditioned_split(OBS, X, c, 1)
        np.testing.assert_allclose(np.concatenate([head, tail], axis=1), want, atol=1e-6)
    np.testing.assert_allclose(jax.jit(F.apply_conditioned)(OBS, X, F.time_conditioning(t)), want, atol=1e-6)
    _ok(JS.naive_sample_conditioned(F, OBS, X, 2))


def test_velocity_outputs_must_be_real():
    """[N-7] [S-2] [S-4] [G-2] [L-1] A velocity_fn (or model) result of complex or boolean dtype, or not an
    array, is an error naming velocity_fn (model.apply_conditioned), as for the reference; a wrong shape in
    rtc_loss names velocity_fn too. An integer result is real and accepted."""
    bad_fns = [lambda o, x, t: x.astype(jnp.complex64), lambda o, x, t: x > 0, lambda o, x, t: None]
    for fn in bad_fns:
        _raises(lambda: JS.naive_sample(fn, OBS, X, 2), "velocity_fn")
        _raises(lambda: JS.rtc_sample(fn, OBS, X, PRIOR, W, 2), "velocity_fn")
        _raises(lambda: JL.rtc_loss(fn, OBS, X, PRIOR, jnp.zeros((B, H)), jnp.zeros(B)), "velocity_fn")
    _raises(lambda: JG.guided_sample(bad_fns[0], OBS, X, PRIOR, W, 2), "velocity_fn")
    _raises(lambda: JL.rtc_loss(lambda o, x, t: x[..., :1], OBS, X, PRIOR, jnp.zeros((B, H)), jnp.zeros(B)),
            "velocity_fn")

    class Complex:
        horizon = H

        def time_conditioning(self, t):
            return F.time_conditioning(t)

        def apply_conditioned(self, obs, x, cond):
            return F.apply_conditioned(obs, x, cond).astype(jnp.complex64)

    _raises(lambda: JS.naive_sample_conditioned(Complex(), OBS, X, 2), "model.apply_conditioned")
    _raises(lambda: JS.rtc_sample_conditioned(Complex(), OBS, X, PRIOR, W, 2), "model.apply_conditioned")
    _raises(lambda: JG.guided_sample_conditioned(Complex(), OBS, X, PRIOR, W, 2), "model.apply_conditioned")
    _ok(JS.naive_sample(lambda o, x, t: x.astype(jnp.int32), OBS, X, 2))
    _ok(JS.naive_sample(F, OBS, X, 2))
    assert np.isfinite(float(JL.rtc_loss(F, OBS, X, PRIOR, jnp.zeros((B, H)), jnp.zeros(B))))


def test_field_parameters_are_checked_like_the_reference():
    """[F-1] [F-3] [N-7] [N-12] [N-10] The JAX field's params: a dict of exactly the six arrays, real, finite,
    no empty axis (K = 0 and an empty Wo rejected), consistent shapes; None or NaN, boolean or complex
    entries raise naming params. Built inside jit from traced params it still works."""
    p = {k: np.asarray(a) for k, a in RF.params.items()}
    bad = [None, 3, "W1", {**p, "W1": np.where(p["W1"] == p["W1"][0, 0], np.nan, p["W1"])},
           {**p, "b1": np.ones(K, bool)}, {**p, "b2": p["b2"].astype(complex)}, {**p, "Wo": np.zeros((0, K))},
           {**p, "extra": np.zeros(1)}, {k: a for k, a in p.items() if k != "b2"},
           {**p, "Wt": p["Wt"][:-1]}, {**p, "b1": np.zeros(K + 1)},
           {"W1": np.zeros((H * A, 0)), "Wt": np.zeros((3 * H, 0)), "Wo": np.zeros((O, 0)), "b1": np.zeros(0),
            "W2": np.zeros((0, H * A)), "b2": np.zeros(H * A)}]
    for params in bad:
        _raises(lambda: JF.ReferenceVelocityField(params), "params")
    f = JF.ReferenceVelocityField(p)
    assert (f.horizon, f.action_dim, f.obs_dim, f.hidden) == (H, A, O, K)
    t = jnp.full((B, H), 0.5)
    built = jax.jit(lambda params, t: JF.ReferenceVelocityField(params)(OBS, X, t))(f.params, t)
    np.testing.assert_allclose(built, F(OBS, X, t), atol=1e-6)


def test_tau_has_the_batch_shape_of_the_weights():
    """[C-1] [C-2] [N-7] tau is a scalar or has exactly the batch shape of the weights: a [1] tau with
    weights [3, H] raises naming tau instead of broadcasting."""
    w3 = jnp.zeros((3, H))
    for tau in (jnp.zeros(1), jnp.zeros((3, 1)), jnp.zeros(2)):
        _raises(lambda: JC.token_times(w3, tau), "tau")
        _raises(lambda: JC.corrupt(jnp.zeros((3, H, A)), jnp.ones((3, H, A)), w3, tau), "tau")
    _raises(lambda: JC.token_times(W, jnp.zeros(1)), "tau")
    assert JC.token_times(w3, jnp.full(3, 0.5)).shape == (3, H)
    assert JC.token_times(w3, 0.5).shape == (3, H)
    x, tj = JC.corrupt(jnp.zeros((3, H, A)), jnp.ones((3, H, A)), w3, jnp.full(3, 0.25))
    np.testing.assert_allclose(x, 0.75)


def test_conditioning_weights_have_the_models_horizon():
    """[S-3] [N-7] rtc_conditioning and conditioning_table reject weights whose last axis is not the model's
    H (a last axis of 1 would be read as one shared time), naming the argument and the model's H;
    method_tables with a model of another H names model and H."""
    msg = _raises(lambda: JS.rtc_conditioning(F, jnp.zeros(1), 2), "weights")
    assert f"H={H}" in msg
    _raises(lambda: JS.rtc_conditioning(F, jnp.zeros((B, 1)), 2), "weights")
    msg = _raises(lambda: JS.conditioning_table(F, jnp.zeros((3, 1)), 2), "weight_table")
    assert f"H={H}" in msg
    _raises(lambda: JS.conditioning_table(F, jnp.zeros((3, H + 1)), 2), "weight_table")
    msg = _raises(lambda: JM.method_tables("naive", F, 8, 4, 2), "model")
    assert "H=8" in msg and f"H={H}" in msg
    _raises(lambda: JM.method_tables("train_hard", F, 8, 4, 2), "model")
    assert JS.rtc_conditioning(F, W, 2).shape == (2, 1, K)
    assert JS.conditioning_table(F, jnp.zeros((3, H)), 2).shape == (3, 2, 1, K)
    assert JM.method_tables("train_hard", F, H, 2, 2)["cond"].shape == (3, 2, 1, K)


def test_effective_endpoint_checks_a_given_s_under_zeros():
    """[W-6] [N-7] effective_endpoint checks s when given, also where overflow="zeros" leaves it unused,
    as the reference does."""
    for s in (0, 9, 2.0, True, "4"):
        _raises(lambda: JW.effective_endpoint(8, 2, 6, s, "zeros"), "s")
    assert int(JW.effective_endpoint(8, 2, 6, 4, "zeros")) == 6
    assert int(JW.effective_endpoint(8, 2, 6, None, "zeros")) == 6
    assert int(JW.effective_endpoint(8, 2, 6, 4, "clip")) == 4


def test_endpoint_by_code_checks_its_arguments():
    """[E-1] [E-5] [N-7] [N-12] [N-10] endpoint_by_code (used by the weight tables) checks concrete arguments:
    kind an integer code in [0, 3] (no -1 wrapping to hard, no rule name, no 7), d and the parameters in
    [0, 4096], parameters the rule lacks 0; traced arguments are checked for dtype and still compile."""
    for kind in (-1, 4, 7, "delay_scaled", True, None, 1.0):
        _raises(lambda: JE.endpoint_by_code(kind, 2.0, 5, 0, 3), "kind")
    _raises(lambda: JE.endpoint_by_code(3, 0.0, 0, 0, -5), "d")
    _raises(lambda: JE.endpoint_by_code(3, 0.0, 0, 0, 2.0), "d")
    _raises(lambda: JE.endpoint_by_code(0, "x", 5, 0, 3), "lam")
    _raises(lambda: JE.endpoint_by_code(0, -1.0, 5, 0, 3), "lam")
    _raises(lambda: JE.endpoint_by_code(0, 2.0, 5000, 0, 3), "h_max")
    _raises(lambda: JE.endpoint_by_code(2, 0.0, 8, -1, 3), "length")
    _raises(lambda: JE.endpoint_by_code(0, 2.0, 5, 3, 3), "length")
    _raises(lambda: jax.jit(lambda k: JE.endpoint_by_code(k, 2.0, 5, 0, 3))(jnp.float32(0)), "kind")
    assert int(JE.endpoint_by_code(0, 2.0, 5, 0, 2)) == 4
    assert int(JE.endpoint_by_code(3, 0.0, 0, 0, 3)) == 3
    f = jax.jit(JE.endpoint_by_code)
    want = [JE.endpoint(r, 2) for r in (JE.delay_scaled(2.0, 5), JE.fixed(3), JE.offset(1, 8), JE.hard())]
    got = [f(jnp.int32(k), jnp.float32([2.0, 0, 0, 0][k]), jnp.int32([5, 0, 8, 0][k]),
             jnp.int32([0, 3, 1, 0][k]), jnp.int32(2)) for k in range(4)]
    assert [int(g) for g in got] == [int(w) for w in want] == [4, 3, 3, 2]


def test_delay_rows_and_select_conditioning_check_tables():
    """[S-6] [S-3] [N-7] [N-12] delay_rows rejects a training table whose conditioning has another number of
    rows than its weights (no silent truncation) and a conditioning that is not a tree of arrays, for every
    method; select_conditioning rejects a non-table and an empty delay vector."""
    tables = JM.method_tables("train_soft", F, H, 2, 2, WIN)
    w, cond = tables["weights"], tables["cond"]
    _raises(lambda: JM.delay_rows("train_soft", {"weights": w[:2], "cond": cond}), "tables['cond']")
    _raises(lambda: JM.delay_rows("train_soft", {"weights": jnp.concatenate([w, w]), "cond": cond}),
            "tables['cond']")
    for method in JM.METHODS:
        _raises(lambda: JM.delay_rows(method, {"weights": w, "cond": "abc"}), "tables['cond']")
    _raises(lambda: JM.delay_rows("naive", {"weights": w.at[0, 0].set(2.0), "cond": cond}), "tables['weights']")
    _raises(lambda: JS.select_conditioning("abc", 0), "table")
    _raises(lambda: JS.select_conditioning(cond, np.zeros(0, int)), "d")
    _raises(lambda: JS.select_conditioning(cond, 3), "d")
    rows = JM.delay_rows("train_soft", tables)
    assert len(rows) == 3 and rows[2]["cond"].shape == (2, 1, K)
    assert JS.select_conditioning(cond, np.array([0, 2])).shape == (2, 2, K)
    assert len(JM.delay_rows("naive", JM.method_tables("naive", F, H, 2, 2))) == 3


def test_generate_chunk_from_row_checks_the_request_whole():
    """[S-8] [X-2] [G-7] [N-7] generate_chunk_from_row checks guided_tokens for every method and the first
    chunk, the row's weights and conditioning also where they are unused, and unroll."""
    tables = {m: JM.method_tables(m, F, H, 2, 2, WIN if m == "train_soft" else None) for m in JM.METHODS}
    rows = {m: JM.delay_rows(m, t) for m, t in tables.items()}
    for m in JM.METHODS:
        for gt in ("x", 0, True, 2.5, H):
            _raises(lambda: JM.generate_chunk_from_row(m, F, OBS, X, PRIOR, 2, rows[m][1], guided_tokens=gt),
                    "guided_tokens")
            _raises(lambda: JM.generate_chunk_from_row(m, F, OBS, X, None, 2, rows[m][0], guided_tokens=gt),
                    "guided_tokens")
        _raises(lambda: JM.generate_chunk_from_row(m, F, OBS, X, PRIOR, 2, rows[m][1], unroll="yes"), "unroll")
        bad_w = {"weights": jnp.zeros(H + 1), "cond": rows[m][0]["cond"]}
        _raises(lambda: JM.generate_chunk_from_row(m, F, OBS, X, None, 2, bad_w), "row['weights']")
        bad_c = {"weights": rows[m][0]["weights"], "cond": "abc"}
        _raises(lambda: JM.generate_chunk_from_row(m, F, OBS, X, None, 2, bad_c), "row['cond']")
        _ok(JM.generate_chunk_from_row(m, F, OBS, X, None, 2, rows[m][0]))
        _ok(JM.generate_chunk_from_row(m, F, OBS, X, PRIOR, 2, rows[m][1]))
        # The first chunk is naive sampling whatever the row's weights.
        np.testing.assert_array_equal(JM.generate_chunk_from_row(m, F, OBS, X, None, 2, rows[m][1]),
                                      JM.generate_chunk_from_row("naive", F, OBS, X, None, 2, rows["naive"][0]))
    _ok(JM.generate_chunk_from_row("inference_soft", F, OBS, X, None, 2, rows["inference_soft"][0],
                                   guided_tokens=2))
    _ok(JM.generate_chunk_from_row("inference_soft", F, OBS, X, PRIOR, 2, rows["inference_soft"][1],
                                   guided_tokens=2))
    # A naive prior must still be a chunk batch ([S-8]); traced rows compile once for every delay.
    _raises(lambda: JM.generate_chunk_from_row("naive", F, OBS, X, PRIOR[:, :1], 2, rows["naive"][1]), "prior")
    f = jax.jit(lambda row: JM.generate_chunk_from_row("train_soft", F, OBS, X, PRIOR, 2, row))
    for row in rows["train_soft"]:
        _ok(f(row))
    assert f._cache_size() == 1


def test_rtc_loss_checks_obs():
    """[L-3] [N-7] rtc_loss checks obs although only velocity_fn reads it: NaN, None, strings and a wrong
    batch size raise naming obs, even when velocity_fn ignores obs."""
    ignore = lambda o, x, t: x  # noqa: E731
    args = (X, PRIOR, jnp.zeros((B, H)), jnp.zeros(B))
    for obs in (jnp.full((B, O), jnp.nan), None, "abc", jnp.zeros((B + 1, O)), jnp.zeros(B), np.zeros((B, O), bool)):
        _raises(lambda: JL.rtc_loss(ignore, obs, *args), "obs")
    assert np.isfinite(float(JL.rtc_loss(ignore, OBS, *args)))
    assert np.isfinite(float(jax.jit(lambda o: JL.rtc_loss(F, o, *args))(OBS)))


def test_samplers_check_unroll_prior_and_weights():
    """[S-1] [S-3] [G-2] [N-7] Every sampler takes unroll as True or False only (no truthy stand-ins), and the
    RTC and guided samplers (straightforward and conditioned) raise ValueError naming prior or weights when
    either is None."""
    calls = {
        "naive_sample": lambda **kw: JS.naive_sample(F, OBS, X, 2, **kw),
        "rtc_sample": lambda **kw: JS.rtc_sample(F, OBS, X, PRIOR, W, 2, **kw),
        "guided_sample": lambda **kw: JG.guided_sample(F, OBS, X, PRIOR, W, 2, **kw),
        "naive_sample_conditioned": lambda **kw: JS.naive_sample_conditioned(F, OBS, X, 2, **kw),
        "rtc_sample_conditioned": lambda **kw: JS.rtc_sample_conditioned(F, OBS, X, PRIOR, W, 2, **kw),
        "guided_sample_conditioned": lambda **kw: JG.guided_sample_conditioned(F, OBS, X, PRIOR, W, 2, **kw),
        "generate_chunk": lambda **kw: JM.generate_chunk("train_hard", F, OBS, X, PRIOR, 2, 1, 2, **kw),
        "generate_chunk_conditioned": lambda **kw: JM.generate_chunk_conditioned("train_hard", F, OBS, X, PRIOR,
                                                                                 2, 1, 2, **kw),
    }
    for name, call in calls.items():
        for bad in (1, "yes", None, np.array([True])):
            _raises(lambda: call(unroll=bad), "unroll")
        _ok(call(unroll=False))
        _ok(call(unroll=np.bool_(True)))
    for fn in (JS.rtc_sample, JG.guided_sample):
        _raises(lambda: fn(F, OBS, X, None, W, 2), "prior")
        _raises(lambda: fn(F, OBS, X, PRIOR, None, 2), "weights")
    for fn in (JS.rtc_sample_conditioned, JG.guided_sample_conditioned):
        _raises(lambda: fn(F, OBS, X, None, W, 2), "prior")
        _raises(lambda: fn(F, OBS, X, PRIOR, None, 2), "weights")


def test_empty_delay_vectors_and_scalar_weights_are_rejected():
    """[N-12] [N-1] [S-6] [S-3] An empty delay vector is an error for method_weights (no [0, H] table) and
    select_conditioning; blend_time and rtc_time_table reject scalar weights (weights are [..., H])."""
    _raises(lambda: JM.method_weights("train_hard", 8, 4, np.zeros(0, int)), "d")
    _raises(lambda: JM.method_weights("naive", 8, 4, jnp.zeros(0, jnp.int32)), "d")
    _raises(lambda: JS.blend_time(0.5, 0.25), "weights")
    _raises(lambda: JS.rtc_time_table(0.25, 2), "weights")
    _raises(lambda: JS.rtc_time_table(np.zeros((2, 0)), 2), "weights")
    assert JM.method_weights("train_hard", 8, 4, np.array([0, 3])).shape == (2, 8)
    np.testing.assert_allclose(JS.blend_time(0.5, jnp.array([1.0, 0.5, 0.0])), [1.0, 0.75, 0.5])
    assert JS.rtc_time_table(W, 2).shape == (2, H)


def test_endpoint_rule_built_directly_checks_lam():
    """[E-1] [E-2] [N-7] An EndpointRule built field by field with a non-numeric lam (or h_max) raises a
    ValueError naming it when used, not a TypeError; the same rule with valid fields works."""
    bad = JE.EndpointRule(lam="x", h_max=jnp.int32(5), length=jnp.int32(0), kind="delay_scaled")
    _raises(lambda: JE.endpoint(bad, 2), "rule.lam")
    _raises(lambda: JW.soft_weights(8, 2, JW.SoftWindow(bad), 4), "rule.lam")
    bad_h = JE.EndpointRule(lam=jnp.float32(2.0), h_max=None, length=jnp.int32(0), kind="delay_scaled")
    _raises(lambda: JE.endpoint(bad_h, 2), "rule.h_max")
    good = JE.EndpointRule(lam=jnp.float32(2.0), h_max=jnp.int32(5), length=jnp.int32(0), kind="delay_scaled")
    assert int(JE.endpoint(good, 2)) == 4
    assert int(jax.jit(JE.endpoint)(good, jnp.int32(2))) == 4


def test_sample_delays_rejects_huge_shapes():
    """[D-3] [D-4] [N-12] [N-7] sample_delays bounds its shape (at most 2^31 - 1 draws): a huge shape raises
    ValueError naming shape rather than a TypeError from JAX."""
    key = jax.random.PRNGKey(0)
    for shape in ((10**30,), (2**31,), (2**16, 2**16), (-1,), (2.0,)):
        _raises(lambda: JD.sample_delays(key, [1.0], 0, shape), "shape")
    d = JD.sample_delays(key, [0.5, 0.5], 1, (3,))
    assert d.shape == (3,) and set(np.asarray(d).tolist()) <= {1, 2}
    assert JD.sample_delays(key, [1.0], 0, (0,)).shape == (0,)


def test_executor_rejects_boolean_delays_and_unordered_collections():
    """[X-5] [X-1] [N-7] A boolean among the delays (which np.asarray reads as 1) is a ValueError naming its
    entry, in every executor function; a dict or set of delays names delays. The same integers run."""
    from softrtc.jax import executor as JX

    chunks = np.arange(3 * 8, dtype=np.float32).reshape(3, 8, 1)
    for bad, name in (([0, True, 1], r"^delays\[1\] must be an integer in \[0, 4\], got True$"),
                      ((0, 1, np.bool_(True)), r"^delays\[2\] must be an integer in \[0, 4\], got "),
                      ({0: 1, 1: 2, 2: 3}, r"^delays must be a non-empty 1-D integer array .*got dict$"),
                      ({0, 1, 2}, r"^delays must be a non-empty 1-D integer array .*got set$")):
        with pytest.raises(ValueError, match=name):
            JX.check_delays(8, 4, bad)
        with pytest.raises(ValueError, match=name):
            JX.execute_chunks(chunks, bad, 4)
        with pytest.raises(ValueError, match=name):
            JX.closed_loop(lambda o, p, d, c: jnp.zeros((8, 1)), lambda st, a: (st, jnp.zeros(2)), jnp.zeros(1),
                           jnp.zeros(2), bad, 8, 4)
    ci = np.asarray(JX.execute_chunks(chunks, [0, 1, 1], 4)["chunk_index"]).tolist()
    assert ci == [0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2]


def test_ranges_are_checked_before_float32_rounding():
    """[C-1] [D-3] [N-10] [N-7] tau = 1 + 1e-9 rounds to 1.0 in float32 but is out of [0, 1]: rejected, as in the
    reference. u = 1 - 1e-12 is a valid draw that float32 rounds to 1.0: accepted, and it draws the table's last
    delay (the reference's answer), never one past the table; u = 1 is rejected."""
    assert np.float32(1.000000001) == 1.0 and np.float32(1 - 1e-12) == 1.0  # the premise
    for tau in (1.000000001, np.array([0.5, 1.000000001]), -1e-12):
        with pytest.raises(ValueError, match=r"^tau values must lie in \[0\.0, 1\.0\]"):
            JC.token_times(np.zeros(2), tau)
        with pytest.raises(ValueError, match=r"^tau .*\[0\.0, 1\.0\]"):
            R.corruption.token_times(np.zeros(2), tau if np.ndim(tau) == 0 else 1.000000001)
    probs = np.full(4, 0.25)
    for u in (1 - 1e-12, np.nextafter(1.0, 0.0), 0.9999999):
        assert int(JD.sample_delay(probs, 2, u)) == R.delays.sample_delay(probs, 2, u) == 5
    np.testing.assert_array_equal(JD.sample_delay(probs, 2, np.array([0.0, 0.25, 0.5, 1 - 1e-12])), [2, 3, 4, 5])
    for u in (1.0, np.array([0.5, 1.0]), -1e-12):
        with pytest.raises(ValueError, match=r"^u values must lie in \[0\.0, 1\.0\)"):
            JD.sample_delay(probs, 2, u)


def test_sampler_shapes_named_by_the_samplers_arguments():
    """[S-2] [S-3] [G-2] [N-7] noise or obs that does not fit the model's declared sizes is named as noise or
    obs by every sampler (straightforward and conditioned), not as the model's internal x."""
    cases = {
        "naive": lambda o, n: JS.naive_sample(F, o, n, 2),
        "rtc": lambda o, n: JS.rtc_sample(F, o, n, n, jnp.zeros(n.shape[1]), 2),
        "guided": lambda o, n: JG.guided_sample(F, o, n, n, jnp.zeros(n.shape[1]), 2),
        "naive_conditioned": lambda o, n: JS.naive_sample_conditioned(F, o, n, 2),
        "rtc_conditioned": lambda o, n: JS.rtc_sample_conditioned(F, o, n, n, jnp.zeros(n.shape[1]), 2),
        "guided_conditioned": lambda o, n: JG.guided_sample_conditioned(F, o, n, n, jnp.zeros(n.shape[1]), 2),
    }
    for name, call in cases.items():
        with pytest.raises(ValueError, match=rf"^noise must have the model's shape \[B, H={H}, A={A}\], "
                                             rf"got \[{B}, {H}, 3\]$"):
            call(OBS, jnp.ones((B, H, 3)))
        with pytest.raises(ValueError, match=rf"^noise must have the model's shape .*got \[{B}, 6, {A}\]$"):
            call(OBS, jnp.ones((B, 6, A)))
        with pytest.raises(ValueError, match=rf"^obs must have the model's shape \[B, O={O}\], got \[{B}, 5\]$"):
            call(jnp.zeros((B, 5)), X)
        assert call(OBS, X).shape == (B, H, A), name


def test_metrics_name_ragged_arguments():
    """[M-1] [M-3] [M-5] [M-6] [N-7] Ragged lists given to the JAX metrics name the argument (actions,
    chunk_index, values, indices), as the reference does, instead of NumPy's inhomogeneous-shape message."""
    from softrtc.jax import metrics as JMt

    cases = [(lambda: JMt.action_delta([[0.0, 1.0], [1.0]]), r"^actions must be a numeric array, got a ragged"),
             (lambda: JMt.boundary_jump(np.zeros((3, 2)), [[0], [1, 2]]),
              r"^chunk_index must be an integer array, got a ragged or non-numeric list$"),
             (lambda: JMt.standard_error([[1.0], [2.0, 3.0]]), r"^values must be a numeric array, got a ragged"),
             (lambda: JMt.bootstrap_interval_from_indices([1.0, 2.0], [[0, 1], [1]]),
              r"^indices must be an integer array, got a ragged or non-numeric list$")]
    for call, match in cases:
        with pytest.raises(ValueError, match=match):
            call()
    assert float(JMt.action_delta([[0.0, 0.0], [3.0, 4.0]])) == 5.0


def test_overflow_of_concrete_results_is_an_error():
    """[N-15] [N-10] Finite float32 inputs whose loss or metric overflows float32 raise ValueError naming the
    input when called with concrete arrays; under jit the same call is not inspected and gives inf."""
    from softrtc.jax import metrics as JMt

    big = 1e30  # finite in float32 (limit about 3.4e38); its square, 1e60, is not
    z = np.zeros((2, 1), np.float32)
    cases = [("pred", lambda: JL.token_errors(np.full((2, 1), big, np.float32), z, z)),
             ("pred", lambda: JL.flow_matching_loss(np.full((2, 1), big, np.float32), z, z, np.zeros(2))),
             ("preds", lambda: JL.batch_loss(np.full((1, 2, 1), big, np.float32), z[None], z[None], np.zeros((1, 2)))),
             ("actions", lambda: JMt.action_delta(np.array([[3e38], [-3e38]], np.float32))),
             # Two action dimensions: XLA may fold sqrt(x * x) of a single one into |x|, which cannot overflow.
             ("actions", lambda: JMt.action_jerk(np.array([[0.0, 0.0], [big, big], [0.0, 0.0]], np.float32))),
             ("actions", lambda: JMt.boundary_jump(np.array([[big, big], [-big, -big]], np.float32),
                                                   np.array([0, 1]))),
             ("values", lambda: JMt.standard_error(np.array([big, -big], np.float32))),
             ("values", lambda: JMt.bootstrap_interval(np.array([3e38, 3e38], np.float32), 4, 0))]
    for name, call in cases:
        with pytest.raises(ValueError, match=rf"^{name} is too large in magnitude: .* overflows float32"):
            call()
    assert np.isinf(jax.jit(JL.token_errors)(np.full((2, 1), big, np.float32), z, z)).all()
    # 2^60 squared is 2^120, exact in float32.
    assert JL.token_errors(np.full((2, 1), 2.0**60, np.float32), z, z).tolist() == [2.0**120, 2.0**120]
    assert float(JMt.action_delta(np.array([[2.0**60], [-(2.0**60)]], np.float32))) == 2.0**61
