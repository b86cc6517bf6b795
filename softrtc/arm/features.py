"""Policy input features of the arm and their normalization ([A-17], [A-18], [A-8])."""

from __future__ import annotations

import dataclasses

import numpy as np

from softrtc.reference._validate import real_array

from .env import ACTION_DIM, NUM_OBJECTS, OBJECT_TARGET_BOX, OBS_DIM, OBS_SLICES, ArmConfig
from .geometry import _validate_config

__all__ = ["FEATURE_DIM", "action_bounds", "policy_features", "Normalizer"]

# policy input: the observation, a one-hot of the current part (the first not completed, as the
# expert picks it, [A-13]) and the tip-relative offsets of that part and of its box. The placed flags
# alone make the current part a discrete function of 4 inputs; handing it over explicitly lets a small
# network switch parts after a placement instead of averaging the phases.
FEATURE_DIM = OBS_DIM + NUM_OBJECTS + 4
_PLACED = np.array([10 + 5 * k + 4 for k in range(NUM_OBJECTS)])
_Y = np.array([10 + 5 * k + 1 for k in range(NUM_OBJECTS)])
_BOX_OF = np.array(OBJECT_TARGET_BOX)

def action_bounds(env_config: ArmConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of an action ([A-8]): joint limits, then the gripper range [0, 1]."""
    cfg = ArmConfig() if env_config is None else env_config
    if not isinstance(cfg, ArmConfig):
        raise ValueError(f"env_config must be an ArmConfig, got {type(cfg).__name__}")
    _validate_config(cfg)
    return (np.array([*cfg.joint_low, 0.0], np.float64), np.array([*cfg.joint_high, 1.0], np.float64))


def policy_features(obs) -> np.ndarray:
    """Policy input ``[..., FEATURE_DIM]`` from observations ``[..., 34]`` ([A-17]).

    The observation, then a one-hot of the current part (the first whose placed
    flag is not set and that is not below the table top; all zeros once every
    part is placed or out of play), then the current part's ``(x, y)`` and its
    box's ``(centre x, floor y)`` minus the gripper tip (zeros once none is left).
    """
    o = _real_array("obs", obs)
    if o.ndim < 1 or o.shape[-1] != OBS_DIM or o.size == 0 or not np.all(np.isfinite(o)):
        raise ValueError(f"obs must be a finite array of shape [..., {OBS_DIM}], got shape {list(o.shape)}")
    # A part below the table top fell out of reach ([A-27]) and is out of play, as for the expert ([A-13]).
    todo = (o[..., _PLACED] < 0.5) & (o[..., _Y] >= 0.0)
    left = todo.any(-1, keepdims=True)
    k = np.argmax(todo, -1)
    onehot = np.eye(NUM_OBJECTS)[k] * left
    tip = o[..., OBS_SLICES["ee"]]
    part = np.take_along_axis(o, (10 + 5 * k)[..., None] + np.arange(2), -1)
    box = np.take_along_axis(o, (30 + 2 * _BOX_OF[k])[..., None] + np.arange(2), -1)
    return np.concatenate([o, onehot, (part - tip) * left, (box - tip) * left], -1)


def _real_array(name, value) -> np.ndarray:
    """``value`` as float64, rejecting booleans, strings and other non-real dtypes ([N-7])."""
    return real_array(name, value).astype(np.float64)


def _rows(name, value, dim) -> np.ndarray:
    """A finite array whose last axis has ``dim`` entries."""
    a = _real_array(name, value)
    if a.ndim < 1 or a.shape[-1] != dim or a.size == 0 or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite with last axis {dim} and no empty axis, got shape {list(a.shape)}")
    return a


def _stats(name, value, dim) -> np.ndarray:
    a = _real_array(name, value)
    if a.shape != (dim,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be a finite vector of shape [{dim}], got shape {list(a.shape)}")
    return a


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """Per-dimension affine normalization of policy features and actions ([A-18])."""

    obs_mean: np.ndarray
    obs_std: np.ndarray
    act_mean: np.ndarray
    act_std: np.ndarray

    def __post_init__(self):
        for name, dim in (("obs_mean", FEATURE_DIM), ("obs_std", FEATURE_DIM), ("act_mean", ACTION_DIM),
                          ("act_std", ACTION_DIM)):
            object.__setattr__(self, name, _stats(name, getattr(self, name), dim))
        if np.any(self.obs_std <= 0) or np.any(self.act_std <= 0):
            raise ValueError("obs_std and act_std must be positive")

    @staticmethod
    def fit(features, actions) -> "Normalizer":
        """Mean and std of the data; a std below 1e-3 (a constant entry) is raised to 1 so it is not amplified."""
        features = _rows("features", features, FEATURE_DIM)
        actions = _rows("actions", actions, ACTION_DIM)
        if features.ndim != 2 or features.shape[0] < 2:
            raise ValueError(f"features must have shape [N >= 2, {FEATURE_DIM}], got {list(features.shape)}")
        # The two statistics are independent: actions may come from more rows (e.g. every label of every chunk).
        if actions.ndim != 2 or actions.shape[0] < 2:
            raise ValueError(f"actions must have shape [M >= 2, {ACTION_DIM}], got {list(actions.shape)}")

        def std(x):
            s = x.std(axis=0)
            return np.where(s < 1e-3, 1.0, s)

        return Normalizer(features.mean(0), std(features), actions.mean(0), std(actions))

    def to_dict(self) -> dict:
        """JSON-able statistics (float64 values round-trip exactly through JSON)."""
        return {k: [float(x) for x in getattr(self, k)] for k in ("obs_mean", "obs_std", "act_mean", "act_std")}

    @staticmethod
    def from_dict(data) -> "Normalizer":
        """Inverse of :meth:`to_dict` (validated)."""
        if not isinstance(data, dict) or set(data) != {"obs_mean", "obs_std", "act_mean", "act_std"}:
            raise ValueError("data must be a dict with obs_mean, obs_std, act_mean, act_std (Normalizer.to_dict)")
        return Normalizer(**{k: _real_array(f"data[{k!r}]", v) for k, v in data.items()})

    def obs(self, features):
        return (_rows("features", features, FEATURE_DIM) - self.obs_mean) / self.obs_std

    def act(self, a):
        return (_rows("a", a, ACTION_DIM) - self.act_mean) / self.act_std

    def unact(self, z):
        return _rows("z", z, ACTION_DIM) * self.act_std + self.act_mean
