"""Expert data generation in the public release's format ([KP-9], [KP-10]).

For one level, one checkpoint per seed folder of an expert run ([KP-6]) is
chosen: a random one (NumPy generator of ``seed``) among those whose stats
reach ``solve_rate_threshold``, else the best one, which is then marked below
threshold ([KP-9]). Every env follows one chosen expert per episode, drawn
uniformly among the experts at or above threshold (all chosen experts when none
is) at the start and after every episode end. Actions are sampled from the
expert's squashed Gaussian and recorded before execution noise, with the env's
raw observation before the step, ``done`` and the release's
``returned_episode_*`` values after it ([K-14]). The recording runs blocks of
``batch_size`` steps per env, rounded up as the release does, and is written to
``<out>/worlds_l_<level>.npz`` (default ``<run>/data``) with
:func:`softrtc.kinetix.data.save_expert_data`, plus the selection in
``worlds_l_<level>.meta.json``.
"""

from __future__ import annotations

import json
import math
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from tqdm.auto import tqdm

from softrtc._files import check_out_dir, write_atomic
from softrtc.reference._validate import check_int

from . import data as kdata
from . import env as kenv
from . import expert as kexp

__all__ = ["select_experts", "steps_per_env", "generate_data"]


def steps_per_env(num_steps: int, num_envs: int, batch_size: int) -> int:
    """Steps recorded per env ([KP-10]): ``ceil(floor(num_steps / num_envs) / batch_size) * batch_size``.

    >>> steps_per_env(1_000_000, 128, 256)
    7936
    """
    num_steps = check_int("num_steps", num_steps, 1, 1 << 40)
    num_envs = check_int("num_envs", num_envs, 1, 1 << 16)
    batch_size = check_int("batch_size", batch_size, 1, 1 << 20)
    return max(1, math.ceil((num_steps // num_envs) / batch_size)) * batch_size


def select_experts(run_dir: str | os.PathLike, level: str, solve_rate_threshold: float = 0.65,
                   seed: int = 0) -> list[dict]:
    """One checkpoint per ``seed_*`` folder of ``run_dir`` for ``level`` ([KP-9]).

    Returns ``[{"seed_dir", "update", "path", "solved", "good"}]`` in folder-name order.
    """
    kenv.check_level_name(level, "level")
    if isinstance(solve_rate_threshold, bool) or not isinstance(solve_rate_threshold, (int, float)) \
            or not 0.0 <= solve_rate_threshold <= 1.0:
        raise ValueError(f"solve_rate_threshold must be a real number in [0, 1], got {solve_rate_threshold!r}")
    seed = check_int("seed", seed, 0, 2**32 - 1)
    run = Path(run_dir)
    if not run.is_dir():
        raise FileNotFoundError(f"run_dir {run} is not a directory")
    gen = np.random.default_rng(seed)
    name = f"worlds_l_{level}"
    chosen = []
    for seed_dir in sorted(p for p in run.glob("seed_*") if p.is_dir()):
        cands = []
        for d in sorted((p for p in seed_dir.iterdir() if p.is_dir() and p.name.isdigit()), key=lambda p: int(p.name)):
            stats, pol = d / "stats" / f"{name}.json", d / "policies" / f"{name}.pkl"
            if stats.is_file() and pol.is_file():
                solved = float(json.loads(stats.read_text()).get("returned_episode_solved", float("nan")))
                cands.append((int(d.name), pol, solved if math.isfinite(solved) else -1.0))
        if not cands:
            continue
        solved = np.array([c[2] for c in cands])
        good = np.nonzero(solved >= solve_rate_threshold)[0]
        i = int(gen.choice(good)) if good.size else int(np.argmax(solved))
        chosen.append({"seed_dir": seed_dir.name, "update": cands[i][0], "path": str(cands[i][1]),
                       "solved": float(cands[i][2]), "good": bool(good.size)})
    if not chosen:
        raise FileNotFoundError(f"run_dir {run} has no seed_*/<update>/policies/{name}.pkl with its stats file")
    return chosen


def generate_data(run_dir: str | os.PathLike, level: str, *, out_dir: str | os.PathLike | None = None,
                  num_envs: int = 128, num_steps: int = 1_000_000, batch_size: int = 256, seed: int = 0,
                  solve_rate_threshold: float = 0.65, levels_dir: str | os.PathLike | None = None,
                  progress: bool = True, resume: bool = True) -> dict:
    """Record expert data for ``level`` from the experts of ``run_dir`` ([KP-9], [KP-10]); returns a summary.

    With ``resume``, a level whose data file and meta file exist for the same experts, envs, steps,
    seed and threshold is not recorded again; its summary is read back (``"resumed": True``) ([KP-15]).
    """
    if not isinstance(resume, bool):
        raise ValueError(f"resume must be a bool, got {resume!r}")
    chosen = select_experts(run_dir, level, solve_rate_threshold, seed)
    num_envs = check_int("num_envs", num_envs, 1, 1 << 16)
    per_env = steps_per_env(num_steps, num_envs, batch_size)
    out = Path(run_dir) / "data" if out_dir is None else Path(out_dir)
    check_out_dir("out_dir", out, (kdata.expert_data_filename(level),))
    meta_path = out / f"worlds_l_{level}.meta.json"
    want = {"level": level, "num_envs": num_envs, "steps_per_env": per_env, "seed": seed,
            "solve_rate_threshold": solve_rate_threshold, "experts": chosen}
    if resume and meta_path.is_file() and (out / kdata.expert_data_filename(level)).is_file():
        saved = json.loads(meta_path.read_text())
        if {k: saved.get(k) for k in want} == json.loads(json.dumps(want)):
            return dict(saved, path=str(out / kdata.expert_data_filename(level)), resumed=True)
    params = [kexp.load_expert(c["path"]) for c in chosen]
    dims = {kexp.expert_dims(p) for p in params}
    task = kenv.make_env(level, levels_dir)
    want_in = kexp.expert_obs_dim(task.obs_dim, task.action_dim)
    if len(dims) != 1 or next(iter(dims))[:2] != (want_in, task.action_dim):
        raise ValueError(f"experts must all take {want_in} inputs and give {task.action_dim} actions, got "
                         f"{sorted(dims)} (input width, action dim, layer width)")
    stacked = jax.tree.map(lambda *xs: jnp.stack(xs), *params)
    good = np.array([c["good"] for c in chosen])
    pool = jnp.asarray(np.nonzero(good)[0] if good.any() else np.arange(len(chosen)), jnp.int32)
    E = num_envs

    def draw(key):
        return pool[jax.random.randint(key, (E,), 0, pool.shape[0])]

    def init(key):
        k_env, k_pol, k_run = jax.random.split(key, 3)
        obs, state = jax.vmap(task.reset)(jax.random.split(k_env, E))
        hist, prev = kexp.history_reset(obs)
        zf = jnp.zeros((E,), jnp.float32)
        return {"rng": k_run, "env": state, "hist": hist, "prev": prev, "policy": draw(k_pol),
                "ep_return": zf, "ep_length": zf, "last_return": zf, "last_length": zf, "last_solved": zf}

    def step(c, _):
        rng, k_act, k_env, k_pol = jax.random.split(c["rng"], 4)
        x = kexp.expert_input(c["hist"], c["prev"])
        means, stds = jax.vmap(lambda p: kexp.actor_mean_std(p, x))(stacked)  # [P, E, A]: every expert, every env
        sel = c["policy"][None, :, None]
        mean = jnp.take_along_axis(means, sel, 0)[0]
        std = jnp.take_along_axis(stds, sel, 0)[0]
        action = kexp.sample_action(k_act, mean, std)
        raw_obs = c["hist"][:, -1, :]
        obs, state, reward, done, info = jax.vmap(task.step)(jax.random.split(k_env, E), c["env"], action)
        ep_ret, ep_len = c["ep_return"] + reward, c["ep_length"] + 1.0
        hist, prev = kexp.history_step(c["hist"], c["prev"], obs, action, done)
        new = dict(c, rng=rng, env=state, hist=hist, prev=prev,
                   policy=jnp.where(done, draw(k_pol), c["policy"]),
                   ep_return=jnp.where(done, 0.0, ep_ret), ep_length=jnp.where(done, 0.0, ep_len),
                   last_return=jnp.where(done, ep_ret, c["last_return"]),
                   last_length=jnp.where(done, ep_len, c["last_length"]),
                   last_solved=jnp.where(done, info["solved"].astype(jnp.float32), c["last_solved"]))
        rec = {"obs": raw_obs, "action": action, "done": done, "solved": new["last_solved"],
               "return_": new["last_return"], "length": new["last_length"]}
        return new, rec

    run_block = jax.jit(lambda c: jax.lax.scan(step, c, None, length=batch_size), donate_argnums=0)
    # Strong types: the carry fed back block after block is then one program input (one compile).
    carry = jax.jit(lambda k: kenv.strong_types(init(k)))(jax.random.fold_in(jax.random.key(seed),
                                                                             kenv.level_index(level)))
    blocks = []
    with tqdm(total=per_env * E, desc=f"generate-data {level}", unit="step", disable=not progress,
              file=sys.stderr) as bar:
        for _ in range(per_env // batch_size):
            carry, rec = run_block(carry)
            blocks.append(jax.device_get(rec))
            bar.update(batch_size * E)
    arrays = {k: np.concatenate([b[k] for b in blocks], axis=0) for k in blocks[0]}
    arrays["done"] = arrays["done"].astype(bool)
    out.mkdir(parents=True, exist_ok=True)
    path = kdata.save_expert_data(out / kdata.expert_data_filename(level), arrays)
    stats = kdata.ExpertData(**arrays).episode_stats()
    meta = {"level": level, "num_envs": E, "steps_per_env": per_env, "seed": seed,
            "solve_rate_threshold": solve_rate_threshold, "experts": chosen, "episode_stats": stats}
    write_atomic(meta_path, lambda f: json.dump(meta, f, indent=2))
    return dict(meta, path=str(path), resumed=False)
