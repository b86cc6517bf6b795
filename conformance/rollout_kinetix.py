"""The Kinetix world of the conformance rollouts: a level stepped by the runner, a Kinetix flow policy served
as the field ([CR-13], [CR-14]).

    softrtc conformance rollout --impl X --env kinetix [--level NAME] [--checkpoint <level>.npz | --init-seed N]

The runner owns the policy and the simulator, as on the arm ([CR-3]): the
implementation under test sees the level's observation (the symbolic-flat
vector of [K-5], 679 float32 values at the benchmark's sizes), makes every
chunk with the served field and returns the actions the ``s = 4`` ticks
execute; the runner steps the level with them through the env of chapter K
(execution noise of [K-8] included), with the keys of the Kinetix
evaluation ([KE-5]), so an episode of the check is the episode ``kinetix
eval --seed S`` runs, up to the sampler noise that [CR-5] draws.

The env's reset and step are compiled once per set of static sizes through
the program cache of [KC-3] (the level is an argument, as in [KE-3]), so a
second process loads them from disk instead of tracing the physics again.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from softrtc.reference._validate import check_choice, check_int

from .rollout_field import TIME_CONVENTIONS, FieldBase, jitted_field

# [CR-14] The policy checkpoint shipped under softrtc/kinetix/checkpoints/ (a `<level>.npz` file name) that is the
# default served policy, its level the default level: the base (behaviour-cloned) policy of the Kinetix study's
# level ([KS-10]). With None the default would be a fresh benchmark-architecture policy from DEFAULT_INIT_SEED on
# FRESH_LEVEL.
SHIPPED_CHECKPOINT: str | None = "m_h0_unicycle.npz"
# [CR-13] the default level of a fresh policy, served when no checkpoint is shipped (spec/42-rollouts.md).
FRESH_LEVEL = "s_h4_thrust_aim"
# [CR-14] the init seed of the fresh policy (the seed `softrtc kinetix eval` uses without --policy-dir).
DEFAULT_INIT_SEED = 0
# Episodes of one run are keyed by [KE-5]'s episode index, which env_seed packs below 10^6 ([CR-5]).
_EPISODE_BASE = 1_000_000


def checkpoints_dir() -> Path:
    """The folder of shipped Kinetix policy checkpoints, ``softrtc/kinetix/checkpoints/`` ([CR-14])."""
    import softrtc.kinetix

    return Path(softrtc.kinetix.__file__).resolve().parent / "checkpoints"


def default_level() -> str:
    """The level served without ``--level``: the shipped checkpoint's, else :data:`FRESH_LEVEL` ([CR-13])."""
    return SHIPPED_CHECKPOINT[: -len(".npz")] if SHIPPED_CHECKPOINT else FRESH_LEVEL


def default_checkpoint() -> Path | None:
    """The shipped checkpoint served by default, or None (a fresh policy, [CR-14])."""
    return None if SHIPPED_CHECKPOINT is None else checkpoints_dir() / SHIPPED_CHECKPOINT


def policy_digest(policy) -> str:
    """SHA-256 of a FlowPolicy's parameters: each leaf's path, then its float32 little-endian bytes, in
    sorted path order ([CR-14]); equal digests serve the same field."""
    import flax.nnx as nnx

    flat = []

    def walk(prefix, node):
        if isinstance(node, dict):
            for k in node:
                walk(f"{prefix}/{k}", node[k])
        else:
            flat.append((prefix, node))

    walk("", nnx.to_pure_dict(nnx.state(policy)))
    h = hashlib.sha256()
    for path, leaf in sorted(flat, key=lambda kv: kv[0]):
        h.update(path.encode())
        h.update(np.ascontiguousarray(np.asarray(leaf, "<f4")).tobytes())
    return h.hexdigest()


_TASKS: dict = {}
_POLICIES: dict = {}


def _task(level: str, levels_dir):
    """The env of ``level`` (chapter K, [K-8] noise), loaded once per process: padding a level takes seconds."""
    from softrtc.kinetix import env as kenv

    key = (level, None if levels_dir is None else str(Path(levels_dir).resolve()))
    if key not in _TASKS:
        _TASKS[key] = kenv.make_env(level, levels_dir)
    return _TASKS[key]


def load_policy(level: str, checkpoint=None, init_seed=None, levels_dir=None) -> tuple:
    """``(policy, about)`` of the served Kinetix policy ([CR-14]): a ``<level>.npz`` checkpoint of
    ``kinetix train-bc`` / ``finetune`` (its metadata must name ``level``, [KE-11]), or a fresh
    benchmark-architecture policy from ``init_seed``. ``about`` names what the vectors' header records."""
    from softrtc.kinetix import env as kenv
    from softrtc.kinetix.levels import check_level_name

    level = check_level_name(level, "level")
    if checkpoint is not None and init_seed is not None:
        raise ValueError("give at most one of checkpoint and init_seed")
    if checkpoint is None and init_seed is None:
        checkpoint = default_checkpoint() if level == default_level() else None
    key = (level, None if checkpoint is None else str(Path(checkpoint).resolve()), init_seed, str(levels_dir))
    if key in _POLICIES:
        return _POLICIES[key]
    if checkpoint is not None:
        from softrtc.kinetix.finetune import read_level_policy

        path = Path(checkpoint)
        if not path.is_file() or path.name != f"{level}.npz":
            raise ValueError(f"checkpoint must name a Kinetix policy checkpoint file {level}.npz of level {level!r} "
                             f"(written by `softrtc kinetix train-bc` or `finetune`), got {str(path)!r}")
        policy, info = read_level_policy(path.parent, level)
        about = {"checkpoint": str(path), "checkpoint_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
                 "init_seed": None, "role": info["role"]}
    else:
        import flax.nnx as nnx

        from softrtc.jax.policy import FlowPolicy, PolicyConfig

        seed = check_int("init_seed", DEFAULT_INIT_SEED if init_seed is None else init_seed, 0, 2**32 - 1)
        obs_dim = _task(level, levels_dir).obs_dim
        policy = FlowPolicy(obs_dim=obs_dim, action_dim=kenv.ACTION_DIM, config=PolicyConfig(), rngs=nnx.Rngs(seed))
        about = {"checkpoint": None, "checkpoint_sha256": None, "init_seed": seed, "role": "fresh"}
    about["policy_sha256"] = policy_digest(policy)
    _POLICIES[key] = (policy, about)
    return _POLICIES[key]


class KinetixField(FieldBase):
    """``v(obs, x, t)`` of a Kinetix flow policy and its VJP in ``x``, in JAX float32 on float32-rounded
    inputs ([CR-14]); the calling form and the time conventions of the arm's field ([CR-3], [V-1])."""

    env = "kinetix"

    def __init__(self, level: str | None = None, checkpoint=None, init_seed=None, levels_dir=None,
                 convention: str = "data_at_1", _shared=None):
        from softrtc.kinetix.protocol import EXECUTE_HORIZON, NUM_FLOW_STEPS

        self.convention = check_choice("convention", convention, TIME_CONVENTIONS)
        if _shared is None:
            level = default_level() if level is None else level
            policy, about = load_policy(level, checkpoint, init_seed, levels_dir)
            _shared = (level, levels_dir, policy, about, *jitted_field(policy))
        self._shared = _shared
        self.level, self.levels_dir, self.policy, self.about, self._v, self._vjp = _shared
        self.checkpoint = self.about["checkpoint"] or f"fresh policy, init seed {self.about['init_seed']}"
        # [KE-1]: the Kinetix protocol's execute horizon and flow steps; H is the policy's chunk.
        self.H, self.s, self.T = int(self.policy.action_chunk_size), EXECUTE_HORIZON, NUM_FLOW_STEPS
        self.action_dim, self.obs_dim = int(self.policy.action_dim), int(self.policy.obs_dim)
        self.calls = {"velocity": 0, "vjp": 0}

    def flipped(self) -> "KinetixField":
        """The same network for a caller in the other time convention ([V-1])."""
        out = KinetixField(convention=self._other_convention(), _shared=self._shared)
        out.calls = self.calls
        return out

    def describe(self) -> dict:
        """What a report and the vectors' header name the served policy by ([CR-8], [CR-14])."""
        ck = self.about["checkpoint"]
        return {"level": self.level, "checkpoint": None if ck is None else Path(ck).as_posix().split("softrtc/")[-1],
                "checkpoint_sha256": self.about["checkpoint_sha256"], "init_seed": self.about["init_seed"],
                "policy_sha256": self.about["policy_sha256"]}


def _programs(task, s: int):
    """The compiled ``reset(level, key) -> (obs, state, run key)`` and ``step(level, state, run key, tick,
    action) -> (obs, state, reward, done, solved)`` of ``task``'s static sizes ([CR-13], [KC-3])."""
    import jax
    from jax.sharding import SingleDeviceSharding

    from softrtc.kinetix import cache
    from softrtc.kinetix.rollout import _level_task

    def reset(level_state, key):
        k_reset, k_run = jax.random.split(key)  # [KE-5]
        obs, state = _level_task(task, level_state).reset(k_reset)
        return obs, state, k_run

    def step(level_state, state, k_run, tick, action):
        # [KE-5]: tick n is step n mod s of request n div s; its key fold_in(split(fold_in(run, c))[1], j).
        c, j = tick // s, tick % s
        step_key = jax.random.fold_in(jax.random.split(jax.random.fold_in(k_run, c))[1], j)
        obs, state, reward, done, info = _level_task(task, level_state).step(step_key, state, action)
        return obs, state, reward, done, info["solved"]

    dev = SingleDeviceSharding(jax.devices()[0])
    config = (s, task.action_noise_std, task.env_params, task.static_env_params, task.obs_dim, task.action_dim)
    key0 = jax.random.key(0)
    r = cache.compile_program("conformance_kinetix_reset", reset, (task.level, key0), (dev, dev), dev,
                              config=config)
    obs, state, k_run = r(task.level, key0)
    state = _strong(state)
    a0 = jax.numpy.zeros((task.action_dim,), jax.numpy.float32)
    t0 = jax.numpy.asarray(0, jax.numpy.int32)
    st = cache.compile_program("conformance_kinetix_step", step, (task.level, state, k_run, t0, a0),
                               (dev,) * 5, dev, config=config)
    return r, st


def _strong(tree):
    from softrtc.kinetix.env import strong_types

    return strong_types(tree)


class KinetixWorld:
    """A Kinetix level as the rollout runner drives it ([CR-13]).

    ``reset(seed)`` takes the episode seed of [CR-5] (``10^6 S + i``) and
    keys the episode as [KE-5] does for seed ``S`` and episode ``i``;
    ``step(action)`` steps the level with the executed action (kinetix adds
    the execution noise of [K-8] and clips, [K-5]). The episode is done at
    the env's first end (goal, fail or step 256, [K-6]) or after
    ``max_steps`` ticks. ``physical`` is the identity: the implementation's
    actions are the env's.
    """

    metric_names = ("return", "solved", "delta", "jerk")

    def __init__(self, field: KinetixField, max_steps: int | None = None):
        if not isinstance(field, KinetixField):
            raise ValueError(f"field must be a KinetixField, got {type(field).__name__}")
        from softrtc.kinetix.env import MAX_TIMESTEPS

        self.level, self.s = field.level, field.s
        self.max_steps = MAX_TIMESTEPS if max_steps is None else check_int("max_steps", max_steps, 1, 1000)
        self.task = _task(field.level, field.levels_dir)
        if self.task.obs_dim != field.obs_dim or self.task.action_dim != field.action_dim:
            raise ValueError(f"the served policy has obs_dim {field.obs_dim} and action_dim {field.action_dim}, "
                             f"level {field.level!r} has {self.task.obs_dim} and {self.task.action_dim}")
        self._reset, self._step = _programs(self.task, self.s)
        self._t, self._ended, self._state, self._run = 0, False, None, None
        self.info = {"return": 0.0, "solved": False}

    def reset(self, seed: int) -> np.ndarray:
        import jax

        from softrtc.kinetix.rollout import episode_keys

        seed = check_int("seed", seed, 0)
        S, i = divmod(seed, _EPISODE_BASE)
        key = episode_keys(S, self.level, i + 1)[i]
        obs, state, self._run = self._reset(self.task.level, key)
        self._state = _strong(state)
        self._t, self._ended = 0, False
        self.info = {"return": 0.0, "solved": False}
        return np.asarray(jax.device_get(obs), np.float64)

    @property
    def done(self) -> bool:
        return self._ended or self._t >= self.max_steps

    @property
    def t(self) -> int:
        return self._t

    @staticmethod
    def physical(action) -> np.ndarray:
        """The action the env is given (the implementation's own, [CR-13])."""
        return np.asarray(action, np.float64)

    def step(self, action) -> np.ndarray:
        import jax
        import jax.numpy as jnp

        a = jnp.asarray(np.asarray(action, np.float32))
        obs, state, reward, done, solved = self._step(self.task.level, self._state, self._run,
                                                      jnp.asarray(self._t, jnp.int32), a)
        obs, reward, done, solved = jax.device_get((obs, reward, done, solved))
        self._state, self._t = state, self._t + 1
        self.info["return"] += float(reward)
        if bool(done):  # [K-9]: the returned state is the reset level's; the episode ends here
            self._ended, self.info["solved"] = True, bool(solved)
        return np.asarray(obs, np.float64)

    def metrics(self, actions: list, chunk_index: list) -> dict:
        """Return, solved and the action delta and jerk of the executed actions, as the Kinetix evaluation
        computes them over an episode ([KE-7], [M-1], [M-2])."""
        from softrtc.kinetix.evaluation import episode_metrics

        out = {"return": self.info["return"], "solved": float(self.info["solved"])}
        if actions:
            out.update(episode_metrics(np.asarray(actions, np.float64), len(actions)))
        else:
            out.update(delta=float("nan"), jerk=float("nan"))
        return out


__all__ = ["KinetixField", "KinetixWorld", "load_policy", "policy_digest", "default_level", "default_checkpoint",
           "SHIPPED_CHECKPOINT", "FRESH_LEVEL", "DEFAULT_INIT_SEED"]
