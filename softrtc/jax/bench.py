"""Runtime benchmark of chunk generation and training steps (spec chapter B, ``spec/32-runtime-bench.md``).

``softrtc bench runtime`` measures, in the spirit of the paper's efficiency
benchmark (Table main, "Runtime / Naive"), the steady-state latency of one
chunk-generation call per method after JIT warm-up, at several batch sizes,
as a median over many calls and as a ratio to the naive sampler measured in
the same run ([B-1], [B-6]); and the time of one training step of Soft RTC
relative to Hard RTC and to plain flow matching ([B-8]).

>>> cfg = BenchConfig(calls=2, warmup=1, batch_sizes=(1,), train_calls=1, train_batch=2, arch="tiny")
>>> res = run_benchmark(cfg)                                   # doctest: +SKIP
>>> from softrtc.jax.bench_report import format_table
>>> print(format_table(res))                                   # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import os
import platform
import statistics
import time
from functools import partial
from typing import Any, Callable, Iterable

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from softrtc.reference._validate import check_choice, check_int

from .bench_config import (ARCHS, ATOL, CHUNK_ROWS, GUIDED_VS_PUBLIC_LIMIT, NAIVE_VS_STRAIGHTFORWARD_LIMIT,
                           PUBLIC_ROWS, REFERENCE_ROWS, ROW_STEPS, RTOL, SOFT_STEP_LIMIT, TRAIN_METHODS, TRAIN_ROWS,
                           TRAIN_SAMPLER_LIMIT, BenchConfig, inputs, make_policy)
from .bench_report import cpu_model
from .endpoints import delay_scaled
from .fast_chunks import FastChunks, guided_tokens_for
from .guidance import guided_sample
from .methods import generate_chunk, method_weights
from .policy import FlowPolicy
from .sampler import naive_conditioning
from .training import TrainConfig, make_train_step
from .vjp import autodiff_vjps
from .weights import SoftWindow

__all__ = [
    "ARCHS",
    "CHUNK_ROWS",
    "BenchConfig",
    "build_rows",
    "check_agreement",
    "guided_tokens_for",
    "make_policy",
    "run_benchmark",
]

# --------------------------------------------------------------------------- chunk functions


def _scalar_time(policy: FlowPolicy) -> Callable:
    """``velocity_fn`` that evaluates the policy at one time per sample ([S-2], [G-2], [P-9]).

    Naive and guided samplers give every token the same time t_k; passing
    ``t[:, 0]`` (shape [B]) makes the policy compute its time conditioning once
    per sample, the public release's scalar-time behaviour.
    """
    return lambda obs, x, t: policy(obs, x, t[:, 0])


def _window(spec):
    return None if spec is None else SoftWindow(rule=delay_scaled(spec[0], spec[1]))


@dataclasses.dataclass
class _Row:
    name: str
    method: str
    path: str
    label: str
    call: Callable  # (obs, noise, prior, d) -> chunk
    compilations: Callable[[], int]
    table_seconds: float
    fn: Callable | None = None  # the straightforward row's jitted (leaves, None, obs, noise, prior, d) -> chunk


def _params(policy: FlowPolicy):
    """(graphdef, treedef, leaves): the state is passed to jitted functions as a flat tuple of arrays.

    A tuple of arrays is flattened by jit's C++ dispatch; an ``nnx.State`` goes
    through a Python flatten on every call, a fixed cost that would blur the
    ratios at batch 1.
    """
    graphdef, state = nnx.split(policy)
    leaves, treedef = jax.tree.flatten(state)
    return graphdef, treedef, tuple(leaves)


def _guided_head(policy: FlowPolicy, config: BenchConfig, batch: int) -> int | None:
    """The guided rows' ``guided_tokens`` at this batch size (the same for hard and soft)."""
    return guided_tokens_for("inference_soft", policy.action_chunk_size, config.execute_horizon, batch)


def _straightforward_fn(graphdef, treedef, method, window, s, T, step="algorithm1"):
    def chunk(leaves, tables, obs, noise, prior, d):
        policy = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        vel = policy if method.startswith("train_") else _scalar_time(policy)
        return generate_chunk(method, vel, obs, noise, prior, s, d, T, window, step=step)
    return jax.jit(chunk)


def _step(name: str) -> str:
    """The solver step of row ``name`` ([B-1], [S-10])."""
    return ROW_STEPS.get(name, "algorithm1")


def _public_guided_fn(graphdef, treedef, method, s, T):
    """The guided sampler as the public release runs it ([B-14]): a scanned loop of T Euler steps, each calling
    the policy at one time per sample (its time conditioning computed in the step) and pulling the weighted
    error back by plain autodiff over all tokens (no closed-form LayerNorm VJP [P-17], no stored transposes
    [P-19], no restriction [G-7])."""
    def chunk(leaves, tables, obs, noise, prior, d):
        policy = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        w = method_weights(method, policy.action_chunk_size, s, d)
        # The switch is read while tracing: this function is traced inside it.
        with autodiff_vjps(layer_norm=True, gelu=True):
            return guided_sample(_scalar_time(policy), obs, noise, prior, w, T, unroll=False)
    return jax.jit(chunk)


def _check_config_policy(config: Any, policy: Any) -> None:
    """``config`` a BenchConfig and ``policy`` a FlowPolicy of its horizon ([N-7], [B-2]).

    ``config.execute_horizon`` and the delays were checked against the horizon of
    ``config.arch``; a policy of another ``H`` would index tables out of range.
    """
    if not isinstance(config, BenchConfig):
        raise ValueError(f"config must be a BenchConfig, got {type(config).__name__}")
    if not isinstance(policy, FlowPolicy):
        raise ValueError(f"policy must be a FlowPolicy, got {type(policy).__name__}")
    if policy.action_chunk_size != config.horizon:
        raise ValueError(f"policy must have action_chunk_size H = {config.horizon} (the horizon of "
                         f"config.arch={config.arch!r}, which fixes execute_horizon and the delays), "
                         f"got {policy.action_chunk_size}")


def _check_names(names: Any) -> tuple:
    """Row names: None (all rows) or a non-empty sequence of distinct keys of :data:`CHUNK_ROWS` ([N-7])."""
    if names is None:
        return tuple(CHUNK_ROWS)
    if isinstance(names, (str, bytes)) or not isinstance(names, Iterable):
        raise ValueError(f"names must be None or a sequence of row names from {tuple(CHUNK_ROWS)}, "
                         f"got {type(names).__name__}")
    names = tuple(names)
    if not names:
        raise ValueError(f"names must name at least one row of {tuple(CHUNK_ROWS)}, got none")
    for n in names:
        check_choice("names entry", n, tuple(CHUNK_ROWS))
    if len(set(names)) != len(names):
        raise ValueError(f"names must not repeat a row, got {names!r}")
    return names


def build_rows(config: BenchConfig, policy: FlowPolicy, names=None) -> list[_Row]:
    """The measured rows ([B-1], [B-3], [B-4], [B-7]): one jitted function per row, delay traced.

    ``names`` (default all) restricts the rows to those keys of :data:`CHUNK_ROWS`
    (a non-empty sequence without repeats). ``policy`` must have the horizon of
    ``config.arch``.

    With ``path="fast"`` the seven method rows use the fast path, and the
    straightforward naive and train-soft (lam=2) samplers and the guided soft
    sampler as the public release runs it ([B-14]) are rows of their own;
    with ``path="straightforward"`` the seven method rows are straightforward.
    Fast-path tables are built here, once per parameter set, and timed apart.
    """
    _check_config_policy(config, policy)
    names = _check_names(names)
    graphdef, treedef, leaves = _params(policy)
    s, T = config.execute_horizon, config.num_steps
    specs = [(name, config.path) for name in CHUNK_ROWS if name in names]
    if config.path == "fast":
        specs += [(name, "straightforward") for name in REFERENCE_ROWS if name in names]
        specs += [(name, "public") for name in PUBLIC_ROWS if name in names]
    rows = []
    for name, path in specs:
        method, wspec, label = CHUNK_ROWS[name]
        window = _window(wspec)
        if path == "fast":
            t0 = time.perf_counter()
            fast = FastChunks(policy, method, s, T, window, step=_step(name)).block_until_ready()
            rows.append(_Row(name, method, path, label, fast.chunk, fast.compilations, time.perf_counter() - t0))
        else:
            fn = (_public_guided_fn(graphdef, treedef, method, s, T) if path == "public"
                  else _straightforward_fn(graphdef, treedef, method, window, s, T, _step(name)))
            rows.append(_Row(name, method, path, label, partial(fn, leaves, None), lambda fn=fn: fn._cache_size(),
                             0.0, fn if path == "straightforward" else None))
    return rows


def _row_key(row: _Row, config: BenchConfig) -> str:
    return row.name if row.path == config.path else f"{row.name}/{row.path}"


# --------------------------------------------------------------------------- measurement


def _agreement(rows, reference: dict, state, inputs, delays) -> dict:
    """Max |row - straightforward| per fast (and public-style, [B-14]) row over all delays, and whether it is
    within tolerance ([B-5]); keyed by the row's name, ``name/public`` for a public-style row."""
    out = {}
    obs, noise, prior = inputs
    for row in rows:
        if row.path == "straightforward":
            continue
        worst, ok = 0.0, True
        for d in delays:
            a = np.asarray(row.call(obs, noise, prior, d))
            b = np.asarray(reference[row.name](state, None, obs, noise, prior, d))
            worst = max(worst, float(np.max(np.abs(a - b))))
            ok = ok and bool(np.all(np.abs(a - b) <= ATOL + RTOL * np.abs(b)))
        out[row.name if row.path == "fast" else f"{row.name}/{row.path}"] = {"max_abs_diff": worst, "ok": ok}
    return out


def check_agreement(config: BenchConfig, policy: FlowPolicy, batch: int, names=None) -> dict:
    """Fast against straightforward chunks of the rows ``names`` (default all) at one batch size ([B-5]).

    Returns ``{name: {"max_abs_diff": float, "ok": bool}}`` over every delay of ``config``.
    """
    _check_config_policy(config, policy)
    check_int("batch", batch, 1, 1 << 16)
    names = _check_names(names)
    fast = dataclasses.replace(config, path="fast")
    rows = [r for r in build_rows(fast, policy, names) if r.path == "fast"]
    graphdef, treedef, state = _params(policy)
    reference = {n: _straightforward_fn(graphdef, treedef, CHUNK_ROWS[n][0], _window(CHUNK_ROWS[n][1]),
                                        config.execute_horizon, config.num_steps, _step(n)) for n in names}
    delays = [jnp.asarray(d, jnp.int32) for d in config.delays]
    return _agreement(rows, reference, state, inputs(config, policy, batch, 1)[0], delays)


def _time_round_robin(fns: dict[str, Callable[[int], Any]], calls: int, warmup: int,
                      seed: int = 0) -> dict[str, list]:
    """Seconds per call of every entry, interleaved in rounds ([B-6]).

    Each round calls every function once in an order drawn afresh from a
    seeded generator, so that no entry always follows the same one: a fixed
    cyclic order would let a heavy row (the guided samplers evict caches)
    slow down the row after it in every round. The first ``warmup`` rounds
    are discarded.
    """
    names = list(fns)
    times = {n: [] for n in names}
    rng = np.random.default_rng(seed)
    for i in range(warmup + calls):
        for j in rng.permutation(len(names)):
            n = names[j]
            t0 = time.perf_counter()
            jax.block_until_ready(fns[n](i))
            dt = time.perf_counter() - t0
            if i >= warmup:
                times[n].append(dt)
    return times


def _stats(ts: list, base: list | None) -> dict:
    med = statistics.median(ts)
    out = {"median_ms": 1e3 * med, "p10_ms": 1e3 * float(np.percentile(ts, 10)),
           "p90_ms": 1e3 * float(np.percentile(ts, 90)), "calls": len(ts)}
    if base is not None:
        out["ratio"] = med / statistics.median(base)
        # Ratio of the two rows' times in the same round, median over rounds: robust to slow drifts.
        out["paired_ratio"] = float(np.median(np.asarray(ts) / np.asarray(base)))
    return out


def _reporter(config, progress) -> Callable[[str], None]:
    """Checks the arguments every benchmark run takes ([N-7]); returns the progress callback (a no-op for None)."""
    if not isinstance(config, BenchConfig):
        raise ValueError(f"config must be a BenchConfig, got {type(config).__name__}")
    if progress is not None and not callable(progress):
        raise ValueError("progress must be callable with one string argument, or None")
    return progress or (lambda msg: None)


def run_benchmark(config: BenchConfig = BenchConfig(), *, progress: Callable[[str], None] | None = None) -> dict:
    """Run the whole benchmark ([B-1]..[B-9]); returns the JSON-able result of [B-10]."""
    say = _reporter(config, progress)
    t_start = time.perf_counter()
    policy = make_policy(config)
    graphdef, treedef, state = _params(policy)
    rows = build_rows(config, policy)
    # Straightforward function of every method, for the agreement check (shared with its row if measured).
    reference = {}
    for name, (method, wspec, _) in CHUNK_ROWS.items():
        own = [r.fn for r in rows if r.name == name and r.path == "straightforward"]
        reference[name] = own[0] if own else _straightforward_fn(graphdef, treedef, method, _window(wspec),
                                                                 config.execute_horizon, config.num_steps,
                                                                 _step(name))
    delays = [jnp.asarray(d, jnp.int32) for d in config.delays]
    naive_key = "naive"

    result: dict = {
        "config": dataclasses.asdict(config),
        "architecture": {"obs_dim": policy.obs_dim, "action_dim": policy.action_dim,
                         **dataclasses.asdict(policy.config), "parameters": int(sum(
                             np.size(a) for a in jax.tree.leaves(nnx.state(policy, nnx.Param))))},
        "environment": {"jax": jax.__version__, "backend": jax.default_backend(),
                        "device": str(jax.devices()[0].device_kind), "cpu_count": os.cpu_count(),
                        "cpu_model": cpu_model(),
                        "machine": platform.machine(), "python": platform.python_version()},
        "tolerance": {"atol": ATOL, "rtol": RTOL},
        "table_build_ms": {r.name: 1e3 * r.table_seconds for r in rows if r.path == "fast"},
        "chunk": {}, "agreement": {}, "compilations": {}, "vjp_cost": {}, "restricted_pullback": {},
        "train_step": None, "targets": []}
    keys = [_row_key(r, config) for r in rows]
    result["rows"] = [{"key": k, "name": r.name, "method": r.method, "path": r.path, "label": r.label}
                      for k, r in zip(keys, rows)]

    for B in config.batch_sizes:
        sets = inputs(config, policy, B, 4)
        say(f"batch {B}: compiling and checking agreement")
        result["agreement"][str(B)] = _agreement(rows, reference, state, sets[0], delays)

        def call(row):
            return lambda i: row.call(*sets[i % len(sets)], delays[i % len(delays)])

        say(f"batch {B}: timing {len(rows)} rows x {config.calls} calls")
        times = _time_round_robin({k: call(r) for k, r in zip(keys, rows)}, config.calls, config.warmup,
                                  config.seed)
        result["chunk"][str(B)] = {k: _stats(times[k], times[naive_key]) for k in keys}
        result["compilations"][str(B)] = {k: r.compilations() for k, r in zip(keys, rows)}
        say(f"batch {B}: timing one forward against one forward + VJP")
        result["vjp_cost"][str(B)] = _vjp_cost(config, policy, sets)
        result["restricted_pullback"][str(B)] = _guided_head(policy, config, B) is not None

    if config.train_calls:
        say(f"training steps: {len(TRAIN_METHODS)} methods x {config.train_calls} calls at batch "
            f"{config.train_batch}")
        result["train_step"] = _train_steps(config, policy)
    result["targets"] = _targets(config, result)
    result["seconds"] = time.perf_counter() - t_start
    return result


def _vjp_cost(config: BenchConfig, policy: FlowPolicy, sets: list) -> dict:
    """One policy forward against one forward plus the VJP with respect to x, interleaved ([B-11]).

    Both on the fast path (precomputed conditioning of step 0, observation
    encoded once); the VJP is the guided rows' own, restricted to the tokens
    j < H - s where they restrict ([G-7], :func:`guided_tokens_for`) and multiplying by the stored transposed kernels
    ([P-19]). The ratio is what a guided Euler step costs relative to a naive
    one before any sampler overhead: a floor for the guided rows.
    """
    graphdef, treedef, state = _params(policy)
    cond = jax.tree.map(lambda a: a[0], naive_conditioning(policy, config.num_steps))
    head = _guided_head(policy, config, sets[0][0].shape[0])

    def merged(leaves, obs):
        p = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        return p, p.encode_obs(obs)

    def forward(leaves, obs, x):
        p, enc = merged(leaves, obs)
        return p.apply_conditioned(obs, x, cond, obs_encoding=enc)

    def fwd_vjp(leaves, kernels_t, obs, x, ct):
        p, enc = merged(leaves, obs)
        if head is None:
            v, pullback = jax.vjp(lambda x: p.apply_conditioned(obs, x, cond, obs_encoding=enc,
                                                                 pullback=kernels_t), x)
            return v, pullback(ct)[0]

        def head_velocity(x):
            v_head, v_tail = p.apply_conditioned_split(obs, x, cond, head, obs_encoding=enc, pullback=kernels_t)
            return v_head, jnp.concatenate([v_head, v_tail], axis=1)

        _, pullback, v = jax.vjp(head_velocity, x, has_aux=True)
        return v, pullback(ct[:, :head])[0]

    forward = jax.jit(forward)
    fwd_vjp = jax.jit(fwd_vjp)
    kernels_t = jax.block_until_ready(policy.pullback_kernels())
    fns = {"forward": lambda i: forward(state, sets[i % len(sets)][0], sets[i % len(sets)][1]),
           "forward_vjp": lambda i: fwd_vjp(state, kernels_t, *sets[i % len(sets)])}
    times = _time_round_robin(fns, config.calls, config.warmup, config.seed)
    f, fv = statistics.median(times["forward"]), statistics.median(times["forward_vjp"])
    return {"forward_ms": 1e3 * f, "forward_vjp_ms": 1e3 * fv, "ratio": fv / f}


def _train_steps(config: BenchConfig, policy: FlowPolicy) -> dict:
    """Training-step time of none / hard / soft, interleaved ([B-8])."""
    rng = np.random.default_rng([config.seed, 1 << 20])
    B, H, A, O = config.train_batch, policy.action_chunk_size, policy.action_dim, policy.obs_dim
    obs = jax.device_put(rng.standard_normal((B, O)).astype(np.float32))
    actions = jax.device_put(rng.standard_normal((B, H, A)).astype(np.float32))
    d_max = min(4, H)
    steps, states = {}, {}
    for m in TRAIN_METHODS:
        cfg = TrainConfig(method=m, batch_size=B, execute_horizon=config.execute_horizon, d_max=d_max)
        steps[m] = make_train_step(policy, cfg)
        states[m] = steps[m].init_state()
    keys = jax.random.split(jax.random.key(config.seed), 8)

    def call(m):
        def f(i):
            # The state is fed back so that every call is a real update of the current parameters.
            states[m], metrics = steps[m].jitted(states[m], obs, actions, keys[i % len(keys)])
            return states[m], metrics
        return f

    times = _time_round_robin({m: call(m) for m in TRAIN_METHODS}, config.train_calls, config.warmup,
                              config.seed)
    out = {"batch": B, "d_max": d_max}
    for m in TRAIN_METHODS:
        out[m] = _stats(times[m], None)
    out["soft_over_hard"] = out["soft"]["median_ms"] / out["hard"]["median_ms"]
    out["soft_over_none"] = out["soft"]["median_ms"] / out["none"]["median_ms"]
    out["hard_over_none"] = out["hard"]["median_ms"] / out["none"]["median_ms"]
    out["soft_over_hard_paired"] = float(np.median(np.asarray(times["soft"]) / np.asarray(times["hard"])))
    return out


def _targets(config: BenchConfig, res: dict) -> list[dict]:
    """PASS/FAIL of every target of [B-9] (timing targets apply to the fast path only)."""
    out = []

    def add(tid, what, value, limit, passed=None):
        out.append({"id": tid, "target": what, "value": value, "limit": limit,
                    "pass": bool(value <= limit) if passed is None else passed})

    agree = [a for per_b in res["agreement"].values() for a in per_b.values()]
    if agree:
        worst = max(a["max_abs_diff"] for a in agree)
        add("B-5", "fast and straightforward chunks agree", worst, None, all(a["ok"] for a in agree))
    if config.path != "fast":
        return out
    for B in config.batch_sizes:
        ch = res["chunk"][str(B)]
        train = max(ch[k]["ratio"] for k in TRAIN_ROWS if k in ch)
        add("B-9", f"train-time samplers / naive, batch {B}", train, TRAIN_SAMPLER_LIMIT)
        add("B-9", f"naive / straightforward naive, batch {B}",
            ch["naive"]["median_ms"] / ch["naive/straightforward"]["median_ms"], NAIVE_VS_STRAIGHTFORWARD_LIMIT)
        if "inference_soft/public" in ch:
            guided = max(ch[k]["median_ms"] for k in ("inference_hard", "inference_soft"))
            add("B-9", f"guided samplers / public-style guided, batch {B}",
                guided / ch["inference_soft/public"]["median_ms"], GUIDED_VS_PUBLIC_LIMIT)
    if res["train_step"] is not None:
        add("B-9", "soft / hard training step", res["train_step"]["soft_over_hard"], SOFT_STEP_LIMIT)
    return out
