"""Tests of the JAX flow policy (spec/30-policy.md, chapter P)."""

from __future__ import annotations

import math
import pickle
import warnings

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
import jax.numpy as jnp  # noqa: E402

from softrtc.jax.mixer import MAX_PERIOD, MIN_PERIOD, MLPMixerBlock, sincos_time_embedding  # noqa: E402
from softrtc.jax.params import load_checkpoint, load_pure_dict, state_pure_dict  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402

TINY = PolicyConfig(channel_dim=16, channel_hidden_dim=24, token_hidden_dim=6, num_layers=2, action_chunk_size=5)
OBS, ACT, H = 7, 3, TINY.action_chunk_size
# [P-14] float32 agreement between differently shaped (hence differently compiled) evaluations.
RTOL = ATOL = 1e-4


def _randomize(model: FlowPolicy, seed: int, scale: float = 0.2) -> FlowPolicy:
    """Replaces every parameter by noise so that adaLN (zero at init) actually depends on time."""
    rng = np.random.default_rng(seed)  # NumPy noise: no per-shape XLA compilation in the tests
    state = nnx.state(model)
    new = jax.tree.map(lambda a: jnp.asarray(scale * rng.standard_normal(a.shape), a.dtype), state)
    nnx.update(model, new)
    return model


# Jitted entry points keep the suite fast (one compilation per shape instead of one per eager op).
_call = nnx.jit(lambda p, obs, x, t: p(obs, x, t))
_tc = nnx.jit(lambda p, t: p.time_conditioning(t))
_apply = nnx.jit(lambda p, obs, x, cond: p.apply_conditioned(obs, x, cond))


def _tiny(seed: int = 0, randomize: bool = True) -> FlowPolicy:
    pol = FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(seed))
    return _randomize(pol, seed + 100) if randomize else pol


def _inputs(b: int, seed: int = 0):
    k1, k2, k3 = jax.random.split(jax.random.key(seed), 3)
    obs = jax.random.normal(k1, (b, OBS))
    x = jax.random.normal(k2, (b, H, ACT))
    t = jax.random.uniform(k3, (b, H))
    return obs, x, t


def _cond_leaves(cond):
    return jax.tree.leaves(cond)


# ----------------------------------------------------------------------------- independent float64 reference


def _ref_forward(pd, obs, x, t, channel_dim):
    """Public-release semantics written out in float64 NumPy from the pure dict; ``t`` is [B, H]."""
    p = jax.tree.map(lambda a: np.asarray(a, np.float64), pd)
    obs, x, t = (np.asarray(a, np.float64) for a in (obs, x, t))

    def lin(name, v):
        out = v @ name["kernel"]
        return out + name["bias"] if "bias" in name else out

    def ln(v):
        mu = v.mean(-1, keepdims=True)
        var = ((v - mu) ** 2).mean(-1, keepdims=True)
        return (v - mu) / np.sqrt(var + 1e-6)

    def gelu(v):  # tanh approximation
        return 0.5 * v * (1 + np.tanh(math.sqrt(2 / math.pi) * (v + 0.044715 * v**3)))

    def swish(v):
        return v / (1 + np.exp(-v))

    half = channel_dim // 2
    period = MIN_PERIOD * (MAX_PERIOD / MIN_PERIOD) ** np.linspace(0, 1, half)
    arg = t[..., None] * (2 * np.pi / period)
    emb = np.concatenate([np.sin(arg), np.cos(arg)], -1)  # [B, H, C]
    c = swish(lin(p["time_mlp"]["layers"][2], swish(lin(p["time_mlp"]["layers"][0], emb))))

    b, h = x.shape[:2]
    hdn = lin(p["in_proj"], np.concatenate([x, np.repeat(obs[:, None], h, 1)], -1))
    for i in sorted(p["mlp_stack"]):
        blk = p["mlp_stack"][i]
        s1, sh1, g1 = np.split(lin(blk["adaln_1"], c), 3, -1)
        s2, sh2, g2 = np.split(lin(blk["adaln_2"], c), 3, -1)
        y = (ln(hdn) * (1 + s1) + sh1).transpose(0, 2, 1)
        y = lin(blk["token_mix_out"], gelu(lin(blk["token_mix_in"], y))).transpose(0, 2, 1)
        hdn = hdn + g1 * y
        y = ln(hdn) * (1 + s2) + sh2
        hdn = hdn + g2 * lin(blk["channel_mix_out"], gelu(lin(blk["channel_mix_in"], y)))
    scale, shift = np.split(lin(p["final_adaln"], c), 2, -1)
    return lin(p["out_proj"], ln(hdn) * (1 + scale) + shift)


# ----------------------------------------------------------------------------- tests


def test_parameter_tree_matches_public_layout():
    """[P-1] [P-7] Benchmark architecture: exact key paths and shapes of the public parameter tree."""
    # Abstract initialisation: shapes and structure without materialising 3M parameters.
    pol = nnx.eval_shape(lambda: FlowPolicy(obs_dim=679, action_dim=6, config=PolicyConfig(), rngs=nnx.Rngs(0)))
    pd = state_pure_dict(pol)
    flat = {
        tuple(str(getattr(k, "key", k)) for k in path): tuple(leaf.shape)
        for path, leaf in jax.tree_util.tree_flatten_with_path(pd)[0]
    }
    want = {
        ("in_proj", "kernel"): (685, 256),
        ("in_proj", "bias"): (256,),
        ("time_mlp", "layers", "0", "kernel"): (256, 256),
        ("time_mlp", "layers", "0", "bias"): (256,),
        ("time_mlp", "layers", "2", "kernel"): (256, 256),
        ("time_mlp", "layers", "2", "bias"): (256,),
        ("final_adaln", "kernel"): (256, 512),
        ("final_adaln", "bias"): (512,),
        ("out_proj", "kernel"): (256, 6),
        ("out_proj", "bias"): (6,),
    }
    for i in range(4):
        blk = {
            ("token_mix_in", "kernel"): (8, 64),
            ("token_mix_out", "kernel"): (64, 8),
            ("channel_mix_in", "kernel"): (256, 512),
            ("channel_mix_out", "kernel"): (512, 256),
            ("adaln_1", "kernel"): (256, 768),
            ("adaln_1", "bias"): (768,),
            ("adaln_2", "kernel"): (256, 768),
            ("adaln_2", "bias"): (768,),
        }
        want.update({("mlp_stack", str(i)) + k: v for k, v in blk.items()})
    assert flat == want
    # Layer indices are int keys, as nnx.State.to_pure_dict writes them.
    assert set(pd["mlp_stack"]) == {0, 1, 2, 3} and set(pd["time_mlp"]["layers"]) == {0, 2}
    assert sum(math.prod(s) for s in want.values()) == 3_072_006
    assert all(leaf.dtype == jnp.float32 for leaf in jax.tree.leaves(pd))


def test_forward_matches_independent_reference():
    """[P-2] [P-3] [P-4] [P-5] [P-9] Forward pass equals a float64 re-derivation of the public network."""
    pol = _tiny(1)
    obs, x, t = _inputs(3, seed=1)
    pd = state_pure_dict(pol)
    got = np.asarray(_call(pol, obs, x, t))
    np.testing.assert_allclose(got, _ref_forward(pd, obs, x, t, TINY.channel_dim), rtol=1e-4, atol=1e-4)
    ts = t[:, 0]
    got_s = np.asarray(_call(pol, obs, x, ts))
    ref_s = _ref_forward(pd, obs, x, np.repeat(np.asarray(ts)[:, None], H, 1), TINY.channel_dim)
    np.testing.assert_allclose(got_s, ref_s, rtol=1e-4, atol=1e-4)
    assert got.shape == (3, H, ACT)


def test_sincos_time_embedding_values():
    """[P-3] Embedding: C/2 geometric periods from MIN_PERIOD to MAX_PERIOD, sines then cosines."""
    assert (MIN_PERIOD, MAX_PERIOD) == (4e-3, 4.0)
    t = jnp.array([[0.0, 0.25, 1.0]])
    e = np.asarray(sincos_time_embedding(t, 8))
    assert e.shape == (1, 3, 8)
    np.testing.assert_array_equal(e[0, 0], [0, 0, 0, 0, 1, 1, 1, 1])
    period = 4e-3 * 1000.0 ** (np.arange(4) / 3)
    ang = 0.25 * 2 * np.pi / period
    np.testing.assert_allclose(e[0, 1], np.concatenate([np.sin(ang), np.cos(ang)]), atol=2e-5)
    with pytest.raises(ValueError, match="embedding_dim"):
        sincos_time_embedding(t, 7)
    with pytest.raises(ValueError, match="t must"):
        sincos_time_embedding(jnp.array([jnp.nan]), 8)


def test_adaln_zero_initialisation():
    """[P-6] adaLN kernels start at zero, so a fresh network ignores flow time."""
    pol = _tiny(2, randomize=False)
    pd = state_pure_dict(pol)
    for blk in pd["mlp_stack"].values():
        for k in ("adaln_1", "adaln_2"):
            assert not np.any(np.asarray(blk[k]["kernel"])) and not np.any(np.asarray(blk[k]["bias"]))
    assert not np.any(np.asarray(pd["final_adaln"]["kernel"]))
    assert np.any(np.asarray(pd["in_proj"]["kernel"]))
    obs, x, t = _inputs(2, seed=2)
    np.testing.assert_array_equal(np.asarray(_call(pol, obs, x, t)), np.asarray(_call(pol, obs, x, jnp.zeros(2))))


def test_scalar_time_equals_uniform_per_token_time():
    """[P-9] [P-14] t of shape [B] equals the same time repeated per token (float32 tolerance)."""
    pol = _tiny(3)
    obs, x, _ = _inputs(4, seed=3)
    ts = jnp.array([0.0, 0.3, 0.77, 1.0])
    a = np.asarray(_call(pol, obs, x, ts))
    b = np.asarray(_call(pol, obs, x, jnp.broadcast_to(ts[:, None], (4, H))))
    np.testing.assert_allclose(a, b, rtol=RTOL, atol=ATOL)


def test_per_token_time_is_local_to_its_token():
    """[P-10] Modulation of token j depends on t[..., j] only and equals the shared-time modulation at t_j."""
    pol = _tiny(4)
    t = jnp.array([[1.0, 0.9, 0.5, 0.2, 0.2]])
    cond = _tc(pol, t)
    t2 = t.at[0, 2].set(0.1)
    cond2 = _tc(pol, t2)
    for a, b in zip(_cond_leaves(cond), _cond_leaves(cond2)):
        changed = np.any(np.asarray(a) != np.asarray(b), axis=-1)[0]
        assert changed.tolist() == [False, False, True, False, False]
    for j in range(H):
        shared = _tc(pol, jnp.full((1, 1), t[0, j]))
        for a, s in zip(_cond_leaves(cond), _cond_leaves(shared)):
            np.testing.assert_allclose(np.asarray(a)[0, j], np.asarray(s)[0, 0], rtol=RTOL, atol=ATOL)
    # Different times on different tokens change the output.
    obs, x, _ = _inputs(1, seed=4)
    assert not np.allclose(np.asarray(_call(pol, obs, x, t)), np.asarray(_call(pol, obs, x, jnp.full((1,), 0.5))))


def test_time_conditioning_structure_and_shapes():
    """[P-11] cond holds every adaLN modulation of every layer; leading dims follow t."""
    pol = _tiny(5)
    c = TINY.channel_dim
    for shape in [(H,), (1, H), (5, 1, H), (2, 3, 1)]:
        cond = _tc(pol, jnp.full(shape, 0.5))
        assert set(cond) == {"mlp_stack", "final_adaln"}
        assert len(cond["mlp_stack"]) == TINY.num_layers
        for layer in cond["mlp_stack"]:
            assert set(layer) == {"adaln_1", "adaln_2"}
            assert layer["adaln_1"].shape == shape + (3 * c,) and layer["adaln_2"].shape == shape + (3 * c,)
        assert cond["final_adaln"].shape == shape + (2 * c,)
    # It is the adaLN projection of the time-MLP features (no observation enters).
    t = jnp.array([[0.2, 0.4, 0.6, 0.8, 1.0]])
    direct = nnx.jit(lambda p, t: p.mlp_stack[1].adaln_2(p.time_mlp(sincos_time_embedding(t, c))))(pol, t)
    np.testing.assert_allclose(np.asarray(_tc(pol, t)["mlp_stack"][1]["adaln_2"]), np.asarray(direct), rtol=RTOL, atol=ATOL)


def test_apply_conditioned_matches_call_and_broadcasts():
    """[P-12] apply_conditioned(obs, x, time_conditioning(t)) equals policy(obs, x, t); batch-1 cond broadcasts."""
    pol = _tiny(6)
    b = 3
    obs, x, t = _inputs(b, seed=6)
    ref = np.asarray(_call(pol, obs, x, t))
    np.testing.assert_allclose(np.asarray(_apply(pol, obs, x, _tc(pol, t))), ref, rtol=RTOL, atol=ATOL)
    # One table row (batch 1) serves every sample that shares the per-token times.
    row = jnp.array([1.0, 0.75, 0.5, 0.4, 0.4])
    ref_row = np.asarray(_call(pol, obs, x, jnp.broadcast_to(row, (b, H))))
    for cond in (_tc(pol, row[None]), _tc(pol, row)):  # [1, H, F] and [H, F]
        np.testing.assert_allclose(np.asarray(_apply(pol, obs, x, cond)), ref_row, rtol=RTOL, atol=ATOL)


def test_precomputed_table_inside_jitted_sampler():
    """[P-11] [P-12] A (step -> cond) table built once is indexed inside jit and reproduces the straightforward sampler."""
    pol = _tiny(7)
    graphdef, state = nnx.split(pol)
    steps = 4
    w = jnp.array([1.0, 1.0, 0.5, 0.0, 0.0])
    tk = jnp.arange(steps) / steps
    table = _tc(pol, (w + (1 - w) * tk[:, None])[:, None, :])  # leaves [T, 1, H, F]
    obs, x0, _ = _inputs(2, seed=7)
    y = jax.random.normal(jax.random.key(8), (H, ACT))

    @jax.jit
    def straight(state, x):
        p = nnx.merge(graphdef, state)
        for k in range(steps):
            x = w[:, None] * y + (1 - w[:, None]) * x
            x = x + p(obs, x, jnp.broadcast_to(w + (1 - w) * tk[k], (2, H))) / steps
        return x

    @jax.jit
    def tabled(state, x, table):
        p = nnx.merge(graphdef, state)

        def step(x, cond):
            x = w[:, None] * y + (1 - w[:, None]) * x
            return x + p.apply_conditioned(obs, x, cond) / steps, None

        return jax.lax.scan(step, x, table)[0]

    np.testing.assert_allclose(np.asarray(tabled(state, x0, table)), np.asarray(straight(state, x0)), rtol=RTOL, atol=ATOL)


def test_shared_time_fast_path():
    """[P-13] A shared time gives cond of shape [1, 1, F] that equals the scalar-time call."""
    pol = _tiny(9)
    obs, x, _ = _inputs(3, seed=9)
    for tk in (0.0, 0.4, 1.0):
        cond = _tc(pol, jnp.full((1, 1), tk))
        assert cond["final_adaln"].shape == (1, 1, 2 * TINY.channel_dim)
        np.testing.assert_allclose(
            np.asarray(_apply(pol, obs, x, cond)),
            np.asarray(_call(pol, obs, x, jnp.full((3,), tk))),
            rtol=RTOL,
            atol=ATOL,
        )


def test_checkpoint_in_public_format_loads(tmp_path):
    """[P-8] A pickled nnx.state(...).to_pure_dict() (public bc layout) loads and reproduces outputs."""
    src = _tiny(10)
    path = tmp_path / "0" / "policies" / "worlds_l_grasp_easy.pkl"
    path.parent.mkdir(parents=True)
    with path.open("wb") as f, warnings.catch_warnings():
        warnings.simplefilter("ignore", DeprecationWarning)  # the public call form, deprecated in flax 0.12
        pickle.dump(nnx.state(src).to_pure_dict(), f)  # exactly what the public trainer writes
    dst = _tiny(11)
    obs, x, t = _inputs(2, seed=10)
    assert not np.allclose(np.asarray(dst(obs, x, t)), np.asarray(src(obs, x, t)))
    assert load_checkpoint(dst, path) is dst
    np.testing.assert_array_equal(np.asarray(dst(obs, x, t)), np.asarray(src(obs, x, t)))
    # NumPy leaves and digit-string layer keys are accepted as well.
    pd = jax.tree.map(np.asarray, state_pure_dict(_tiny(12)))
    pd["mlp_stack"] = {str(k): v for k, v in pd["mlp_stack"].items()}
    load_pure_dict(dst, pd)
    np.testing.assert_array_equal(np.asarray(dst(obs, x, t)), np.asarray(_tiny(12)(obs, x, t)))
    # A truncated pickle, or an .npz given by mistake, is a ValueError naming the file.
    bad = tmp_path / "bad.pkl"
    bad.write_bytes(path.read_bytes()[:40])
    with pytest.raises(ValueError, match="bad.pkl: not a readable pickled checkpoint"):
        load_checkpoint(dst, bad)
    npz = tmp_path / "x.npz"
    np.savez(npz, a=np.zeros(2))
    with pytest.raises(ValueError, match="x.npz: not a readable pickled checkpoint"):
        load_checkpoint(dst, npz)


def test_load_pure_dict_rejects_mismatches():
    """[P-8] [P-15] Missing/extra keys, wrong shapes, bad dtypes and non-finite values raise ValueError."""
    pol = _tiny(13)
    good = jax.tree.map(np.asarray, state_pure_dict(pol))

    def mutated(fn):
        pd = jax.tree.map(lambda a: a, good)
        fn(pd)
        return pd

    with pytest.raises(ValueError, match=r"missing key 'mlp_stack/1/adaln_2/kernel' \(expected shape \(16, 48\)\)"):
        load_pure_dict(pol, mutated(lambda pd: pd["mlp_stack"][1]["adaln_2"].pop("kernel")))
    with pytest.raises(ValueError, match=r"unexpected key 'final_norm/scale'"):
        load_pure_dict(pol, mutated(lambda pd: pd.update(final_norm={"scale": np.ones(16, np.float32)})))
    with pytest.raises(ValueError, match=r"in_proj/kernel.*shape \(9, 16\), expected shape \(10, 16\)"):
        load_pure_dict(pol, mutated(lambda pd: pd["in_proj"].update(kernel=np.zeros((9, 16), np.float32))))
    with pytest.raises(ValueError, match=r"out_proj/bias.*floating"):
        load_pure_dict(pol, mutated(lambda pd: pd["out_proj"].update(bias=np.zeros(3, np.int32))))
    with pytest.raises(ValueError, match=r"out_proj/bias.*finite"):
        load_pure_dict(pol, mutated(lambda pd: pd["out_proj"].update(bias=np.full(3, np.nan, np.float32))))
    with pytest.raises(ValueError, match="pure_dict"):
        load_pure_dict(pol, [1, 2])
    with pytest.raises(ValueError, match="'mlp_stack/0/.*' twice"):
        load_pure_dict(pol, mutated(lambda pd: pd["mlp_stack"].update({"0": pd["mlp_stack"][0]})))
    with pytest.raises(ValueError, match="path"):
        load_checkpoint(pol, "/nonexistent/policies/x.pkl")
    # A failed load leaves the model untouched.
    np.testing.assert_array_equal(np.asarray(pol.in_proj.kernel[...]), good["in_proj"]["kernel"])


def test_input_validation():
    """[P-15] Public entry points raise ValueError naming the argument and the allowed shape/range."""
    pol = _tiny(14)
    obs, x, t = _inputs(2, seed=14)
    cases = [
        (lambda: pol(obs[:, :-1], x, t), "obs"),
        (lambda: pol(obs, x[:, :-1], t), "x must have shape"),
        (lambda: pol(obs, x, t[:1]), r"t must have shape \[B\] or \[B, 5\]"),
        (lambda: pol(obs, x, t + 1.5), r"t must lie in \[0, 1\]"),
        (lambda: pol(obs, x, t.at[0, 0].set(jnp.nan)), "t must"),
        (lambda: pol(obs, x, t > 0.5), "t must have"),
        (lambda: pol(obs.astype(jnp.int32), x, t), "obs must have a floating dtype"),
        (lambda: pol(obs, x.at[0, 0, 0].set(jnp.inf), t), "x must contain only finite"),
        (lambda: pol.time_conditioning(jnp.zeros((2, 3))), r"t must have shape \[\.\.\., 5\] or \[\.\.\., 1\]"),
        (lambda: pol.time_conditioning(jnp.zeros(())), "t must have shape"),
        (lambda: pol.apply_conditioned(obs, x, {"mlp_stack": ()}), "cond must be a mapping"),
        (lambda: pol.apply_conditioned(obs, x, _tc(pol, jnp.zeros((3, H)))), r"b in \{1, 2\}"),
        (lambda: pol.apply_conditioned(obs, x, _tc(pol, jnp.zeros((1, 2, H)))), "cond"),
        (lambda: FlowPolicy(obs_dim=0, action_dim=2, config=TINY, rngs=nnx.Rngs(0)), "obs_dim"),
        (lambda: FlowPolicy(obs_dim=3, action_dim=2.0, config=TINY, rngs=nnx.Rngs(0)), "action_dim"),
        (lambda: FlowPolicy(obs_dim=3, action_dim=2, config=TINY, rngs=0), "rngs"),
        (lambda: FlowPolicy(obs_dim=3, action_dim=2, config={}, rngs=nnx.Rngs(0)), "config"),
        (lambda: PolicyConfig(channel_dim=15), "channel_dim must be even"),
        (lambda: PolicyConfig(num_layers=True), "num_layers"),
        (lambda: sincos_time_embedding(jnp.array([0.5, 1.5]), 4), r"t must lie in \[0, 1\]"),
        (lambda: MLPMixerBlock(H, 0, 16, 24, rngs=nnx.Rngs(0)), "token_hidden_dim"),
        (lambda: pol.mlp_stack[0](jnp.zeros((2, H, 15)), jnp.zeros((1, 1, 48)), jnp.zeros((1, 1, 48))),
         r"x must have shape \[B, 5, 16\]"),
        (lambda: pol.mlp_stack[0](jnp.zeros((2, H, 16)), jnp.zeros((1, 1, 47)), jnp.zeros((1, 1, 48))), "m1"),
    ]
    for fn, msg in cases:
        with pytest.raises(ValueError, match=msg):
            fn()
    # Integer times are accepted (0 and 1 are valid flow times).
    assert _call(pol, obs, x, jnp.array([0, 1])).shape == (2, H, ACT)
    # NumPy integer sizes are stored as int, so that the config serializes to JSON.
    cfg = PolicyConfig(channel_dim=np.int64(16))
    assert type(cfg.channel_dim) is int and cfg == PolicyConfig(channel_dim=16)


def test_validation_under_jit_checks_shapes_only():
    """[P-15] Under tracing, shapes are still checked; value checks apply only to concrete inputs."""
    pol = _tiny(15)
    graphdef, state = nnx.split(pol)
    obs, x, t = _inputs(2, seed=15)

    def f(state, obs, x, t):
        return nnx.merge(graphdef, state)(obs, x, t)

    out = jax.jit(f)(state, obs, x, t)
    np.testing.assert_allclose(np.asarray(out), np.asarray(_call(pol, obs, x, t)), rtol=RTOL, atol=ATOL)
    with pytest.raises(ValueError, match="t must have shape"):
        jax.jit(f)(state, obs, x, t[:, :2])


def test_explicit_seeds_are_deterministic():
    """[P-16] Initialisation depends only on the explicit seed."""
    a = state_pure_dict(FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(3)))
    b = state_pure_dict(FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(3)))
    c = state_pure_dict(FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(4)))
    for la, lb in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(la), np.asarray(lb))
    assert not np.array_equal(np.asarray(a["in_proj"]["kernel"]), np.asarray(c["in_proj"]["kernel"]))


def test_layer_norm_custom_vjp_matches_autodiff():
    """P-17, P-14: the hand-written LayerNorm VJP keeps the module's forward bitwise and its gradient
    within tolerance, alone and through the whole policy (the guided samplers' VJP in x)."""
    import jax

    from softrtc.jax.vjp import layer_norm

    rng = np.random.default_rng(3)
    norm = nnx.LayerNorm(16, use_scale=False, use_bias=False, rngs=nnx.Rngs(0))
    x = jnp.asarray(rng.standard_normal((2, 5, 16)) * 3 + 1, jnp.float32)
    g = jnp.asarray(rng.standard_normal((2, 5, 16)), jnp.float32)
    y, pb = jax.vjp(lambda a: layer_norm(norm, a), x)
    y0, pb0 = jax.vjp(norm, x)
    assert np.array_equal(np.asarray(y), np.asarray(y0))
    np.testing.assert_allclose(pb(g)[0], pb0(g)[0], rtol=1e-4, atol=1e-5)
    # A constant row (variance 0) gives the centred cotangent times 1/sqrt(eps), like autodiff.
    c = jnp.ones((1, 16), jnp.float32)
    np.testing.assert_allclose(jax.vjp(lambda a: layer_norm(norm, a), c)[1](g[0, :1])[0],
                               jax.vjp(norm, c)[1](g[0, :1])[0], rtol=1e-4, atol=1e-2)

    pol = _randomize(FlowPolicy(obs_dim=5, action_dim=2, config=TINY, rngs=nnx.Rngs(1)), 5)
    obs = jnp.asarray(rng.standard_normal((3, 5)), jnp.float32)
    xs = jnp.asarray(rng.standard_normal((3, TINY.action_chunk_size, 2)), jnp.float32)
    t = jnp.full((3, TINY.action_chunk_size), 0.3)
    ct = jnp.asarray(rng.standard_normal(xs.shape), jnp.float32)
    got = jax.vjp(lambda a: pol(obs, a, t), xs)[1](ct)[0]
    import softrtc.jax.vjp as P

    with P.autodiff_vjps(layer_norm=True):  # plain autodiff of the flax module
        want = jax.vjp(lambda a: pol(obs, a, t), xs)[1](ct)[0]
    np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5)
    assert float(jnp.max(jnp.abs(want))) > 1e-3  # the gradient is not trivially zero


def test_gelu_recomputing_vjp_matches_autodiff():
    """P-20, P-14: the alternative GELU VJP (recomputing tanh) is bitwise nnx.gelu forward, and its gradient
    (alone, through the policy in x, and in the parameters) agrees with the shipped autodiff of nnx.gelu."""
    import jax

    import softrtc.jax.vjp as P

    x = jnp.asarray(np.concatenate([np.linspace(-12.0, 12.0, 4001), [0.0, -0.5, 3e-4]]), jnp.float32)
    assert np.array_equal(np.asarray(P.gelu(x)), np.asarray(nnx.gelu(x)))
    got = jax.grad(lambda a: jnp.sum(P.gelu(a)))(x)
    want = jax.grad(lambda a: jnp.sum(nnx.gelu(a)))(x)
    # Near x = -5 both lose digits to 1 + tanh ~ 0 (float32): compare with the float64 derivative too.
    xd = np.asarray(x, np.float64)
    th = np.tanh(np.sqrt(2 / np.pi) * (xd + 0.044715 * xd ** 3))
    exact = 0.5 * (1 + th) + 0.5 * xd * (1 - th ** 2) * np.sqrt(2 / np.pi) * (1 + 3 * 0.044715 * xd ** 2)
    np.testing.assert_allclose(got, exact, rtol=1e-5, atol=5e-6)
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
    assert float(jnp.min(want)) < -0.1 and float(jnp.max(want)) > 1.1  # the derivative's dip and overshoot

    rng = np.random.default_rng(20)
    pol = _randomize(FlowPolicy(obs_dim=5, action_dim=2, config=TINY, rngs=nnx.Rngs(20)), 20)
    obs = jnp.asarray(rng.standard_normal((3, 5)), jnp.float32)
    xs = jnp.asarray(rng.standard_normal((3, TINY.action_chunk_size, 2)), jnp.float32)
    t = jnp.asarray(rng.uniform(size=(3, TINY.action_chunk_size)), jnp.float32)
    ct = jnp.asarray(rng.standard_normal(xs.shape), jnp.float32)
    graphdef, params = nnx.split(pol)

    def loss(prm, a):
        return jnp.sum(nnx.merge(graphdef, prm)(obs, a, t) * ct)

    with P.autodiff_vjps(gelu=False):  # the recomputing VJP; the shipped blocks use autodiff of nnx.gelu
        got_x, got_p = jax.grad(loss, argnums=1)(params, xs), jax.grad(loss)(params, xs)
        recompute_hlo = jax.jit(jax.grad(loss, argnums=1)).lower(params, xs).as_text()
    want_x, want_p = jax.grad(loss, argnums=1)(params, xs), jax.grad(loss)(params, xs)
    assert recompute_hlo != jax.jit(jax.grad(loss, argnums=1)).lower(params, xs).as_text()
    np.testing.assert_allclose(got_x, want_x, rtol=1e-4, atol=1e-5)
    assert float(jnp.max(jnp.abs(want_x))) > 1e-3
    for a, b in zip(jax.tree.leaves(got_p), jax.tree.leaves(want_p)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-4, atol=1e-5)


def test_autodiff_vjps_switches_blocks_only_while_tracing_and_restores():
    """B-12, P-17, P-20: the ablation switch changes how the blocks are differentiated (the compiled VJP
    differs), not their values, is restored on exit and on error, and takes bools only."""
    import jax

    import softrtc.jax.vjp as P

    pol = _randomize(FlowPolicy(obs_dim=5, action_dim=2, config=TINY, rngs=nnx.Rngs(22)), 22)
    obs = jnp.ones((1, 5), jnp.float32)
    xs = jnp.ones((1, TINY.action_chunk_size, 2), jnp.float32)
    t = jnp.full((1, TINY.action_chunk_size), 0.4)

    def vjp_hlo():
        f = jax.jit(lambda a: jax.vjp(lambda b: pol(obs, b, t), a)[1](a)[0])
        return f.lower(xs).as_text(), f(xs)

    shipped, g0 = vjp_hlo()
    assert P._AUTODIFF == {"layer_norm": False, "gelu": True}  # [P-17] closed form, [P-20] autodiff
    with P.autodiff_vjps():  # the defaults are the shipped choices
        assert vjp_hlo()[0] == shipped
    with P.autodiff_vjps(layer_norm=True, gelu=True):
        plain, g1 = vjp_hlo()
        assert P._AUTODIFF == {"layer_norm": True, "gelu": True}
    assert shipped != plain  # e.g. the closed-form LayerNorm backward's product is gone
    np.testing.assert_allclose(g0, g1, rtol=1e-4, atol=1e-5)
    with P.autodiff_vjps(gelu=False):
        recompute, g2 = vjp_hlo()
        assert P._AUTODIFF == {"layer_norm": False, "gelu": False}
    assert recompute not in (shipped, plain)  # the recomputing GELU backward
    np.testing.assert_allclose(g0, g2, rtol=1e-4, atol=1e-5)
    assert P._AUTODIFF == {"layer_norm": False, "gelu": True}
    with pytest.raises(RuntimeError, match="inside"):
        with P.autodiff_vjps(gelu=False):
            raise RuntimeError("inside")
    assert P._AUTODIFF == {"layer_norm": False, "gelu": True}
    with pytest.raises(ValueError, match="gelu must be a bool"):
        with P.autodiff_vjps(gelu=1):
            pass


def test_gelu_and_layer_norm_validate_their_inputs():
    """P-15: the custom-VJP building blocks name the argument and the allowed dtype or shape."""
    from softrtc.jax.vjp import gelu, layer_norm

    with pytest.raises(ValueError, match="x must have a floating dtype"):
        gelu(jnp.arange(3))
    with pytest.raises(ValueError, match="x must have a floating dtype"):
        gelu(jnp.array([True]))
    norm = nnx.LayerNorm(4, use_scale=False, use_bias=False, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match=r"x must have shape \[\.\.\., 4\]"):
        layer_norm(norm, jnp.ones((2, 5)))
    with pytest.raises(ValueError, match="norm must be an nnx.LayerNorm"):
        layer_norm(lambda a: a, jnp.ones((2, 4)))
    with pytest.raises(ValueError, match="x must have a floating dtype"):
        layer_norm(norm, jnp.ones((2, 4), jnp.int32))


_split = nnx.jit(lambda p, obs, x, cond, head: p.apply_conditioned_split(obs, x, cond, head), static_argnums=4)


def test_apply_conditioned_split_matches_apply_conditioned():
    """[P-18] The two token groups concatenated equal apply_conditioned, for per-token and shared conditioning."""
    pol = _tiny(21)
    obs, x, t = _inputs(3, seed=21)
    enc = pol.encode_obs(obs)
    for cond in (_tc(pol, t), _tc(pol, jnp.full((1, 1), 0.3)), _tc(pol, t[0])):
        ref = np.asarray(_apply(pol, obs, x, cond))
        for head in range(1, H):
            v_head, v_tail = _split(pol, obs, x, cond, head)
            assert v_head.shape == (3, head, ACT) and v_tail.shape == (3, H - head, ACT)
            np.testing.assert_allclose(np.concatenate([v_head, v_tail], axis=1), ref, rtol=RTOL, atol=ATOL)
    # With the observation encoded once ([B-3]) the result is the same function.
    cond = _tc(pol, t)
    v_head, v_tail = pol.apply_conditioned_split(obs, x, cond, 2, obs_encoding=enc)
    np.testing.assert_allclose(np.concatenate([v_head, v_tail], axis=1), np.asarray(_apply(pol, obs, x, cond)),
                               rtol=RTOL, atol=ATOL)
    for bad, msg in ((0, "head must be an integer in"), (H, "head must be an integer in"), (True, "head must"),
                     (2.0, "head must")):
        with pytest.raises(ValueError, match=msg):
            pol.apply_conditioned_split(obs, x, cond, bad)
    with pytest.raises(ValueError, match="obs_encoding must have shape"):
        pol.apply_conditioned_split(obs, x, cond, 2, obs_encoding=enc[:, 0])


def test_guided_pull_back_restricted_to_guided_tokens():
    """[P-18] [G-7] The guided sampler through the split policy gives the chunks of the full pull-back, and its
    compiled program does less arithmetic (the tail tokens' last layers have no backward)."""
    from softrtc.jax import methods as JM

    pol = _tiny(23)
    graphdef, state = nnx.split(pol)
    obs, x0, _ = _inputs(2, seed=23)
    prior = jax.random.normal(jax.random.key(24), (2, H, ACT))
    s = 2

    def run(method, restrict):
        def f(state, obs, noise, prior, d):
            p = nnx.merge(graphdef, state)
            tables = JM.method_tables(method, p, H, s, 3)
            return JM.generate_chunk_conditioned(method, p, obs, noise, prior, s, d, 3, tables=tables,
                                                 restrict_guidance=restrict)
        return jax.jit(f)

    for method in ("inference_hard", "inference_soft"):
        full, part = run(method, False), run(method, True)
        for d in range(min(s, H - s) + 1):
            a = np.asarray(part(state, obs, x0, prior, d))
            np.testing.assert_allclose(a, np.asarray(full(state, obs, x0, prior, d)), rtol=RTOL, atol=ATOL)
        flops = [f.lower(state, obs, x0, prior, 1).compile().cost_analysis()["flops"] for f in (full, part)]
        assert flops[1] < flops[0], flops


def test_pullback_kernels_same_values_and_gradients():
    """[P-19] With the stored transposed kernels the forward is bitwise the same, and the VJP with respect to x
    and the gradients of the parameters agree with plain autodiff."""
    pol = _tiny(25)
    obs, x, t = _inputs(3, seed=25)
    cond = _tc(pol, t)
    pb = pol.pullback_kernels()
    np.testing.assert_array_equal(np.asarray(pb["mlp_stack"][1]["channel_mix_in"]),
                                  np.asarray(pol.mlp_stack[1].channel_mix_in.kernel[...]).T)
    np.testing.assert_array_equal(np.asarray(pb["in_proj_x"]), np.asarray(pol.in_proj.kernel[...][:ACT]).T)
    enc = pol.encode_obs(obs)
    with_pb = nnx.jit(lambda p, x, pb: p.apply_conditioned(obs, x, cond, obs_encoding=enc, pullback=pb))
    plain = nnx.jit(lambda p, x: p.apply_conditioned(obs, x, cond, obs_encoding=enc))
    assert np.array_equal(np.asarray(with_pb(pol, x, pb)), np.asarray(plain(pol, x)))
    split = nnx.jit(lambda p, x, pb: p.apply_conditioned_split(obs, x, cond, 2, pullback=pb))
    split0 = nnx.jit(lambda p, x: p.apply_conditioned_split(obs, x, cond, 2))
    for a, b in zip(split(pol, x, pb), split0(pol, x)):
        assert np.array_equal(np.asarray(a), np.asarray(b))

    ct = jax.random.normal(jax.random.key(26), x.shape)
    vjp_pb = jax.vjp(lambda x: pol.apply_conditioned(obs, x, cond, obs_encoding=enc, pullback=pb), x)[1](ct)[0]
    vjp = jax.vjp(lambda x: pol.apply_conditioned(obs, x, cond, obs_encoding=enc), x)[1](ct)[0]
    np.testing.assert_allclose(np.asarray(vjp_pb), np.asarray(vjp), rtol=RTOL, atol=ATOL)
    assert not np.allclose(np.asarray(vjp), 0.0)

    def loss(p, pb):
        return jnp.sum(jnp.sin(p.apply_conditioned(obs, x, cond, pullback=pb)))

    g_pb, g = nnx.grad(loss)(pol, pb), nnx.grad(loss)(pol, None)
    for a, b in zip(jax.tree.leaves(g_pb), jax.tree.leaves(g)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=RTOL, atol=ATOL)

    bad = dict(pb, out_proj=pb["out_proj"].T)
    for wrong in ({"a": 1}, bad, dict(pb, mlp_stack=pb["mlp_stack"][:1])):
        with pytest.raises(ValueError, match="pullback must be the mapping returned by pullback_kernels"):
            pol.apply_conditioned(obs, x, cond, pullback=wrong)
