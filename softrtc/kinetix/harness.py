"""Kinetix evaluation protocol of the RTC benchmark (spec ``20-kinetix.md``, [KE-1]..[KE-12]).

Every method of chapter S ([S-6]) is run in closed loop on the benchmark
levels with the asynchronous executor of chapter X: execute horizon
``s = 4``, delays ``d in {0, .., 4}``, 5 flow steps, ``N`` episodes per
(level, delay, method), 256 control steps per episode, metrics of chapter M
on the executed actions up to the end of each env's first episode.

One jitted rollout serves a whole *sampler family* ([KE-3]): ``naive``,
``train_hard`` and ``train_soft`` use the training-time sampler with the
method's per-delay weight table (all zeros for ``naive``, bitwise the naive
sampler by [S-7]); ``inference_hard`` and ``inference_soft`` use the guided
sampler. Policy parameters, the level, the weight table, the delays and the
PRNG keys are arguments of the compiled function, so one compile serves
every level, delay, window and checkpoint of a family. The rollout is a
``lax.scan`` over chunks of a batch of envs; the env axis is sharded over a
1-D device mesh ([KE-4]).

>>> from softrtc.kinetix.harness import parse_method
>>> parse_method("train_soft:offset:1").label
'train_soft:offset:1'
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import math
import numbers
import re
import os
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from tqdm.auto import tqdm

from softrtc._files import check_out_dir
from softrtc.reference._validate import real_array
from softrtc.jax import methods as jmethods
from softrtc.jax.guidance import guided_sample_conditioned
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.jax.sampler import conditioning_table, naive_conditioning, rtc_sample_conditioned, select_conditioning
from softrtc.reference import endpoints as ref_endpoints
from softrtc.reference import metrics as ref_metrics
from softrtc.reference import weights as ref_weights
from softrtc.reference.methods import METHODS

from . import env as kenv
from .limits import EPISODE_STEPS_MAX, EPISODE_STEPS_MIN, EPISODES_MAX, NUM_ENVS_MAX, REPEATS_MAX

__all__ = [
    "EXECUTE_HORIZON",
    "DELAYS",
    "NUM_FLOW_STEPS",
    "EPISODES",
    "EPISODE_STEPS",
    "MethodSpec",
    "parse_method",
    "PAPER_METHODS",
    "method_family",
    "rollout_weight_table",
    "Rollout",
    "make_rollout",
    "episode_keys",
    "episode_metrics",
    "EvalConfig",
    "evaluate",
    "summarize",
    "main_table",
    "write_results",
    "bench_harness",
]

# [KE-1] the protocol of the paper's Experimental Setup.
EXECUTE_HORIZON = 4
DELAYS = (0, 1, 2, 3, 4)
NUM_FLOW_STEPS = 5
EPISODES = 32
EPISODE_STEPS = kenv.MAX_TIMESTEPS
HIGH_DELAYS = ref_metrics.HIGH_DELAYS

_DISPLAY = {
    "naive": "Base Naive",
    "inference_hard": "Inference Hard RTC",
    "inference_soft": "Inference Soft RTC",
    "train_hard": "Train Hard RTC",
    "train_soft": "Train Soft RTC",
}


def _check_int(name: str, value: Any, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        rng = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise ValueError(f"{name} must be an integer {rng}, got {value!r}")
    if value < lo or (hi is not None and value > hi):
        rng = f"in [{lo}, {hi}]" if hi is not None else f">= {lo}"
        raise ValueError(f"{name} must be an integer {rng}, got {value}")
    return int(value)


# ----------------------------------------------------------------------------- methods


@dataclasses.dataclass(frozen=True)
class MethodSpec:
    """One evaluated method ([S-6], [KE-2]): a method name of chapter S and, for
    ``train_soft``, its soft window (reference :class:`~softrtc.reference.weights.SoftWindow`)."""

    method: str
    window: ref_weights.SoftWindow | None = None
    label: str = ""

    def __post_init__(self):
        if self.method not in METHODS:
            raise ValueError(f"method must be one of {', '.join(METHODS)}, got {self.method!r}")
        if self.window is not None:
            if not isinstance(self.window, ref_weights.SoftWindow):
                raise ValueError(f"window must be a softrtc.reference.weights.SoftWindow, got {type(self.window).__name__}")
            if self.method != "train_soft":
                raise ValueError(f"window is only used by method 'train_soft', got method {self.method!r}")
        if self.method == "train_soft" and self.window is None:
            object.__setattr__(self, "window", ref_weights.SoftWindow())
        if not isinstance(self.label, str):
            raise ValueError(f"label must be a string, got {type(self.label).__name__}")
        if not self.label:
            object.__setattr__(self, "label", self.method)
        # [KE-2], [KE-8]: a label that reads as a method string must name this method and window,
        # so a table row is never shown under another method's name; other labels are free text.
        try:
            name, window = _parse_method_parts(self.label)
        except ValueError:
            return
        if (name, window) != (self.method, self.window):
            raise ValueError(f"label {self.label!r} parses as method {name!r} with window {window}, "
                             f"but this MethodSpec is method {self.method!r} with window {self.window}; "
                             f"label must be a free-form name or a method string of this method and window")

    @property
    def display(self) -> str:
        """Row name in the style of the paper's main table."""
        base = _DISPLAY[self.method]
        return base if self.label == self.method else f"{base} ({self.label.split(':', 1)[1]})" \
            if self.label.startswith(self.method + ":") else self.label


def parse_method(text: str) -> MethodSpec:
    """Parse a method string ([KE-2]).

    ``naive``, ``inference_hard``, ``inference_soft``, ``train_hard``,
    ``train_soft`` (the paper's main window, delay-scaled lam=2, h_max=5,
    linear), or ``train_soft:<rule>:<params>`` with rule
    ``delay_scaled:LAM[:H_MAX]`` (default h_max 5), ``offset:L[:H_MAX]``
    (default 8), ``fixed:H``, ``hard``; optionally followed by
    ``:zeros`` to select ``overflow="zeros"`` ([W-6]); ``train_soft:zeros`` is the main window zero-padded.
    """
    name, window = _parse_method_parts(text)
    if window is None or text.strip() == name:
        return MethodSpec(name)
    return MethodSpec(name, window, label=text.strip())


def _parse_method_parts(text: Any) -> tuple:
    """``(method, window)`` of a method string ([KE-2]); ``window`` is None for methods other than train_soft."""
    if not isinstance(text, str) or not text.strip():
        raise ValueError(f"method must be a non-empty string such as 'train_soft:delay_scaled:2', got {text!r}")
    parts = [p.strip() for p in text.strip().split(":")]
    name = parts[0]
    if name not in METHODS:
        raise ValueError(f"method must start with one of {', '.join(METHODS)}, got {text!r}")
    if len(parts) == 1:
        return name, (ref_weights.SoftWindow() if name == "train_soft" else None)
    if name != "train_soft":
        raise ValueError(f"method {name!r} takes no window parameters, got {text!r}")
    overflow = "clip"
    if parts[-1] == "zeros":
        overflow, parts = "zeros", parts[:-1]
    if len(parts) == 1:  # train_soft:zeros, the main window with zero padding
        return "train_soft", ref_weights.SoftWindow(overflow=overflow)
    rule_name, args = (parts[1], parts[2:]) if len(parts) > 1 else ("delay_scaled", [])
    # Plain ASCII decimals only: Python's int/float would also take "1_0" (10) or other scripts' digits.
    if not all(re.fullmatch(r"[0-9]+(\.[0-9]+)?", a) for a in args):
        raise ValueError(f"method {text!r} is not a valid soft window: parameters must be plain decimal numbers")
    try:
        if rule_name == "delay_scaled" and 1 <= len(args) <= 2:
            rule = ref_endpoints.delay_scaled(float(args[0]), int(args[1]) if len(args) > 1 else 5)
        elif rule_name == "offset" and 1 <= len(args) <= 2:
            rule = ref_endpoints.offset(int(args[0]), int(args[1]) if len(args) > 1 else 8)
        elif rule_name == "fixed" and len(args) == 1:
            rule = ref_endpoints.fixed(int(args[0]))
        elif rule_name == "hard" and not args:
            rule = ref_endpoints.hard()
        else:
            raise ValueError("unknown rule or wrong number of parameters")
    except ValueError as exc:
        raise ValueError(
            f"method {text!r} is not a valid soft window: use train_soft:delay_scaled:LAM[:H_MAX], "
            f"train_soft:offset:L[:H_MAX], train_soft:fixed:H or train_soft:hard, optionally ':zeros' ({exc})"
        ) from None
    return "train_soft", ref_weights.SoftWindow(rule, overflow=overflow)


# The rows of the paper's main table whose method differs ([KE-2]); N=1 and N=2 are lam = 1, 2.
PAPER_METHODS = ("naive", "inference_hard", "inference_soft", "train_hard",
                 "train_soft:delay_scaled:1", "train_soft:delay_scaled:2")


def method_family(method: str) -> str:
    """``"rtc"`` for naive / train_hard / train_soft, ``"guided"`` for inference_* ([KE-3])."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    return "guided" if method.startswith("inference_") else "rtc"


def rollout_weight_table(spec: MethodSpec, H: int, s: int) -> np.ndarray:
    """Weights per delay for the rollout ([KE-3]): ``[D + 1, H]`` float32, D = min(s, H - s) + 1.

    Row ``d`` is the method's weights for delay ``d`` ([S-6], [G-1], [W-7],
    [W-8]; all zeros for ``naive``, [W-9]); the extra last row is all zeros
    and generates the first chunk of every episode, which is the naive
    sampler by [S-7] / [G-6] ([X-2]).
    """
    if not isinstance(spec, MethodSpec):
        raise ValueError(f"spec must be a MethodSpec, got {type(spec).__name__}")
    H = _check_int("H", H, 1)
    s = _check_int("s", s, 1, H)
    table = np.asarray(jmethods.method_weight_table(spec.method, H, s, spec.window), np.float32)
    return np.concatenate([table, np.zeros((1, H), np.float32)], axis=0)


# ----------------------------------------------------------------------------- rollout


def episode_keys(seed: int, level: str, episodes: int) -> jax.Array:
    """Per-episode keys ``fold_in(fold_in(key(seed), level index), episode)`` ([KE-5], [N-9]).

    They do not depend on the method or the delay: every method and delay
    sees the same initial states, sampler noise and execution noise
    (common random numbers).
    """
    seed = _check_int("seed", seed, 0, 2**32 - 1)
    if level not in kenv.LEVEL_NAMES:
        raise ValueError(f"level must be one of {', '.join(kenv.LEVEL_NAMES)}, got {level!r}")
    episodes = _check_int("episodes", episodes, 1, 2**20)
    base = jax.random.fold_in(jax.random.key(seed), kenv.LEVEL_NAMES.index(level))
    return jax.vmap(lambda e: jax.random.fold_in(base, e))(jnp.arange(episodes, dtype=jnp.uint32))


def _level_task(template: kenv.KinetixTask, level_state) -> kenv.KinetixTask:
    """The template's task resetting to ``level_state`` (traced): one compile for every level ([KE-3]).

    All benchmark levels share static params ([K-4]), so their ``EnvState``s
    have the same shapes; the auto-reset replays ``level_state`` ([K-9]).
    """
    # A shallow copy shares the physics engine (built from static params only) and swaps the reset state.
    env = copy.copy(template.env)
    env.reset_function = lambda _key: level_state
    return dataclasses.replace(template, level=level_state, env=env)


def _build_rollout_fn(template, graphdef, family, H, A, s, T, C):
    """Pure ``fn(params, level, table, keys [n], delays [n]) -> dict`` of one family ([KE-3]..[KE-6])."""
    D = min(s, H - s) + 1

    def fn(params, level_state, table, keys, delays):
        model = nnx.merge(graphdef, params)
        task = _level_task(template, level_state)
        n = keys.shape[0]
        k_reset, k_run = jnp.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0)
        obs0, state0 = jax.vmap(task.reset)(k_reset)
        if family == "rtc":
            cond_table = conditioning_table(model, table, T)
        else:
            cond = naive_conditioning(model, T)

        def env_step(carry, inp):
            state, _ = carry
            step_keys, action = inp
            obs, state, reward, done, info = jax.vmap(task.step)(step_keys, state, action)
            return (state, obs), (reward, done, info["solved"])

        def chunk(carry, c):
            state, obs, prev = carry
            first = c == 0
            # Row D of the table is all zeros: the first chunk is the naive sampler ([X-2], [S-7], [G-6]).
            row = jnp.where(first, D, delays)
            d = jnp.where(first, 0, delays)
            kc = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, c)))(k_run)
            noise = jax.vmap(lambda k: jax.random.normal(k, (H, A), jnp.float32))(kc[:, 0])
            prior = jnp.where(first, 0.0, _shift(prev, s))
            w = table[row]
            if family == "rtc":
                new = rtc_sample_conditioned(model, obs, noise, prior, w, T, cond=select_conditioning(cond_table, row))
            else:
                new = guided_sample_conditioned(model, obs, noise, prior, w, T, cond=cond)
            # prev[s : s + d] then new[d : s]; d = 0 for the first chunk.
            i = jnp.arange(s)
            from_prev = prev[:, jnp.minimum(s + i, H - 1)]
            seg = jnp.where((i[None, :] < d[:, None])[..., None], from_prev, new[:, :s])
            step_keys = jax.vmap(lambda k: jax.vmap(lambda j: jax.random.fold_in(k, j))(i))(kc[:, 1])
            (state, obs), (rew, done, solved) = jax.lax.scan(
                env_step, (state, obs), (jnp.swapaxes(step_keys, 0, 1), jnp.swapaxes(seg, 0, 1)))
            return (state, obs, new), (seg, new, rew, done, solved)

        prev0 = jnp.zeros((n, H, A), jnp.float32)
        _, (segs, chunks, rew, done, solved) = jax.lax.scan(
            chunk, (state0, obs0, prev0), jnp.arange(C, dtype=jnp.int32))
        N = C * s
        actions = jnp.swapaxes(segs, 0, 1).reshape(n, N, A)  # [C, n, s, A] -> [n, C*s, A]
        rew, done, solved = (x.reshape(N, n).T for x in (rew, done, solved))
        # [M-4]: the first episode of each env, truncated at its end.
        any_done = done.any(axis=1)
        first_done = jnp.argmax(done, axis=1)
        length = jnp.where(any_done, first_done + 1, N)
        mask = jnp.arange(N)[None, :] < length[:, None]
        ret = jnp.sum(jnp.where(mask, rew, 0.0), axis=1)
        solved_ep = any_done & jnp.take_along_axis(solved, first_done[:, None], axis=1)[:, 0]
        return {"actions": actions, "chunks": jnp.swapaxes(chunks, 0, 1), "length": length.astype(jnp.int32),
                "return": ret, "solved": solved_ep, "ended": any_done}

    return fn


def _shift(prev, s):
    """Prior Y[j] = prev[j + s], zero past the overlap ([X-3]); batched over envs."""
    H = prev.shape[-2]
    j = jnp.arange(H)
    src = prev[:, jnp.minimum(j + s, H - 1)]
    return jnp.where((j < H - s)[None, :, None], src, 0.0)


_LEVELS: dict = {}
_ROLLOUTS: dict = {}


def _level_state(template, level: str):
    """Loaded level states, cached per (levels dir, level): parsing a level file takes seconds."""
    if level == template.level_name:
        return template.level
    key = (str(template.levels_dir), level)
    if key not in _LEVELS:
        _LEVELS[key] = kenv.load_level(level, template.levels_dir)
    return _LEVELS[key]


def _check_policy(policy) -> FlowPolicy:
    if not isinstance(policy, FlowPolicy):
        raise ValueError(f"policy must be a softrtc.jax.policy.FlowPolicy, got {type(policy).__name__}")
    return policy


class Rollout:
    """A compiled closed-loop rollout of one sampler family ([KE-3]..[KE-6]).

    Build with :func:`make_rollout`. ``rollout(policy, spec, level, keys,
    delays)`` runs ``len(keys)`` episodes (one per key, with the delay of the
    same index) and returns host NumPy arrays: ``actions [n, C*s, A]`` (the
    executed actions, [X-4]), ``chunks [n, C, H, A]`` (every generated
    chunk), ``length``, ``return``, ``solved``, ``ended`` (``[n]``) and
    ``delays``. ``compile_s`` is the time of the last lower-and-compile.
    """

    def __init__(self, template, policy, family, s, num_flow_steps, num_chunks, num_envs, mesh):
        self.template = template
        self.family = family
        self.s, self.T, self.C, self.num_envs = s, num_flow_steps, num_chunks, num_envs
        self.H, self.A = policy.action_chunk_size, policy.action_dim
        self.obs_dim, self.config = policy.obs_dim, policy.config
        graphdef, params = nnx.split(policy)
        self._params_struct = jax.tree.map(lambda a: (a.shape, a.dtype), params)
        self.mesh = mesh
        self.num_devices = mesh.devices.size
        # Pad the env axis to a multiple of the device count; padded envs are dropped.
        self.padded = -(-num_envs // self.num_devices) * self.num_devices
        rep = NamedSharding(mesh, PartitionSpec())
        env_axis = NamedSharding(mesh, PartitionSpec("env"))
        self._shardings = (rep, env_axis)
        fn = _build_rollout_fn(template, graphdef, family, self.H, self.A, s, num_flow_steps, num_chunks)
        self._jit = jax.jit(fn, in_shardings=(rep, rep, rep, env_axis, env_axis))
        self._compiled = None
        self.compile_s = None

    def _args(self, policy, spec, level, keys, delays):
        policy = _check_policy(policy)
        if (policy.obs_dim, policy.action_dim, policy.config) != (self.obs_dim, self.A, self.config):
            raise ValueError("policy must have the architecture (obs_dim, action_dim, config) the rollout was built for")
        if not isinstance(spec, MethodSpec):
            raise ValueError(f"spec must be a MethodSpec, got {type(spec).__name__}")
        if method_family(spec.method) != self.family:
            raise ValueError(f"spec.method must belong to the {self.family!r} family of this rollout, got {spec.method!r}")
        if level not in kenv.LEVEL_NAMES:
            raise ValueError(f"level must be one of {', '.join(kenv.LEVEL_NAMES)}, got {level!r}")
        keys = jnp.asarray(keys)
        if not jnp.issubdtype(keys.dtype, jax.dtypes.prng_key) or keys.shape != (self.num_envs,):
            raise ValueError(f"keys must be a typed PRNG key array of shape ({self.num_envs},), "
                             f"got {keys.dtype} {tuple(keys.shape)}")
        hi = min(self.s, self.H - self.s)
        want = f"delays must be an integer array of shape ({self.num_envs},) with entries in [0, {hi}] ([X-1])"
        try:
            ds = real_array("delays", delays, "iu")
        except ValueError as e:
            raise ValueError(f"{want}: {e}") from None
        if ds.shape != (self.num_envs,):
            raise ValueError(f"{want}, got dtype {ds.dtype} shape {ds.shape}")
        if ds.min() < 0 or ds.max() > hi:
            raise ValueError(f"{want}, got {np.ravel(ds).tolist()[:8]}")
        pad = self.padded - self.num_envs
        if pad:  # exact copies of env 0, key and delay ([KE-4]); their results are dropped
            keys = jnp.concatenate([keys, jnp.broadcast_to(keys[:1], (pad,))])
            ds = np.concatenate([ds, np.broadcast_to(ds[:1], (pad,))])
        level_state = _level_state(self.template, level)
        table = jnp.asarray(rollout_weight_table(spec, self.H, self.s))
        params = nnx.state(policy)
        return params, level_state, table, keys, jnp.asarray(ds, jnp.int32)

    def compile(self, policy, spec, level, keys, delays) -> float:
        """Lower and compile for these argument shapes; returns and stores ``compile_s``."""
        args = self._args(policy, spec, level, keys, delays)
        t0 = time.perf_counter()
        self._compiled = self._jit.lower(*args).compile()
        self.compile_s = time.perf_counter() - t0
        return self.compile_s

    def __call__(self, policy, spec, level, keys, delays) -> dict:
        args = self._args(policy, spec, level, keys, delays)
        if self._compiled is None:
            t0 = time.perf_counter()
            self._compiled = self._jit.lower(*args).compile()
            self.compile_s = time.perf_counter() - t0
        out = jax.device_get(self._compiled(*args))
        out = {k: np.asarray(v)[: self.num_envs] for k, v in out.items()}
        out["delays"] = np.asarray(delays, np.int64)
        return out


def make_rollout(task: kenv.KinetixTask, policy: FlowPolicy, family: str, num_envs: int,
                 execute_horizon: int = EXECUTE_HORIZON, num_flow_steps: int = NUM_FLOW_STEPS,
                 episode_steps: int = EPISODE_STEPS, devices: Sequence | None = None) -> Rollout:
    """A :class:`Rollout` for ``policy``'s architecture ([KE-3]..[KE-6]).

    ``task`` is any level's :class:`~softrtc.kinetix.env.KinetixTask` (its
    settings, noise and levels directory are used; the level itself is an
    argument of each call). ``family`` is ``"rtc"`` or ``"guided"``
    (:func:`method_family`). The rollout runs ``C = ceil(episode_steps / s)``
    chunks; ``episode_steps`` lies in the range of ``EvalConfig.episode_steps``
    ([KE-1]). ``devices`` (default all) form the 1-D mesh of the env axis.
    """
    if not isinstance(task, kenv.KinetixTask):
        raise ValueError(f"task must be a KinetixTask (softrtc.kinetix.env.make_env), got {type(task).__name__}")
    policy = _check_policy(policy)
    if family not in ("rtc", "guided"):
        raise ValueError(f"family must be 'rtc' or 'guided', got {family!r}")
    if (policy.obs_dim, policy.action_dim) != (task.obs_dim, task.action_dim):
        raise ValueError(f"policy must have obs_dim={task.obs_dim} and action_dim={task.action_dim} (the task's), "
                         f"got {policy.obs_dim} and {policy.action_dim}")
    num_envs = _check_int("num_envs", num_envs, 1, 2**20)
    H = policy.action_chunk_size
    s = _check_int("execute_horizon", execute_horizon, 1, H)
    T = _check_int("num_flow_steps", num_flow_steps, 1, 1024)
    steps = _check_int("episode_steps", episode_steps, EPISODE_STEPS_MIN, EPISODE_STEPS_MAX)
    if devices is None:
        devs = list(jax.devices())
    else:
        if isinstance(devices, (str, bytes)) or not isinstance(devices, Sequence):
            raise ValueError(f"devices must be None or a non-empty sequence of jax.Device objects, "
                             f"got {type(devices).__name__}")
        devs = list(devices)
        bad = [d for d in devs if not isinstance(d, jax.Device)]
        if bad:
            raise ValueError(f"devices must be a non-empty sequence of jax.Device objects (e.g. jax.devices()), "
                             f"got entry {bad[0]!r}")
        if len(set(devs)) != len(devs):
            raise ValueError("devices must not repeat a device")
    if not devs:
        raise ValueError("devices must be a non-empty sequence of JAX devices")
    mesh = Mesh(np.array(devs), ("env",))
    # Rollouts are cached by everything that shapes the compiled code, so that repeated
    # evaluations in one process (tests, sweeps) compile once.
    key = (family, policy.obs_dim, policy.action_dim, policy.config, s, T, math.ceil(steps / s), num_envs,
           task.action_noise_std, task.env_params, task.static_env_params, str(task.levels_dir),
           tuple(str(d) for d in devs))
    if key not in _ROLLOUTS:
        _ROLLOUTS[key] = Rollout(task, policy, family, s, T, math.ceil(steps / s), num_envs, mesh)
    return _ROLLOUTS[key]


def episode_metrics(actions: np.ndarray, length: int) -> dict:
    """Action delta and jerk of one episode's executed actions, truncated at ``length`` ([M-1], [M-2], [M-4]).

    ``nan`` when the episode is too short for the difference ([M-1] needs
    N > k); such episodes are left out of that metric's means ([KE-7]).
    """
    a = real_array("actions", actions).astype(np.float64)
    if a.ndim != 2 or 0 in a.shape:
        raise ValueError(f"actions must have shape [N >= 1, A >= 1], got {list(a.shape)}")
    length = _check_int("length", length, 1, a.shape[0])
    a = a[:length]
    return {"delta": ref_metrics.action_delta(a) if length > 1 else float("nan"),
            "jerk": ref_metrics.action_jerk(a) if length > 2 else float("nan")}


# ----------------------------------------------------------------------------- evaluation


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """The evaluation protocol ([KE-1]); every field is validated.

    ``methods`` holds method strings (:func:`parse_method`) or
    :class:`MethodSpec`s. ``seed`` fixes every random draw ([KE-5]).
    """

    levels: tuple = kenv.LEVEL_NAMES
    methods: tuple = PAPER_METHODS
    delays: tuple = DELAYS
    episodes: int = EPISODES
    execute_horizon: int = EXECUTE_HORIZON
    num_flow_steps: int = NUM_FLOW_STEPS
    episode_steps: int = EPISODE_STEPS
    seed: int = 0
    levels_dir: str | None = None
    bootstrap_resamples: int = 10000
    bootstrap_seed: int = 0

    def __post_init__(self):
        levels = _as_tuple("levels", self.levels, "distinct level names", single=(str,))
        for lv in levels:
            if not isinstance(lv, str):
                raise ValueError(f"levels entries must be level names among {', '.join(kenv.LEVEL_NAMES)}, got {lv!r}")
        if not levels or len(set(levels)) != len(levels):
            raise ValueError(f"levels must be a non-empty sequence of distinct level names, got {self.levels!r}")
        for lv in levels:
            if lv not in kenv.LEVEL_NAMES:
                raise ValueError(f"levels entries must be among {', '.join(kenv.LEVEL_NAMES)}, got {lv!r}")
        object.__setattr__(self, "levels", levels)
        meths = tuple(m if isinstance(m, MethodSpec) else parse_method(m) for m in
                      _as_tuple("methods", self.methods, "distinct methods", single=(str, MethodSpec)))
        if not meths or len({m.label for m in meths}) != len(meths):
            raise ValueError(f"methods must be a non-empty sequence of distinct methods, got {self.methods!r}")
        seen: dict = {}
        for m in meths:  # [KE-2] two spellings of one method and window (lam 2 and 2.0) are one method
            same = seen.setdefault((m.method, m.window), m.label)
            if same != m.label:
                raise ValueError(f"methods must be distinct methods: {same!r} and {m.label!r} are the same method "
                                 f"and window")
        object.__setattr__(self, "methods", meths)
        s = _check_int("execute_horizon", self.execute_horizon, 1, 1 << 12)
        ds = _as_tuple("delays", self.delays, f"distinct integers in [0, {s}]")
        for d in ds:
            _check_int("delays entries", d, 0, s)
        if not ds or len(set(ds)) != len(ds):
            raise ValueError(f"delays must be a non-empty sequence of distinct integers in [0, {s}], "
                             f"got {self.delays!r}")
        for d in ds:
            _check_int("delays entries", d, 0, s)
        object.__setattr__(self, "delays", tuple(int(d) for d in ds))
        _check_int("episodes", self.episodes, 1, EPISODES_MAX)
        _check_int("num_flow_steps", self.num_flow_steps, 1, 1024)
        _check_int("episode_steps", self.episode_steps, EPISODE_STEPS_MIN, EPISODE_STEPS_MAX)
        _check_int("seed", self.seed, 0, 2**32 - 1)
        _check_int("bootstrap_resamples", self.bootstrap_resamples, 1, 10**7)
        _check_int("bootstrap_seed", self.bootstrap_seed, 0, 2**32 - 1)
        if self.levels_dir is not None and not isinstance(self.levels_dir, (str, os.PathLike)):
            raise ValueError(f"levels_dir must be a path or None, got {type(self.levels_dir).__name__}")


def _as_tuple(name: str, value: Any, what: str, single: tuple = ()) -> tuple:
    """``value`` as a tuple ([N-7]): an instance of ``single`` is a one-entry sequence; any other
    non-iterable (``delays=3``) or a string where a string is no entry is a ``ValueError`` naming ``name``."""
    if single and isinstance(value, single):
        return (value,)
    if not isinstance(value, (str, bytes)):
        try:
            return tuple(value)
        except TypeError:  # not iterable, e.g. a bare integer or a 0-d array
            pass
    raise ValueError(f"{name} must be a non-empty sequence of {what}, got {value!r}")


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
    template = kenv.make_env(config.levels[0], levels_dir)
    E, ds = config.episodes, config.delays
    n = E * len(ds)
    delays = np.repeat(np.asarray(ds, np.int64), E)
    # Every (method, level) policy is resolved and checked before the first rollout, so a missing
    # policy or a delay its chunk cannot hold stops the run before any work, not hours into it.
    pols: dict = {}
    for spec in config.methods:
        for level in config.levels:
            pol = _resolve_policy(policies, spec, level)
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
                rkey = (fam, pol.obs_dim, pol.action_dim, pol.config)
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


METRICS = ("return", "solved", "delta", "jerk")
SCOPES = ("overall", "high")


def _nanmean(x) -> float:
    x = np.asarray(x, np.float64)
    x = x[np.isfinite(x)]
    return float(x.mean()) if x.size else float("nan")


def _check_rows(rows: list) -> None:
    """Episode rows of :func:`evaluate` ([KE-8]): str method/level, int delay, real metric values."""
    need = ("method", "level", "delay", *METRICS)
    for i, r in enumerate(rows):
        if not isinstance(r, Mapping) or any(k not in r for k in need):
            raise ValueError(f"rows[{i}] must be a mapping with keys {list(need)} (an episode row of evaluate), "
                             f"got {r if not isinstance(r, Mapping) else sorted(map(str, r))}")
        for k in ("method", "level"):
            if not isinstance(r[k], str) or not r[k]:
                raise ValueError(f"rows[{i}][{k!r}] must be a non-empty string, got {r[k]!r}")
        _check_int(f"rows[{i}]['delay']", r["delay"], 0, 4096)
        for k in METRICS:
            v = r[k]
            ok = isinstance(v, (numbers.Real, np.bool_)) and not isinstance(v, np.datetime64)
            if k != "solved" and isinstance(v, (bool, np.bool_)):
                ok = False
            if ok and k in ("return", "solved") and not math.isfinite(float(v)):
                ok = False
            if not ok:
                what = "a bool or 0/1 number" if k == "solved" else (
                    "a finite real number" if k == "return" else "a real number (NaN when undefined)")
                raise ValueError(f"rows[{i}][{k!r}] must be {what}, got {v!r}")


def summarize(rows: Iterable[Mapping], *, bootstrap_resamples: int = 10000, bootstrap_seed: int = 0) -> dict:
    """Per-level and pooled metrics ([M-4], [M-5], [M-7], [KE-7]).

    Per (method, level, scope): each metric is the mean over its episodes,
    each delay of the scope weighted equally (``overall``: every delay
    evaluated, ``high``: d in {3, 4}). Pooled: the mean over levels with its
    bootstrap 95% interval over levels. Returns ``{"per_level": [...],
    "pooled": [...]}`` row lists.
    """
    if isinstance(rows, (str, bytes, Mapping)) or not isinstance(rows, Iterable):
        raise ValueError(f"rows must be an iterable of episode rows (mappings, as in evaluate()['episodes']), "
                         f"got {type(rows).__name__}")
    rows = list(rows)
    if not rows:
        raise ValueError("rows must hold at least one episode row")
    _check_rows(rows)
    _check_int("bootstrap_resamples", bootstrap_resamples, 1, 10**7)
    _check_int("bootstrap_seed", bootstrap_seed, 0, 2**32 - 1)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    levels = list(dict.fromkeys(r["level"] for r in rows))
    per_level, pooled = [], []
    for m in methods:
        for scope in SCOPES:
            vals = {k: [] for k in METRICS}
            for lv in levels:
                sel = [r for r in rows if r["method"] == m and r["level"] == lv
                       and (scope == "overall" or r["delay"] in HIGH_DELAYS)]
                if not sel:
                    continue
                # Each delay weighted equally ([M-4]), then episodes within a delay.
                by_d = {}
                for r in sel:
                    by_d.setdefault(r["delay"], []).append(r)
                entry = {"method": m, "level": lv, "scope": scope, "episodes": len(sel)}
                for k in METRICS:
                    entry[k] = _nanmean([_nanmean([float(r[k]) for r in rs]) for rs in by_d.values()])
                    vals[k].append(entry[k])
                per_level.append(entry)
            if not vals["return"]:
                continue
            entry = {"method": m, "scope": scope, "levels": len(vals["return"])}
            for k in METRICS:
                v = np.asarray(vals[k], np.float64)
                v = v[np.isfinite(v)]
                entry[k] = float(v.mean()) if v.size else float("nan")
                if v.size:
                    lo, hi = ref_metrics.bootstrap_interval(v, bootstrap_resamples, bootstrap_seed)
                else:
                    lo = hi = float("nan")
                entry[k + "_lo"], entry[k + "_hi"] = lo, hi
            pooled.append(entry)
    return {"per_level": per_level, "pooled": pooled}


def _display(label: str) -> str:
    try:
        return parse_method(label).display
    except ValueError:
        return label


def main_table(summary: Mapping) -> str:
    """Markdown table in the layout of the paper's main table ([KE-8]).

    Columns: Method | Overall Return | Overall Solve | High-delay Solve |
    High-delay Jerk | Overall Delta | Overall Jerk | High-delay Delta, each
    pooled over levels with its bootstrap 95% interval.
    """
    if not isinstance(summary, Mapping) or "pooled" not in summary:
        raise ValueError("summary must be the dict returned by summarize()")
    need = ("method", "scope", *METRICS, *(k + "_lo" for k in METRICS), *(k + "_hi" for k in METRICS))
    if isinstance(summary["pooled"], (str, bytes, Mapping)) or not isinstance(summary["pooled"], Sequence):
        raise ValueError("summary['pooled'] must be the list of pooled rows returned by summarize()")
    for i, r in enumerate(summary["pooled"]):
        if not isinstance(r, Mapping):
            raise ValueError(f"summary['pooled'][{i}] must be a mapping (a pooled row of summarize()), got {r!r}")
        missing = [k for k in need if k not in r]
        if missing:
            raise ValueError(f"summary['pooled'][{i}] is missing key(s) {', '.join(missing)}")
        if not isinstance(r["method"], str) or r["scope"] not in SCOPES:
            raise ValueError(f"summary['pooled'][{i}] must have a str 'method' and 'scope' in {SCOPES}, "
                             f"got {r['method']!r}, {r['scope']!r}")
        for k in need[2:]:
            if isinstance(r[k], bool) or not isinstance(r[k], numbers.Real):
                raise ValueError(f"summary['pooled'][{i}][{k!r}] must be a real number, got {r[k]!r}")
    cols = [("overall", "return", "Overall Return"), ("overall", "solved", "Overall Solve"),
            ("high", "solved", "High-delay Solve"), ("high", "jerk", "High-delay Jerk ↓"),
            ("overall", "delta", "Overall Delta ↓"), ("overall", "jerk", "Overall Jerk ↓"),
            ("high", "delta", "High-delay Delta ↓")]
    pooled = {(r["method"], r["scope"]): r for r in summary["pooled"]}
    methods = list(dict.fromkeys(r["method"] for r in summary["pooled"]))
    lines = ["| Method | " + " | ".join(c[2] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for m in methods:
        cells = []
        for scope, k, _ in cols:
            r = pooled.get((m, scope))
            if r is None or not np.isfinite(r[k]):
                cells.append("–")
            else:
                cells.append(f"{r[k]:.3f} [{r[k + '_lo']:.3f}, {r[k + '_hi']:.3f}]")
        lines.append(f"| {_display(m)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def write_results(result: Mapping, out_dir: str | os.PathLike, *, bootstrap_resamples: int = 10000,
                  bootstrap_seed: int = 0) -> dict:
    """Write ``episodes.csv``, ``per_level.csv``, ``pooled.csv`` and ``table.md`` ([KE-8]); returns the paths."""
    if not isinstance(result, Mapping) or "episodes" not in result:
        raise ValueError("result must be the dict returned by evaluate()")
    out = check_out_dir("out_dir", out_dir, ("episodes.csv", "per_level.csv", "pooled.csv", "table.md"))
    # Rows are checked and summarized before anything is created.
    summary = summarize(result["episodes"], bootstrap_resamples=bootstrap_resamples, bootstrap_seed=bootstrap_seed)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"episodes": out / "episodes.csv", "per_level": out / "per_level.csv",
             "pooled": out / "pooled.csv", "table": out / "table.md"}
    _write_csv(paths["episodes"], list(result["episodes"]))
    _write_csv(paths["per_level"], summary["per_level"])
    _write_csv(paths["pooled"], summary["pooled"])
    paths["table"].write_text(main_table(summary))
    return {k: str(v) for k, v in paths.items()} | {"summary": summary}


# ----------------------------------------------------------------------------- bench


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
    if level not in kenv.LEVEL_NAMES:
        raise ValueError(f"level must be one of {', '.join(kenv.LEVEL_NAMES)}, got {level!r}")
    num_envs = _check_int("num_envs", num_envs, 1, NUM_ENVS_MAX)
    seed = _check_int("seed", seed, 0, 2**32 - 1)
    repeats = _check_int("repeats", repeats, 1, REPEATS_MAX)
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
