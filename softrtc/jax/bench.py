"""Runtime benchmark of chunk generation and training steps (spec chapter B, ``spec/32-runtime-bench.md``).

``softrtc bench runtime`` measures, in the spirit of the paper's efficiency
benchmark (Table main, "Runtime / Naive"), the steady-state latency of one
chunk-generation call per method after JIT warm-up, at several batch sizes,
as a median over many calls and as a ratio to the naive sampler measured in
the same run ([B-1], [B-6]); and the time of one training step of Soft RTC
relative to Hard RTC and to plain flow matching ([B-8]).

>>> cfg = BenchConfig(calls=2, warmup=1, batch_sizes=(1,), train_calls=1, train_batch=2, arch="tiny")
>>> res = run_benchmark(cfg)                                   # doctest: +SKIP
>>> print(format_table(res))                                   # doctest: +SKIP
"""

from __future__ import annotations

import dataclasses
import json
import math
import numbers
import os
import platform
import statistics
import time
from typing import Any, Callable, Iterable, Mapping

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import write_atomic
from softrtc.reference._validate import check_choice, check_int

from .endpoints import delay_scaled
from .methods import delay_rows, generate_chunk, generate_chunk_from_row, method_tables
from .policy import FlowPolicy, PolicyConfig
from .sampler import naive_conditioning
from .training import TrainConfig, make_train_step
from .weights import SoftWindow

__all__ = [
    "ARCHS",
    "CHUNK_ROWS",
    "BenchConfig",
    "build_rows",
    "cpu_model",
    "guided_tokens_for",
    "run_benchmark",
    "run_vjp_ablation",
    "format_vjp_table",
    "VJP_VARIANTS",
    "format_table",
    "write_json",
]

# [B-2] Benchmark architecture (spec chapter P defaults) and a tiny one for smoke runs and tests.
ARCHS = {
    "benchmark": dict(obs_dim=679, action_dim=6, config=PolicyConfig()),
    "tiny": dict(obs_dim=7, action_dim=3,
                 config=PolicyConfig(channel_dim=16, channel_hidden_dim=24, token_hidden_dim=6, num_layers=1,
                                     action_chunk_size=8)),
}

# [B-1] Chunk-generation rows: name -> (method of [S-6], soft window or None, label).
CHUNK_ROWS = {
    "naive": ("naive", None, "naive (base policy)"),
    "inference_hard": ("inference_hard", None, "inference hard RTC"),
    "inference_soft": ("inference_soft", None, "inference soft RTC"),
    "train_hard": ("train_hard", None, "train hard RTC"),
    "train_soft_lam1": ("train_soft", (1.0, 5), "train soft RTC (lam=1)"),
    "train_soft_lam2": ("train_soft", (2.0, 5), "train soft RTC (lam=2)"),
}
# [B-4] Straightforward reference rows measured next to the fast path.
REFERENCE_ROWS = ("naive", "train_soft_lam2")
TRAIN_METHODS = ("none", "hard", "soft")

# [B-5] Fast and straightforward chunks agree within this float32 tolerance: |a - b| <= ATOL + RTOL |b|.
ATOL = RTOL = 1e-4

# [B-9] Targets (limits on ratios of medians).
TRAIN_SAMPLER_LIMIT = 1.05
NAIVE_VS_STRAIGHTFORWARD_LIMIT = 0.9
SOFT_STEP_LIMIT = 1.03
GUIDED_LIMIT_B1 = 1.7
GUIDED_LIMIT = 2.0

# [B-3] The guided rows restrict their pull-back ([G-7]) when each of the two token groups it
# evaluates has at least this many rows (batch * min(H - s, s)).
RESTRICT_MIN_ROWS = 16


# --------------------------------------------------------------------------- config


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """Everything the benchmark varies ([B-2], [B-6], [B-8]); every field is validated.

    ``delay`` is ``None`` to rotate d over 0 .. min(s, H - s) across calls
    (default), or one fixed delay. ``path`` selects the implementation of the
    six method rows ("fast" or "straightforward", [B-3], [B-4]).
    """

    calls: int = 200
    warmup: int = 5
    batch_sizes: tuple = (1, 32)
    delay: int | None = None
    seed: int = 0
    num_steps: int = 5
    execute_horizon: int = 4
    path: str = "fast"
    train_batch: int = 32
    train_calls: int = 50
    arch: str = "benchmark"

    def __post_init__(self) -> None:
        check_int("calls", self.calls, 1, 10**7)
        check_int("warmup", self.warmup, 1, 10**6)
        if not isinstance(self.batch_sizes, tuple) or not self.batch_sizes:
            raise ValueError(f"batch_sizes must be a non-empty tuple of integers >= 1, got {self.batch_sizes!r}")
        for b in self.batch_sizes:
            check_int("batch_sizes entry", b, 1, 1 << 16)
        if len(set(self.batch_sizes)) != len(self.batch_sizes):
            raise ValueError(f"batch_sizes must not repeat a size, got {self.batch_sizes!r}")
        check_choice("arch", self.arch, tuple(ARCHS))
        H = ARCHS[self.arch]["config"].action_chunk_size
        check_int("execute_horizon", self.execute_horizon, 1, H)
        if self.delay is not None:
            check_int("delay", self.delay, 0, self.max_delay)
        check_int("seed", self.seed, 0, 2**31 - 1)
        check_int("num_steps", self.num_steps, 1, 1000)
        check_choice("path", self.path, ("fast", "straightforward"))
        check_int("train_batch", self.train_batch, 1, 1 << 16)
        check_int("train_calls", self.train_calls, 0, 10**7)

    @property
    def horizon(self) -> int:
        return ARCHS[self.arch]["config"].action_chunk_size

    @property
    def max_delay(self) -> int:
        """Largest executable delay min(s, H - s) ([X-1])."""
        return min(self.execute_horizon, self.horizon - self.execute_horizon)

    @property
    def delays(self) -> tuple:
        """Delays used call by call: rotating 0 .. max_delay, or the fixed one ([B-2])."""
        return tuple(range(self.max_delay + 1)) if self.delay is None else (self.delay,)


# --------------------------------------------------------------------------- policy and inputs


def make_policy(config: BenchConfig) -> FlowPolicy:
    """The benchmark policy ([B-2]): seed-initialised, adaLN kernels redrawn so that time matters.

    adaLN-zero initialisation ([P-6]) makes a fresh network independent of
    time, which would make the path-agreement check of [B-5] vacuous.
    """
    if not isinstance(config, BenchConfig):
        raise ValueError(f"config must be a BenchConfig, got {type(config).__name__}")
    arch = ARCHS[config.arch]
    policy = FlowPolicy(obs_dim=arch["obs_dim"], action_dim=arch["action_dim"], config=arch["config"],
                        rngs=nnx.Rngs(config.seed))
    rng = np.random.default_rng(config.seed)
    for block in policy.mlp_stack:
        for lin in (block.adaln_1, block.adaln_2):
            lin.kernel[...] = jnp.asarray(0.02 * rng.standard_normal(lin.kernel.shape), jnp.float32)
    policy.final_adaln.kernel[...] = jnp.asarray(0.02 * rng.standard_normal(policy.final_adaln.kernel.shape),
                                                 jnp.float32)
    return policy


def _inputs(config: BenchConfig, policy: FlowPolicy, batch: int, count: int) -> list[tuple]:
    """``count`` input sets (obs, noise, prior) on the device, drawn once so no call times a draw."""
    rng = np.random.default_rng([config.seed, batch])
    H, A, O = policy.action_chunk_size, policy.action_dim, policy.obs_dim
    out = []
    for _ in range(count):
        out.append(tuple(jax.device_put(np.asarray(a, np.float32)) for a in (
            rng.standard_normal((batch, O)), rng.standard_normal((batch, H, A)), rng.standard_normal((batch, H, A)))))
    return out


# --------------------------------------------------------------------------- chunk functions


class _Encoded:
    """The policy seen through one observation encoding ([B-3]) and, optionally, its pull-back kernels ([P-19]).

    Exposes the ``time_conditioning`` / ``apply_conditioned`` interface that
    the conditioned samplers use, with ``in_proj``'s observation half computed
    once per sampler call instead of once per Euler step.
    """

    def __init__(self, policy: FlowPolicy, obs_encoding: jax.Array, pullback=None):
        self.policy = policy
        self.obs_encoding = obs_encoding
        self.pullback = pullback

    def time_conditioning(self, t):
        return self.policy.time_conditioning(t)

    def apply_conditioned(self, obs, x, cond):
        return self.policy.apply_conditioned(obs, x, cond, obs_encoding=self.obs_encoding, pullback=self.pullback)

    def apply_conditioned_split(self, obs, x, cond, head):
        return self.policy.apply_conditioned_split(obs, x, cond, head, obs_encoding=self.obs_encoding,
                                                   pullback=self.pullback)


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
    fn: Callable  # jitted (state, tables, obs, noise, prior, d) -> chunk
    tables: Any
    table_seconds: float

    def tables_for(self, d: int):
        """What ``fn`` takes for delay ``d``: the fast path's per-delay row, looked up on the host, with the
        policy's pull-back kernels for the guided rows ([B-3])."""
        return self.tables[d] if self.path == "fast" else self.tables


def _params(policy: FlowPolicy):
    """(graphdef, treedef, leaves): the state is passed to jitted functions as a flat tuple of arrays.

    A tuple of arrays is flattened by jit's C++ dispatch; an ``nnx.State`` goes
    through a Python flatten on every call, a fixed cost that would blur the
    ratios at batch 1.
    """
    graphdef, state = nnx.split(policy)
    leaves, treedef = jax.tree.flatten(state)
    return graphdef, treedef, tuple(leaves)


def guided_tokens_for(method: str, H: int, s: int, batch: int) -> int | None:
    """``guided_tokens`` of the benchmark's fast path: ``H - s`` or None (the full pull-back) ([B-3], [G-7]).

    Only the guided methods restrict, and only when each token group of the
    split evaluation ([P-18]) has at least :data:`RESTRICT_MIN_ROWS` rows,
    ``batch * min(H - s, s) >= 16``. The split runs the last layers' matrix
    products twice on half the rows; on XLA:CPU a product with few rows costs
    about as much as one with twice as many, so with small batches the split
    costs more forward time than the restricted backward saves.

    >>> guided_tokens_for("inference_soft", 8, 4, 1), guided_tokens_for("inference_soft", 8, 4, 32)
    (None, 4)
    """
    check_choice("method", method, tuple(dict.fromkeys(m for m, _, _ in CHUNK_ROWS.values())))
    H = check_int("H", H, 1)
    s = check_int("s", s, 1, H)
    batch = check_int("batch", batch, 1)
    if not method.startswith("inference_") or s == H or batch * min(H - s, s) < RESTRICT_MIN_ROWS:
        return None
    return H - s


def _guided_head(policy: FlowPolicy, config: BenchConfig, batch: int) -> int | None:
    """The guided rows' ``guided_tokens`` at this batch size (the same for hard and soft)."""
    return guided_tokens_for("inference_soft", policy.action_chunk_size, config.execute_horizon, batch)


def _fast_fn(graphdef, treedef, method, window, s, T, H, guided="rule"):
    # ``row`` is delay_rows(method, method_tables(...))[d], picked on the host: the delay
    # selects an input of fixed shape, so one compilation serves every delay.
    # ``guided`` is "rule" (guided_tokens_for at the traced batch size) or an explicit guided_tokens.
    def chunk(leaves, tables, obs, noise, prior, d):
        row, pullback = tables
        policy = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        model = _Encoded(policy, policy.encode_obs(obs), pullback)
        # [G-7] Guidance weights vanish for j >= H - s: with enough rows the pull-back skips those tokens' last layers.
        tokens = guided_tokens_for(method, H, s, obs.shape[0]) if guided == "rule" else guided
        return generate_chunk_from_row(method, model, obs, noise, prior, T, row, guided_tokens=tokens)
    return jax.jit(chunk)


def _straightforward_fn(graphdef, treedef, method, window, s, T):
    def chunk(leaves, tables, obs, noise, prior, d):
        policy = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
        vel = policy if method.startswith("train_") else _scalar_time(policy)
        return generate_chunk(method, vel, obs, noise, prior, s, d, T, window)
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

    With ``path="fast"`` the six method rows use the fast path and the
    straightforward naive and train-soft (lam=2) samplers are rows of their
    own; with ``path="straightforward"`` the six method rows are straightforward.
    Fast-path tables are built here, once per parameter set, and timed apart.
    """
    _check_config_policy(config, policy)
    names = _check_names(names)
    graphdef, treedef, _ = _params(policy)
    H, s, T = policy.action_chunk_size, config.execute_horizon, config.num_steps
    specs = [(name, config.path) for name in CHUNK_ROWS if name in names]
    if config.path == "fast":
        specs += [(name, "straightforward") for name in REFERENCE_ROWS if name in names]
    rows, kernels_t = [], None
    for name, path in specs:
        method, wspec, label = CHUNK_ROWS[name]
        window = _window(wspec)
        if path == "fast":
            t0 = time.perf_counter()
            per_delay = delay_rows(method, method_tables(method, policy, H, s, T, window))
            # [P-19] The guided rows' VJP multiplies by transposed kernels, stored once per parameter set
            # and shared by both guided rows.
            if method.startswith("inference_") and kernels_t is None:
                kernels_t = policy.pullback_kernels()
            pullback = kernels_t if method.startswith("inference_") else None
            tables = jax.block_until_ready(tuple((row, pullback) for row in per_delay))
            secs = time.perf_counter() - t0
            fn = _fast_fn(graphdef, treedef, method, window, s, T, H)
        else:
            tables, secs = None, 0.0
            fn = _straightforward_fn(graphdef, treedef, method, window, s, T)
        rows.append(_Row(name, method, path, label, fn, tables, secs))
    return rows


def _row_key(row: _Row, config: BenchConfig) -> str:
    return row.name if row.path == config.path else f"{row.name}/{row.path}"


# --------------------------------------------------------------------------- measurement


def _agreement(rows, reference: dict, state, inputs, delays) -> dict:
    """Max |fast - straightforward| per fast row over all delays, and whether it is within tolerance ([B-5])."""
    out = {}
    obs, noise, prior = inputs
    for row in rows:
        if row.path != "fast":
            continue
        worst, ok = 0.0, True
        for d in delays:
            a = np.asarray(row.fn(state, row.tables_for(d), obs, noise, prior, d))
            b = np.asarray(reference[row.name](state, None, obs, noise, prior, d))
            worst = max(worst, float(np.max(np.abs(a - b))))
            ok = ok and bool(np.all(np.abs(a - b) <= ATOL + RTOL * np.abs(b)))
        out[row.name] = {"max_abs_diff": worst, "ok": ok}
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
                                        config.execute_horizon, config.num_steps) for n in names}
    delays = [jnp.asarray(d, jnp.int32) for d in config.delays]
    return _agreement(rows, reference, state, _inputs(config, policy, batch, 1)[0], delays)


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
                                                                 config.execute_horizon, config.num_steps)
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
        sets = _inputs(config, policy, B, 4)
        say(f"batch {B}: compiling and checking agreement")
        result["agreement"][str(B)] = _agreement(rows, reference, state, sets[0], delays)

        def call(row):
            return lambda i: row.fn(state, row.tables_for(delays[i % len(delays)]), *sets[i % len(sets)],
                                    delays[i % len(delays)])

        say(f"batch {B}: timing {len(rows)} rows x {config.calls} calls")
        times = _time_round_robin({k: call(r) for k, r in zip(keys, rows)}, config.calls, config.warmup,
                                  config.seed)
        result["chunk"][str(B)] = {k: _stats(times[k], times[naive_key]) for k in keys}
        result["compilations"][str(B)] = {k: r.fn._cache_size() for k, r in zip(keys, rows)}
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
        train = max(ch[k]["ratio"] for k in ("train_hard", "train_soft_lam1", "train_soft_lam2"))
        add("B-9", f"train-time samplers / naive, batch {B}", train, TRAIN_SAMPLER_LIMIT)
        add("B-9", f"naive / straightforward naive, batch {B}",
            ch["naive"]["median_ms"] / ch["naive/straightforward"]["median_ms"], NAIVE_VS_STRAIGHTFORWARD_LIMIT)
        guided = max(ch[k]["ratio"] for k in ("inference_hard", "inference_soft"))
        add("B-9", f"guided samplers / naive, batch {B}", guided, GUIDED_LIMIT_B1 if B == 1 else GUIDED_LIMIT)
    if res["train_step"] is not None:
        add("B-9", "soft / hard training step", res["train_step"]["soft_over_hard"], SOFT_STEP_LIMIT)
    return out


# --------------------------------------------------------------------------- pull-back ablation

# [B-12] Variants of the guided soft row: label, LayerNorm VJP by autodiff ([P-17] off), GELU VJP by
# autodiff (as shipped, [P-20]; False = the recomputing VJP), stored transposed kernels ([P-19]), pull-back
# ("rule" = guided_tokens_for, "flip" = the other choice, "full" = over all tokens, [G-7]).
VJP_VARIANTS = {
    "shipped": ("as shipped", False, True, True, "rule"),
    "layer_norm_autodiff": ("LayerNorm VJP by autodiff", True, True, True, "rule"),
    "gelu_recompute": ("GELU VJP recomputing tanh", False, False, True, "rule"),
    "no_stored_transposes": ("no stored transposes", False, True, False, "rule"),
    "other_pullback": ("the other pull-back", False, True, True, "flip"),
    "plain_autodiff": ("plain autodiff, full pull-back", True, True, False, "full"),
}


def _variant_tokens(choice: str, rule: int | None, H: int, s: int) -> int | None:
    if choice == "rule":
        return rule
    if choice == "full" or s == H:
        return None
    return H - s if rule is None else None


def run_vjp_ablation(config: BenchConfig = BenchConfig(), *,
                     progress: Callable[[str], None] | None = None) -> dict:
    """Each design choice of the guided pull-back against the shipped one, side by side ([B-12]).

    The guided soft row (``inference_soft``, fast path) is compiled once per
    variant of :data:`VJP_VARIANTS` and batch size, its chunks are compared
    with the shipped variant's at every delay (they MUST agree within the
    tolerance of [B-5]), and all variants and the naive row are timed
    interleaved as in [B-6]. Uses ``calls``, ``warmup``, ``batch_sizes``,
    ``delay``, ``seed``, ``num_steps``, ``execute_horizon`` and ``arch`` of
    ``config``; the path is always the fast one.
    """
    from .policy import autodiff_vjps

    say = _reporter(config, progress)
    t_start = time.perf_counter()
    config = dataclasses.replace(config, path="fast")
    policy = make_policy(config)
    graphdef, treedef, state = _params(policy)
    H, s, T = policy.action_chunk_size, config.execute_horizon, config.num_steps
    method, wspec, _ = CHUNK_ROWS["inference_soft"]
    window = _window(wspec)
    per_delay = delay_rows(method, method_tables(method, policy, H, s, T, window))
    kernels_t = policy.pullback_kernels()
    naive = [r for r in build_rows(config, policy, ("naive",)) if r.path == "fast"][0]
    delays = [jnp.asarray(d, jnp.int32) for d in config.delays]
    result: dict = {
        "config": dataclasses.asdict(config),
        "environment": {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
                        "cpu_model": cpu_model()},
        "tolerance": {"atol": ATOL, "rtol": RTOL},
        "variants": {k: {"label": v[0], "layer_norm_autodiff": v[1], "gelu_autodiff": v[2],
                         "stored_transposes": v[3], "pullback": v[4]} for k, v in VJP_VARIANTS.items()},
        "chunk": {}, "agreement": {}, "restricted_pullback": {}}
    for B in config.batch_sizes:
        sets = _inputs(config, policy, B, 4)
        rule = guided_tokens_for(method, H, s, B)
        fns, tables = {}, {}
        say(f"batch {B}: compiling {len(VJP_VARIANTS)} variants of the guided soft row")
        for key, (_, ln, ge, stored, choice) in VJP_VARIANTS.items():
            tokens = _variant_tokens(choice, rule, H, s)
            tables[key] = tuple((row, kernels_t if stored else None) for row in per_delay)
            fn = _fast_fn(graphdef, treedef, method, window, s, T, H, guided=tokens)
            # The switch acts while tracing, so lower and compile inside it.
            with autodiff_vjps(layer_norm=ln, gelu=ge):
                fns[key] = fn.lower(state, tables[key][0], *sets[0], delays[0]).compile()
            result["restricted_pullback"].setdefault(str(B), {})[key] = tokens is not None
        agree, obs, noise, prior = {}, *sets[0]
        want = [np.asarray(fns["shipped"](state, tables["shipped"][int(d)], obs, noise, prior, d)) for d in delays]
        for key in VJP_VARIANTS:
            worst, ok = 0.0, True
            for d, b in zip(delays, want):
                a = np.asarray(fns[key](state, tables[key][int(d)], obs, noise, prior, d))
                worst = max(worst, float(np.max(np.abs(a - b))))
                ok = ok and bool(np.all(np.abs(a - b) <= ATOL + RTOL * np.abs(b)))
            agree[key] = {"max_abs_diff": worst, "ok": ok}
        result["agreement"][str(B)] = agree

        def call(fn, tabs):
            return lambda i: fn(state, tabs[int(delays[i % len(delays)])], *sets[i % len(sets)],
                                delays[i % len(delays)])

        timed = {"naive": lambda i: naive.fn(state, naive.tables_for(delays[i % len(delays)]),
                                             *sets[i % len(sets)], delays[i % len(delays)])}
        timed.update({k: call(fns[k], tables[k]) for k in VJP_VARIANTS})
        say(f"batch {B}: timing naive and {len(VJP_VARIANTS)} variants x {config.calls} calls")
        times = _time_round_robin(timed, config.calls, config.warmup, config.seed)
        stats = {k: _stats(times[k], times["naive"]) for k in timed}
        shipped = statistics.median(times["shipped"])
        for k in VJP_VARIANTS:
            stats[k]["over_shipped"] = statistics.median(times[k]) / shipped
        result["chunk"][str(B)] = stats
    result["seconds"] = time.perf_counter() - t_start
    return result


def _formatted(producer: str, fmt: Callable[[dict], str], res: Any, keys: tuple) -> str:
    """``fmt(res)``, with a result that lacks a key it reads reported as ``ValueError`` naming the key ([N-7])."""
    if not isinstance(res, Mapping):
        raise ValueError(f"res must be a result of {producer}, got {type(res).__name__}")
    missing = [k for k in keys if k not in res]
    if missing:
        raise ValueError(f"res must be a result of {producer}; it lacks the key(s) {missing}")
    try:
        return fmt(res)
    except KeyError as exc:
        raise ValueError(f"res must be a complete result of {producer}; it lacks the key {exc.args[0]!r}") from None
    except (TypeError, AttributeError, IndexError, ValueError) as exc:
        raise ValueError(f"res must be a result of {producer}; an entry has the wrong type or form ({exc})") from None


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``, else ``platform.processor()``), or ``"unknown"``.

    Ratios between rows depend on the CPU model, not only on the core count ([B-10]).
    """
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def _machine(env: Mapping) -> str:
    # Results written before the CPU model was recorded lack the key.
    model = env.get("cpu_model")
    return f"{env['backend']} ({env['cpu_count']} cores{', ' + model if model else ''})"


_VJP_KEYS = ("config", "environment", "variants", "chunk", "agreement", "restricted_pullback", "seconds")
_RUNTIME_KEYS = ("config", "architecture", "environment", "rows", "chunk", "agreement", "targets", "seconds")


def format_vjp_table(res: dict) -> str:
    """The printed table of [B-12]: per batch size, every variant's median, ratio to naive and to shipped.

    A result without a key the table reads raises ``ValueError`` naming the key.
    """
    return _formatted("run_vjp_ablation", _format_vjp_table, res, _VJP_KEYS)


def _format_vjp_table(res: dict) -> str:
    cfg = res["config"]
    lines = [f"softrtc bench vjp: guided soft RTC (fast path), {cfg['arch']} network, s {cfg['execute_horizon']}, "
             f"T {cfg['num_steps']}; median of {cfg['calls']} interleaved calls after {cfg['warmup']} warm-up "
             f"rounds; {_machine(res['environment'])}, "
             f"jax {res['environment']['jax']}"]
    for b, stats in res["chunk"].items():
        head = f"{'variant':<32s} {'pull-back':<10s} {'ms':>9s} {'/naive':>7s} {'/shipped':>9s} {'max|v-shipped|':>15s}"
        lines += ["", f"batch {b}", head, "-" * len(head),
                  f"{'naive (base policy)':<32s} {'-':<10s} {stats['naive']['median_ms']:>9.3f} {1.0:>6.2f}x"]
        for k, v in res["variants"].items():
            st, ag = stats[k], res["agreement"][b][k]
            pb = "j < H - s" if res["restricted_pullback"][b][k] else "all"
            lines.append(f"{v['label']:<32s} {pb:<10s} {st['median_ms']:>9.3f} {st['ratio']:>6.2f}x "
                         f"{st['over_shipped']:>8.3f}x {ag['max_abs_diff']:>10.1e} {'ok' if ag['ok'] else 'FAIL'}")
    lines.append(f"total {res['seconds']:.0f} s")
    return "\n".join(lines)


# --------------------------------------------------------------------------- output


def format_table(res: dict) -> str:
    """The printed table of [B-10]: rows x batch sizes (median ms, ratio to naive), agreement, targets.

    A result without a key the table reads raises ``ValueError`` naming the key.
    """
    return _formatted("run_benchmark", _format_table, res, _RUNTIME_KEYS)


def _format_table(res: dict) -> str:
    cfg, arch = res["config"], res["architecture"]
    bs = list(res["chunk"])
    d = "rotating " + "..".join(map(str, (0, max(0, len(_delays_of(cfg)) - 1)))) \
        if cfg["delay"] is None else str(cfg["delay"])
    lines = [f"softrtc bench runtime: obs {arch['obs_dim']}, action {arch['action_dim']}, "
             f"H {arch['action_chunk_size']}, s {cfg['execute_horizon']}, T {cfg['num_steps']}, d {d}; "
             f"median of {cfg['calls']} interleaved calls after {cfg['warmup']} warm-up rounds; "
             f"{_machine(res['environment'])}, "
             f"jax {res['environment']['jax']}"]
    head = f"{'method':<26s} {'path':<15s}" + "".join(f" {'b=' + b + ' ms':>10s} {'/naive':>7s}" for b in bs) \
        + f" {'max|fast-sf|':>12s}"
    lines += [head, "-" * len(head)]
    for r in res["rows"]:
        k = r["key"]
        cells = "".join(f" {res['chunk'][b][k]['median_ms']:>10.3f} {res['chunk'][b][k]['ratio']:>6.2f}x"
                        for b in bs)
        diffs = [res["agreement"][b][r["name"]]["max_abs_diff"] for b in bs
                 if r["path"] == "fast" and r["name"] in res["agreement"][b]]
        lines.append(f"{r['label']:<26s} {r['path']:<15s}{cells} {(f'{max(diffs):.1e}' if diffs else '-'):>12s}")
    if res.get("vjp_cost"):
        lines += ["", "context (not targets)"]
        for b in bs:
            ch, vc = res["chunk"][b], res["vjp_cost"][b]
            guided = max(ch[k]["median_ms"] for k in ("inference_hard", "inference_soft"))
            if "naive/straightforward" in ch:
                lines.append(f"  guided / straightforward naive, batch {b:<6s} "
                             f"{guided / ch['naive/straightforward']['median_ms']:>6.2f}x")
            restricted = res.get("restricted_pullback", {}).get(b)
            lines.append(f"  one forward + VJP / one forward, batch {b:<4s} {vc['ratio']:>6.2f}x "
                         f"({vc['forward_vjp_ms']:.3f} / {vc['forward_ms']:.3f} ms)"
                         + ("" if restricted is None else
                            f"; pull-back {'restricted to j < H - s' if restricted else 'over all tokens'}"))
    ts = res.get("train_step")
    if ts:
        lines += ["", f"training step (batch {ts['batch']}, delays 0..{ts['d_max']}, "
                      f"median of {ts['none']['calls']} interleaved calls)",
                  f"{'method':<26s} {'ms':>10s} {'/hard':>7s} {'/none':>7s}"]
        for m in TRAIN_METHODS:
            lines.append(f"{m:<26s} {ts[m]['median_ms']:>10.2f} "
                         f"{ts[m]['median_ms'] / ts['hard']['median_ms']:>6.2f}x "
                         f"{ts[m]['median_ms'] / ts['none']['median_ms']:>6.2f}x")
    if res["targets"]:
        lines += ["", "targets"]
        for t in res["targets"]:
            val = f"{t['value']:.1e} (tol {res['tolerance']['atol']:.0e})" if t["limit"] is None \
                else f"{t['value']:.3f} <= {t['limit']:.2f}"
            lines.append(f"  {'PASS' if t['pass'] else 'FAIL'}  [{t['id']}] {t['target']:<44s} {val}")
    lines.append(f"total {res['seconds']:.0f} s")
    return "\n".join(lines)


def _delays_of(cfg: dict) -> list:
    H = ARCHS[cfg["arch"]]["config"].action_chunk_size
    s = cfg["execute_horizon"]
    return list(range(min(s, H - s) + 1))


def _json_value(value: Any, where: str) -> Any:
    """``value`` as plain JSON data ([B-10]): NumPy and JAX scalars and arrays become numbers and lists,
    tuples lists, and every non-finite float (NaN, inf) ``None`` (JSON ``null``)."""
    if value is None or isinstance(value, (str, bool, np.bool_)):
        return bool(value) if isinstance(value, np.bool_) else value
    if isinstance(value, Mapping):
        out = {}
        for k, x in value.items():
            if not isinstance(k, str):
                raise ValueError(f"res{where} must have string keys, got {k!r}")
            out[k] = _json_value(x, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_json_value(x, f"{where}[{i}]") for i, x in enumerate(value)]
    if isinstance(value, (np.ndarray, np.generic, jax.Array)):
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"res{where} must hold JSON values (numbers, strings, bools, None, lists, dicts), "
                             f"got an array of dtype {arr.dtype}")
        return _json_value(arr.tolist(), where)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        f = float(value)
        return f if math.isfinite(f) else None
    raise ValueError(f"res{where} must hold JSON values (numbers, strings, bools, None, lists, dicts), "
                     f"got {type(value).__name__}")


def write_json(res: dict, path: str | os.PathLike) -> None:
    """Write the result of :func:`run_benchmark` ([B-10]) or :func:`run_vjp_ablation` ([B-12]) as JSON.

    The output is strict JSON: NumPy and JAX numbers are written as plain
    numbers and non-finite ones (NaN, inf) as ``null`` ([B-10]). The text is
    built first and then written to a temporary file in the target folder and
    renamed, so a failure never leaves a partial file at ``path``. Creates the
    parent folder; ``path`` must not be a directory.
    """
    if not isinstance(res, Mapping) or "chunk" not in res:
        raise ValueError("res must be a result of run_benchmark or run_vjp_ablation")
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ValueError(f"path must be a file path, got {path!r}")
    if os.path.isdir(path):
        raise ValueError(f"path must be a file path, got the directory {os.fspath(path)!r}")
    text = json.dumps(_json_value(res, ""), indent=1, sort_keys=True, allow_nan=False) + "\n"
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    write_atomic(path, lambda f: f.write(text), prefix=".bench-")
