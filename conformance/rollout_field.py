"""The policy of the conformance rollouts: a shipped arm checkpoint served as a velocity field ([CR-2], [CR-3]).

The runner owns the network. An implementation under test never loads it: it
calls ``field(obs, x, t)`` and, for a guided sampler, ``field.vjp(obs, x, t,
cotangent)``, in process or over the JSON-lines protocol ([CR-4]). Both run
the checkpoint's JAX network in float32 on float32-rounded inputs, so every
implementation, in any language, sees the same numbers for the same inputs.

Everything the implementation handles lives in the network's normalized
space ("chunk space", [CR-3]): the observation is the normalized policy
feature vector of [A-17], [A-18], chunks, priors, noise and executed actions
are normalized actions. The world side (:class:`ArmWorld`) maps an executed
action to physical units and clips it to the ranges of [A-8] before the
simulator steps; the implementation never sees physical units.
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np

from softrtc.reference._validate import check_array, check_choice, check_int

TIME_CONVENTIONS = ("data_at_1", "noise_at_1")


def default_checkpoint() -> Path:
    """The drift task's shipped base ([A-21], [AX-8]): the field of every rollout method ([CR-3])."""
    from softrtc.arm.checkpoints import default_checkpoint_dir

    return default_checkpoint_dir() / "drift" / "base.npz"


def jitted_field(model) -> tuple:
    """(jitted velocity, jitted VJP) of a FlowPolicy ``model`` for one observation, in float32 ([CR-3]):
    ``v(obs [O], x [H, A], t [H])`` and ``vjp(obs, x, t, cotangent [H, A])``. Shared by the arm's and
    Kinetix's served fields ([CR-3], [CR-13])."""
    import flax.nnx as nnx
    import jax
    import jax.numpy as jnp

    graphdef, state = nnx.split(model)

    def vel(state, obs, x, t):
        return nnx.merge(graphdef, state)(obs[None], x[None], t[None])[0]

    def vjp(state, obs, x, t, ct):
        _, pull = jax.vjp(lambda xx: vel(state, obs, xx, t), x)
        return pull(ct)[0]

    f32 = jnp.float32
    jv = jax.jit(lambda o, x, t: vel(state, o.astype(f32), x.astype(f32), t.astype(f32)))
    jj = jax.jit(lambda o, x, t, c: vjp(state, o.astype(f32), x.astype(f32), t.astype(f32), c.astype(f32)))
    return jv, jj


@functools.lru_cache(maxsize=4)
def _load(path: str):
    """(policy, jitted velocity, jitted VJP) of one checkpoint file, loaded once per process."""
    from softrtc.arm.checkpoints import load_arm_checkpoint

    policy = load_arm_checkpoint(path)
    return (policy, *jitted_field(policy.model))


class FieldBase:
    """A served field ``v(obs, x, t)`` and its VJP in ``x`` ([CR-3], [F-1]'s calling form), in the caller's
    time convention ([V-1]). Subclasses set ``H``, ``s``, ``T``, ``action_dim``, ``obs_dim``, ``convention``,
    ``calls`` and the jitted ``_v``, ``_vjp``, and implement ``flipped``."""

    def _inputs(self, obs, x, t):
        obs = check_array("obs", obs, shape=(self.obs_dim,))
        x = check_array("x", x, shape=(self.H, self.action_dim))
        t = np.broadcast_to(check_array("t", np.asarray(t, np.float64), lo=0.0, hi=1.0), (self.H,))
        if self.convention == "noise_at_1":
            t = 1.0 - t
        return obs, x, t

    def __call__(self, obs, x, t) -> np.ndarray:
        obs, x, t = self._inputs(obs, x, t)
        self.calls["velocity"] += 1
        out = np.asarray(self._v(obs, x, t), np.float64)
        return -out if self.convention == "noise_at_1" else out

    def vjp(self, obs, x, t, cotangent) -> np.ndarray:
        obs, x, t = self._inputs(obs, x, t)
        c = check_array("cotangent", cotangent, shape=x.shape)
        self.calls["vjp"] += 1
        out = np.asarray(self._vjp(obs, x, t, c), np.float64)
        return -out if self.convention == "noise_at_1" else out

    def _other_convention(self) -> str:
        return "noise_at_1" if self.convention == "data_at_1" else "data_at_1"


class ServedField(FieldBase):
    """``v(obs, x, t)`` of a shipped arm checkpoint and its VJP in ``x`` ([CR-3], [F-1]'s calling form).

    ``convention`` is the caller's time convention ([V-1]): under
    ``noise_at_1`` the field is ``u(obs, x, t') = -v(obs, x, 1 - t')`` and its
    VJP ``-(dv/dx)^T c`` at ``1 - t'``, as [CF-10] maps the vectors' field.
    Inputs are float64 arrays (or anything NumPy reads); they are rounded to
    float32, the network's precision, and the result comes back as float64.
    ``calls`` counts the evaluations (velocity and VJP separately).
    """

    env = "arm"

    def __init__(self, checkpoint=None, convention: str = "data_at_1"):
        path = Path(default_checkpoint() if checkpoint is None else checkpoint)
        if not path.is_file():
            raise ValueError(f"checkpoint must name an arm checkpoint file (.npz), got {str(path)!r}")
        self.checkpoint = str(path)
        self.convention = check_choice("convention", convention, TIME_CONVENTIONS)
        self.policy, self._v, self._vjp = _load(str(path.resolve()))
        self.H, self.s, self.T = self.policy.H, self.policy.s, self.policy.T
        self.action_dim = int(self.policy.model.action_dim)
        self.obs_dim = int(self.policy.model.obs_dim)
        self.calls = {"velocity": 0, "vjp": 0}

    def flipped(self) -> "ServedField":
        """The same network for a caller in the other time convention ([V-1])."""
        out = ServedField(self.checkpoint, self._other_convention())
        out.calls = self.calls
        return out

    def describe(self) -> dict:
        """What a report names the served policy by ([CR-8])."""
        return {"checkpoint": self.checkpoint.replace("\\", "/").split("softrtc/")[-1]}


class ArmWorld:
    """The arm simulator as the rollout runner drives it ([CR-3], [A-8], [A-17], [A-18]).

    ``reset(seed)`` and ``step(action)`` take and give chunk space: the
    observation as the normalized feature vector (float32-rounded, the
    network's input), the action as a normalized action mapped here to
    physical units and clipped to [A-8]. ``physical`` keeps the commands sent.
    """

    def __init__(self, field: ServedField, env_config=None, max_steps: int | None = None):
        from softrtc.arm.env import ArmSortEnv
        from softrtc.arm.features import action_bounds
        from softrtc.arm.tasks import DRIFT_CONFIG

        cfg = DRIFT_CONFIG if env_config is None else env_config
        self.env = ArmSortEnv(cfg)
        self.low, self.high = action_bounds(cfg)
        limit = self.env.config.max_steps
        self.max_steps = limit if max_steps is None else check_int("max_steps", max_steps, 1, limit)
        nm = field.policy.normalizer
        self._obs_mean, self._obs_std = nm.obs_mean, nm.obs_std
        self._act_mean, self._act_std = nm.act_mean, nm.act_std
        self.dt = self.env.config.dt
        self.info = {"success": False, "num_completed": 0, "success_step": None}

    def _features(self, raw) -> np.ndarray:
        from softrtc.arm.features import policy_features

        z = (policy_features(raw).astype(np.float32) - self._obs_mean.astype(np.float32)) \
            / self._obs_std.astype(np.float32)
        return z.astype(np.float64)

    def reset(self, seed: int) -> np.ndarray:
        self.info = {"success": False, "num_completed": 0, "success_step": None}
        return self._features(self.env.reset(check_int("seed", seed, 0)))

    @property
    def done(self) -> bool:
        return bool(self.env.done) or self.env.t >= self.max_steps

    @property
    def t(self) -> int:
        return int(self.env.t)

    # The paired outcomes of [CR-7] on the arm.
    metric_names = ("success", "completed", "D1", "D2", "D3", "boundary")

    def metrics(self, actions: list, chunk_index: list) -> dict:
        """The episode's outcomes of [CR-7] from the commands sent and each tick's chunk index."""
        from .rollout_loop import episode_metrics

        return episode_metrics(self, actions, chunk_index)

    def physical(self, action) -> np.ndarray:
        """A chunk-space action in physical units, clipped to the ranges of [A-8]."""
        a = np.asarray(action, np.float64) * self._act_std + self._act_mean
        return np.clip(a, self.low, self.high)

    def step(self, action) -> np.ndarray:
        raw, self.info = self.env.step(self.physical(action))
        return self._features(raw)
