"""The 12 large Kinetix levels of the RTC benchmark as a pure-functional env.

Implements chapter K of the spec (``spec/20-kinetix.md``): benchmark
settings [K-5], [K-6], the keyed step with execution noise and automatic
reset [K-7]..[K-10], batching [K-11], input validation [K-12] and the
bare-env benchmark [K-13]. The level set, lookup and loading [K-1]..[K-4]
are :mod:`softrtc.kinetix.levels`; their names are importable from here too.

This module imports JAX and kinetix at import time; ``softrtc.kinetix`` loads
it lazily so that ``import softrtc`` stays free of both.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
import os
import time
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

# levels first: it drops grain's start-up notice before kinetix is imported.
from .levels import (
    FRAME_SKIP,
    LARGE_ENV_PARAMS,
    LEVEL_NAMES,
    MAX_TIMESTEPS,
    NUM_MOTOR_BINDINGS,
    NUM_THRUSTER_BINDINGS,
    LEVELS_HINT,
    OWN_SHAPES_SUFFIX,
    PACKAGE_SETS,
    _check_level_name,
    benchmark_static_env_params,
    check_level_name,
    default_levels_dir,
    is_package_level,
    level_index,
    level_static_env_params,
    load_level,
    package_level_names,
    package_levels_dir,
    project_root,
    resolve_levels_dir,
)

from kinetix.environment.env import make_kinetix_env
from kinetix.environment.env_state import EnvParams, StaticEnvParams
from kinetix.environment.spaces import ActionType, ObservationType

from softrtc.reference._validate import check_int, real_array

from .limits import BATCH_MAX, NUM_ENVS_MAX, NUM_STEPS_MAX, REPEATS_MAX

__all__ = [
    "LEVEL_NAMES", "LARGE_ENV_PARAMS", "FRAME_SKIP", "NUM_MOTOR_BINDINGS", "NUM_THRUSTER_BINDINGS",
    "MAX_TIMESTEPS", "ACTION_NOISE_STD", "OBS_DIM", "ACTION_DIM", "project_root", "default_levels_dir",
    "resolve_levels_dir", "benchmark_static_env_params", "load_level", "KinetixTask", "make_env", "strong_types",
    "random_actions", "make_random_rollout", "bench_bare_env", "LEVELS_HINT", "OWN_SHAPES_SUFFIX", "PACKAGE_SETS",
    "check_level_name", "is_package_level", "level_index", "level_static_env_params", "package_level_names",
    "package_levels_dir",
]

# [K-8] std of the Gaussian noise added to every executed action.
ACTION_NOISE_STD = 0.1
# [K-5] dimensions of the symbolic-flat observation and the continuous action (every level at the
# benchmark's sizes; a level at its own sizes has its own obs_dim, [K-21]).
OBS_DIM = 679
ACTION_DIM = NUM_MOTOR_BINDINGS + NUM_THRUSTER_BINDINGS


# ----------------------------------------------------------------------------
# validation helpers ([K-12])
# ----------------------------------------------------------------------------


def _check_nonneg_float(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a finite real number >= 0, got {value!r}")
    try:
        value = float(value)
    except OverflowError:
        raise ValueError(f"{name} must be a finite real number >= 0, got a value too large for a float") from None
    if not math.isfinite(value) or value < 0.0:
        raise ValueError(f"{name} must be a finite real number >= 0, got {value}")
    return value


def _check_key(name: str, key: Any) -> None:
    """Accept a typed PRNG key (shape ``()``) or a raw ``uint32[2]`` key."""
    shape = getattr(key, "shape", None)
    dtype = getattr(key, "dtype", None)
    if shape is None or dtype is None:
        raise ValueError(f"{name} must be a JAX PRNG key (jax.random.key(...)), got {type(key).__name__}")
    if jnp.issubdtype(dtype, jax.dtypes.prng_key):
        if tuple(shape) != ():
            raise ValueError(f"{name} must be a single PRNG key of shape (), got shape {tuple(shape)}")
        return
    if dtype == jnp.uint32 and tuple(shape) == (2,):
        return
    raise ValueError(
        f"{name} must be a JAX PRNG key: typed key of shape () or uint32 array of shape (2,), "
        f"got dtype {dtype} shape {tuple(shape)}"
    )


def _check_action(name: str, action: Any, shape: tuple[int, ...]) -> jax.Array:
    # Only static properties are checked: values are traced under jit.
    a_shape = getattr(action, "shape", None)
    if a_shape is None:
        try:
            host = real_array(name, action, "f")
        except ValueError as e:
            raise ValueError(f"{e} (expected a floating-point array of shape {shape})") from None
        action = jnp.asarray(host)
        a_shape = action.shape
    if tuple(a_shape) != shape:
        raise ValueError(f"{name} must have shape {shape}, got {tuple(a_shape)}")
    dtype = getattr(action, "dtype", None)
    if dtype is None or not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"{name} must be a floating-point array with values in [-1, 1], got dtype {dtype}")
    return action


# ----------------------------------------------------------------------------
# the task ([K-5]..[K-11])
# ----------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True, eq=False)
class KinetixTask:
    """One benchmark level as pure functions of explicit PRNG keys [K-7].

    Build with :func:`make_env`. ``reset``/``step`` act on one environment,
    ``reset_batch``/``step_batch`` on a leading batch axis via ``jax.vmap``
    [K-11]. All are traceable; wrap them in ``jax.jit`` yourself.
    """

    level_name: str
    levels_dir: Path
    level: Any  # kinetix EnvState the level resets to [K-9]
    env: Any
    env_params: EnvParams
    static_env_params: StaticEnvParams
    obs_dim: int
    action_dim: int
    action_noise_std: float = ACTION_NOISE_STD

    def __post_init__(self):
        # [K-12], [N-7]: build with make_env; a hand-built task is checked field by field.
        _check_level_name(self.level_name)
        if not isinstance(self.levels_dir, Path):
            raise ValueError(f"levels_dir must be a pathlib.Path, got {type(self.levels_dir).__name__}")
        if not (callable(getattr(self.env, "reset", None)) and callable(getattr(self.env, "step", None))):
            raise ValueError(f"env must be a kinetix environment with reset/step, got {type(self.env).__name__}")
        if not isinstance(self.env_params, EnvParams):
            raise ValueError(f"env_params must be a kinetix EnvParams, got {type(self.env_params).__name__}")
        if not isinstance(self.static_env_params, StaticEnvParams):
            raise ValueError(f"static_env_params must be a kinetix StaticEnvParams, got {type(self.static_env_params).__name__}")
        if self.level is None or not hasattr(self.level, "polygon"):
            raise ValueError(f"level must be a kinetix EnvState (from load_level), got {type(self.level).__name__}")
        check_int("obs_dim", self.obs_dim, 1)
        check_int("action_dim", self.action_dim, 1)
        object.__setattr__(self, "action_noise_std", _check_nonneg_float("action_noise_std", self.action_noise_std))

    def _state_template(self):
        # Shapes/dtypes of one env's state, from an abstract reset (cached per task).
        tmpl = self.__dict__.get("_state_shape")
        if tmpl is None:
            tmpl = jax.eval_shape(lambda k: self.env.reset(k, self.env_params)[1], jax.random.key(0))
            object.__setattr__(self, "_state_shape", tmpl)
        return tmpl

    def _check_state(self, state, batch: int | None) -> None:
        tmpl = self._state_template()
        want_def = jax.tree.structure(tmpl)
        try:
            got_def = jax.tree.structure(state)
        except Exception as e:  # pragma: no cover - exotic pytrees
            raise ValueError(f"state must be a kinetix env state from reset, got {type(state).__name__}") from e
        if got_def != want_def:
            raise ValueError(f"state must be a kinetix env state from reset/step (same structure), got {type(state).__name__}")
        lead = () if batch is None else (batch,)
        for want, got in zip(jax.tree.leaves(tmpl), jax.tree.leaves(state)):
            shape = tuple(getattr(got, "shape", np.shape(got)))
            if shape != lead + tuple(want.shape):
                what = "state" if batch is None else f"state (batched, leading dimension n={batch})"
                raise ValueError(f"{what} leaf must have shape {lead + tuple(want.shape)}, got {shape}")

    def reset(self, key: jax.Array):
        """``(obs [obs_dim], state)`` at the level's initial state [K-7], [K-9]."""
        _check_key("key", key)
        obs, state = self.env.reset(key, self.env_params)
        return obs, state

    def step(self, key: jax.Array, state, action: jax.Array):
        """One control step: ``(obs, state, reward, done, info)`` [K-7]..[K-10].

        ``key`` is split into a noise key (the N(0, std^2) noise added to
        ``action`` [K-8]) and the kinetix step key. When the step ends the
        episode the returned ``obs``/``state`` are those of the reset level
        [K-9]. ``info`` holds ``solved`` (episode ended by reaching the goal),
        ``timeout`` (episode ended on its 256th step without reaching the goal,
        a fail or NaN state on that step included), ``executed_action`` (the
        noisy action) and ``distance`` [K-10].
        """
        _check_key("key", key)
        action = _check_action("action", action, (self.action_dim,))
        self._check_state(state, None)
        noise_key, env_key = jax.random.split(key)
        noisy = action + self.action_noise_std * jax.random.normal(noise_key, action.shape, action.dtype)
        # [K-10]: timeout = the step count reaches the limit on this step and the goal is not reached;
        # a fail or NaN on that same step counts as a timeout too (kinetix reports the goal, not a fail).
        next_t = state.timestep + 1
        obs, state, reward, done, kinfo = self.env.step(env_key, state, noisy, self.env_params)
        goal = jnp.asarray(kinfo["GoalR"], bool)
        info = {
            "solved": jnp.logical_and(done, goal),
            "timeout": jnp.logical_and(done, jnp.logical_and(~goal, next_t >= self.env_params.max_timesteps)),
            "executed_action": noisy,
            "distance": kinfo["distance"],
        }
        return obs, state, reward, done, info

    def reset_batch(self, key: jax.Array, n: int):
        """``n`` independent resets, ``obs`` of shape ``[n, obs_dim]`` [K-11]."""
        _check_key("key", key)
        n = check_int("n", n, 1, BATCH_MAX)
        return jax.vmap(self.reset)(jax.random.split(key, n))

    def step_batch(self, key: jax.Array, state, action: jax.Array):
        """Step ``n`` environments; ``action`` is ``[n, action_dim]`` [K-11].

        Environment ``i`` uses ``jax.random.split(key, n)[i]`` as its key.
        """
        _check_key("key", key)
        shape = getattr(action, "shape", None)
        if shape is None or len(shape) != 2 or shape[0] < 1:
            raise ValueError(f"action must have shape [n >= 1, {self.action_dim}], got {shape}")
        n = shape[0]
        _check_action("action", action, (n, self.action_dim))
        self._check_state(state, n)
        return jax.vmap(self.step)(jax.random.split(key, n), state, action)


def strong_types(tree):
    """``tree`` with every array leaf strongly typed (same dtypes and values; typed PRNG keys kept).

    Kinetix keeps its step counter weakly typed, and a carried state that comes back from a ``scan``
    or from a resume file is strongly typed; jit compiles anew when a weak type changes, so a loop that
    feeds a state back into the same program (PPO iterations, data blocks) makes it strong first.
    """
    return jax.tree.map(lambda x: x if jnp.issubdtype(x.dtype, jax.dtypes.prng_key) else x.astype(x.dtype), tree)


def make_env(
    level_name: str,
    levels_dir: str | os.PathLike | None = None,
    action_noise_std: float = ACTION_NOISE_STD,
) -> KinetixTask:
    """Build the benchmark env for ``level_name`` [K-1]..[K-6], [K-20]..[K-21].

    ``levels_dir`` defaults to ``<project root>/../shared/kinetix-levels``
    [K-2]; a package level ([K-20]) is read from kinetix-env instead. ``action_noise_std`` (default 0.1 [K-8]) may be set to 0 for
    noiseless execution.
    """
    _check_level_name(level_name)
    action_noise_std = _check_nonneg_float("action_noise_std", action_noise_std)
    d = resolve_levels_dir(levels_dir, (level_name,))
    level = load_level(level_name, d)
    static = level_static_env_params(level_name)
    params = EnvParams()
    # reset_fn returning the level makes kinetix's auto-reset replay the same
    # level, as the benchmark's AutoReplayWrapper did [K-9].
    env = make_kinetix_env(
        ActionType.CONTINUOUS,
        ObservationType.SYMBOLIC_FLAT,
        lambda _key: level,
        params,
        static,
        auto_reset=True,
    )
    obs_dim = int(env.observation_space(params).shape[0])
    action_dim = int(env.action_space(params).shape[0])
    return KinetixTask(
        level_name=level_name,
        levels_dir=d,
        level=level,
        env=env,
        env_params=params,
        static_env_params=static,
        obs_dim=obs_dim,
        action_dim=action_dim,
        action_noise_std=action_noise_std,
    )


# ----------------------------------------------------------------------------
# bare-env benchmark ([K-13])
# ----------------------------------------------------------------------------


def random_actions(key: jax.Array, shape: tuple[int, ...]) -> jax.Array:
    """Uniform actions ``[*shape, 6]``: motors in [-1, 1], thrusters in [0, 1] (kinetix's ranges)."""
    if not (isinstance(key, jax.Array) and (jnp.issubdtype(key.dtype, jax.dtypes.prng_key)
                                            or (key.dtype == jnp.uint32 and key.shape == (2,)))):
        raise ValueError(f"key must be a JAX PRNG key (jax.random.key or jax.random.PRNGKey), got {key!r}")
    if not isinstance(shape, (tuple, list)):
        raise ValueError(f"shape must be a tuple of integers >= 1, got {shape!r}")
    if not shape:
        raise ValueError("shape must be a non-empty tuple of integers >= 1, got ()")
    shape = tuple(check_int("shape entry", n, 1, BATCH_MAX) for n in shape)
    if math.prod(shape) * ACTION_DIM > 2**31 - 1:
        raise ValueError(f"shape must have prod(shape) * {ACTION_DIM} <= 2^31 - 1 values, got {shape}")
    a = jax.random.uniform(key, (*shape, ACTION_DIM), minval=-1.0, maxval=1.0)
    return a.at[..., NUM_MOTOR_BINDINGS:].set(jnp.abs(a[..., NUM_MOTOR_BINDINGS:]))


def make_random_rollout(task: KinetixTask, num_envs: int, num_steps: int):
    """Jittable ``rollout(key) -> summary`` stepping ``num_envs`` envs ``num_steps`` times [K-13]."""
    if not isinstance(task, KinetixTask):
        raise ValueError(f"task must be a KinetixTask (from make_env), got {type(task).__name__}")
    num_envs = check_int("num_envs", num_envs, 1, BATCH_MAX)
    num_steps = check_int("num_steps", num_steps, 1, NUM_STEPS_MAX)

    def rollout(key):
        key, rkey = jax.random.split(key)
        _, state = task.reset_batch(rkey, num_envs)

        def body(carry, _):
            state, key, dones, solved, ret = carry
            key, akey, skey = jax.random.split(key, 3)
            action = random_actions(akey, (num_envs,))
            _, state, reward, done, info = task.step_batch(skey, state, action)
            return (state, key, dones + done.sum(), solved + info["solved"].sum(), ret + reward.sum()), None

        zero_i = jnp.zeros((), jnp.int32)
        init = (state, key, zero_i, zero_i, jnp.zeros((), jnp.float32))
        (state, _, dones, solved, ret), _ = jax.lax.scan(body, init, None, length=num_steps)
        return {"episodes_done": dones, "episodes_solved": solved, "reward_sum": ret}

    return rollout


def bench_bare_env(
    level: str,
    num_envs: int = 64,
    num_steps: int = 256,
    seed: int = 0,
    levels_dir: str | os.PathLike | None = None,
    repeats: int = 1,
) -> dict:
    """Steps/s of the bare env under random actions, compile time apart [K-13].

    One jitted ``lax.scan`` of ``num_steps`` batched steps over ``num_envs``
    environments is lowered and compiled (timed as ``compile_s``), then run
    ``repeats`` times; ``env_steps_per_s`` uses the fastest run.
    """
    _check_level_name(level)
    num_envs = check_int("num_envs", num_envs, 1, NUM_ENVS_MAX)
    num_steps = check_int("num_steps", num_steps, 1, NUM_STEPS_MAX)
    seed = check_int("seed", seed, 0, 2**32 - 1)
    repeats = check_int("repeats", repeats, 1, REPEATS_MAX)
    task = make_env(level, levels_dir)
    key = jax.random.key(seed)
    t0 = time.perf_counter()
    compiled = jax.jit(make_random_rollout(task, num_envs, num_steps)).lower(key).compile()
    compile_s = time.perf_counter() - t0
    run_times = []
    out = None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = jax.block_until_ready(compiled(key))
        run_times.append(time.perf_counter() - t0)
    best = min(run_times)
    total = num_envs * num_steps
    return {
        "level": level,
        "num_envs": num_envs,
        "num_steps": num_steps,
        "seed": seed,
        "env_steps": total,
        "compile_s": compile_s,
        "run_s": best,
        "run_s_all": run_times,
        "env_steps_per_s": total / best,
        "episodes_done": int(out["episodes_done"]),
        "episodes_solved": int(out["episodes_solved"]),
        "device": str(jax.devices()[0]),
    }
