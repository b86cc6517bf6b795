"""The compiled closed-loop rollout of the Kinetix evaluation ([KE-3]..[KE-6]).

One jitted rollout serves a whole *sampler family* ([KE-3]): ``naive``,
``train_hard`` and ``train_soft`` use the training-time sampler with the
method's per-delay weight table (all zeros for ``naive``, bitwise the naive
sampler by [S-7]); ``inference_hard`` and ``inference_soft`` use the guided
sampler. Policy parameters, the level, the weight table, the delays and the
PRNG keys are arguments of the compiled function, so one compile serves
every level, delay, window and checkpoint of a family. So is the solver
step of the training-time family ([KE-13]): a boolean argument picks
Algorithm 1's step or the time-consistent one ([S-10]) by ``lax.cond``. The rollout is a
``lax.scan`` over chunks of a batch of envs; the env axis is sharded over a
1-D device mesh ([KE-4]).
"""

from __future__ import annotations

import copy
import dataclasses
import math
from typing import Sequence

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from softrtc.jax import executor as jexec
from softrtc.jax.fast_chunks import FastChunks
from softrtc.jax.policy import FlowPolicy
from softrtc.reference._validate import check_int, real_array

from . import cache
from . import env as kenv
from .limits import EPISODE_STEPS_MAX, EPISODE_STEPS_MIN
from .methods import FAMILY_SAMPLERS, MethodSpec, method_family, rollout_weight_table
from .protocol import EPISODE_STEPS, EXECUTE_HORIZON, NUM_FLOW_STEPS

__all__ = ["episode_keys", "Rollout", "make_rollout", "rollout_sampler"]


def episode_keys(seed: int, level: str, episodes: int) -> jax.Array:
    """Per-episode keys ``fold_in(fold_in(key(seed), level index), episode)`` ([KE-5], [N-9]).

    They do not depend on the method or the delay: every method and delay
    sees the same initial states, sampler noise and execution noise
    (common random numbers).
    """
    seed = check_int("seed", seed, 0, 2**32 - 1)
    kenv.check_level_name(level, "level")
    episodes = check_int("episodes", episodes, 1, 2**20)
    base = jax.random.fold_in(jax.random.key(seed), kenv.level_index(level))
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


def rollout_sampler(policy: FlowPolicy, family: str, s: int, T: int, table, consistent):
    """The chunk requests of a family's rollout ([KE-3], [KE-13]): ``(first, next_chunk)``.

    ``first(obs [n, O], keys [n])`` is the naive first chunk ([X-2]) and
    ``next_chunk(obs, prior [n, H, A], delays [n], keys [n])`` a later one,
    with the weight table ``[min(s, H - s) + 1, H]`` of the method. For the
    ``"rtc"`` family the scalar boolean ``consistent`` (traced in the
    rollout) picks the solver step ([S-10]) with ``lax.cond``: both samplers
    are in the program, only the chosen one runs. The guided family has no
    blended step ([S-14]) and ignores the flag, which the rollout sets False.
    """
    policy = _check_policy(policy)
    if family not in FAMILY_SAMPLERS:
        raise ValueError(f"family must be 'rtc' or 'guided', got {family!r}")
    s = check_int("s", s, 1, policy.action_chunk_size)
    T = check_int("T", T, 1, 1024)
    if isinstance(consistent, bool):
        if consistent and family != "rtc":
            raise ValueError("consistent must be False for the 'guided' family (no blended step, [S-14])")
    elif not (isinstance(consistent, (jax.Array, np.ndarray)) and consistent.shape == ()
              and consistent.dtype == np.bool_):
        raise ValueError(f"consistent must be a bool or a boolean scalar array, got {consistent!r}")
    sampler = FAMILY_SAMPLERS[family]  # with the traced weight table of the method ([KE-3])
    chunks = FastChunks(policy, sampler, s, T, weights=table, stored_transposes=False)
    if family != "rtc":
        return chunks.first, chunks.next
    cons = FastChunks(policy, sampler, s, T, weights=table, stored_transposes=False, step="consistent")

    def next_chunk(obs, prior, delays, keys):
        return jax.lax.cond(consistent, lambda: cons.next(obs, prior, delays, keys),
                            lambda: chunks.next(obs, prior, delays, keys))

    return chunks.first, next_chunk


def _build_rollout_fn(template, graphdef, family, H, A, s, T, C):
    """Pure ``fn(params, level, table, consistent, keys [n], delays [n]) -> dict`` of one family
    ([KE-3]..[KE-6], [KE-13])."""

    def fn(params, level_state, table, consistent, keys, delays):
        first_chunk, next_chunk = rollout_sampler(nnx.merge(graphdef, params), family, s, T, table, consistent)
        task = _level_task(template, level_state)
        k_reset, k_run = jnp.moveaxis(jax.vmap(jax.random.split)(keys), 1, 0)
        obs0, state0 = jax.vmap(task.reset)(k_reset)

        def env_step(carry, inp):
            state, _ = carry
            step_keys, action = inp
            obs, state, reward, done, info = jax.vmap(task.step)(step_keys, state, action)
            return (state, obs), (reward, done, info["solved"])

        def request_keys(c):
            """Per env: the key of request c's noise and of its s env steps ([KE-5])."""
            kc = jax.vmap(lambda k: jax.random.split(jax.random.fold_in(k, c)))(k_run)
            i = jnp.arange(s)
            return kc[:, 0], jax.vmap(lambda k: jax.vmap(lambda j: jax.random.fold_in(k, j))(i))(kc[:, 1])

        def execute(state, obs, seg, step_keys):
            (state, obs), (rew, done, solved) = jax.lax.scan(
                env_step, (state, obs), (jnp.swapaxes(step_keys, 0, 1), jnp.swapaxes(seg, 0, 1)))
            return state, obs, (seg, rew, done, solved)

        def request(carry, c):
            # Segment c executes, then request c + 1 is made at the observation that follows ([X-3],
            # each env with its own delay). The env's step appears once in the program: its
            # compilation costs about what the bare env's scan costs ([KC-6]). The chunk of the last
            # iteration (request C) is not made.
            state, obs, prev, seg = carry
            _, step_keys = request_keys(c)
            state, obs, (seg, rew, done, solved) = execute(state, obs, seg, step_keys)
            noise_keys, _ = request_keys(c + 1)
            # After the last segment there is no request to make: its chunk would be dropped.
            new = jax.lax.cond(c + 1 < C, lambda: next_chunk(obs, jexec.shift_prior(prev, s), delays, noise_keys),
                               lambda: prev)
            return (state, obs, new, jexec.segment(prev, new, s, delays)), (seg, new, rew, done, solved)

        # Request 0: the naive sampler, no prior, d = 0; its chunk executes its own tokens 0 .. s-1.
        noise_keys, _ = request_keys(jnp.int32(0))
        first = first_chunk(obs0, noise_keys)
        _, (segs, later, rew, done, solved) = jax.lax.scan(
            request, (state0, obs0, first, first[:, :s]), jnp.arange(C, dtype=jnp.int32))
        chunks_out = jnp.concatenate([first[None], later[:-1]])
        n = keys.shape[0]
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
        return {"actions": actions, "chunks": jnp.swapaxes(chunks_out, 0, 1), "length": length.astype(jnp.int32),
                "return": ret, "solved": solved_ep, "ended": any_done}

    return fn


_LEVELS: dict = {}
_ROLLOUTS: dict = {}


def _level_state(template, level: str):
    """Loaded level states, cached per (levels dir, level): parsing a level file takes seconds."""
    if level == template.level_name:
        return template.level
    if kenv.level_static_env_params(level) != template.static_env_params:
        raise ValueError(f"level {level!r} runs at other static sizes than the rollout's level "
                         f"{template.level_name!r} ([K-21]); build a rollout from its own task")
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
    same index) with the weight table and solver step of ``spec`` ([KE-13])
    and returns host NumPy arrays: ``actions [n, C*s, A]`` (the
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
        self._fn = _build_rollout_fn(template, graphdef, family, self.H, self.A, s, num_flow_steps, num_chunks)
        # Everything the traced program closes over ([KC-3]); argument shapes and devices are added by the cache.
        self._program_config = ("kinetix_rollout", family, type(policy).__qualname__, policy.obs_dim, self.A,
                                policy.config, s, num_flow_steps, num_chunks, template.action_noise_std,
                                template.env_params, template.static_env_params)
        self._compiled = None
        self.compile_s = None
        self.compile_source = None

    def _args(self, policy, spec, level, keys, delays):
        policy = _check_policy(policy)
        if (policy.obs_dim, policy.action_dim, policy.config) != (self.obs_dim, self.A, self.config):
            raise ValueError("policy must have the architecture (obs_dim, action_dim, config) the rollout was built for")
        if not isinstance(spec, MethodSpec):
            raise ValueError(f"spec must be a MethodSpec, got {type(spec).__name__}")
        if method_family(spec.method) != self.family:
            raise ValueError(f"spec.method must belong to the {self.family!r} family of this rollout, got {spec.method!r}")
        kenv.check_level_name(level, "level")
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
        consistent = jnp.asarray(spec.step == "consistent")  # [KE-13]; False for every guided method ([S-14])
        params = nnx.state(policy)
        return params, level_state, table, consistent, keys, jnp.asarray(ds, jnp.int32)

    def _compile(self, args) -> None:
        # [KC-3]: through the program cache (skips tracing for a configuration compiled before);
        # outputs replicated, so with several processes every one gets all episodes ([KD-2]).
        rep, env_axis = self._shardings
        self._compiled = cache.compile_program("kinetix_rollout", self._fn, args,
                                               (rep, rep, rep, rep, env_axis, env_axis),
                                               rep, config=self._program_config)
        self.compile_s, self.compile_source = self._compiled.seconds, self._compiled.source

    def compile(self, policy, spec, level, keys, delays) -> float:
        """Compile (or load, [KC-3]) for these argument shapes; returns and stores ``compile_s``
        (``compile_source`` says ``"compiled"``, ``"disk"`` or ``"memory"``)."""
        self._compile(self._args(policy, spec, level, keys, delays))
        return self.compile_s

    def __call__(self, policy, spec, level, keys, delays) -> dict:
        args = self._args(policy, spec, level, keys, delays)
        if self._compiled is None:
            self._compile(args)
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
    num_envs = check_int("num_envs", num_envs, 1, 2**20)
    H = policy.action_chunk_size
    s = check_int("execute_horizon", execute_horizon, 1, H)
    T = check_int("num_flow_steps", num_flow_steps, 1, 1024)
    steps = check_int("episode_steps", episode_steps, EPISODE_STEPS_MIN, EPISODE_STEPS_MAX)
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
