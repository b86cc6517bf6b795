"""Tests of JAX behaviour-cloning training and checkpoints (spec/31-training-jax.md, chapter T).

Compilation dominates the runtime, so the tests share a few train-step configs
(steps with equal architecture and config share one compilation).
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

jax = pytest.importorskip("jax")
nnx = pytest.importorskip("flax.nnx")
optax = pytest.importorskip("optax")
import jax.numpy as jnp  # noqa: E402

from softrtc.jax import checkpoint as C  # noqa: E402
from softrtc.jax import weights as JW  # noqa: E402
from softrtc.jax.params import state_pure_dict  # noqa: E402
from softrtc.jax.policy import FlowPolicy, PolicyConfig  # noqa: E402
from softrtc.jax.training import TrainConfig, TrainState, make_optimizer, make_train_step, train  # noqa: E402
from softrtc.reference import corruption as RC  # noqa: E402
from softrtc.reference import delays as RD  # noqa: E402
from softrtc.reference import endpoints as RE  # noqa: E402
from softrtc.reference import loss as RL  # noqa: E402
from softrtc.reference import weights as RW  # noqa: E402

TINY = PolicyConfig(channel_dim=16, channel_hidden_dim=16, token_hidden_dim=4, num_layers=1, action_chunk_size=6)
OBS, ACT, H, S, B = 3, 2, 6, 3, 8
WINDOW = RW.SoftWindow(RE.delay_scaled(2.0, 5), "linear", "rtc", "clip")
SOFT = TrainConfig(method="soft", window=WINDOW, execute_horizon=S, delay_dist="exponential", d_min=1, d_max=3,
                   delay_decay=0.5, batch_size=B, learning_rate=3e-3)


def _policy(seed: int = 0, randomize: bool = False) -> FlowPolicy:
    pol = FlowPolicy(obs_dim=OBS, action_dim=ACT, config=TINY, rngs=nnx.Rngs(seed))
    if randomize:
        # adaLN kernels start at zero; random values make the output depend on the per-token time.
        # NumPy draws: eager jax.random would compile one program per parameter shape.
        rng = np.random.default_rng(seed + 100)
        state = nnx.state(pol)
        leaves, tree = jax.tree.flatten(state)
        nnx.update(pol, jax.tree.unflatten(tree, [jnp.asarray(0.3 * rng.standard_normal(a.shape), a.dtype)
                                                  for a in leaves]))
    return pol


def _data(n: int = 32, seed: int = 0):
    rng = np.random.default_rng(seed)
    obs = rng.standard_normal((n, OBS))
    # A learnable target: each action is a fixed linear map of the observation times a token ramp.
    proj = np.random.default_rng(1234).standard_normal((OBS, ACT))
    actions = (obs @ proj)[:, None, :] * np.linspace(0.5, 1.5, H)[None, :, None]
    return obs.astype(np.float32), actions.astype(np.float32)


def _leaves(tree):
    return [np.asarray(a) for a in jax.tree.leaves(tree)]


def _bitwise_equal(a, b) -> bool:
    return all(np.array_equal(x, y) for x, y in zip(_leaves(a), _leaves(b)))


@pytest.fixture(scope="module")
def soft_step():
    return make_train_step(_policy(0), SOFT)


# ----------------------------------------------------------------------------- config


def test_config_defaults_and_roundtrip():
    """T-1: defaults are the paper's main setting; the config is frozen, hashable and round-trips as JSON."""
    cfg = TrainConfig()
    assert (cfg.method, cfg.execute_horizon, cfg.delay_dist, cfg.d_min, cfg.d_max) == ("soft", 4, "uniform", 0, 4)
    assert cfg.window == RW.SoftWindow()
    assert (cfg.learning_rate, cfg.weight_decay, cfg.grad_clip_norm, cfg.warmup_steps, cfg.decay_steps) == \
        (3e-4, 1e-2, 1.0, 0, None)
    import dataclasses

    with pytest.raises(dataclasses.FrozenInstanceError, match="learning_rate"):
        cfg.learning_rate = 1.0  # frozen
    hash(cfg)
    again = TrainConfig.from_dict(json.loads(json.dumps(SOFT.to_dict())))
    assert again == SOFT
    # A JAX window is stored as the equivalent reference window.
    jw = JW.SoftWindow(JW.delay_scaled(2.0, 5), "exp", "paper", "zeros")
    got = TrainConfig(window=jw, execute_horizon=None)
    assert got.window == RW.SoftWindow(RE.delay_scaled(2.0, 5), "exp", "paper", "zeros")


@pytest.mark.parametrize("field,value", [
    ("method", "rtc"), ("window", "linear"), ("execute_horizon", 0), ("execute_horizon", 2.0),
    ("delay_dist", "normal"), ("d_min", -1), ("d_max", 0), ("d_min", True), ("delay_decay", 65.0),
    ("delay_decay", float("nan")), ("batch_size", 0), ("learning_rate", 0.0), ("learning_rate", float("inf")),
    ("weight_decay", -0.1), ("adam_b1", 1.0), ("adam_b2", -0.5), ("adam_eps", 0.0), ("grad_clip_norm", 0.0),
    ("warmup_steps", -1), ("decay_steps", 0), ("final_lr_ratio", 1.5),
])
def test_config_validation_names_field(field, value):
    """T-1 N-7: every invalid hyper-parameter raises ValueError naming the field."""
    kw = {"d_min": 1, "d_max": 3} if field == "d_max" else {}
    kw[field] = value
    with pytest.raises(ValueError, match=field):
        TrainConfig(**kw)


def test_config_soft_clip_needs_execute_horizon():
    """T-1 T-3 W-6 D-4: soft training with the clipped window needs s; the zeros overflow does not."""
    with pytest.raises(ValueError, match="execute_horizon"):
        TrainConfig(method="soft", execute_horizon=None)
    TrainConfig(method="soft", execute_horizon=None, window=RW.SoftWindow(overflow="zeros"))
    TrainConfig(method="hard", execute_horizon=None)


def test_make_train_step_checks_horizon():
    """T-3 D-4 E-1: d_max <= H, s <= H and the window bound <= H are checked against the policy."""
    pol = _policy()
    with pytest.raises(ValueError, match="d_max"):
        make_train_step(pol, TrainConfig(method="hard", d_max=H + 1))
    with pytest.raises(ValueError, match="execute_horizon"):
        make_train_step(pol, TrainConfig(method="hard", execute_horizon=H + 1))
    with pytest.raises(ValueError, match="h_max"):
        make_train_step(pol, TrainConfig(window=RW.SoftWindow(RE.delay_scaled(2.0, H + 1)), execute_horizon=S))
    with pytest.raises(ValueError, match="policy"):
        make_train_step("policy", SOFT)
    with pytest.raises(ValueError, match="config"):
        make_train_step(pol, {"method": "soft"})


# ----------------------------------------------------------------------------- draws, weights, loss


def test_draws_follow_reference(soft_step):
    """T-2 T-3 D-2 D-3 D-4 C-1 W-7: per-example delay (inverse CDF), tau, noise and weights of one key."""
    key = jax.random.key(7)
    n = 4000
    draw = soft_step.draw(key, n)
    k_d, k_tau, k_eps = jax.random.split(key, 3)
    u = np.asarray(jax.random.uniform(k_d, (n,)), np.float64)
    probs = RD.delay_probs("exponential", 1, 3, 0.5)
    want_d = np.array([RD.sample_delay(probs, 1, x) for x in u])
    d = np.asarray(draw["delay"])
    assert np.mean(d == want_d) > 0.999  # float32 vs float64 CDF may differ within 1e-7 of an edge [N-8]
    freq = np.bincount(d - 1, minlength=3) / n
    np.testing.assert_allclose(freq, probs, atol=0.03)
    np.testing.assert_array_equal(np.asarray(draw["tau"]), np.asarray(jax.random.uniform(k_tau, (n,))))
    np.testing.assert_array_equal(np.asarray(draw["noise"]), np.asarray(jax.random.normal(k_eps, (n, H, ACT))))
    assert np.all((np.asarray(draw["tau"]) >= 0) & (np.asarray(draw["tau"]) < 1))
    w = np.asarray(draw["weights"])
    for dd in (1, 2, 3):
        rows = w[d == dd]
        np.testing.assert_allclose(rows, np.broadcast_to(RW.soft_weights(H, dd, WINDOW, S), rows.shape), atol=1e-6)
    # The table holds every delay 0 .. H, including delays beyond this config's d_max [D-4].
    assert soft_step.weight_table.shape == (H + 1, H)


def test_method_weight_tables():
    """T-3 W-8 W-9: hard uses 1[j < d]; none uses w = 0 for every example."""
    hard = make_train_step(_policy(), TrainConfig(method="hard", d_max=H, execute_horizon=None))
    np.testing.assert_array_equal(np.asarray(hard.weight_table),
                                  np.stack([RW.hard_weights(H, d) for d in range(H + 1)]))
    none = make_train_step(_policy(), TrainConfig(method="none"))
    assert not np.any(np.asarray(none.weight_table))


def test_loss_matches_reference(soft_step):
    """T-4 C-1 C-2 L-1 L-2 L-3: the step's loss is the reference loss on the reference corruption."""
    pol = _policy(3, randomize=True)
    obs, actions = _data(B, seed=3)
    key = jax.random.key(11)
    _, metrics = soft_step(soft_step.init_state(pol), (obs, actions), key)  # loss before the update
    draw = soft_step.draw(key, B)
    ws, xs, ts, eps = [], [], [], np.asarray(draw["noise"], np.float64)
    for i in range(B):
        w = RW.soft_weights(H, int(draw["delay"][i]), WINDOW, S)
        x, tj = RC.corrupt(actions[i], eps[i], w, float(draw["tau"][i]))
        ws.append(w), xs.append(x), ts.append(tj)
    forward = jax.jit(lambda o, x, t: pol(o, x, t))  # one compilation instead of op-by-op dispatch
    v = np.asarray(forward(jnp.asarray(obs), jnp.asarray(np.stack(xs), jnp.float32),
                           jnp.asarray(np.stack(ts), jnp.float32)), np.float64)
    want = RL.batch_loss(v, actions, eps, np.stack(ws))
    np.testing.assert_allclose(float(metrics["loss"]), want, rtol=2e-5)


def test_none_equals_zero_delay():
    """T-5 C-3 L-4 E-6: none is hard/soft with d forced to 0 (hard vs soft bitwise; none to rounding)."""
    pol = _policy(5, randomize=True)
    obs, actions = _data(B, seed=5)
    key = jax.random.key(5)
    common = dict(d_min=0, d_max=0, batch_size=B, execute_horizon=S, learning_rate=SOFT.learning_rate)
    out = {}
    for m in ("none", "hard", "soft"):
        step = make_train_step(pol, TrainConfig(method=m, window=WINDOW, **common))
        out[m] = step(step.init_state(), (obs, actions), key)
        draw = step.draw(key, B)
        assert not np.any(np.asarray(draw["weights"]))
        out[m + "_draw"] = draw
    for m in ("hard", "soft"):
        for k in ("tau", "noise"):
            np.testing.assert_array_equal(np.asarray(out["none_draw"][k]), np.asarray(out[m + "_draw"][k]))
    assert _bitwise_equal(out["hard"][0].params, out["soft"][0].params)
    assert float(out["hard"][1]["loss"]) == float(out["soft"][1]["loss"])
    # none feeds one time per sample ([B]); the policy's shared-time path equals the repeated
    # per-token time up to float rounding of the time MLP ([P-8]).
    np.testing.assert_allclose(float(out["none"][1]["loss"]), float(out["hard"][1]["loss"]), rtol=1e-5)
    for a, b in zip(_leaves(out["none"][0].params), _leaves(out["hard"][0].params)):
        np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


# ----------------------------------------------------------------------------- step, optimiser


def test_one_compilation_serves_all_delays(soft_step):
    """T-7 D-4: d is drawn inside the jitted step; new keys, delays, windows or hard/soft do not recompile."""
    from softrtc.jax import training as T

    obs, actions = _data(B)
    state = soft_step.init_state()
    state, _ = soft_step(state, (obs, actions), jax.random.key(0))
    size = T._update._cache_size()
    means = set()
    other = make_train_step(_policy(1), SOFT)  # equal architecture and config
    for i in range(1, 6):
        state, metrics = (soft_step if i % 2 else other)(state, {"obs": obs, "actions": actions}, jax.random.key(i))
        means.add(float(metrics["delay_mean"]))
        assert set(metrics) == {"loss", "grad_norm", "learning_rate", "delay_mean"}
    # hard, another window and another delay distribution: traced tables, same program.
    for cfg in (TrainConfig(method="hard", d_max=H, batch_size=B, learning_rate=SOFT.learning_rate),
                TrainConfig(window=RW.SoftWindow(RE.offset(1, 4), "exp", "paper", "zeros"), d_min=2, d_max=2,
                            batch_size=B, learning_rate=SOFT.learning_rate)):
        alt = make_train_step(_policy(2), cfg)
        _, metrics = alt(alt.init_state(), (obs, actions), jax.random.key(9))
    assert float(metrics["delay_mean"]) == 2.0
    assert T._update._cache_size() == size
    assert len(means) > 1  # the delays really differ between steps
    assert int(state.step) == 6 and isinstance(state, TrainState)


def test_optimizer_is_clipped_adamw_with_schedule():
    """T-6: global-norm clipping, then AdamW with decay on kernels only; warm-up and cosine schedule."""
    cfg = TrainConfig(learning_rate=1e-2, weight_decay=0.1, grad_clip_norm=1.0, warmup_steps=10, decay_steps=110,
                      final_lr_ratio=0.1)
    tx, sched = make_optimizer(cfg)
    assert float(sched(0)) == 0.0
    assert math.isclose(float(sched(5)), 5e-3, rel_tol=1e-6)
    assert math.isclose(float(sched(10)), 1e-2, rel_tol=1e-6)
    assert math.isclose(float(sched(60)), 1e-2 * (0.1 + 0.9 * 0.5), rel_tol=1e-5)
    assert math.isclose(float(sched(110)), 1e-3, rel_tol=1e-5)
    const = make_optimizer(TrainConfig(learning_rate=2e-3))[1]
    assert float(const(0)) == float(const(10**6)) == pytest.approx(2e-3)

    params = {"kernel": jnp.ones((2, 3)), "bias": jnp.ones((3,))}
    manual = optax.chain(optax.clip_by_global_norm(1.0),
                         optax.adamw(sched, weight_decay=0.1, mask={"kernel": True, "bias": False}))
    s1, s2 = tx.init(params), manual.init(params)
    p1 = p2 = params
    for g in (100.0, 0.5, 3.0):  # first gradient far above the clip norm
        grads = jax.tree.map(lambda a: g * jnp.ones_like(a), params)
        u1, s1 = tx.update(grads, s1, p1)
        u2, s2 = manual.update(grads, s2, p2)
        p1, p2 = optax.apply_updates(p1, u1), optax.apply_updates(p2, u2)
    for a, b in zip(_leaves(p1), _leaves(p2)):
        np.testing.assert_allclose(a, b, rtol=1e-6)  # the step clips a flattened vector: same norm, other sum order
    # Zero gradient: only the decoupled weight decay moves the kernel, never the bias.
    zeros = jax.tree.map(jnp.zeros_like, params)
    u, _ = make_optimizer(TrainConfig(learning_rate=1e-2, weight_decay=0.5))[0].update(
        zeros, make_optimizer(TrainConfig())[0].init(params), params)
    np.testing.assert_allclose(np.asarray(u["kernel"]), -1e-2 * 0.5, rtol=1e-6)
    np.testing.assert_array_equal(np.asarray(u["bias"]), 0.0)
    with pytest.raises(ValueError, match="config"):
        make_optimizer({"learning_rate": 1e-3})


def test_step_validates_inputs(soft_step):
    """T-10 N-7 N-9: batch shapes, dtypes and values, the key and the state are checked before the jit."""
    obs, actions = _data(B)
    state = soft_step.init_state()
    key = jax.random.key(0)
    bad = [
        ((obs[:, :2], actions), key, "obs"),
        ((obs, actions[:, :, :1]), key, "actions"),
        ((obs[:4], actions), key, "batch size"),
        ((obs, np.where(np.arange(H)[None, :, None] == 0, np.nan, actions)), key, "finite"),
        ((obs.astype(bool), actions), key, "obs"),
        ((obs,), key, "batch"),
        ({"obs": obs}, key, "actions"),
        ((obs, actions), 0, "key"),
        ((obs, actions), jax.random.split(key, 2), "key"),
        ((np.full_like(obs, 1e300, dtype=np.float64), actions), key, "float32 range"),
    ]
    for batch, k, msg in bad:
        with pytest.raises(ValueError, match=msg):
            soft_step(state, batch, k)
    with pytest.raises(ValueError, match="state"):
        soft_step({"params": state.params}, (obs, actions), key)
    import dataclasses
    for step in (-5.5, np.int64(2**40), True):
        with pytest.raises(ValueError, match="^state.step must be an integer scalar"):
            soft_step(dataclasses.replace(state, step=step), (obs, actions), key)
    with pytest.raises(ValueError, match="params"):
        soft_step.loss({"x": jnp.zeros(2)}, (obs, actions), key)
    with pytest.raises(ValueError, match="batch_size"):
        soft_step.draw(key, 0)
    with pytest.raises(ValueError, match="architecture"):
        soft_step.init_state(FlowPolicy(obs_dim=OBS + 1, action_dim=ACT, config=TINY, rngs=nnx.Rngs(0)))
    # A raw uint32 key works as well as a typed key.
    soft_step.draw(jax.random.PRNGKey(0), 2)


# ----------------------------------------------------------------------------- training loop


def test_train_is_deterministic_and_learns(soft_step):
    """T-8 T-9: same key and data give bitwise the same parameters; loss falls; the input policy is untouched."""
    obs, actions = _data(32)
    pol = _policy(0)
    before = _leaves(state_pure_dict(pol))
    a, hist_a = train(pol, (obs, actions), SOFT, jax.random.key(1), 40, progress=True)
    b, hist_b = train(_policy(0), {"obs": obs, "actions": actions}, SOFT, jax.random.key(1), 40, progress=False)
    assert _bitwise_equal(state_pure_dict(a), state_pure_dict(b))
    np.testing.assert_array_equal(hist_a, hist_b)
    assert hist_a.shape == (40,) and np.all(np.isfinite(hist_a))
    assert np.mean(hist_a[-10:]) < 0.7 * np.mean(hist_a[:10])
    assert all(np.array_equal(x, y) for x, y in zip(before, _leaves(state_pure_dict(pol))))
    c, _ = train(_policy(0), (obs, actions), SOFT, jax.random.key(2), 3, progress=False)
    assert not _bitwise_equal(state_pure_dict(a), state_pure_dict(c))


def test_train_with_batch_iterator(soft_step):
    """T-9 T-10: an iterable of batches is consumed one per step; running out or bad arguments raise."""
    obs, actions = _data(32)
    batches = [(obs[i:i + B], actions[i:i + B]) for i in range(0, 32, B)]
    pol, hist = train(_policy(0), iter(batches), SOFT, jax.random.key(3), 4, progress=False)
    assert isinstance(pol, FlowPolicy) and hist.shape == (4,)
    with pytest.raises(ValueError, match="ran out"):
        train(_policy(0), iter(batches), SOFT, jax.random.key(3), 5, progress=False)
    with pytest.raises(ValueError, match="num_steps"):
        train(_policy(0), (obs, actions), SOFT, jax.random.key(3), 0)
    with pytest.raises(ValueError, match="progress"):
        train(_policy(0), (obs, actions), SOFT, jax.random.key(3), 1, progress="yes")
    with pytest.raises(ValueError, match="data"):
        train(_policy(0), 42, SOFT, jax.random.key(3), 1)
    with pytest.raises(ValueError, match="batch_size"):
        train(_policy(0), (obs[:4], actions[:4]), SOFT, jax.random.key(3), 1)
    with pytest.raises(ValueError, match="key"):
        train(_policy(0), (obs, actions), SOFT, 3, 1)


# ----------------------------------------------------------------------------- checkpoints


def _raw(path):
    with np.load(path, allow_pickle=False) as z:
        members = {k: z[k] for k in z.files}
    return json.loads(members.pop(C.HEADER_KEY).tobytes()), members


def _write(path, header, members, fix_checksum=True):
    if fix_checksum:
        header = dict(header, checksum=C.checkpoint_checksum(header, members))
    out = dict(members)
    out[C.HEADER_KEY] = np.frombuffer(json.dumps(header).encode(), np.uint8)
    with open(path, "wb") as f:
        np.savez(f, **out)


def test_checkpoint_roundtrip(tmp_path):
    """T-11: the file is self-describing (tag, version, constructor config, checksum) and round-trips bitwise."""
    pol = _policy(4, randomize=True)
    meta = {"step": 12, "train_config": SOFT.to_dict(), "note": "ok"}
    path = tmp_path / "p.npz"
    C.save_checkpoint(path, pol, meta)
    header, members = _raw(path)
    assert header["format"] == C.FORMAT and header["version"] == C.VERSION
    assert header["policy"] == {"obs_dim": OBS, "action_dim": ACT, "config": {
        "channel_dim": 16, "channel_hidden_dim": 16, "token_hidden_dim": 4, "num_layers": 1, "action_chunk_size": 6}}
    assert header["checksum"] == C.checkpoint_checksum(header, members)
    # The byte stream of [T-11], written out independently of checkpoint_checksum.
    import hashlib
    import json as _json
    h = hashlib.sha256(_json.dumps({k: v for k, v in header.items() if k != "checksum"}, sort_keys=True,
                                   separators=(",", ":")).encode())
    for name in sorted(members):
        a = np.ascontiguousarray(members[name])
        for part in (name.encode(), a.dtype.str.encode(), str(list(a.shape)).encode()):
            h.update(len(part).to_bytes(8, "little") + part)
        h.update(a.tobytes())
    assert header["checksum"] == "sha256:" + h.hexdigest()
    import os
    import stat
    umask = os.umask(0)
    os.umask(umask)
    assert stat.S_IMODE(os.stat(path).st_mode) == 0o666 & ~umask  # not owner-only
    assert "params/mlp_stack/0/adaln_1/kernel" in members
    restored, got_meta = C.load_checkpoint(path)
    assert got_meta == meta and TrainConfig.from_dict(got_meta["train_config"]) == SOFT
    assert _bitwise_equal(state_pure_dict(restored), state_pure_dict(pol))
    # Loading into an existing policy of the same architecture replaces its parameters in place.
    target = _policy(9)
    C.load_checkpoint(path, target)
    assert _bitwise_equal(state_pure_dict(target), state_pure_dict(pol))
    assert not list(tmp_path.glob(".ckpt-*"))  # no temporary file left behind


def test_checkpoint_rejects_damaged_files(tmp_path):
    """T-12: truncated or garbled bytes, wrong tag or version, checksum and tree mismatches raise ValueError."""
    path = tmp_path / "good.npz"
    C.save_checkpoint(path, _policy(0), {"step": 1})
    raw = path.read_bytes()
    header, members = _raw(path)

    def expect(name, data_or_writer, match):
        p = tmp_path / name
        if isinstance(data_or_writer, bytes):
            p.write_bytes(data_or_writer)
        else:
            data_or_writer(p)
        with pytest.raises(ValueError, match=match):
            C.load_checkpoint(p)

    expect("trunc.npz", raw[: len(raw) // 2], "corrupt")
    expect("empty.npz", b"", "corrupt")
    garbled = bytearray(raw)
    mid = len(raw) // 2
    garbled[mid:mid + 64] = bytes(b ^ 0xFF for b in garbled[mid:mid + 64])
    expect("garbled.npz", bytes(garbled), "corrupt|checksum|header|dtype")
    expect("tag.npz", lambda p: _write(p, dict(header, format="other"), members), "format tag")
    expect("version.npz", lambda p: _write(p, dict(header, version=2), members), "version")
    expect("nohead.npz", lambda p: np.savez(open(p, "wb"), **members), "__header__")
    tampered = dict(members)
    name = "params/out_proj/bias"
    tampered[name] = members[name] + 1.0
    expect("sum.npz", lambda p: _write(p, header, tampered, fix_checksum=False), "checksum")
    expect("meta.npz", lambda p: _write(p, dict(header, metadata={"step": 2}), members, fix_checksum=False),
           "checksum")
    # A consistent file whose arrays do not fit its policy config.
    cfg = dict(header["policy"]["config"], channel_dim=8)
    expect("tree.npz", lambda p: _write(p, dict(header, policy=dict(header["policy"], config=cfg)), members),
           "does not match.*shape")
    fewer = {k: v for k, v in members.items() if k != name}
    arrays = {k: v for k, v in header["arrays"].items() if k != name}
    expect("missing.npz", lambda p: _write(p, dict(header, arrays=arrays), fewer), "missing key")
    expect("unlisted.npz", lambda p: _write(p, header, fewer), "differ from the header")
    bad_cfg = dict(header["policy"]["config"], channel_dim=7)
    expect("cfg.npz", lambda p: _write(p, dict(header, policy=dict(header["policy"], config=bad_cfg)), members),
           "policy constructor config")
    # A single .npy array and NaN in the metadata are damaged files too, named in the message.
    expect("single.npz", lambda p: np.save(open(p, "wb"), np.zeros(3)), r"single\.npz.*\.npy")
    expect("nan.npz", lambda p: _write(p, dict(header, metadata={"a": float("nan")}), members, fix_checksum=False),
           r"nan\.npz.*corrupt header")
    other = FlowPolicy(obs_dim=OBS, action_dim=ACT + 1, config=TINY, rngs=nnx.Rngs(0))
    with pytest.raises(ValueError, match="differs from the given policy"):
        C.load_checkpoint(path, other)


def test_checkpoint_rejects_appended_bytes_and_deep_headers(tmp_path):
    """T-12: bytes after the archive's end and a header nested past the JSON reader's depth are damaged files."""
    path = tmp_path / "good.npz"
    C.save_checkpoint(path, _policy(0), {"step": 1})
    raw = path.read_bytes()
    header, members = _raw(path)
    for name, tail in (("tail.npz", b"garbage"), ("zeros.npz", bytes(4096)), ("one.npz", b"\0")):
        (tmp_path / name).write_bytes(raw + tail)
        with pytest.raises(ValueError, match=rf"{name}.*{len(tail)} bytes after the end of the archive"):
            C.load_checkpoint(tmp_path / name)
    # A record cut inside its 22 bytes is damaged as well.
    (tmp_path / "cut.npz").write_bytes(raw[:-3])
    with pytest.raises(ValueError, match=r"cut\.npz.*corrupt"):
        C.load_checkpoint(tmp_path / "cut.npz")
    deep = dict(members)
    deep[C.HEADER_KEY] = np.frombuffer(("[" * 100_000 + "]" * 100_000).encode(), np.uint8)
    with open(tmp_path / "deep.npz", "wb") as f:
        np.savez(f, **deep)
    with pytest.raises(ValueError, match=r"deep\.npz.*corrupt header.*nested too deeply"):
        C.load_checkpoint(tmp_path / "deep.npz")
    # Metadata just shallow enough for json.loads still reaches the checksum's recursive checks.
    import sys
    nested: list = []
    for _ in range(sys.getrecursionlimit() - 60):
        nested = [nested]
    text = json.dumps(dict(header, metadata={"x": None})).replace('{"x": null}', '{"x": ' + json.dumps(nested) + "}")
    near = dict(members)
    near[C.HEADER_KEY] = np.frombuffer(text.encode(), np.uint8)
    with open(tmp_path / "near.npz", "wb") as f:
        np.savez(f, **near)
    with pytest.raises(ValueError, match=r"near\.npz.*corrupt header"):
        C.load_checkpoint(tmp_path / "near.npz")
    C.load_checkpoint(path)  # the untouched file still loads


def test_checkpoint_argument_validation(tmp_path):
    """T-10 T-11: bad paths, policies and non-JSON metadata are rejected before anything is written."""
    pol = _policy(0)
    with pytest.raises(ValueError, match="metadata"):
        C.save_checkpoint(tmp_path / "a.npz", pol, {"x": float("nan")})
    with pytest.raises(ValueError, match="metadata"):
        C.save_checkpoint(tmp_path / "a.npz", pol, {"x": object()})
    with pytest.raises(ValueError, match="metadata"):
        C.save_checkpoint(tmp_path / "a.npz", pol, {1: "int key"})
    with pytest.raises(ValueError, match="policy"):
        C.save_checkpoint(tmp_path / "a.npz", {"w": 1}, {})
    with pytest.raises(ValueError, match="directory"):
        C.save_checkpoint(tmp_path / "no" / "a.npz", pol, {})
    with pytest.raises(ValueError, match="path"):
        C.load_checkpoint(tmp_path / "absent.npz")
    with pytest.raises(ValueError, match="got the directory"):
        C.save_checkpoint(tmp_path, pol, {})
    with pytest.raises(ValueError, match="string keys at every depth"):
        C.save_checkpoint(tmp_path / "a.npz", pol, {"a": {1: 2}})
    for header, arrays, word in (({1: 2}, {}, "str keys"), ({"a": {1, 2}}, {}, "JSON values"),
                                 ({}, {1: np.zeros(2)}, "str name")):
        with pytest.raises(ValueError, match=word):
            C.checkpoint_checksum(header, arrays)
    assert not (tmp_path / "a.npz").exists()
