"""PPO experts on the symbolic observations of one Kinetix level ([KP-4]..[KP-8]).

The project's own small PPO in JAX, following the algorithm of the public
release's expert training: clipped policy and value losses, generalised
advantage estimation, advantages normalised per minibatch, "robust policy
optimisation" (the Gaussian mean shifted by uniform noise in ``[-rpo_alpha,
rpo_alpha]`` inside the loss), global-norm clipping then Adam. Rollouts and
updates of one PPO iteration are one jitted function; blocks of
``log_interval`` iterations are written out together.

Outputs in the release's layout ([KP-6]):
``<run>/seed_<s>/<update>/policies/worlds_l_<level>.pkl`` (expert parameters,
:mod:`softrtc.kinetix.expert`) and ``.../stats/worlds_l_<level>.json`` (the
release's ``returned_episode_*`` keys, means over the iterations of that
block), plus ``<run>/seed_<s>/curve_worlds_l_<level>.csv`` and ``.png`` (one
row per iteration) and ``resume_worlds_l_<level>.npz`` (everything the next
iteration needs, [KP-7]).

>>> PPOConfig(num_envs=4, num_steps=8, num_minibatches=2).minibatch_size
16
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from tqdm.auto import tqdm

from softrtc._files import check_out_dir, write_atomic
from softrtc.reference._validate import check_int

from . import env as kenv
from . import expert as kexp
from .curves import plot_curves, write_curve_csv
from .resume import load_state, save_state

__all__ = ["PPOConfig", "train_reward", "make_ppo", "train_expert", "expert_paths", "CURVE_FIELDS"]

CURVE_FIELDS = ("update", "env_steps", "wall_s", "episodes", "return", "solved", "length", "train_reward",
                "loss", "pg_loss", "v_loss", "approx_kl", "clipfrac", "grad_norm")


def _check_real(name: str, value: Any, lo: float, hi: float, lo_open: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a real number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v > hi or v < lo or (lo_open and v == lo):
        raise ValueError(f"{name} must be a real number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    return v


@dataclasses.dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters ([KP-4]); defaults are the release's (256 envs x 256 steps per iteration)."""

    num_envs: int = 256
    num_steps: int = 256
    num_minibatches: int = 8
    num_epochs: int = 4
    gamma: float = 0.995
    gae_lambda: float = 0.9
    clip_eps: float = 0.2
    v_loss_coef: float = 0.5
    rpo_alpha: float = 0.3
    layer_width: int = 256
    grad_norm_clip: float = 1.0
    lr: float = 3e-4

    def __post_init__(self):
        check_int("num_envs", self.num_envs, 1, 1 << 16)
        check_int("num_steps", self.num_steps, 1, 1 << 16)
        check_int("num_minibatches", self.num_minibatches, 1, 1 << 20)
        check_int("num_epochs", self.num_epochs, 1, 1000)
        check_int("layer_width", self.layer_width, 1, 1 << 14)
        for name, lo, hi, lo_open in (("gamma", 0.0, 1.0, False), ("gae_lambda", 0.0, 1.0, False),
                                      ("clip_eps", 0.0, 10.0, True), ("v_loss_coef", 0.0, 1e3, False),
                                      ("rpo_alpha", 0.0, 10.0, False), ("grad_norm_clip", 0.0, 1e6, True),
                                      ("lr", 0.0, 10.0, True)):
            _check_real(name, getattr(self, name), lo, hi, lo_open)
        if (self.num_envs * self.num_steps) % self.num_minibatches:
            raise ValueError(f"num_minibatches must divide num_envs * num_steps = {self.num_envs * self.num_steps}, "
                             f"got {self.num_minibatches}")

    @property
    def batch_size(self) -> int:
        return self.num_envs * self.num_steps

    @property
    def minibatch_size(self) -> int:
        return self.batch_size // self.num_minibatches

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def train_reward(reward, distance, timestep, done, max_timesteps: int = kenv.MAX_TIMESTEPS):
    """The release's training reward ([KP-5]): the task reward minus a distance penalty
    ``p = distance / 6 / max_timesteps`` on every step without a positive reward, charged
    ``max_timesteps - timestep`` times on the step that ends the episode (``timestep`` counts the
    steps taken before this one)."""
    pen = jnp.where(reward > 0, 0.0, distance / 6.0 / max_timesteps)
    return reward - jnp.where(done, (max_timesteps - timestep) * pen, pen)


def _optimizer(config: PPOConfig):
    return optax.chain(optax.clip_by_global_norm(config.grad_norm_clip), optax.adam(config.lr))


def make_ppo(task: kenv.KinetixTask, config: PPOConfig):
    """``(init, update)`` for ``task`` ([KP-4]), both jitted.

    ``init(key) -> state`` resets ``num_envs`` envs and initialises the expert and Adam;
    ``update(state) -> (state, metrics)`` runs one PPO iteration (``num_steps`` steps of every env,
    then ``num_epochs`` passes of ``num_minibatches`` minibatches); ``metrics`` holds a scalar for every
    name of ``CURVE_FIELDS`` that the device computes. One compile serves every iteration.
    """
    if not isinstance(task, kenv.KinetixTask):
        raise ValueError(f"task must be a KinetixTask (softrtc.kinetix.env.make_env), got {type(task).__name__}")
    if not isinstance(config, PPOConfig):
        raise ValueError(f"config must be a PPOConfig, got {type(config).__name__}")
    E, S, M = config.num_envs, config.num_steps, config.num_minibatches
    tx = _optimizer(config)
    max_t = task.env_params.max_timesteps

    def init(key):
        k_env, k_par, k_run = jax.random.split(key, 3)
        obs, state = jax.vmap(task.reset)(jax.random.split(k_env, E))
        params = kexp.init_expert(k_par, kexp.expert_obs_dim(task.obs_dim, task.action_dim), task.action_dim,
                                  config.layer_width)
        hist, prev = kexp.history_reset(obs)
        zf = jnp.zeros((E,), jnp.float32)
        return {"rng": k_run, "env": state, "hist": hist, "prev": prev, "ep_return": zf, "ep_length": zf,
                "last_return": zf, "last_length": zf, "last_solved": zf,
                "params": params, "opt": tx.init(params), "update": jnp.zeros((), jnp.int32)}

    def rollout_step(params, c, _):
        rng, k_act, k_env = jax.random.split(c["rng"], 3)
        x = kexp.expert_input(c["hist"], c["prev"])
        mean, std = kexp.actor_mean_std(params, x)
        action = kexp.sample_action(k_act, mean, std)
        logp = kexp.action_log_prob(mean, std, action)
        value = kexp.critic_value(params, x)
        t = c["env"].timestep
        obs, state, reward, done, info = jax.vmap(task.step)(jax.random.split(k_env, E), c["env"], action)
        r_train = train_reward(reward, info["distance"], t, done, max_t)
        ep_ret, ep_len = c["ep_return"] + reward, c["ep_length"] + 1.0
        hist, prev = kexp.history_step(c["hist"], c["prev"], obs, action, done)
        new = dict(c, rng=rng, env=state, hist=hist, prev=prev,
                   ep_return=jnp.where(done, 0.0, ep_ret), ep_length=jnp.where(done, 0.0, ep_len),
                   last_return=jnp.where(done, ep_ret, c["last_return"]),
                   last_length=jnp.where(done, ep_len, c["last_length"]),
                   last_solved=jnp.where(done, info["solved"].astype(jnp.float32), c["last_solved"]))
        tr = {"x": x, "action": action, "logp": logp, "value": value, "reward": r_train,
              "done": done.astype(jnp.float32), "ret": new["last_return"], "len": new["last_length"],
              "solved": new["last_solved"]}
        return new, tr

    def loss_fn(params, mb, key):
        mean, std = kexp.actor_mean_std(params, mb["x"])
        z = jax.random.uniform(key, mean.shape, minval=-config.rpo_alpha, maxval=config.rpo_alpha)
        logp = kexp.action_log_prob(mean + z, std, mb["action"])
        log_ratio = logp - mb["logp"]
        ratio = jnp.exp(log_ratio)
        adv = (mb["adv"] - mb["adv"].mean()) / (mb["adv"].std() + 1e-8)
        pg = jnp.maximum(-adv * ratio, -adv * jnp.clip(ratio, 1 - config.clip_eps, 1 + config.clip_eps)).mean()
        value = kexp.critic_value(params, mb["x"])
        v_clip = mb["value"] + jnp.clip(value - mb["value"], -config.clip_eps, config.clip_eps)
        v_loss = 0.5 * jnp.maximum((value - mb["ret_target"]) ** 2, (v_clip - mb["ret_target"]) ** 2).mean()
        loss = pg + config.v_loss_coef * v_loss
        return loss, {"pg_loss": pg, "v_loss": v_loss, "approx_kl": ((ratio - 1) - log_ratio).mean(),
                      "clipfrac": (jnp.abs(ratio - 1) > config.clip_eps).mean()}

    def one_update(c, _):
        params = c["params"]
        c, tr = jax.lax.scan(lambda cc, u: rollout_step(params, cc, u), c, None, length=S)
        last_v = kexp.critic_value(params, kexp.expert_input(c["hist"], c["prev"]))

        def gae(carry, t):
            g, next_v = carry
            nd = 1.0 - t["done"]
            delta = t["reward"] + config.gamma * next_v * nd - t["value"]
            g = delta + config.gamma * config.gae_lambda * nd * g
            return (g, t["value"]), g

        _, adv = jax.lax.scan(gae, (jnp.zeros_like(last_v), last_v), tr, reverse=True)
        data = {"x": tr["x"], "action": tr["action"], "logp": tr["logp"], "value": tr["value"], "adv": adv,
                "ret_target": adv + tr["value"]}
        data = jax.tree.map(lambda a: a.reshape((S * E,) + a.shape[2:]), data)

        def epoch(ec, _):
            params, opt, rng = ec
            rng, k_perm, k_mb = jax.random.split(rng, 3)
            perm = jax.random.permutation(k_perm, S * E)
            batches = jax.tree.map(lambda a: a[perm].reshape((M, -1) + a.shape[1:]), data)

            def minibatch(mc, xs):
                params, opt = mc
                mb, k = xs
                (loss, info), grads = jax.value_and_grad(loss_fn, has_aux=True)(params, mb, k)
                upd, opt = tx.update(grads, opt, params)
                return (optax.apply_updates(params, upd), opt), dict(info, loss=loss,
                                                                     grad_norm=optax.global_norm(grads))

            (params, opt), info = jax.lax.scan(minibatch, (params, opt), (batches, jax.random.split(k_mb, M)))
            return (params, opt, rng), info

        rng, k_ep = jax.random.split(c["rng"])
        (params, opt, _), info = jax.lax.scan(epoch, (params, c["opt"], k_ep), None, length=config.num_epochs)
        n_done = tr["done"].sum()
        denom = jnp.maximum(n_done, 1.0)
        nan = jnp.float32(jnp.nan)
        metrics = {k: v.mean() for k, v in info.items()}
        metrics.update({"episodes": n_done,
                        "return": jnp.where(n_done > 0, (tr["ret"] * tr["done"]).sum() / denom, nan),
                        "solved": jnp.where(n_done > 0, (tr["solved"] * tr["done"]).sum() / denom, nan),
                        "length": jnp.where(n_done > 0, (tr["len"] * tr["done"]).sum() / denom, nan),
                        "train_reward": tr["reward"].mean()})
        c = dict(c, rng=rng, params=params, opt=opt, update=c["update"] + 1)
        return c, metrics

    def update(state):
        state, metrics = one_update(state, None)
        return kenv.strong_types(state), metrics

    # A fresh state and one read back from a resume file are then the same program input ([KP-7]).
    return jax.jit(lambda key: kenv.strong_types(init(key))), jax.jit(update, donate_argnums=0)



# make_ppo's programs per level and configuration, built once per process: a run resumed or repeated in
# the same process (a script training in stages, the tests) neither retraces nor recompiles.
_PROGRAMS: dict = {}


def _ppo_programs(task: kenv.KinetixTask, config: PPOConfig):
    key = (task.level_name, str(task.levels_dir), task.action_noise_std, task.env_params, task.static_env_params,
           config)
    if key not in _PROGRAMS:
        _PROGRAMS[key] = make_ppo(task, config)
    return _PROGRAMS[key]


def expert_paths(run_dir: str | os.PathLike, seed: int, level: str, update: int | None = None) -> dict:
    """File names of one expert run ([KP-6]); ``update`` selects a checkpoint folder."""
    base = Path(run_dir) / f"seed_{seed}"
    name = f"worlds_l_{level}"
    out = {"seed_dir": base, "curve_csv": base / f"curve_{name}.csv", "curve_png": base / f"curve_{name}.png",
           "resume": base / f"resume_{name}.npz"}
    if update is not None:
        out["policy"] = base / str(update) / "policies" / f"{name}.pkl"
        out["stats"] = base / str(update) / "stats" / f"{name}.json"
    return out


def train_expert(level: str, run_dir: str | os.PathLike, *, updates: int, seed: int = 0,
                 config: PPOConfig | None = None, log_interval: int = 20, max_minutes: float | None = None,
                 levels_dir: str | os.PathLike | None = None, resume: bool = True, progress: bool = True,
                 clock: Callable[[], float] = time.monotonic) -> dict:
    """Train (or continue) one PPO expert on ``level`` up to ``updates`` iterations ([KP-4]..[KP-8]).

    Blocks of ``log_interval`` iterations run as one compiled call; after each block the expert,
    its stats, the learning curve (CSV and PNG) and the resume state are written ([KP-6], [KP-7]).
    With ``resume`` a run continues from its resume file when one exists (bitwise the run that was
    never interrupted, [KP-7]). ``max_minutes`` (wall clock, read from ``clock``) stops after the
    first block that ends past it ([KP-8]). Returns a summary with the last block's stats.
    """
    kenv.check_level_name(level, "level")
    updates = check_int("updates", updates, 1, 1 << 24)
    seed = check_int("seed", seed, 0, 2**31 - 1)
    log_interval = check_int("log_interval", log_interval, 1, 1 << 20)
    config = PPOConfig() if config is None else config
    if not isinstance(config, PPOConfig):
        raise ValueError(f"config must be a PPOConfig, got {type(config).__name__}")
    if max_minutes is not None:
        max_minutes = _check_real("max_minutes", max_minutes, 0.0, 1e7, lo_open=True)
    if not isinstance(resume, bool) or not isinstance(progress, bool):
        raise ValueError("resume and progress must be bools")
    check_out_dir("run_dir", run_dir)
    paths = expert_paths(run_dir, seed, level)
    task = kenv.make_env(level, levels_dir)
    init, update = _ppo_programs(task, config)
    state = init(jax.random.fold_in(jax.random.key(seed), kenv.level_index(level)))
    meta = {"level": level, "seed": seed, "config": config.to_dict(), "format": 1}
    rows: list[dict] = []
    wall0 = 0.0
    if resume and paths["resume"].is_file():
        state, saved = load_state(paths["resume"], state, "this configuration")
        if {k: saved.get(k) for k in ("level", "seed", "config")} != {k: meta[k] for k in ("level", "seed", "config")}:
            raise ValueError(f"resume file {paths['resume']} was written for another level, seed or configuration "
                             f"({saved.get('level')}, seed {saved.get('seed')}); use another run folder or resume=False")
        rows = saved.get("rows", [])
        wall0 = float(rows[-1]["wall_s"]) if rows else 0.0
    done = int(state["update"])
    paths["seed_dir"].mkdir(parents=True, exist_ok=True)
    t_start = clock()
    stopped_early = False
    with tqdm(total=updates * config.batch_size, initial=min(done, updates) * config.batch_size, unit="step",
              desc=f"ppo {level}", disable=not progress, file=sys.stderr) as bar:
        while done < updates:
            n = min(log_interval, updates - done)
            block_start = done
            metrics = []
            for _ in range(n):  # one compiled iteration, called n times (a block size never recompiles)
                state, m = update(state)
                metrics.append(m)
                bar.update(config.batch_size)
            metrics = jax.tree.map(lambda *xs: np.stack(xs), *jax.device_get(metrics))
            done = int(state["update"])
            wall = wall0 + clock() - t_start
            for i in range(n):
                row = {"update": block_start + i + 1, "env_steps": (block_start + i + 1) * config.batch_size,
                       "wall_s": round(wall, 3)}
                row.update({k: float(metrics[k][i]) for k in CURVE_FIELDS if k in metrics})
                rows.append(row)
            p = expert_paths(run_dir, seed, level, block_start)
            p["policy"].parent.mkdir(parents=True, exist_ok=True)
            p["stats"].parent.mkdir(parents=True, exist_ok=True)
            kexp.save_expert(p["policy"], state["params"])
            block = rows[-n:]
            stats = {"returned_episode_returns": _nanmean([r["return"] for r in block]),
                     "returned_episode_solved": _nanmean([r["solved"] for r in block]),
                     "returned_episode_lengths": _nanmean([r["length"] for r in block]),
                     "episodes": float(sum(r["episodes"] for r in block)),
                     "updates": done, "env_steps": done * config.batch_size,
                     **{k: _nanmean([r[k] for r in block]) for k in ("loss", "pg_loss", "v_loss", "approx_kl",
                                                                    "clipfrac", "grad_norm")}}
            write_atomic(p["stats"], lambda f: json.dump(stats, f, indent=2))
            write_curve_csv(paths["curve_csv"], rows, CURVE_FIELDS)
            save_state(paths["resume"], state, dict(meta, rows=rows))
            bar.set_postfix_str(f"solved {stats['returned_episode_solved']:.3f}")
            if max_minutes is not None and clock() - t_start >= 60.0 * max_minutes and done < updates:
                stopped_early = True
                break
    if rows:
        plot_curves(paths["curve_csv"], paths["curve_png"], title=f"PPO expert, {level}, seed {seed}")
    last = rows[-1] if rows else {}
    return {"level": level, "seed": seed, "updates": done, "env_steps": done * config.batch_size,
            "stopped_early": stopped_early, "last": last, "curve_csv": str(paths["curve_csv"]),
            "curve_png": str(paths["curve_png"]) if rows else None}


def _nanmean(xs) -> float:
    a = np.asarray(xs, np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else float("nan")
