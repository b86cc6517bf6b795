"""Flow policies for the arm study: behaviour cloning, RTC fine-tuning, checkpoints (spec [A-17]..[A-21]).

A small MLP-Mixer flow policy (``softrtc.jax.policy.FlowPolicy``) is trained by
behaviour cloning on DART demonstrations of the scripted expert ([A-15]), then
fine-tuned with training-time Hard RTC and Soft RTC. Training is
``softrtc.jax.training.train`` (chapter T: [T-1]..[T-9]) and checkpoints are
``softrtc.jax.checkpoint`` files ([T-11], [T-12]) whose metadata carries the
arm config, the normalization statistics and the training config ([A-18]).
The policy reads the observation plus a few target features ([A-17]);
features and actions are normalized per dimension. Chunks leave the policy in
physical units and inside the action ranges of [A-8] ([A-19]); inference uses
``softrtc.jax.methods`` ([S-6]).
"""

from __future__ import annotations

import dataclasses
import math
import os
import tempfile
import time
from functools import partial
from pathlib import Path

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import check_out_dir, package_data_dir
from softrtc.reference._validate import real_array
from softrtc.jax import methods as jmethods
from softrtc.jax import sampler as jsampler
from softrtc.jax.checkpoint import load_checkpoint, save_checkpoint
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.jax.training import TrainConfig, train
from softrtc.jax import weights as jweights
from softrtc.jax.weights import SoftWindow
from softrtc.reference.weights import SoftWindow as RefSoftWindow

from .env import (ACTION_DIM, NUM_OBJECTS, OBJECT_TARGET_BOX, OBS_DIM, OBS_SLICES, ArmConfig, _is_real,
                  _validate_config)

__all__ = [
    "ArmPolicyConfig", "Normalizer", "ArmPolicy", "TRAIN_METHODS", "STUDY_METHODS", "METHOD_LABELS",
    "FEATURE_DIM", "policy_features", "chunk_dataset", "arm_train_config", "train_flow_policy",
    "save_arm_checkpoint", "load_arm_checkpoint", "train_arm_policies", "default_checkpoint_dir",
    "load_policies", "untrained_policy", "action_bounds",
]

# Training objective of each checkpoint ([A-20]): base = ordinary flow matching (w = 0).
TRAIN_METHODS = ("naive", "train_hard", "train_soft")
# The chapter-T method of each objective ([T-3]).
_OBJECTIVE = {"naive": "none", "train_hard": "hard", "train_soft": "soft"}
# The study's three policies and the sampler each is run with ([S-6]).
STUDY_METHODS = ("naive", "train_hard", "train_soft")
METHOD_LABELS = {"naive": "Base", "train_hard": "Train Hard RTC", "train_soft": "Train Soft RTC",
                 "inference_hard": "Inference Hard RTC", "inference_soft": "Inference Soft RTC"}
_CKPT_FILES = {"naive": "base.npz", "train_hard": "train_hard.npz", "train_soft": "train_soft.npz"}
# Tag of the arm section in a chapter-T checkpoint's metadata ([A-18]).
ARM_FORMAT = "softrtc-arm-policy-2"

# policy input: the observation, a one-hot of the current part (the first not completed, as the
# expert picks it, [A-13]) and the tip-relative offsets of that part and of its box. The placed flags
# alone make the current part a discrete function of 4 inputs; handing it over explicitly lets a small
# network switch parts after a placement instead of averaging the phases.
FEATURE_DIM = OBS_DIM + NUM_OBJECTS + 4
_PLACED = np.array([10 + 5 * k + 4 for k in range(NUM_OBJECTS)])
_BOX_OF = np.array(OBJECT_TARGET_BOX)


def _check_int(name, value, lo, hi=None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi if hi is not None else 'inf'}], got {value!r}")
    if value < lo or (hi is not None and value > hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi if hi is not None else 'inf'}], got {value}")
    return int(value)


def _check_float(name, value, lo, hi, lo_open=False) -> float:
    if not _is_real(value):  # booleans, NaN/inf and integers too large for a float ([N-7])
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    v = float(value)
    if v < lo or v > hi or (lo_open and v == lo):
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    return v


def _check_choice(name, value, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


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
    flag is not set; all zeros once every part is placed), then the current
    part's ``(x, y)`` and its box's ``(centre x, floor y)`` minus the gripper
    tip (zeros once every part is placed).
    """
    o = _real_array("obs", obs)
    if o.ndim < 1 or o.shape[-1] != OBS_DIM or o.size == 0 or not np.all(np.isfinite(o)):
        raise ValueError(f"obs must be a finite array of shape [..., {OBS_DIM}], got shape {list(o.shape)}")
    todo = o[..., _PLACED] < 0.5
    left = todo.any(-1, keepdims=True)
    k = np.argmax(todo, -1)
    onehot = np.eye(NUM_OBJECTS)[k] * left
    tip = o[..., OBS_SLICES["ee"]]
    part = np.take_along_axis(o, (10 + 5 * k)[..., None] + np.arange(2), -1)
    box = np.take_along_axis(o, (30 + 2 * _BOX_OF[k])[..., None] + np.arange(2), -1)
    return np.concatenate([o, onehot, (part - tip) * left, (box - tip) * left], -1)


@dataclasses.dataclass(frozen=True)
class ArmPolicyConfig:
    """Horizon, execute horizon, Euler steps and network sizes of the arm policies ([A-17]).

    ``horizon`` H = 10 and ``execute_horizon`` s = 5 at 50 Hz give executable
    delays up to ``min(s, H - s) = 5`` ticks (100 ms, [X-1]).
    """

    horizon: int = 10
    execute_horizon: int = 5
    num_steps: int = 5
    channel_dim: int = 128
    channel_hidden_dim: int = 256
    token_hidden_dim: int = 32
    num_layers: int = 2

    def __post_init__(self):
        _check_int("horizon", self.horizon, 2, 64)
        _check_int("execute_horizon", self.execute_horizon, 1, self.horizon - 1)
        _check_int("num_steps", self.num_steps, 1, 64)
        _check_int("channel_dim", self.channel_dim, 2, 1024)
        if self.channel_dim % 2:
            raise ValueError(f"channel_dim must be even, got {self.channel_dim}")
        _check_int("channel_hidden_dim", self.channel_hidden_dim, 1, 4096)
        _check_int("token_hidden_dim", self.token_hidden_dim, 1, 1024)
        _check_int("num_layers", self.num_layers, 1, 16)

    @property
    def max_delay(self) -> int:
        """Largest executable delay min(s, H - s) ([X-1])."""
        return min(self.execute_horizon, self.horizon - self.execute_horizon)

    def policy_config(self) -> PolicyConfig:
        """The ``FlowPolicy`` sizes ([P-1]) with ``action_chunk_size = horizon``."""
        return PolicyConfig(channel_dim=self.channel_dim, channel_hidden_dim=self.channel_hidden_dim,
                            token_hidden_dim=self.token_hidden_dim, num_layers=self.num_layers,
                            action_chunk_size=self.horizon)


def _new_model(config: ArmPolicyConfig, seed: int) -> FlowPolicy:
    return FlowPolicy(obs_dim=FEATURE_DIM, action_dim=ACTION_DIM, config=config.policy_config(),
                      rngs=nnx.Rngs(seed))


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


def chunk_dataset(data: dict, horizon: int) -> dict:
    """Training pairs (observation, chunk of the next H clean labels) from a demo file's arrays ([A-17]).

    The chunk of row i holds the labels of rows i .. i+H-1 of its episode; past
    the episode's last row the last label is repeated (the arm holds its final
    command), so every row of every episode yields one example. ``obs`` are the
    raw observations; :func:`policy_features` maps them to the policy input.
    """
    horizon = _check_int("horizon", horizon, 1, 64)
    if not isinstance(data, dict) or not {"obs", "action", "episode_start", "episode_length"} <= set(data):
        raise ValueError("data must be a dict with obs, action, episode_start, episode_length (load_demos)")
    obs = _rows("data['obs']", data["obs"], OBS_DIM)
    act = _rows("data['action']", data["action"], ACTION_DIM)
    if obs.ndim != 2 or act.ndim != 2 or obs.shape[0] != act.shape[0] or obs.shape[0] < 1:
        raise ValueError(f"data['obs'] and data['action'] must have shapes [N >= 1, {OBS_DIM}] and "
                         f"[N, {ACTION_DIM}], got {list(obs.shape)} and {list(act.shape)}")
    n = obs.shape[0]
    ep = {}
    for name in ("episode_start", "episode_length"):
        v = np.asarray(data[name])
        if v.dtype.kind not in "iu" or v.ndim != 1 or v.size < 1:
            raise ValueError(f"data['{name}'] must be a non-empty 1-D integer array, got dtype {v.dtype} "
                             f"and shape {list(v.shape)}")
        ep[name] = v.astype(np.int64)
    starts, lengths = ep["episode_start"], ep["episode_length"]
    # layout: episodes of >= 1 row, concatenated in order, covering every row exactly once.
    if lengths.shape != starts.shape or np.any(lengths < 1):
        raise ValueError(f"data['episode_length'] must hold one integer >= 1 per episode start, got {lengths!r}")
    expected = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    if not np.array_equal(starts, expected) or int(lengths.sum()) != n:
        raise ValueError(f"data['episode_start'] must be the running sum of data['episode_length'] from 0, with the "
                         f"lengths summing to the {n} rows ([A-16]), got starts {starts!r}")
    idx = []
    for st, ln in zip(starts, lengths):
        rows = st + np.arange(ln)
        idx.append(np.minimum(rows[:, None] + np.arange(horizon)[None], st + ln - 1))
    idx = np.concatenate(idx)
    return {"obs": np.asarray(data["obs"])[idx[:, 0]], "chunks": np.asarray(data["action"])[idx]}


def arm_train_config(method: str, config: ArmPolicyConfig, steps: int, batch_size: int = 128,
                     learning_rate: float = 1e-3) -> TrainConfig:
    """The chapter-T config of an arm objective ([A-20], [T-1]).

    ``naive`` -> ``none``, ``train_hard`` -> ``hard``, ``train_soft`` -> ``soft``
    with the default window of [W-7] (delay-scaled, lambda = 2, h_max = 5,
    linear, rtc, clip); ``execute_horizon`` = s; delays uniform on
    ``0 .. min(s, H - s)`` ([D-1], [D-4]); AdamW (weight decay 1e-4, Adam
    moments at the [T-1] defaults) with gradient clipping at 1, linear warm-up
    over ``min(200, steps // 10)`` steps, then cosine decay to 5% of
    ``learning_rate`` at ``steps`` ([T-6]); batch 128 by default.
    """
    method = _check_choice("method", method, TRAIN_METHODS)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    steps = _check_int("steps", steps, 1, 10**7)
    batch_size = _check_int("batch_size", batch_size, 1, 1 << 16)
    learning_rate = _check_float("learning_rate", learning_rate, 0.0, 1.0, lo_open=True)
    return TrainConfig(method=_OBJECTIVE[method], window=RefSoftWindow(), execute_horizon=config.execute_horizon,
                       delay_dist="uniform", d_min=0, d_max=config.max_delay, batch_size=batch_size,
                       learning_rate=learning_rate, weight_decay=1e-4, grad_clip_norm=1.0,
                       warmup_steps=min(200, steps // 10), decay_steps=steps, final_lr_ratio=0.05)


def train_flow_policy(dataset: dict, normalizer: Normalizer, method: str, steps: int, seed: int, *,
                      config: ArmPolicyConfig = ArmPolicyConfig(), init: FlowPolicy | None = None,
                      batch_size: int = 128, learning_rate: float = 1e-3,
                      progress: bool = False) -> tuple[FlowPolicy, np.ndarray, TrainConfig]:
    """Train (or fine-tune ``init``) a flow policy with the objective of ``method`` ([A-20]).

    Delegates to ``softrtc.jax.training.train`` ([T-9]) with
    :func:`arm_train_config`; the data are the normalized policy features and
    chunks of ``dataset`` (:func:`chunk_dataset`). A new policy is initialised
    with ``nnx.Rngs(seed)``; every training draw comes from
    ``jax.random.key(seed)`` ([T-8], [N-9]). ``init`` is not modified ([T-9]).
    Returns ``(policy, per-step losses, TrainConfig)``.
    """
    tc = arm_train_config(method, config, steps, batch_size, learning_rate)
    seed = _check_int("seed", seed, 0, 2**31 - 1)
    if not isinstance(normalizer, Normalizer):
        raise ValueError(f"normalizer must be a Normalizer, got {type(normalizer).__name__}")
    if not isinstance(dataset, dict) or "obs" not in dataset or "chunks" not in dataset:
        raise ValueError(f"dataset must be a dict with 'obs' [N, {OBS_DIM}] and 'chunks' [N, H, 4] (chunk_dataset)")
    H = config.horizon
    chunks = _real_array("dataset['chunks']", dataset["chunks"])
    if chunks.ndim != 3 or chunks.shape[1:] != (H, ACTION_DIM) or chunks.shape[0] < 1 \
            or not np.all(np.isfinite(chunks)):
        raise ValueError(f"dataset['chunks'] must be finite with shape [N >= 1, {H}, {ACTION_DIM}], got {list(chunks.shape)}")
    obs = normalizer.obs(policy_features(dataset["obs"]))
    if obs.shape[0] != chunks.shape[0]:
        raise ValueError(f"dataset obs and chunks must have the same length, got {obs.shape[0]} and {chunks.shape[0]}")
    if init is None:
        init = _new_model(config, seed)
    elif not isinstance(init, FlowPolicy):
        raise ValueError(f"init must be a FlowPolicy or None, got {type(init).__name__}")
    elif init.config != config.policy_config() or init.obs_dim != FEATURE_DIM:
        raise ValueError("init must have the architecture of config (ArmPolicyConfig.policy_config)")
    data = {"obs": jnp.asarray(obs, jnp.float32), "actions": jnp.asarray(normalizer.act(chunks), jnp.float32)}
    model, losses = train(init, data, tc, jax.random.key(seed), steps, progress=progress)
    return model, losses, tc


# --------------------------------------------------------------------------- checkpoints


def save_arm_checkpoint(path, model: FlowPolicy, normalizer: Normalizer, config: ArmPolicyConfig,
                        method: str, meta: dict | None = None, train_config: TrainConfig | None = None) -> str:
    """Write an arm policy as a chapter-T checkpoint ([A-18], [T-11]).

    ``softrtc.jax.checkpoint.save_checkpoint`` stores the parameters; its
    metadata holds ``{"arm": {"format": ARM_FORMAT, "method", "config",
    "normalizer", "train_config", "meta"}}`` (all JSON).
    """
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path).endswith(".npz"):
        raise ValueError(f"path must be a str or PathLike ending in '.npz', got {path!r}")
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    if not isinstance(normalizer, Normalizer):
        raise ValueError(f"normalizer must be a Normalizer, got {type(normalizer).__name__}")
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    if model.config != config.policy_config() or model.obs_dim != FEATURE_DIM or model.action_dim != ACTION_DIM:
        raise ValueError("model must have the architecture of config (ArmPolicyConfig.policy_config)")
    method = _check_choice("method", method, TRAIN_METHODS)
    if meta is not None and not isinstance(meta, dict):
        raise ValueError(f"meta must be a dict or None, got {type(meta).__name__}")
    if train_config is not None and not isinstance(train_config, TrainConfig):
        raise ValueError(f"train_config must be a TrainConfig or None, got {type(train_config).__name__}")
    arm = {"format": ARM_FORMAT, "method": method, "config": dataclasses.asdict(config),
           "normalizer": normalizer.to_dict(), "train_config": None if train_config is None else train_config.to_dict(),
           "meta": meta or {}}
    save_checkpoint(path, model, {"arm": arm})
    return os.fspath(path)


def load_arm_checkpoint(path, sampler_method: str | None = None) -> "ArmPolicy":
    """Load a checkpoint written by :func:`save_arm_checkpoint` into an :class:`ArmPolicy` ([A-18], [T-12]).

    ``sampler_method`` (default: the method the checkpoint was trained with)
    selects the chunk generator ([S-6]); e.g. ``inference_soft`` on the base.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint .npz file, got {path!r}")
    if sampler_method is not None:
        _check_choice("sampler_method", sampler_method, jmethods.METHODS)
    model, metadata = load_checkpoint(path)
    arm = metadata.get("arm") if isinstance(metadata, dict) else None
    if not isinstance(arm, dict) or arm.get("format") != ARM_FORMAT:
        raise ValueError(f"path {os.fspath(path)!r} is not a softrtc arm checkpoint (no '{ARM_FORMAT}' metadata)")
    try:
        config = ArmPolicyConfig(**arm["config"])
        norm = Normalizer.from_dict(arm["normalizer"])
        method = _check_choice("method", arm["method"], TRAIN_METHODS)
    except (KeyError, TypeError, ValueError) as exc:
        raise ValueError(f"path {os.fspath(path)!r}: invalid arm metadata ({exc})") from exc
    if model.config != config.policy_config() or model.obs_dim != FEATURE_DIM or model.action_dim != ACTION_DIM:
        raise ValueError(f"path {os.fspath(path)!r}: stored policy does not match its arm config")
    window = None
    if (sampler_method or method) == "train_soft" and isinstance(arm.get("train_config"), dict):
        # The training window is the inference window ([W-7]): run the sampler with the one stored.
        try:
            window = jweights.from_reference(TrainConfig.from_dict(arm["train_config"]).window)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"path {os.fspath(path)!r}: invalid train_config in arm metadata ({exc})") from exc
    pol = ArmPolicy(model, norm, config, sampler_method or method, trained_as=method, meta=arm.get("meta", {}),
                    window=window)
    pol.train_config = arm.get("train_config")
    return pol


# --------------------------------------------------------------------------- inference

# Module-level compiled generators: policies with the same architecture share compilations
# (graphdef, H, s, T and the method are static; parameters, window parameters and d are traced).


@partial(jax.jit, static_argnums=(0,))
def _first_chunk(static, state, nm, obs, key):
    # The first chunk is naive for every method ([X-2], [S-6]).
    gd, H, s, T = static
    m = nnx.merge(gd, state)
    noise = jax.random.normal(key, (1, H, ACTION_DIM))
    z = jsampler.naive_sample_conditioned(m, ((obs - nm[0]) / nm[1])[None], noise, T, unroll=False)
    return z[0] * nm[3] + nm[2]


@partial(jax.jit, static_argnums=(0, 1))
def _later_chunk(static, method, state, window, nm, obs, prior, d, key):
    gd, H, s, T = static
    m = nnx.merge(gd, state)
    noise = jax.random.normal(key, (1, H, ACTION_DIM))
    y = ((prior - nm[2]) / nm[3])[None]
    # Weights and time conditioning of delay d are computed inside the compiled call
    # (a few small ops), so building a policy does no eager per-delay work.
    z = jmethods.generate_chunk_conditioned(method, m, ((obs - nm[0]) / nm[1])[None], noise, y, s, d, T,
                                            window, unroll=False)
    return z[0] * nm[3] + nm[2]



def _check_window(window) -> None:
    """``window`` is None or a JAX :class:`softrtc.jax.weights.SoftWindow` ([W-7]), checked before any compilation."""
    if window is not None and not isinstance(window, SoftWindow):
        raise ValueError(f"window must be a softrtc.jax.weights.SoftWindow or None (convert a reference window with "
                         f"softrtc.jax.weights.from_reference), got {type(window).__name__}")


class ArmPolicy:
    """A flow policy with its normalizer and chunk generator ([A-19], [S-6]).

    ``generate(obs, prior, d, key)`` returns a chunk ``[H, 4]`` in physical units.
    ``prior`` (``[H, 4]``, physical, [X-3]) is ``None`` for the first chunk,
    which every method generates with the naive sampler and ``d = 0`` ([X-2]).
    The network's output is mapped back to physical units and clipped to the
    action ranges of [A-8] ([A-19]); the clipped chunk is what is executed and
    what later priors are built from.
    """

    def __init__(self, model: FlowPolicy, normalizer: Normalizer, config: ArmPolicyConfig, method: str,
                 trained_as: str | None = None, meta: dict | None = None, env_config: ArmConfig | None = None,
                 window: SoftWindow | None = None):
        if not isinstance(model, FlowPolicy):
            raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
        if not isinstance(normalizer, Normalizer):
            raise ValueError(f"normalizer must be a Normalizer, got {type(normalizer).__name__}")
        if not isinstance(config, ArmPolicyConfig):
            raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
        self.method = _check_choice("method", method, jmethods.METHODS)
        _check_window(window)
        if trained_as is not None and not isinstance(trained_as, str):
            raise ValueError(f"trained_as must be a str or None, got {trained_as!r}")
        if meta is not None and not isinstance(meta, dict):
            raise ValueError(f"meta must be a dict or None, got {type(meta).__name__}")
        self.trained_as = trained_as or method
        self.meta = dict(meta or {})
        if model.config != config.policy_config() or model.obs_dim != FEATURE_DIM or model.action_dim != ACTION_DIM:
            raise ValueError("model must have the architecture of config (ArmPolicyConfig.policy_config)")
        self.model, self.normalizer, self.config = model, normalizer, config
        self.train_config = None
        self.H, self.s, self.T = config.horizon, config.execute_horizon, config.num_steps
        self.low, self.high = action_bounds(env_config)
        self._graphdef, self._state = nnx.split(model)
        # train_soft's window ([W-7]); default the paper's main setting.
        self.window = SoftWindow() if window is None else window
        self._static = (self._graphdef, self.H, self.s, self.T)
        self._nm = tuple(jnp.asarray(a, jnp.float32) for a in (normalizer.obs_mean, normalizer.obs_std,
                                                              normalizer.act_mean, normalizer.act_std))

    def _obs(self, obs) -> jnp.ndarray:
        o = _real_array("obs", obs)
        if o.shape != (OBS_DIM,) or not np.all(np.isfinite(o)):
            raise ValueError(f"obs must be a finite vector of shape [{OBS_DIM}], got shape {list(o.shape)}")
        return jnp.asarray(policy_features(o), jnp.float32)

    def generate(self, obs, prior, d, key) -> np.ndarray:
        """One chunk ``[H, 4]`` (float64, physical units, within [A-8]) for delay ``d`` ([S-6], [A-19])."""
        o = self._obs(obs)
        if not isinstance(key, jax.Array) or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed))")
        if key.shape != ():
            raise ValueError(f"key must be a single typed JAX PRNG key of shape (), got shape {tuple(key.shape)}")
        if prior is None:
            _check_int("d", d, 0, 0)
            z = _first_chunk(self._static, self._state, self._nm, o, key)
        else:
            d = _check_int("d", d, 0, self.config.max_delay)
            p = _real_array("prior", prior)
            if p.shape != (self.H, ACTION_DIM) or not np.all(np.isfinite(p)):
                raise ValueError(f"prior must be a finite array of shape [{self.H}, {ACTION_DIM}], got {list(p.shape)}")
            z = _later_chunk(self._static, self.method, self._state, self.window, self._nm, o, jnp.asarray(p, jnp.float32),
                            jnp.int32(d), key)
        return np.clip(np.asarray(z, np.float64), self.low, self.high)

    def warmup(self) -> None:
        """Compile both generators once (so the first timed call is not a compilation)."""
        obs = np.zeros(OBS_DIM)
        c = self.generate(obs, None, 0, jax.random.key(0))
        self.generate(obs, c, min(1, self.config.max_delay), jax.random.key(1))


def untrained_policy(seed: int = 0, method: str = "naive", config: ArmPolicyConfig = ArmPolicyConfig(),
                     window: SoftWindow | None = None) -> ArmPolicy:
    """A randomly initialised policy with identity normalization, for fast conformance tests.

    adaLN-zero makes the mixer blocks identity at initialisation, so the output
    is an affine function of the inputs; the normalizer maps it onto the action
    centre of the joint ranges so rollouts stay valid.
    """
    seed = _check_int("seed", seed, 0, 2**31 - 1)
    method = _check_choice("method", method, jmethods.METHODS)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    _check_window(window)
    model = _new_model(config, seed)
    norm = Normalizer(np.zeros(FEATURE_DIM), np.ones(FEATURE_DIM), np.array([0.0, -1.0, 0.0, 0.5]),
                      np.array([0.3, 0.3, 0.3, 0.3]))
    return ArmPolicy(model, norm, config, method, trained_as="untrained", window=window)


def default_checkpoint_dir() -> Path:
    """The shipped checkpoints: package data ``softrtc/arm/checkpoints`` ([A-21])."""
    return package_data_dir("softrtc.arm", "checkpoints")


def load_policies(checkpoint_dir=None, methods=STUDY_METHODS) -> dict:
    """``{method: ArmPolicy}`` from ``base.npz``, ``train_hard.npz``, ``train_soft.npz`` ([A-21]).

    Method ``naive`` and the inference-time methods use the base checkpoint.
    """
    if checkpoint_dir is not None and not isinstance(checkpoint_dir, (str, os.PathLike)):
        raise ValueError(f"checkpoint_dir must be a str, PathLike or None, got {checkpoint_dir!r}")
    if isinstance(methods, str) or not hasattr(methods, "__iter__"):
        raise ValueError(f"methods must be a sequence of method names, got {methods!r}")
    folder = Path(default_checkpoint_dir() if checkpoint_dir is None else checkpoint_dir)
    if not folder.is_dir():
        raise ValueError(f"checkpoint_dir must be an existing folder, got {str(folder)!r}")
    methods = list(methods)
    if not methods:
        raise ValueError("methods must be a non-empty sequence of method names")
    for m in methods:
        _check_choice("methods entry", m, jmethods.METHODS)
    out = {}
    for m in methods:
        f = folder / _CKPT_FILES.get(m, "base.npz")
        if not f.is_file():
            raise ValueError(f"checkpoint {str(f)!r} is missing; run `softrtc arm train --out {folder}`")
        out[m] = load_arm_checkpoint(f, sampler_method=m)
    return out


# Arrays of a generate_demos file that training reads ([A-16]).
_DEMO_KEYS = ("obs", "action", "episode_start", "episode_length", "seed", "noise_std")


def _check_out_dir(out_dir) -> Path:
    """An output folder that exists or can be created: not a file, under a writable folder ([A-12])."""
    return check_out_dir("out_dir", out_dir)


def train_arm_policies(out_dir, episodes: int = 400, steps: int = 4000, finetune_steps: int | None = 800,
                       seed: int = 0, noise_std: float = 0.03, config: ArmPolicyConfig = ArmPolicyConfig(),
                       batch_size: int = 128, learning_rate: float = 1e-3, demos=None,
                       verbose: bool = True) -> dict:
    """Demos, base BC policy, then Train Hard / Train Soft RTC fine-tunes, saved to ``out_dir`` ([A-20]).

    Demonstrations: ``generate_demos(episodes, seed, noise_std)`` ([A-15])
    written to a temporary folder that is removed afterwards, or the file
    ``demos`` written by it with those arguments (checked against its stored
    seed and noise level). Only ``base.npz``, ``train_hard.npz`` and
    ``train_soft.npz`` are written to ``out_dir``; nothing there is removed. The base is trained for ``steps`` steps with
    seed ``seed``; each fine-tune starts from the base and runs
    ``finetune_steps`` (``None``: ``steps // 4``) with seed ``seed + 1`` (hard)
    and ``seed + 2`` (soft), learning rate ``learning_rate / 3``. Training is
    :func:`train_flow_policy` ([T-9]). Returns ``{method: path}``.
    """
    from .demos import generate_demos, load_demos

    if not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a str or PathLike, got {out_dir!r}")
    episodes = _check_int("episodes", episodes, 1, 100000)
    steps = _check_int("steps", steps, 1, 10**7)
    finetune_steps = max(steps // 4, 1) if finetune_steps is None else _check_int("finetune_steps", finetune_steps, 1,
                                                                                   10**7)
    seed = _check_int("seed", seed, 0, 2**31 - 3)
    noise_std = _check_float("noise_std", noise_std, 0.0, 1.0)
    batch_size = _check_int("batch_size", batch_size, 1, 1 << 16)
    learning_rate = _check_float("learning_rate", learning_rate, 0.0, 1.0, lo_open=True)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    out = _check_out_dir(out_dir)
    data = None
    if demos is not None:
        # Checked before out_dir is created or any training starts ([A-12]).
        if not isinstance(demos, (str, os.PathLike)) or not os.path.isfile(demos):
            raise ValueError(f"demos must name an existing demo .npz file or be None, got {demos!r}")
        try:
            data = load_demos(os.fspath(demos))
        except ValueError as exc:
            raise ValueError(f"demos: {exc}") from None
        missing = [k for k in _DEMO_KEYS if k not in data]
        if missing:
            raise ValueError(f"demos file {os.fspath(demos)!r} is not a generate_demos file: missing {missing}")
        try:
            got = (len(data["episode_start"]), int(data["seed"]), float(data["noise_std"]))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"demos file {os.fspath(demos)!r} has malformed seed/noise_std/episode_start ({exc})") \
                from None
        if got[0] != episodes or got[1] != seed or not math.isclose(got[2], noise_std, rel_tol=1e-6):
            raise ValueError(f"demos file {os.fspath(demos)!r} holds (episodes, seed, noise_std) = {got}, "
                             f"expected {(episodes, seed, noise_std)}")
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if demos is None:
        # the demonstrations are reproducible from (episodes, seed, noise_std) and not kept: they go to a
        # temporary folder of this call, so no file of out_dir but the three checkpoints is written or removed.
        with tempfile.TemporaryDirectory(prefix="softrtc-arm-demos-") as tmp:
            demo_path = Path(tmp) / "demos.npz"
            info = generate_demos(episodes, seed, noise_std, str(demo_path))
            data = load_demos(str(demo_path))
        if verbose:
            print(f"demos: {info['episodes']} episodes, {info['steps']} steps, expert success "
                  f"{info['success_rate']:.2f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    ds = chunk_dataset(data, config.horizon)
    norm = Normalizer.fit(policy_features(data["obs"]), data["action"])
    meta = {"episodes": episodes, "seed": seed, "noise_std": noise_std, "steps": steps,
            "finetune_steps": finetune_steps, "batch_size": batch_size, "learning_rate": learning_rate}

    def report(name, losses):
        if verbose:
            k = max(len(losses) // 10, 1)
            print(f"{name}: loss {float(np.mean(losses[:k])):.4f} -> {float(np.mean(losses[-k:])):.4f} "
                  f"({time.perf_counter() - t0:.0f} s)", flush=True)

    base, losses, tc = train_flow_policy(ds, norm, "naive", steps, seed, config=config, batch_size=batch_size,
                                         learning_rate=learning_rate, progress=verbose)
    paths = {"naive": save_arm_checkpoint(out / _CKPT_FILES["naive"], base, norm, config, "naive", meta, tc)}
    report("naive", losses)
    for i, m in enumerate(("train_hard", "train_soft")):
        # Fine-tuning starts from trained weights: a lower peak rate keeps it from undoing the base.
        ft, losses, tc = train_flow_policy(ds, norm, m, finetune_steps, seed + 1 + i, config=config, init=base,
                                           batch_size=batch_size, learning_rate=learning_rate / 3,
                                           progress=verbose)
        paths[m] = save_arm_checkpoint(out / _CKPT_FILES[m], ft, norm, config, m,
                                       {**meta, "finetuned_from": "base"}, tc)
        report(m, losses)
    return paths
