"""The Kinetix harness benchmark: harness env steps/s against the bare env's ([KE-9], [K-13])."""

from __future__ import annotations

import os
import sys
import time

import flax.nnx as nnx
import jax
import numpy as np
from tqdm.auto import tqdm

from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.reference._validate import check_int

from . import env as kenv
from .limits import NUM_ENVS_MAX, REPEATS_MAX
from .methods import MethodSpec, method_family, parse_method
from .rollout import make_rollout

__all__ = ["bench_harness"]


def bench_harness(level: str = "grasp_easy", num_envs: int = 64, method: str = "naive", seed: int = 0,
                  levels_dir: str | os.PathLike | None = None, policy: FlowPolicy | None = None,
                  repeats: int = 1, progress: bool = True) -> dict:
    """Harness env steps/s vs the bare env's under random actions ([KE-9], [K-13]).

    One episode-length rollout of ``num_envs`` envs at delay 0..4 (cycled)
    with ``policy`` (default: a freshly initialised benchmark-size policy,
    ``nnx.Rngs(seed)``) is compiled (``compile_s``) and run ``repeats``
    times; the fastest run gives ``harness_steps_per_s``. The bare env is
    measured with :func:`softrtc.kinetix.env.bench_bare_env` on the same
    level, envs and steps. ``ratio = harness / bare``.
    """
    kenv.check_level_name(level, "level")
    num_envs = check_int("num_envs", num_envs, 1, NUM_ENVS_MAX)
    seed = check_int("seed", seed, 0, 2**32 - 1)
    repeats = check_int("repeats", repeats, 1, REPEATS_MAX)
    spec = parse_method(method) if isinstance(method, str) else method
    if not isinstance(spec, MethodSpec):
        raise ValueError(f"method must be a method string or MethodSpec, got {type(method).__name__}")
    task = kenv.make_env(level, levels_dir)
    if policy is None:
        policy = FlowPolicy(obs_dim=task.obs_dim, action_dim=task.action_dim, config=PolicyConfig(),
                            rngs=nnx.Rngs(seed))
    ro = make_rollout(task, policy, method_family(spec.method), num_envs)
    keys = jax.random.split(jax.random.key(seed), num_envs)
    delays = np.arange(num_envs) % (min(ro.s, ro.H - ro.s) + 1)
    steps = num_envs * ro.C * ro.s
    stages = tqdm(total=2 + repeats, desc="bench", disable=not progress, file=sys.stderr)
    stages.set_postfix_str("compiling harness rollout")
    compile_s = ro.compile(policy, spec, level, keys, delays)
    stages.update(1)
    times = []
    for _ in range(repeats):
        stages.set_postfix_str("running harness rollout")
        t0 = time.perf_counter()
        ro(policy, spec, level, keys, delays)
        times.append(time.perf_counter() - t0)
        stages.update(1)
    stages.set_postfix_str("bare env (compile + run)")
    bare = kenv.bench_bare_env(level, num_envs=num_envs, num_steps=ro.C * ro.s, seed=seed,
                               levels_dir=levels_dir, repeats=repeats)
    stages.update(1)
    stages.close()
    harness_sps = steps / min(times)
    return {"level": level, "method": spec.label, "num_envs": num_envs, "env_steps": steps,
            "policy_params": int(sum(np.size(x) for x in jax.tree.leaves(nnx.state(policy)))),
            "harness_compile_s": compile_s, "harness_run_s": min(times),
            "harness_steps_per_s": harness_sps, "bare_compile_s": bare["compile_s"],
            "bare_run_s": bare["run_s"], "bare_steps_per_s": bare["env_steps_per_s"],
            "ratio": harness_sps / bare["env_steps_per_s"], "device": bare["device"],
            "num_devices": ro.num_devices}
