"""One compiled JAX function serves every delay and every soft-window parameter.

Each test counts traces with a Python side effect inside the traced function
(it runs only while tracing) and checks the jit cache size, then calls the
function with d = 0..4 and several window parameters (lam, h_max, L, h).
"""

import jax
import jax.numpy as jnp
import numpy as np

from softrtc import reference as R
from softrtc.jax import endpoints as JE
from softrtc.jax import executor as JX
from softrtc.jax import methods as JM
from softrtc.jax import velocity as JF
from softrtc.jax import weights as JW

H, A, O, B, S = 8, 2, 3, 2, 4
RF = R.velocity.ReferenceVelocityField.init(3, H, A, O, hidden=16)
FIELD = JF.ReferenceVelocityField(RF.params)


def counted(fn, **jit_kw):
    count = {"n": 0}

    def traced(*args, **kw):
        count["n"] += 1
        return fn(*args, **kw)

    return jax.jit(traced, **jit_kw), count


def test_soft_weights_one_compilation_per_rule_kind():
    """W-7, E-2, E-3, E-4, D-4: soft weights for every d and every lam / h_max / L / h
    compile once per (rule kind, schedule, parametrization, overflow)."""
    f, count = counted(lambda d, window: JW.soft_weights(H, d, window, S))
    windows = {
        "delay_scaled": [JW.SoftWindow(JE.delay_scaled(lam, hm)) for lam, hm in [(2.0, 5), (1.0, 8), (0.5, 3), (3.25, 7)]],
        "offset": [JW.SoftWindow(JE.offset(L, hm)) for L, hm in [(0, 8), (1, 6), (3, 8)]],
        "fixed": [JW.SoftWindow(JE.fixed(h)) for h in (0, 3, 6)],
    }
    for kind, ws in windows.items():
        before_n, before_cache = count["n"], f._cache_size()
        for w in ws:
            for d in range(5):
                got = f(jnp.int32(d), w)
                ref_w = R.SoftWindow(R.endpoints.EndpointRule(kind, **_ref_params(w.rule)))
                np.testing.assert_allclose(got, R.soft_weights(H, d, ref_w, S), atol=1e-6)
        assert count["n"] - before_n == 1, kind
        assert f._cache_size() - before_cache == 1, kind


def _ref_params(rule):
    if rule.kind == "delay_scaled":
        return {"lam": float(rule.lam), "h_max": int(rule.h_max)}
    if rule.kind == "offset":
        return {"length": int(rule.length), "h_max": int(rule.h_max)}
    return {"length": int(rule.length)}


def test_rtc_sampler_one_compilation_for_all_delays():
    """S-3, S-4, W-7: one compiled training-time RTC chunk generator for every delay and window."""
    gen, count = counted(lambda field, obs, noise, prior, d, window:
                         JM.generate_chunk("train_soft", field, obs, noise, prior, S, d, 5, window))
    rng = np.random.default_rng(0)
    obs, noise, prior = rng.standard_normal((B, O)), rng.standard_normal((B, H, A)), rng.standard_normal((B, H, A))
    for lam, hm in [(2.0, 5), (1.0, 4), (1.5, 8)]:
        win = JW.SoftWindow(JE.delay_scaled(lam, hm))
        for d in range(5):
            got = gen(FIELD, obs, noise, prior, jnp.int32(d), win)
            w = R.soft_weights(H, d, R.SoftWindow(R.delay_scaled(lam, hm)), S)
            want = np.stack([R.sampler.rtc_sample(RF, obs[i], noise[i], prior[i], w, 5) for i in range(B)])
            np.testing.assert_allclose(got, want, atol=1e-4, rtol=1e-4)
    assert count["n"] == 1 and gen._cache_size() == 1


def test_guided_and_table_paths_one_compilation():
    """G-1, S-6, S-3: guided and table-driven conditioned generators compile once for d = 0..4
    (scalar delays) and once more for per-example delays [B]."""
    rng = np.random.default_rng(1)
    obs, noise, prior = rng.standard_normal((B, O)), rng.standard_normal((B, H, A)), rng.standard_normal((B, H, A))
    for method in ("inference_soft", "train_soft"):
        tables = JM.method_tables(method, FIELD, H, S, 5)
        gen, count = counted(lambda field, tables, obs, noise, prior, d:
                             JM.generate_chunk_conditioned(method, field, obs, noise, prior, S, d, 5, tables=tables))
        for d in range(5):
            gen(FIELD, tables, obs, noise, prior, jnp.int32(d))
        assert count["n"] == 1 and gen._cache_size() == 1, method
        for ds in ([0, 4], [1, 2], [3, 3]):
            gen(FIELD, tables, obs, noise, prior, jnp.asarray(ds, jnp.int32))
        assert count["n"] == 2 and gen._cache_size() == 2, method


def test_executor_one_compilation_for_all_delay_sequences():
    """X-4, X-5: execute_chunks compiles once for every delay sequence of a given C, H, s."""
    f, count = counted(lambda chunks, delays: JX.execute_chunks(chunks, delays, S))
    chunks = np.random.default_rng(2).standard_normal((5, H, A))
    for ds in ([0, 0, 0, 0, 0], [0, 1, 2, 3, 4], [0, 4, 4, 1, 0], [0, 2, 2, 2, 2]):
        got = f(chunks, jnp.asarray(ds, jnp.int32))
        np.testing.assert_allclose(got["actions"], R.executor.execute_chunks(chunks, ds, S)["actions"], atol=1e-6)
    assert count["n"] == 1 and f._cache_size() == 1


def test_vmap_over_delays_and_windows():
    """W-7, E-2, D-4: soft weights vmap over delays and window parameters (one trace)."""
    f, count = counted(jax.vmap(lambda d, lam: JW.soft_weights(H, d, JW.SoftWindow(JE.delay_scaled(lam, 6)), S)))
    ds = jnp.arange(5, dtype=jnp.int32)
    for lams in ([2.0] * 5, [0.25, 0.5, 1.0, 1.5, 4.0]):
        got = f(ds, jnp.asarray(lams, jnp.float32))
        for i in range(5):
            want = R.soft_weights(H, i, R.SoftWindow(R.delay_scaled(lams[i], 6)), S)
            np.testing.assert_allclose(got[i], want, atol=1e-6)
    assert count["n"] == 1


def test_weight_table_compiles_once_per_horizon_for_every_variant():
    """W-7, W-3, W-4, W-5, W-6, E-1: the eager weight_table / prefix_weights entry points compile
    once per horizon H, whatever the rule kind, schedule, parametrization, overflow and s."""
    rules = [(JE.delay_scaled(2.0, 5), R.endpoints.delay_scaled(2.0, 5)), (JE.offset(1, 6), R.endpoints.offset(1, 6)),
             (JE.fixed(3), R.endpoints.fixed(3)), (JE.hard(), R.endpoints.hard())]
    before_table, before_prefix = JW._weight_table._cache_size(), JW._prefix_jit._cache_size()
    for jr, rr in rules:
        for sched in JW.SCHEDULES:
            for par in JW.PARAMETRIZATIONS:
                for ov in JW.OVERFLOWS:
                    for s in (2, 4):
                        got = JW.weight_table(H, JW.SoftWindow(jr, sched, par, ov), s)
                        want = np.stack([R.soft_weights(H, d, R.SoftWindow(rr, sched, par, ov), s)
                                         for d in range(H + 1)])
                        np.testing.assert_allclose(got, want, atol=1e-6)
                    e = min(H, 6)
                    np.testing.assert_allclose(JW.prefix_weights(H, 2, e, sched, par),
                                               R.prefix_weights(H, 2, e, sched, par), atol=1e-6)
    # Other tests may already have compiled H = 8; either way at most one new entry each.
    assert JW._weight_table._cache_size() - before_table <= 1
    assert JW._prefix_jit._cache_size() - before_prefix <= 1
    JW.weight_table(H + 1, JW.SoftWindow(), S)
    assert JW._weight_table._cache_size() - before_table <= 2
