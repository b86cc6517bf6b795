"""Running the Kinetix evaluation protocol: every (method, level) rollout and its episode rows ([KE-1]..[KE-7], [KE-11])."""

from __future__ import annotations

import sys
from typing import Mapping

import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from softrtc.jax.policy import FlowPolicy
from softrtc.reference import metrics as ref_metrics
from softrtc.reference._validate import check_int, real_array

from . import env as kenv
from .methods import MethodSpec, method_family
from .protocol import EvalConfig
from .rollout import episode_keys, make_rollout

__all__ = ["episode_metrics", "evaluate"]


def episode_metrics(actions: np.ndarray, length: int) -> dict:
    """Action delta and jerk of one episode's executed actions, truncated at ``length`` ([M-1], [M-2], [M-4]).

    ``nan`` when the episode is too short for the difference ([M-1] needs
    N > k); such episodes are left out of that metric's means ([KE-7]).
    """
    a = real_array("actions", actions).astype(np.float64)
    if a.ndim != 2 or 0 in a.shape:
        raise ValueError(f"actions must have shape [N >= 1, A >= 1], got {list(a.shape)}")
    length = check_int("length", length, 1, a.shape[0])
    a = a[:length]
    return {"delta": ref_metrics.action_delta(a) if length > 1 else float("nan"),
            "jerk": ref_metrics.action_jerk(a) if length > 2 else float("nan")}


def _resolve_policy(policies, spec: MethodSpec, level: str) -> FlowPolicy:
    if isinstance(policies, FlowPolicy):
        return policies
    if callable(policies):
        pol = policies(spec, level)
    elif isinstance(policies, Mapping):
        pol = policies.get(level)
    else:
        pol = None
    if not isinstance(pol, FlowPolicy):
        raise ValueError(f"policies must give a FlowPolicy for method {spec.label!r} and level {level!r} "
                         f"(a FlowPolicy, a mapping level -> FlowPolicy, or a callable (spec, level) -> FlowPolicy)")
    return pol


def evaluate(config: EvalConfig, policies, *, progress: bool = True) -> dict:
    """Run the protocol of ``config`` ([KE-1]..[KE-7]); returns ``{"episodes": rows, "compile_s": {...}}``.

    ``policies`` is a :class:`FlowPolicy` used for every method and level, a
    mapping level -> policy, or a callable ``(spec, level) -> FlowPolicy``
    (e.g. base checkpoints for naive / inference methods and fine-tuned ones
    for training-time methods), called once per (method, level): every policy
    is resolved and checked (dims, ``s <= H``, delays ``<= min(s, H - s)``)
    before the first rollout ([KE-11]). Each (method, level) is one call of the
    family's compiled rollout with ``episodes * len(delays)`` envs; episode
    ``e`` uses the key of :func:`episode_keys` at every delay. Every row of
    ``episodes`` is one episode: method, level, delay, episode, return,
    solved, length, delta, jerk.
    """
    if not isinstance(config, EvalConfig):
        raise ValueError(f"config must be an EvalConfig, got {type(config).__name__}")
    if not isinstance(progress, bool):
        raise ValueError(f"progress must be a bool, got {progress!r}")
    levels_dir = kenv.resolve_levels_dir(config.levels_dir, config.levels)
    # One template task per set of static sizes: levels at the benchmark's sizes share a compiled
    # rollout ([KE-3]); a level at its own sizes ([K-21]) gets its own.
    templates: dict = {}
    level_template: dict = {}
    for level in config.levels:
        static = kenv.level_static_env_params(level)
        if static not in templates:
            templates[static] = kenv.make_env(level, levels_dir)
        level_template[level] = templates[static]
    E, ds = config.episodes, config.delays
    n = E * len(ds)
    delays = np.repeat(np.asarray(ds, np.int64), E)
    # Every (method, level) policy is resolved and checked before the first rollout, so a missing
    # policy or a delay its chunk cannot hold stops the run before any work, not hours into it.
    pols: dict = {}
    for spec in config.methods:
        for level in config.levels:
            pol = _resolve_policy(policies, spec, level)
            template = level_template[level]
            if (pol.obs_dim, pol.action_dim) != (template.obs_dim, template.action_dim):
                raise ValueError(f"policies must have obs_dim={template.obs_dim} and action_dim="
                                 f"{template.action_dim} (the levels'), got {pol.obs_dim} and {pol.action_dim} "
                                 f"for method {spec.label!r} and level {level!r}")
            if not 1 <= config.execute_horizon <= pol.action_chunk_size:
                raise ValueError(f"execute_horizon must lie in [1, {pol.action_chunk_size}] (the chunk size H of the "
                                 f"policy of method {spec.label!r} and level {level!r}), got {config.execute_horizon}")
            hi = min(config.execute_horizon, pol.action_chunk_size - config.execute_horizon)
            if max(ds) > hi:
                raise ValueError(f"delays must lie in [0, {hi}] for H={pol.action_chunk_size}, "
                                 f"s={config.execute_horizon} ([X-1]), got {max(ds)} "
                                 f"(policy of method {spec.label!r} and level {level!r})")
            pols[(spec.label, level)] = pol
    rollouts: dict = {}
    compile_s: dict = {}
    rows: list[dict] = []
    total = len(config.methods) * len(config.levels)
    with tqdm(total=total, desc="eval", disable=not progress, file=sys.stderr) as bar:
        for spec in config.methods:
            for level in config.levels:
                pol = pols[(spec.label, level)]
                fam = method_family(spec.method)
                template = level_template[level]
                rkey = (fam, pol.obs_dim, pol.action_dim, pol.config, template.static_env_params)
                if rkey not in rollouts:
                    rollouts[rkey] = make_rollout(template, pol, fam, n, config.execute_horizon,
                                                  config.num_flow_steps, config.episode_steps)
                ro = rollouts[rkey]
                keys = episode_keys(config.seed, level, E)
                keys = jnp.tile(keys, len(ds))
                bar.set_postfix_str(f"{spec.label} {level}" + ("" if ro._compiled else " (compiling)"))
                out = ro(pol, spec, level, keys, delays)
                if fam not in compile_s:
                    compile_s[fam] = ro.compile_s
                for i in range(n):
                    m = episode_metrics(out["actions"][i], int(out["length"][i]))
                    rows.append({"method": spec.label, "level": level, "delay": int(delays[i]),
                                 "episode": i % E, "return": float(out["return"][i]),
                                 "solved": bool(out["solved"][i]), "length": int(out["length"][i]),
                                 "delta": m["delta"], "jerk": m["jerk"]})
                bar.update(1)
    return {"episodes": rows, "compile_s": compile_s, "config": config}
