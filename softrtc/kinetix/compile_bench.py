"""Compile-time and throughput benchmark of the Kinetix rollouts against the bare env ([KC-6]).

Measured side by side in one process, in a fresh temporary cache folder (so
"cold" is cold whatever the user's cache holds): for the bare env's scan of
[K-13] and for the rollout of every sampler family ([KE-3]), the cold compile
(trace + compile, empty cache) and the warm one (the same program again after
the process's in-memory caches are cleared, as a new process would see it);
then the fastest of ``repeats`` runs of each. Ratios printed by
``softrtc kinetix bench``: warm / cold per program (target <= 0.10), rollout
cold / bare cold (target <= 1.5) and rollout / bare env steps per second
(target >= 0.75).
"""

from __future__ import annotations

import os
import shutil
import sys
import tempfile
import time

import flax.nnx as nnx
import jax
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from softrtc._machine import cpu_model
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.reference._validate import check_int

from . import cache
from . import env as kenv
from .limits import NUM_ENVS_MAX, REPEATS_MAX
from .methods import method_family, parse_method
from .protocol import EPISODE_STEPS, EXECUTE_HORIZON, NUM_FLOW_STEPS
from .rollout import Rollout

__all__ = ["FAMILY_METHODS", "bench_compile", "add_ratios", "format_compile_bench"]

# The method each family is measured with ([KE-3]); weights are arguments, so any method of a family compiles alike.
FAMILY_METHODS = {"rtc": "naive", "guided": "inference_soft"}


def bench_compile(level: str = "grasp_easy", num_envs: int = 64, seed: int = 0,
                  levels_dir: str | os.PathLike | None = None, repeats: int = 1,
                  methods: tuple = tuple(FAMILY_METHODS.values()), progress: bool = True) -> dict:
    """Cold and warm compile times and throughput of the bare env and of the rollout of each method in
    ``methods`` (method strings of distinct sampler families, default one per family) ([KC-6])."""
    if level not in kenv.LEVEL_NAMES:
        raise ValueError(f"level must be one of {', '.join(kenv.LEVEL_NAMES)}, got {level!r}")
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
    bar = tqdm(total=2 * (1 + len(families)) + (1 + len(families)), desc="bench", disable=not progress,
               file=sys.stderr)
    try:
        cache.enable_compile_cache(tmp)
        bare_fn = kenv.make_random_rollout(task, num_envs, steps)
        bare_cfg = ("bare_env", num_envs, steps, task.action_noise_std, task.env_params, task.static_env_params)
        entry = {}
        for phase in ("cold", "warm"):
            bar.set_postfix_str(f"bare env: {phase} compile")
            cache.clear_memory()
            prog = cache.compile_program("bare_env", bare_fn, (key,), (rep,), rep, config=bare_cfg)
            entry[phase + "_s"], entry[phase + "_source"] = prog.seconds, prog.source
            bar.update(1)
        bar.set_postfix_str("bare env: run")
        entry["run_s"] = _best(lambda: jax.block_until_ready(prog(key)), repeats)
        bar.update(1)
        rows["bare"] = entry
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
            bar.set_postfix_str(f"rollout {fam}: run")
            entry["run_s"] = _best(lambda: ro(policy, spec, level, keys, delays), repeats)
            bar.update(1)
            rows[fam] = entry
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
    return {"level": level, "num_envs": num_envs, "env_steps": env_steps, "repeats": repeats, "seed": seed,
            "policy_params": int(sum(np.size(x) for x in jax.tree.leaves(nnx.state(policy)))),
            "device": str(jax.devices()[0]), "num_devices": len(jax.devices()), "cpu": cpu_model(),
            "programs": rows}


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


def _best(run, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    return min(times)




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
    lines.append("targets: warm/cold <= 0.10; rollout cold compile <= 1.5x the bare env's; "
                 "rollout throughput >= 0.75x the bare env's")
    return "\n".join(lines) + "\n"
