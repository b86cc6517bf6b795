"""Validation of the JAX policy, training, checkpoint, metrics, executor and benchmark entry points ([N-7]).

Every invalid call raises ``ValueError`` naming the argument; every test also
makes one valid call, so a check that rejects everything would fail here.
Sizes are tiny so that the few compilations stay fast.
"""

from __future__ import annotations

import dataclasses
import json
import os

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

from softrtc.jax import bench, bench_report, bench_vjp, checkpoint, executor, metrics  # noqa: E402
from softrtc.jax.mixer import MLPMixerBlock, sincos_time_embedding  # noqa: E402
from softrtc.jax.params import load_pure_dict, state_pure_dict  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.jax.vjp import gelu, layer_norm  # noqa: E402
from softrtc.jax.training import TrainConfig, make_train_step  # noqa: E402

# One tiny architecture for every test (the benchmark's "tiny" one), so that its eager initialisation and
# compilations are paid once.
BENCH = bench.BenchConfig(arch="tiny", calls=1, warmup=1, batch_sizes=(1,), num_steps=1, delay=0)
TINY: PolicyConfig = bench.ARCHS["tiny"]["config"]
OBS, ACT = bench.ARCHS["tiny"]["obs_dim"], bench.ARCHS["tiny"]["action_dim"]
H, C = TINY.action_chunk_size, TINY.channel_dim


def _random_policy(seed: int) -> FlowPolicy:
    """A tiny policy with NumPy noise as parameters (adaLN included, so time matters), built without running
    the eager initialisers (each would compile on its own)."""
    model = nnx.eval_shape(lambda: FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(seed)))
    rng = np.random.default_rng(seed)
    nnx.update(model, jax.tree.map(lambda a: jnp.asarray(0.2 * rng.standard_normal(a.shape), a.dtype),
                                   nnx.state(model)))
    return model


@pytest.fixture(scope="module")
def pol():
    return _random_policy(0)


def _raises(name: str, fn):
    """``fn()`` raises ValueError whose message names ``name``."""
    with pytest.raises(ValueError) as info:
        fn()
    assert name in str(info.value), f"message does not name {name!r}: {info.value}"
    return info.value


# ----------------------------------------------------------------------------- policy (P)


def test_conditioning_leaves_need_a_real_float_dtype_and_finite_values(pol):
    """N-7, P-12, P-15, P-18: a cond leaf that is complex, boolean or integer is rejected (not cast, not
    reduced to its real part), and a concrete NaN leaf too, in apply_conditioned and its split form; under
    jit the dtype is still checked; a valid cond still gives the velocity."""
    # NumPy inputs and jitted valid calls: eager JAX would compile every primitive on its own.
    obs, x = np.zeros((1, OBS), np.float32), np.zeros((1, H, ACT), np.float32)
    cond = jax.tree.map(np.asarray, jax.jit(pol.time_conditioning)(np.full((1, H), 0.5, np.float32)))
    fin = cond["final_adaln"]
    for bad in (fin + 1j, fin > 0, fin.astype(np.int32), fin * np.nan):
        c = dict(cond, final_adaln=bad)
        _raises("cond['final_adaln']", lambda: pol.apply_conditioned(obs, x, c))
        _raises("cond['final_adaln']", lambda: pol.apply_conditioned_split(obs, x, c, 2))
    layer = dict(cond["mlp_stack"][0], adaln_1=cond["mlp_stack"][0]["adaln_1"] + 1j)
    _raises("cond['mlp_stack'][0]['adaln_1']",
            lambda: pol.apply_conditioned(obs, x, dict(cond, mlp_stack=(layer,))))
    _raises("cond['final_adaln']", lambda: jax.jit(lambda c: pol.apply_conditioned(obs, x, c))(
        dict(cond, final_adaln=fin + 1j)))
    # Valid: the concrete cond (checked for finiteness while tracing) gives the velocity and its two token groups.
    v, (head, tail) = jax.jit(lambda: (pol.apply_conditioned(obs, x, cond),
                                       pol.apply_conditioned_split(obs, x, cond, 2)))()
    assert v.shape == (1, H, ACT) and v.dtype == jnp.float32
    assert head.shape == (1, 2, ACT) and tail.shape == (1, H - 2, ACT)
    np.testing.assert_allclose(np.concatenate([head, tail], axis=1), v, rtol=1e-4, atol=1e-4)


def test_load_pure_dict_checks_finiteness_after_the_cast(pol):
    """P-8, N-7: a float64 leaf that is finite but beyond float32 (1e39) would become inf in the policy;
    it is rejected naming its key path, and the policy keeps its parameters; a float64 leaf in range loads."""
    target = _random_policy(1)
    before = np.asarray(target.out_proj.bias[...])
    pure = jax.tree.map(lambda a: np.asarray(a, np.float64), state_pure_dict(pol))
    pure["out_proj"]["bias"] = np.full(pure["out_proj"]["bias"].shape, 1e39)
    _raises("out_proj/bias", lambda: load_pure_dict(target, pure))
    np.testing.assert_array_equal(np.asarray(target.out_proj.bias[...]), before)
    pure["out_proj"]["bias"] = np.full(pure["out_proj"]["bias"].shape, 0.25)
    load_pure_dict(target, pure)
    assert target.out_proj.bias[...].dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(target.out_proj.bias[...]), 0.25)


def test_mixer_block_rngs_and_public_halves_are_validated(pol):
    """P-4, P-15, P-18, N-7, N-12: MLPMixerBlock needs an nnx.Rngs; token_mixing, channel_mixing and modulation
    reject None, scalars, a wrong last axis, an extra leading axis, empty axes, complex modulations and
    concrete NaN with ValueError naming the argument, also while tracing (dtype and shape); valid calls work."""
    _raises("rngs", lambda: MLPMixerBlock(4, 4, 8, 8, rngs=None))
    block = pol.mlp_stack[0]
    z = lambda *shape: np.zeros(shape, np.float32)  # noqa: E731 - NumPy: no compilation per shape
    x, m = z(2, H, C), z(1, H, 3 * C)
    for bad_x in (None, np.float32(1.0), z(1, 2, H, C), z(2, H, C + 1), z(0, H, C), np.full((2, H, C), np.nan),
                  np.zeros((2, H, C), np.int32)):
        _raises("x", lambda: block.token_mixing(bad_x, m))
        _raises("x", lambda: block.channel_mixing(bad_x, m))
    _raises("x", lambda: block.token_mixing(z(2, H - 1, C), m))  # token mixing needs all H tokens
    for bad_m in (None, np.float32(1.0), z(1, H, 3 * C + 1), z(3, H, 3 * C), z(1, 1, H, 3 * C), m + 1j,
                  np.full((1, H, 3 * C), np.inf)):
        _raises("m1", lambda: block.token_mixing(x, bad_m))
        _raises("m2", lambda: block.channel_mixing(x, bad_m))
    _raises("pullback", lambda: block.token_mixing(x, m, {"token_mix_in": z(1, 1)}))
    for bad_f in (None, np.float32(1.0), z(3, C + 1), z(0, C), np.full((3, C), np.nan)):
        _raises("time_features", lambda: block.modulation(bad_f))
    _raises("m1", lambda: jax.jit(lambda m: block.token_mixing(x, m))(m + 1j))
    _raises("x", lambda: jax.jit(lambda x: block.channel_mixing(x, m))(z(1, 2, H, C)))
    # Valid: full and shared modulations, a subset of tokens for channel mixing with the stored transposes,
    # the modulation itself and the whole block; concrete inputs, checked while tracing.
    pb = pol.pullback_kernels()["mlp_stack"][0]
    out = jax.jit(lambda: (block.token_mixing(x, m), block.token_mixing(x, z(H, 3 * C)),
                           block.channel_mixing(z(2, 1, C), z(2, 1, 3 * C), pb), block.modulation(z(5, C)),
                           block(x, m, m)))()
    assert [o.shape for o in out[:3]] == [(2, H, C), (2, H, C), (2, 1, C)]
    assert out[3]["adaln_1"].shape == (5, 3 * C) and out[3]["adaln_2"].shape == (5, 3 * C)
    assert out[4].shape == (2, H, C)


def test_gelu_and_layer_norm_check_shape_and_dtype(pol):
    """P-15, P-17, P-20, N-12: gelu and layer_norm reject non-arrays, non-float dtypes and empty axes by name
    (shape and dtype only: nothing is added to a compiled graph); valid inputs give the modules' values."""
    for bad in (None, "abc", np.zeros((0, C)), np.zeros((2, C), np.complex64), np.zeros((2, C), bool)):
        _raises("x", lambda: gelu(bad))
        _raises("x", lambda: layer_norm(pol.final_norm, bad))
    _raises("x", lambda: layer_norm(pol.final_norm, np.zeros((2, C + 1), np.float32)))
    _raises("norm", lambda: layer_norm(None, np.zeros((2, C), np.float32)))
    _raises("x", lambda: jax.jit(gelu)(np.zeros((2, C), np.complex64)))
    y = np.linspace(-1.0, 1.0, 2 * C, dtype=np.float32).reshape(2, C)
    got = jax.jit(lambda y: (gelu(y), layer_norm(pol.final_norm, y), nnx.gelu(y), pol.final_norm(y)))(y)
    np.testing.assert_array_equal(np.asarray(got[0]), np.asarray(got[2]))
    np.testing.assert_array_equal(np.asarray(got[1]), np.asarray(got[3]))


def test_time_inputs_reject_empty_axes_and_huge_embedding_dims(pol):
    """P-3, P-11, P-15, N-12: time_conditioning and sincos_time_embedding reject t with an empty axis;
    sincos_time_embedding rejects an embedding_dim beyond its bound (10**30) by name; valid calls work."""
    _raises("t", lambda: pol.time_conditioning(np.zeros((0, H))))
    _raises("t", lambda: sincos_time_embedding(np.zeros((0, H)), C))
    _raises("t", lambda: sincos_time_embedding(np.zeros((2, 0)), C))
    for bad in (10**30, 0, 7, 2.0, True, None):
        _raises("embedding_dim", lambda: sincos_time_embedding(0.5, bad))
    one, many, cond = jax.jit(lambda: (sincos_time_embedding(0.5, 2), sincos_time_embedding(np.zeros((2, 3)), C),
                                       pol.time_conditioning(np.full((3, 1), 0.25, np.float32))))()
    assert one.shape == (2,) and many.shape == (2, 3, C)
    assert cond["final_adaln"].shape == (3, 1, 2 * C)


# ----------------------------------------------------------------------------- training and checkpoints (T)


def test_train_step_checks_the_optimiser_state(pol):
    """T-10, T-7, N-7: a TrainState whose opt_state is None, or the optimiser state of another architecture,
    is rejected naming state.opt_state before the jitted update runs; a state from init_state still steps."""
    step = make_train_step(pol, TrainConfig(method="hard", batch_size=2, d_max=2, execute_horizon=2))
    state = step.init_state()
    batch = (jnp.zeros((2, OBS)), jnp.zeros((2, H, ACT)))
    key = jax.random.key(0)
    _raises("state.opt_state", lambda: step(dataclasses.replace(state, opt_state=None), batch, key))
    # The Adam moments live on the flattened parameter vector: one entry fewer is a smaller architecture's
    # state (it used to fail inside the update with "add got incompatible shapes").
    smaller = jax.tree.map(lambda a: a[:-1] if jnp.ndim(a) == 1 else a, state.opt_state)
    _raises("state.opt_state", lambda: step(dataclasses.replace(state, opt_state=smaller), batch, key))
    _raises("state.opt_state", lambda: step.policy(dataclasses.replace(state, opt_state=(1, 2))))
    new, met = step(state, batch, key)
    assert int(new.step) == 1 and np.isfinite(float(met["loss"]))
    new, _ = step(jax.device_get(new), batch, key)  # host copies of a valid state are valid
    assert int(new.step) == 2


def test_checkpoint_checksum_rejects_nested_non_string_keys(tmp_path, pol):
    """T-11, N-7: a header with a nested non-string key is rejected (not hashed as its JSON string form);
    string keys hash, and a saved checkpoint still loads."""
    _raises("header", lambda: checkpoint.checkpoint_checksum({"m": {1: 2}}, {}))
    _raises("header", lambda: checkpoint.checkpoint_checksum({"m": [{1: 2}]}, {}))
    assert checkpoint.checkpoint_checksum({"m": {"1": 2}}, {}).startswith("sha256:")
    path = tmp_path / "p.npz"
    checkpoint.save_checkpoint(path, pol, {"a": {"b": 1}})
    restored, meta = checkpoint.load_checkpoint(path, pol)  # the same values, loaded back in place
    assert meta == {"a": {"b": 1}} and restored is pol


# ----------------------------------------------------------------------------- metrics (M)


def test_metrics_reject_empty_out_of_range_and_non_numeric_inputs():
    """M-3, M-4, M-5, M-7, N-7, N-10, N-12: switch_mask and is_high_delay reject empty input; is_high_delay
    bounds concrete delays to [0, 4096]; boundary_jump names chunk_index for strings and None; solve_rate
    names solved for strings and objects; the bootstrap needs B >= 1 resamples; valid calls work."""
    _raises("chunk_index", lambda: metrics.switch_mask(np.zeros(0, int)))
    np.testing.assert_array_equal(np.asarray(metrics.switch_mask(np.array([0, 0, 1]))), [False, False, True])
    _raises("d", lambda: metrics.is_high_delay(5000))
    _raises("d", lambda: metrics.is_high_delay(-1))
    _raises("d", lambda: metrics.is_high_delay(np.zeros(0, int)))
    np.testing.assert_array_equal(np.asarray(metrics.is_high_delay(np.array([3, 4096, 0]))), [True, False, False])
    assert bool(jax.jit(metrics.is_high_delay)(jnp.int32(4)))
    actions = np.arange(6.0).reshape(3, 2)
    for bad in ("abc", None, np.array([0.0, 0.0, 1.0]), [0, 1]):
        _raises("chunk_index", lambda: metrics.boundary_jump(actions, bad))
    assert float(metrics.boundary_jump(actions, [0, 0, 1])) == pytest.approx(np.sqrt(8.0))
    for bad in (["a", "b"], np.array([None, True], dtype=object), [[True], [True, False]], [], [1, 0]):
        _raises("solved", lambda: metrics.solve_rate(bad))
    assert float(metrics.solve_rate([True, False])) == 0.5
    _raises("indices", lambda: metrics.bootstrap_interval_from_indices(np.ones(4), np.zeros((0, 4), int)))
    lo, hi = metrics.bootstrap_interval_from_indices(np.arange(4.0), np.array([[0, 1, 2, 3], [0, 0, 0, 0]]))
    assert float(lo) <= float(hi)


# ----------------------------------------------------------------------------- executor (X)


def test_closed_loop_checks_observations_chunks_and_obs0():
    """X-6, X-2, N-7, N-10: closed_loop rejects, naming the function, an env_step observation of another
    shape, a non-pair return or a state of another shape, a complex or re-shaped chunk from generate (not
    reduced to its real part), and a complex or empty obs0; a valid loop runs, eagerly and under jit."""
    Hc, s, delays = 8, 4, [0, 1, 2]

    def gen(obs, prior, d, c):
        return jnp.ones((Hc, 2)) * obs[0]

    def env(state, a):
        state = 0.9 * state + a[:1]
        return state, state

    z = jnp.zeros(1)
    _raises("env_step", lambda: executor.closed_loop(gen, lambda st, a: (st, jnp.zeros(2)), z, z, delays, Hc, s))
    _raises("env_step", lambda: executor.closed_loop(gen, lambda st, a: st, z, z, delays, Hc, s))
    _raises("env_step", lambda: executor.closed_loop(gen, lambda st, a: (jnp.zeros(3), st), z, z, delays, Hc, s))
    _raises("env_step", lambda: executor.closed_loop(gen, lambda st, a: (st, st > 0), z, z, delays, Hc, s))
    _raises("generate", lambda: executor.closed_loop(lambda *a: jnp.ones((Hc, 2)) + 1j, env, z, z, delays, Hc, s))
    later_complex = lambda o, p, d, c: jnp.ones((Hc, 2)) if p is None else jnp.ones((Hc, 2)) + 1j  # noqa: E731
    _raises("generate", lambda: executor.closed_loop(later_complex, env, z, z, delays, Hc, s))
    other_a = lambda o, p, d, c: jnp.ones((Hc, 2)) if p is None else jnp.ones((Hc, 3))  # noqa: E731
    _raises("generate", lambda: executor.closed_loop(other_a, env, z, z, delays, Hc, s))
    _raises("obs0", lambda: executor.closed_loop(gen, env, z, z + 1j, delays, Hc, s))
    _raises("obs0", lambda: executor.closed_loop(gen, env, z, jnp.zeros(0), delays, Hc, s))
    _raises("obs0", lambda: jax.jit(lambda o: executor.closed_loop(gen, env, z, o, delays, Hc, s))(z + 1j))
    out = executor.closed_loop(gen, env, z, z, delays, Hc, s)
    assert out["actions"].shape == (len(delays) * s, 2) and out["request_obs"].shape == (len(delays), 1)
    jitted = jax.jit(lambda ds: executor.closed_loop(gen, env, z, z, ds, Hc, s))(jnp.asarray(delays, jnp.int32))
    np.testing.assert_allclose(np.asarray(jitted["actions"]), np.asarray(out["actions"]))


# ----------------------------------------------------------------------------- benchmark (B)


def test_write_json_is_strict_atomic_and_refuses_directories(tmp_path):
    """B-10, N-7: write_json writes strict JSON (NumPy scalars as numbers, NaN and inf as null), refuses a
    directory by naming path, and a value JSON cannot hold raises ValueError naming it before the file is
    touched (an existing file stays whole, no temporary file is left)."""
    path = tmp_path / "out" / "bench.json"
    res = {"chunk": {"1": {"x": np.float32(1.5), "n": np.int64(3), "ok": np.bool_(True)}},
           "bad": [float("nan"), np.float32(np.inf)], "t": (1, 2)}
    bench_report.write_json(res, path)
    text = path.read_text()
    assert "NaN" not in text and "Infinity" not in text
    loaded = json.loads(text)
    assert loaded == {"chunk": {"1": {"x": 1.5, "n": 3, "ok": True}}, "bad": [None, None], "t": [1, 2]}
    bench_report.write_json({"chunk": {}, "z": np.float32(1)}, path)
    assert json.loads(path.read_text()) == {"chunk": {}, "z": 1.0}
    _raises("path", lambda: bench_report.write_json({"chunk": {}}, tmp_path))
    _raises("res['z']", lambda: bench_report.write_json({"chunk": {}, "z": object()}, path))
    _raises("res['chunk']", lambda: bench_report.write_json({"chunk": {1: 2}}, path))
    assert json.loads(path.read_text()) == {"chunk": {}, "z": 1.0}
    assert os.listdir(path.parent) == ["bench.json"]


def test_bench_rows_names_policy_and_tables_are_validated(pol):
    """B-1, B-2, B-5, B-10, B-12, N-7: build_rows and check_agreement name policy when its horizon is not
    the config's and names when it is not a non-empty sequence of row names; format_table and
    format_vjp_table name the key a partial result lacks; valid calls work."""
    config, policy = BENCH, pol
    # A policy of another horizon: its shapes are enough, nnx.eval_shape builds no arrays.
    short = nnx.eval_shape(lambda: FlowPolicy(obs_dim=OBS, action_dim=ACT, rngs=nnx.Rngs(0),
                                              config=dataclasses.replace(TINY, action_chunk_size=4)))
    _raises("policy", lambda: bench.check_agreement(config, short, 1, ("naive",)))
    _raises("policy", lambda: bench.build_rows(config, short))
    for bad in (3, "naive", (), ("naive", "naive"), ("fast",)):
        _raises("names", lambda: bench.build_rows(config, policy, names=bad))
        _raises("names", lambda: bench.check_agreement(config, policy, 1, bad))
    rows = bench.build_rows(config, policy, names=["naive"])
    assert [(r.name, r.path) for r in rows] == [("naive", "fast"), ("naive", "straightforward")]
    agree = bench.check_agreement(config, policy, 1, ("naive",))
    assert agree["naive"]["ok"]
    e = _raises("rows", lambda: bench_report.format_table({"chunk": {}, "config": {}}))
    assert "run_benchmark" in str(e)
    partial = {k: {} for k in ("config", "architecture", "environment", "chunk", "agreement", "seconds")}
    _raises("'delay'", lambda: bench_report.format_table(dict(partial, rows=[], targets=[])))
    _raises("variants", lambda: bench_vjp.format_vjp_table({"chunk": {}}))
    _raises("'arch'", lambda: bench_vjp.format_vjp_table(
        {k: {} for k in ("config", "environment", "variants", "chunk", "agreement", "restricted_pullback",
                         "seconds")}))
    full = {"config": dataclasses.asdict(config), "environment": {"backend": "cpu", "cpu_count": 2, "jax": "x"},
            "architecture": {"obs_dim": 7, "action_dim": 3, "action_chunk_size": 8}, "rows": [], "chunk": {},
            "agreement": {}, "targets": [], "seconds": 1.0}
    assert "softrtc bench runtime" in bench_report.format_table(full)


def test_policy_sizes_are_bounded():
    """P-1, N-12: every PolicyConfig size and FlowPolicy's input sizes have an upper bound, checked before any
    parameter is allocated: a typo such as 10**9 layers is a ValueError naming the field, not an exhausted
    memory; the bounds themselves are accepted."""
    from softrtc.jax.policy import ACTION_DIM_MAX, CONFIG_MAX, OBS_DIM_MAX

    for name, hi in CONFIG_MAX.items():
        _raises(name, lambda: PolicyConfig(**{name: hi + (2 if name == "channel_dim" else 1)}))
        assert getattr(PolicyConfig(**{name: hi}), name) == hi
    assert CONFIG_MAX["action_chunk_size"] == 4096
    for name, hi in (("obs_dim", OBS_DIM_MAX), ("action_dim", ACTION_DIM_MAX)):
        kw = {"obs_dim": OBS, "action_dim": ACT, name: hi + 1}
        _raises(name, lambda: FlowPolicy(**kw, config=TINY, rngs=nnx.Rngs(0)))
    # The bounds are those of the reference field ([F-3]).
    assert (OBS_DIM_MAX, ACTION_DIM_MAX) == (1 << 20, 4096)
