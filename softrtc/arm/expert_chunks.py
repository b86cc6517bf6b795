"""Chunked open-loop scripted expert under simulated delay: the delay-sensitivity screen of a task ([AX-8]).

A task is worth training on only if executing older plans hurts on it. The
screen asks that of the scripted expert ([A-13]) before any policy is trained:
at request ``c`` (step ``c s``) the expert is rolled forward ``H`` ticks on a
copy of the world in which nothing moves on its own from then on (boxes stop
where they are, no later hop, [A-27]), and those ``H`` actions are the chunk;
the episode executes chunks exactly as the simulated-delay executor does
([A-22], [X-4]): ``previous[s .. s + d - 1]`` then ``new[d .. s - 1]``. With
``s = 1`` and ``d = 0`` this is the closed-loop expert.
"""

from __future__ import annotations

import copy

import numpy as np

from softrtc.reference._validate import check_int

from .env import ACTION_DIM, ArmConfig, ArmSortEnv
from .expert import ScriptedExpert
from .geometry import _check_env_config

__all__ = ["expert_chunk", "run_expert_chunk_episode", "delay_screen"]


def expert_chunk(env: ArmSortEnv, expert: ScriptedExpert, horizon: int) -> np.ndarray:
    """``[horizon, 4]`` expert actions rolled out on a frozen-world copy of ``env`` ([AX-8]).

    The copy's boxes stop at their current centres and hop no more, so the
    plan is what the current observation predicts; ``env`` is not touched. A
    copy that ends (success or tick limit) repeats its last action.
    """
    if not isinstance(env, ArmSortEnv) or env.done:
        raise ValueError("env must be an ArmSortEnv that is reset and not done")
    horizon = check_int("horizon", horizon, 1, None)
    world = copy.deepcopy(env)
    sc = world._scene
    if sc.box_bodies:
        sc.hops = [{} for _ in sc.hops]
        sc.box_goals = np.array([b.position.x for b in sc.box_bodies])
    obs = world._observe()
    out = np.empty((horizon, ACTION_DIM))
    for j in range(horizon):
        if world.done:
            out[j] = out[j - 1]
            continue
        out[j] = expert.act(obs)
        obs, _ = world.step(out[j])
    return out


def run_expert_chunk_episode(env_config: ArmConfig | None, env_seed: int, execute_horizon: int, delay: int,
                             horizon: int = 10, max_steps: int | None = None) -> dict:
    """One episode of the chunked expert with constant delay ``delay`` for requests ``c >= 1`` ([AX-8]).

    ``delay`` must satisfy [X-1]: ``0 <= delay <= min(s, H - s)``. Returns
    ``success``, ``num_completed``, ``success_step`` (None if unsolved) and ``steps``.
    """
    cfg = _check_env_config(env_config, "env_config")
    horizon = check_int("horizon", horizon, 1, None)
    s = check_int("execute_horizon", execute_horizon, 1, horizon)
    d = check_int("delay", delay, 0, min(s, horizon - s))
    env_seed = check_int("env_seed", env_seed, 0, None)
    env = ArmSortEnv(cfg)
    limit = cfg.max_steps if max_steps is None else check_int("max_steps", max_steps, 1, cfg.max_steps)
    expert = ScriptedExpert(cfg)
    env.reset(env_seed)
    info = {"success": False, "num_completed": 0, "success_step": None}
    prev, c = None, 0
    while not env.done and env.t < limit:
        dc = 0 if c == 0 else d
        new = expert_chunk(env, expert, horizon)
        # prev[s .. s + d - 1], then new[d .. s - 1].
        seg = [prev[s + j] for j in range(dc)] + [new[j] for j in range(dc, s)]
        for a in seg:
            if env.done or env.t >= limit:
                break
            _, info = env.step(a)
        prev, c = new, c + 1
    return {"success": bool(info["success"]), "num_completed": int(info["num_completed"]),
            "success_step": info["success_step"], "steps": env.t}


def delay_screen(env_config: ArmConfig | None, execute_horizon: int, delays, seeds, horizon: int = 10,
                 max_steps: int | None = None) -> dict:
    """Success rate and mean success step of the chunked expert per delay, on paired ``seeds`` ([AX-8])."""
    seeds = [check_int(f"seeds[{i}]", x, 0, None) for i, x in enumerate(seeds)]
    if not seeds:
        raise ValueError("seeds must not be empty")
    out = {}
    for d in delays:
        runs = [run_expert_chunk_episode(env_config, sd, execute_horizon, d, horizon, max_steps) for sd in seeds]
        steps = [r["success_step"] for r in runs if r["success"]]
        out[int(d)] = {"success": sum(r["success"] for r in runs) / len(runs),
                       "completion": float(np.mean([r["num_completed"] / 4 for r in runs])),
                       "mean_success_step": float(np.mean(steps)) if steps else float("nan"),
                       "solved": [r["success"] for r in runs]}
    return out
