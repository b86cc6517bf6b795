"""Compile-time and throughput benchmark of the Kinetix rollouts against the bare env ([KC-6]).

Measured side by side in one process, in a fresh temporary cache folder (so
"cold" is cold whatever the user's cache holds): for the bare env's scan of
[K-13] and for the rollout of every sampler family ([KE-3]), the cold compile
(trace + compile, empty cache) and the warm one (the same program again after
the process's in-memory caches are cleared, as a new process would see it);
then ``repeats`` rounds that run every program once in turn (bare env, then
each family, then each family's policy calls alone, without the env), and
the fastest run of each. Ratios printed by
``softrtc kinetix bench``: warm / cold per program (target <= 0.10), rollout
cold / bare cold (target <= 1.5), and per family the rollout's run time over
the bare env's plus the policy's alone (target <= 1.10: what the harness
itself adds), with ``bare / (bare + policy alone)``, the highest throughput
ratio any harness could reach with this policy here.
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from softrtc._machine import cpu_model
from softrtc.jax import executor as jexec
from softrtc.jax.fast_chunks import FastChunks
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.reference._validate import check_int

from . import cache
from . import env as kenv
from .limits import NUM_ENVS_MAX, REPEATS_MAX
from .methods import FAMILY_SAMPLERS, method_family, parse_method, rollout_weight_table
from .protocol import EPISODE_STEPS, EXECUTE_HORIZON, NUM_FLOW_STEPS
from .rollout import Rollout

__all__ = ["FAMILY_METHODS", "HARNESS_TARGET", "bench_compile", "add_ratios", "add_policy_bounds",
           "harness_ratios", "format_compile_bench"]

# The method each family is measured with ([KE-3]); weights are arguments, so any method of a family compiles alike.
FAMILY_METHODS = {"rtc": "naive", "guided": "inference_soft"}
# [KC-6] the throughput target: a rollout's run time at most this multiple of the bare env's plus the
# policy's alone, measured in the same rounds; the part of the rollout the harness controls.
HARNESS_TARGET = 1.10


def bench_compile(level: str = "grasp_easy", num_envs: int = 64, seed: int = 0,
                  levels_dir: str | os.PathLike | None = None, repeats: int = 1,
                  methods: tuple = tuple(FAMILY_METHODS.values()), progress: bool = True) -> dict:
    """Cold and warm compile times and throughput of the bare env and of the rollout of each method in
    ``methods`` (method strings of distinct sampler families, default one per family) ([KC-6])."""
    kenv.check_level_name(level, "level")
    num_envs = check_int("num_envs", num_envs, 1, NUM_ENVS_MAX)
    seed = check_int("seed", seed, 0, 2**32 - 1)
    repeats = check_int("repeats", repeats, 1, REPEATS_MAX)
    if isinstance(methods, str) or not isinstance(methods, (tuple, list)) or not methods:
        raise ValueError(f"methods must be a non-empty sequence of method strings, got {methods!r}")
    specs = {}
    for m in methods:
        spec = parse_method(m)
        fam = method_family(spec.method)
        if fam in specs:
            raise ValueError(f"method entries must belong to distinct sampler families; {specs[fam].label!r} and "
                             f"{spec.label!r} are both {fam!r}")
        specs[fam] = spec
    families = tuple(specs)
    task = kenv.make_env(level, levels_dir)
    policy = FlowPolicy(obs_dim=task.obs_dim, action_dim=task.action_dim, config=PolicyConfig(), rngs=nnx.Rngs(seed))
    s, T = EXECUTE_HORIZON, NUM_FLOW_STEPS
    C = -(-EPISODE_STEPS // s)
    steps = C * s
    mesh = Mesh(np.array(jax.devices()), ("env",))
    rep = NamedSharding(mesh, PartitionSpec())
    key = jax.random.key(seed)
    keys = jax.random.split(key, num_envs)
    delays = np.arange(num_envs) % (min(s, policy.action_chunk_size - s) + 1)
    prev_dir, prev_configured = cache._state["dir"], cache._state["configured"]
    tmp = tempfile.mkdtemp(prefix="softrtc-bench-cache-")
    rows: dict = {}
    # Per program: cold and warm compiles (the policy-alone programs: one compile), then one run per round.
    bar = tqdm(total=(2 + repeats) * (1 + len(families)) + (1 + repeats) * len(families), desc="bench",
               disable=not progress, file=sys.stderr)
    try:
        cache.enable_compile_cache(tmp)
        bare_fn = kenv.make_random_rollout(task, num_envs, steps)
        bare_cfg = ("bare_env", num_envs, steps, task.action_noise_std, task.env_params, task.static_env_params)
        runs = {}
        entry = {}
        for phase in ("cold", "warm"):
            bar.set_postfix_str(f"bare env: {phase} compile")
            cache.clear_memory()
            prog = cache.compile_program("bare_env", bare_fn, (key,), (rep,), rep, config=bare_cfg)
            entry[phase + "_s"], entry[phase + "_source"] = prog.seconds, prog.source
            bar.update(1)
        rows["bare"] = entry
        runs["bare"] = lambda prog=prog: jax.block_until_ready(prog(key))
        for fam in families:
            spec = specs[fam]
            entry = {"method": spec.label}
            for phase in ("cold", "warm"):
                bar.set_postfix_str(f"rollout {fam}: {phase} compile")
                cache.clear_memory()
                ro = Rollout(task, policy, fam, s, T, C, num_envs, mesh)
                entry[phase + "_s"] = ro.compile(policy, spec, level, keys, delays)
                entry[phase + "_source"] = ro.compile_source
                bar.update(1)
            rows[fam] = entry
            runs[fam] = lambda ro=ro, spec=spec: ro(policy, spec, level, keys, delays)
        # What the policy alone adds: each family's C chunk requests without the env ([KC-6]).
        obs0, _ = jax.vmap(task.reset)(keys)
        for fam in families:
            bar.set_postfix_str(f"policy alone {fam}: compile")
            runs["policy_" + fam] = _chunks_alone(policy, fam, specs[fam], s, T, C, obs0, keys, delays)
            bar.update(1)
        # The runs are interleaved (bare, each family, bare, ...), so every program's best run is taken
        # under the same machine conditions as the others'.
        times = {name: [] for name in runs}
        for r in range(repeats):
            for name, run in runs.items():
                bar.set_postfix_str(f"run {r + 1}/{repeats}: {name}")
                times[name].append(_timed(run))
                bar.update(1)
        policy_alone = {}
        for name, ts in times.items():
            if name.startswith("policy_"):
                policy_alone[name[len("policy_"):]] = {"calls": C, "run_s": min(ts), "run_times_s": ts}
            else:
                rows[name]["run_s"] = min(ts)
                rows[name]["run_times_s"] = ts
    finally:
        bar.close()
        cache.clear_memory()
        if prev_configured:
            cache.enable_compile_cache(prev_dir)
        else:
            cache.enable_compile_cache(None)
            cache._state["configured"] = False
        shutil.rmtree(tmp, ignore_errors=True)
    env_steps = num_envs * steps
    rows = add_ratios(rows, env_steps)
    policy_alone = add_policy_bounds(policy_alone, rows["bare"]["run_s"])
    return {"level": level, "num_envs": num_envs, "env_steps": env_steps, "repeats": repeats, "seed": seed,
            "policy_params": int(sum(np.size(x) for x in jax.tree.leaves(nnx.state(policy)))),
            "device": str(jax.devices()[0]), "num_devices": len(jax.devices()), "cpu": cpu_model(),
            "programs": rows, "policy_alone": policy_alone}


def _chunks_alone(policy, family: str, spec, s: int, T: int, C: int, obs, keys, delays):
    """The rollout's policy calls alone ([KC-6]): request 0 with the naive sampler, then ``C - 1`` requests
    of ``family``'s sampler at a fixed observation, each from the previous chunk's shifted prior, with the
    rollout's weight table, batch and delays. No env step runs, so its time is what the policy adds."""
    graphdef, params = nnx.split(policy)
    table = jnp.asarray(rollout_weight_table(spec, policy.action_chunk_size, s))
    sampler = FAMILY_SAMPLERS[family]
    d = jnp.asarray(delays, jnp.int32)

    @jax.jit
    def run(params, obs, keys):
        chunks = FastChunks(nnx.merge(graphdef, params), sampler, s, T, weights=table, stored_transposes=False)

        def request(prev, c):
            noise = jax.vmap(lambda k: jax.random.fold_in(k, c))(keys)
            new = chunks.next(obs, jexec.shift_prior(prev, s), d, noise)
            return new, None

        first = chunks.first(obs, keys)
        last, _ = jax.lax.scan(request, first, jnp.arange(1, C, dtype=jnp.int32))
        return last

    jax.block_until_ready(run(params, obs, keys))  # compile before the timed rounds
    return lambda: jax.block_until_ready(run(params, obs, keys))


def add_ratios(programs: dict, env_steps: int) -> dict:
    """The ratios of [KC-6] added to each program's entry (``bare`` plus one per family): env steps per
    second, warm / cold compile, and for each family cold compile and throughput relative to the bare env."""
    if "bare" not in programs or len(programs) < 2:
        raise ValueError(f"programs must hold 'bare' and at least one family, got {sorted(programs)}")
    env_steps = check_int("env_steps", env_steps, 1)
    out = {k: dict(v) for k, v in programs.items()}
    for entry in out.values():
        for f in ("cold_s", "warm_s", "run_s"):
            if not isinstance(entry.get(f), float) or not entry[f] > 0:
                raise ValueError(f"programs entries must have a positive float {f!r}, got {entry.get(f)!r}")
        entry["steps_per_s"] = env_steps / entry["run_s"]
        entry["warm_over_cold"] = entry["warm_s"] / entry["cold_s"]
    for name, entry in out.items():
        if name != "bare":
            entry["cold_over_bare"] = entry["cold_s"] / out["bare"]["cold_s"]
            entry["throughput_over_bare"] = entry["steps_per_s"] / out["bare"]["steps_per_s"]
    return out


def add_policy_bounds(policy_alone: dict, bare_run_s: float) -> dict:
    """Each family's entry of ``policy_alone`` with ``bound_over_bare = bare / (bare + policy alone)``
    ([KC-6]): the highest throughput ratio a rollout of this policy can reach on this machine, where
    the harness itself would cost nothing beyond the env's steps and the policy's calls."""
    if not isinstance(bare_run_s, float) or not bare_run_s > 0:
        raise ValueError(f"bare_run_s must be a positive float, got {bare_run_s!r}")
    out = {}
    for fam, entry in policy_alone.items():
        if not isinstance(entry.get("run_s"), float) or not entry["run_s"] > 0:
            raise ValueError(f"policy_alone entries must have a positive float 'run_s', got {entry.get('run_s')!r}")
        out[fam] = dict(entry, bound_over_bare=bare_run_s / (bare_run_s + entry["run_s"]))
    return out


def harness_ratios(programs: dict, policy_alone: dict) -> dict:
    """Per family, ``rollout run / (bare run + policy alone run)`` ([KC-6]) from the fastest runs
    (``over_parts``) and from each round's three runs (``by_round``, in round order).

    Computed from the run times alone, so a committed result gives it without running anything again.
    """
    bare = programs.get("bare", {})
    out = {}
    for fam, alone in policy_alone.items():
        ro = programs.get(fam)
        if ro is None:
            raise ValueError(f"programs must hold the rollout of every policy_alone family, missing {fam!r}")
        for name, e in (("bare", bare), (fam, ro), (f"policy_alone {fam}", alone)):
            if not isinstance(e.get("run_s"), float) or not e["run_s"] > 0:
                raise ValueError(f"{name} must have a positive float 'run_s', got {e.get('run_s')!r}")
        rounds = [r / (b + p) for r, b, p in zip(ro.get("run_times_s", []), bare.get("run_times_s", []),
                                                  alone.get("run_times_s", []))]
        out[fam] = {"over_parts": ro["run_s"] / (bare["run_s"] + alone["run_s"]), "by_round": rounds}
    return out


def _timed(run) -> float:
    t0 = time.perf_counter()
    run()
    return time.perf_counter() - t0




def format_compile_bench(res: dict) -> str:
    """The side-by-side table of :func:`bench_compile`'s result ([KC-6])."""
    p = res["programs"]
    lines = [f"level {res['level']}, {res['num_envs']} envs, {res['env_steps']} env steps per run, policy "
             f"{res['policy_params']:,} params, {res['num_devices']} device(s): {res['device']} ({res['cpu']})",
             "program         | cold compile s | warm compile s | warm/cold | run s | env steps/s | vs bare env",
             "---|---|---|---|---|---|---"]
    for name, e in p.items():
        label = "bare env scan" if name == "bare" else f"rollout {name}"
        vs = "–" if name == "bare" else (f"compile {e['cold_over_bare']:.2f}x, "
                                        f"throughput {e['throughput_over_bare']:.3f}x")
        lines.append(f"{label} | {e['cold_s']:.1f} | {e['warm_s']:.2f} ({e['warm_source']}) | "
                     f"{e['warm_over_cold']:.3f} | {e['run_s']:.1f} | {e['steps_per_s']:.0f} | {vs}")
    alone = res.get("policy_alone", {})
    for fam, e in alone.items():
        lines.append(f"policy alone, {fam}: {e['calls']} chunk requests x {res['num_envs']} envs, no env step | "
                     f"run {e['run_s']:.1f} s | bare env + policy alone bound the throughput at "
                     f"{e['bound_over_bare']:.3f}x")
    for fam, h in harness_ratios(p, alone).items():
        rounds = h["by_round"]
        spread = (f" (per round {min(rounds):.3f} to {max(rounds):.3f}, median {float(np.median(rounds)):.3f})"
                  if rounds else "")
        lines.append(f"harness, {fam}: rollout {p[fam]['run_s']:.1f} s / (bare env {p['bare']['run_s']:.1f} s + "
                     f"policy alone {alone[fam]['run_s']:.1f} s) = {h['over_parts']:.3f}x{spread}")
    lines.append(f"targets: warm/cold <= 0.10; rollout cold compile <= 1.5x the bare env's; rollout run time "
                 f"<= {HARNESS_TARGET:.2f}x (bare env + policy alone) in the same rounds")
    return "\n".join(lines) + "\n"
