"""Flow policies for the arm study: behaviour cloning, RTC fine-tuning, checkpoints (spec [A-17]..[A-21]).

A small MLP-Mixer flow policy (``softrtc.jax.policy.FlowPolicy``) is trained by
behaviour cloning on DART demonstrations of the scripted expert ([A-15]), then
fine-tuned with training-time Hard RTC and Soft RTC (spec chapters D, C, L).
Observations and actions are normalized per dimension; the statistics travel
with the checkpoint ([A-18]). Chunks leave the policy in physical units and
inside the action ranges of [A-8] ([A-19]).

Training uses the JAX twin's corruption and loss (``softrtc.jax.loss.rtc_loss``,
[C-1], [C-2], [L-1]..[L-3]), its delay sampler ([D-1], [D-3]) and its weights
([W-7], [W-8]); inference uses ``softrtc.jax.methods`` ([S-6]).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
from functools import partial
from pathlib import Path

import flax.nnx as nnx
import jax
import jax.numpy as jnp
import numpy as np
import optax

from softrtc.jax import delays as jdelays
from softrtc.jax import methods as jmethods
from softrtc.jax import sampler as jsampler
from softrtc.jax.loss import rtc_loss
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.jax.weights import SoftWindow, hard_weights, weight_table

from .env import ACTION_DIM, OBS_DIM, ArmConfig

__all__ = [
    "ArmPolicyConfig", "Normalizer", "ArmPolicy", "TRAIN_METHODS", "STUDY_METHODS", "METHOD_LABELS",
    "chunk_dataset", "train_flow_policy", "save_arm_checkpoint", "load_arm_checkpoint",
    "train_arm_policies", "default_checkpoint_dir", "load_policies", "untrained_policy", "action_bounds",
]

# Training objective of each checkpoint ([A-20]): base = ordinary flow matching (w = 0).
TRAIN_METHODS = ("naive", "train_hard", "train_soft")
# The study's three policies and the sampler each is run with ([S-6]).
STUDY_METHODS = ("naive", "train_hard", "train_soft")
METHOD_LABELS = {"naive": "Base", "train_hard": "Train Hard RTC", "train_soft": "Train Soft RTC",
                 "inference_hard": "Inference Hard RTC", "inference_soft": "Inference Soft RTC"}
_CKPT_FILES = {"naive": "base.npz", "train_hard": "train_hard.npz", "train_soft": "train_soft.npz"}
_FORMAT = "softrtc-arm-policy-1"


def _check_int(name, value, lo, hi=None) -> int:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi if hi is not None else 'inf'}], got {value!r}")
    if value < lo or (hi is not None and value > hi):
        raise ValueError(f"{name} must be an integer in [{lo}, {hi if hi is not None else 'inf'}], got {value}")
    return int(value)


def _check_float(name, value, lo, hi, lo_open=False) -> float:
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    v = float(value)
    if not math.isfinite(v) or v < lo or v > hi or (lo_open and v == lo):
        raise ValueError(f"{name} must be a finite number in {'(' if lo_open else '['}{lo}, {hi}], got {value!r}")
    return v


def _check_choice(name, value, choices) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name} must be one of {tuple(choices)}, got {value!r}")
    return value


def action_bounds(env_config: ArmConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper bounds of an action ([A-8]): joint limits, then the gripper range [0, 1]."""
    cfg = env_config or ArmConfig()
    if not isinstance(cfg, ArmConfig):
        raise ValueError(f"env_config must be an ArmConfig, got {type(cfg).__name__}")
    return (np.array([*cfg.joint_low, 0.0], np.float64), np.array([*cfg.joint_high, 1.0], np.float64))


@dataclasses.dataclass(frozen=True)
class ArmPolicyConfig:
    """Horizon, execute horizon, Euler steps and network sizes of the arm policies ([A-17]).

    ``horizon`` H = 10 and ``execute_horizon`` s = 5 at 50 Hz give executable
    delays up to ``min(s, H - s) = 5`` ticks (100 ms, [X-1]).
    """

    horizon: int = 10
    execute_horizon: int = 5
    num_steps: int = 5
    channel_dim: int = 64
    channel_hidden_dim: int = 128
    token_hidden_dim: int = 16
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
        return PolicyConfig(channel_dim=self.channel_dim, channel_hidden_dim=self.channel_hidden_dim,
                            token_hidden_dim=self.token_hidden_dim, num_layers=self.num_layers,
                            action_chunk_size=self.horizon)


@dataclasses.dataclass(frozen=True)
class Normalizer:
    """Per-dimension affine normalization of observations and actions ([A-18])."""

    obs_mean: np.ndarray
    obs_std: np.ndarray
    act_mean: np.ndarray
    act_std: np.ndarray

    @staticmethod
    def fit(obs, actions) -> "Normalizer":
        """Mean and std of the data; a std below 1e-3 (a constant entry) is raised to 1 so it is not amplified."""
        obs = np.asarray(obs, np.float64)
        actions = np.asarray(actions, np.float64)
        if obs.ndim != 2 or obs.shape[1] != OBS_DIM or obs.shape[0] < 2:
            raise ValueError(f"obs must have shape [N >= 2, {OBS_DIM}], got {list(obs.shape)}")
        if actions.ndim != 2 or actions.shape[1] != ACTION_DIM or actions.shape[0] < 2:
            raise ValueError(f"actions must have shape [N >= 2, {ACTION_DIM}], got {list(actions.shape)}")

        def std(x):
            s = x.std(axis=0)
            return np.where(s < 1e-3, 1.0, s)

        return Normalizer(obs.mean(0), std(obs), actions.mean(0), std(actions))

    def obs(self, o):
        return (np.asarray(o, np.float64) - self.obs_mean) / self.obs_std

    def act(self, a):
        return (np.asarray(a, np.float64) - self.act_mean) / self.act_std

    def unact(self, z):
        return np.asarray(z, np.float64) * self.act_std + self.act_mean


def chunk_dataset(data: dict, horizon: int) -> dict:
    """Training pairs (observation, chunk of the next H clean labels) from a demo file's arrays ([A-17]).

    The chunk of row i holds the labels of rows i .. i+H-1 of its episode; past
    the episode's last row the last label is repeated (the arm holds its final
    command), so every row of every episode yields one example.
    """
    horizon = _check_int("horizon", horizon, 1, 64)
    if not isinstance(data, dict) or not {"obs", "action", "episode_start", "episode_length"} <= set(data):
        raise ValueError("data must be a dict with obs, action, episode_start, episode_length (load_demos)")
    obs, act = np.asarray(data["obs"]), np.asarray(data["action"])
    idx = []
    for st, ln in zip(np.asarray(data["episode_start"]), np.asarray(data["episode_length"])):
        rows = st + np.arange(ln)
        idx.append(np.minimum(rows[:, None] + np.arange(horizon)[None], st + ln - 1))
    idx = np.concatenate(idx)
    return {"obs": obs[idx[:, 0]], "chunks": act[idx]}


def _weight_table(method: str, H: int, s: int, d_max: int) -> jnp.ndarray:
    """Training weights for delays 0..d_max ([S-6]): zeros, 1[j < d] ([W-8]) or soft ([W-7])."""
    ds = jnp.arange(d_max + 1, dtype=jnp.int32)
    if method == "naive":
        return jnp.zeros((d_max + 1, H), jnp.float32)
    if method == "train_hard":
        return jax.vmap(lambda d: hard_weights(H, d))(ds)
    return weight_table(H, SoftWindow(), s)[: d_max + 1]


def train_flow_policy(dataset: dict, normalizer: Normalizer, method: str, steps: int, seed: int, *,
                      config: ArmPolicyConfig = ArmPolicyConfig(), init: FlowPolicy | None = None,
                      batch_size: int = 64, learning_rate: float = 1e-3, log_every: int = 0) -> FlowPolicy:
    """Train (or fine-tune ``init``) a flow policy with the objective of ``method`` ([A-20]).

    ``naive`` is ordinary flow matching (weights 0, [C-3], [L-4]); ``train_hard``
    and ``train_soft`` draw one delay per example uniformly from
    ``0 .. min(s, H - s)`` ([D-1], [D-4]) and use the weights of [W-8] / [W-7]
    (lambda = 2, h_max = 5, linear, rtc, clip). Every random draw (batch rows,
    flow times, noise, delays) comes from ``jax.random.key(seed)`` ([N-9]).
    ``init`` is copied, never modified.
    """
    method = _check_choice("method", method, TRAIN_METHODS)
    steps = _check_int("steps", steps, 1, 10**7)
    seed = _check_int("seed", seed, 0, 2**31 - 1)
    batch_size = _check_int("batch_size", batch_size, 1, 1 << 16)
    learning_rate = _check_float("learning_rate", learning_rate, 0.0, 1.0, lo_open=True)
    log_every = _check_int("log_every", log_every, 0)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    if not isinstance(normalizer, Normalizer):
        raise ValueError(f"normalizer must be a Normalizer, got {type(normalizer).__name__}")
    if not isinstance(dataset, dict) or "obs" not in dataset or "chunks" not in dataset:
        raise ValueError("dataset must be a dict with 'obs' [N, 34] and 'chunks' [N, H, 4] (chunk_dataset)")
    H, s = config.horizon, config.execute_horizon
    if dataset["chunks"].shape[1:] != (H, ACTION_DIM) or dataset["obs"].shape[1:] != (OBS_DIM,):
        raise ValueError(f"dataset chunks must have shape [N, {H}, {ACTION_DIM}], got {dataset['chunks'].shape}")

    obs = jnp.asarray(normalizer.obs(dataset["obs"]), jnp.float32)
    chunks = jnp.asarray(normalizer.act(dataset["chunks"]), jnp.float32)
    N = obs.shape[0]
    d_max = config.max_delay
    table = _weight_table(method, H, s, d_max)
    probs = jdelays.delay_probs("uniform", 0, d_max)

    key = jax.random.key(seed)
    key, init_key = jax.random.split(key)
    if init is None:
        model = FlowPolicy(obs_dim=OBS_DIM, action_dim=ACTION_DIM, config=config.policy_config(),
                           rngs=nnx.Rngs(int(jax.random.randint(init_key, (), 0, 2**31 - 1))))
    else:
        if not isinstance(init, FlowPolicy):
            raise ValueError(f"init must be a FlowPolicy or None, got {type(init).__name__}")
        # A deep copy (split/merge alone would share the parameter variables): fine-tuning leaves the base intact.
        gd, st = nnx.split(init)
        model = nnx.merge(gd, jax.tree_util.tree_map(jnp.copy, st))
    schedule = optax.warmup_cosine_decay_schedule(0.0, learning_rate, min(200, steps // 10 + 1), steps,
                                                  learning_rate * 0.05)
    opt = nnx.Optimizer(model, optax.chain(optax.clip_by_global_norm(1.0), optax.adamw(schedule, weight_decay=1e-4)),
                        wrt=nnx.Param)

    # probs and table are arguments (not closure constants) so they are traced inside jit.
    @nnx.jit
    def step(model, opt, key, probs, table):
        k_idx, k_tau, k_eps, k_d = jax.random.split(key, 4)
        rows = jax.random.randint(k_idx, (batch_size,), 0, N)
        o, a = obs[rows], chunks[rows]
        tau = jax.random.uniform(k_tau, (batch_size,))
        eps = jax.random.normal(k_eps, a.shape)
        d = jdelays.sample_delays(k_d, probs, 0, (batch_size,))
        w = table[d]

        def loss_fn(m):
            return rtc_loss(m, o, a, eps, w, tau)

        loss, grads = nnx.value_and_grad(loss_fn)(model)
        opt.update(model, grads)
        return loss

    running = None
    for i in range(steps):
        key, sub = jax.random.split(key)
        loss = step(model, opt, sub, probs, table)
        if log_every and ((i + 1) % log_every == 0 or i == 0):
            lv = float(loss)
            running = lv if running is None else running
            print(f"  [{method}] step {i + 1}/{steps} loss {lv:.4f}", flush=True)
    return model


# --------------------------------------------------------------------------- checkpoints


def _flatten(tree, prefix=""):
    out = {}
    for k, v in tree.items():
        name = f"{prefix}/{k}" if prefix else str(k)
        if isinstance(v, dict):
            out.update(_flatten(v, name))
        else:
            out[name] = np.asarray(v)
    return out


def _unflatten(flat: dict) -> dict:
    tree: dict = {}
    for name, arr in flat.items():
        node = tree
        parts = name.split("/")
        for p in parts[:-1]:
            node = node.setdefault(int(p) if p.isdigit() else p, {})
        node[int(parts[-1]) if parts[-1].isdigit() else parts[-1]] = arr
    return tree


def save_arm_checkpoint(path, model: FlowPolicy, normalizer: Normalizer, config: ArmPolicyConfig,
                        method: str, meta: dict | None = None) -> str:
    """Write parameters, normalization statistics and config to one ``.npz`` ([A-18]).

    No pickle: parameters are stored as named float32 arrays (``param/<path>``),
    the config and metadata as JSON strings.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path).endswith(".npz"):
        raise ValueError(f"path must be a str or PathLike ending in '.npz', got {path!r}")
    if not os.path.isdir(os.path.dirname(os.path.abspath(os.fspath(path)))):
        raise ValueError(f"path's folder does not exist: {path!r}")
    if not isinstance(model, FlowPolicy):
        raise ValueError(f"model must be a FlowPolicy, got {type(model).__name__}")
    method = _check_choice("method", method, TRAIN_METHODS)
    params = {f"param/{k}": v.astype(np.float32) for k, v in _flatten(nnx.state(model).to_pure_dict()).items()}
    header = {"format": _FORMAT, "method": method, "config": dataclasses.asdict(config), "meta": meta or {}}
    np.savez_compressed(path, header=np.array(json.dumps(header)),
                        obs_mean=normalizer.obs_mean, obs_std=normalizer.obs_std,
                        act_mean=normalizer.act_mean, act_std=normalizer.act_std, **params)
    return os.fspath(path)


def load_arm_checkpoint(path, sampler_method: str | None = None) -> "ArmPolicy":
    """Load a checkpoint written by :func:`save_arm_checkpoint` into an :class:`ArmPolicy` ([A-18]).

    ``sampler_method`` (default: the method the checkpoint was trained with)
    selects the chunk generator ([S-6]); e.g. ``inference_soft`` on the base.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing checkpoint .npz file, got {path!r}")
    with np.load(path, allow_pickle=False) as f:
        header = json.loads(str(f["header"]))
        if header.get("format") != _FORMAT:
            raise ValueError(f"path {path!r} is not a softrtc arm checkpoint (format {header.get('format')!r})")
        norm = Normalizer(f["obs_mean"], f["obs_std"], f["act_mean"], f["act_std"])
        params = {k[len("param/"):]: f[k] for k in f.files if k.startswith("param/")}
    config = ArmPolicyConfig(**header["config"])
    model = FlowPolicy(obs_dim=OBS_DIM, action_dim=ACTION_DIM, config=config.policy_config(), rngs=nnx.Rngs(0))
    from softrtc.jax.policy import load_pure_dict
    load_pure_dict(model, _unflatten(params))
    return ArmPolicy(model, norm, config, sampler_method or header["method"], trained_as=header["method"],
                     meta=header.get("meta", {}))


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
        self.trained_as = trained_as or method
        self.meta = dict(meta or {})
        self.model, self.normalizer, self.config = model, normalizer, config
        self.H, self.s, self.T = config.horizon, config.execute_horizon, config.num_steps
        self.low, self.high = action_bounds(env_config)
        self._graphdef, self._state = nnx.split(model)
        # train_soft's window ([W-7]); default the paper's main setting.
        self.window = SoftWindow() if window is None else window
        self._static = (self._graphdef, self.H, self.s, self.T)
        self._nm = tuple(jnp.asarray(a, jnp.float32) for a in (normalizer.obs_mean, normalizer.obs_std,
                                                              normalizer.act_mean, normalizer.act_std))

    def _obs(self, obs) -> jnp.ndarray:
        o = np.asarray(obs, np.float64)
        if o.shape != (OBS_DIM,) or not np.all(np.isfinite(o)):
            raise ValueError(f"obs must be a finite vector of shape [{OBS_DIM}], got shape {list(o.shape)}")
        return jnp.asarray(o, jnp.float32)

    def generate(self, obs, prior, d, key) -> np.ndarray:
        """One chunk ``[H, 4]`` (float64, physical units, within [A-8]) for delay ``d`` ([S-6], [A-19])."""
        o = self._obs(obs)
        if not isinstance(key, jax.Array) or not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
            raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed))")
        if prior is None:
            _check_int("d", d, 0, 0)
            z = _first_chunk(self._static, self._state, self._nm, o, key)
        else:
            d = _check_int("d", d, 0, self.config.max_delay)
            p = np.asarray(prior, np.float64)
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
    model = FlowPolicy(obs_dim=OBS_DIM, action_dim=ACTION_DIM, config=config.policy_config(), rngs=nnx.Rngs(seed))
    norm = Normalizer(np.zeros(OBS_DIM), np.ones(OBS_DIM), np.array([0.0, -1.0, 0.0, 0.5]),
                      np.array([0.3, 0.3, 0.3, 0.3]))
    return ArmPolicy(model, norm, config, method, trained_as="untrained", window=window)


def default_checkpoint_dir() -> Path:
    """The shipped checkpoints: ``softrtc/arm/checkpoints`` ([A-21])."""
    return Path(__file__).resolve().parent / "checkpoints"


def load_policies(checkpoint_dir=None, methods=STUDY_METHODS) -> dict:
    """``{method: ArmPolicy}`` from ``base.npz``, ``train_hard.npz``, ``train_soft.npz`` ([A-21]).

    Method ``naive`` and the inference-time methods use the base checkpoint.
    """
    folder = Path(default_checkpoint_dir() if checkpoint_dir is None else checkpoint_dir)
    if not folder.is_dir():
        raise ValueError(f"checkpoint_dir must be an existing folder, got {str(folder)!r}")
    out = {}
    for m in methods:
        _check_choice("methods entry", m, jmethods.METHODS)
        f = folder / _CKPT_FILES.get(m, "base.npz")
        if not f.is_file():
            raise ValueError(f"checkpoint {str(f)!r} is missing; run `softrtc arm train --out {folder}`")
        out[m] = load_arm_checkpoint(f, sampler_method=m)
    return out


def train_arm_policies(out_dir, episodes: int = 100, steps: int = 4000, finetune_steps: int | None = None,
                       seed: int = 0, noise_std: float = 0.03, config: ArmPolicyConfig = ArmPolicyConfig(),
                       batch_size: int = 64, verbose: bool = True) -> dict:
    """Demos, base BC policy, then Train Hard / Train Soft RTC fine-tunes, saved to ``out_dir`` ([A-20]).

    Demonstrations: ``generate_demos(episodes, seed, noise_std)`` ([A-15]).
    The base is trained for ``steps`` steps with key ``seed``; each fine-tune
    starts from the base and runs ``finetune_steps`` (default ``steps // 2``)
    with key ``seed + 1`` (hard) and ``seed + 2`` (soft). Returns the paths.
    """
    import time
    from .demos import generate_demos, load_demos

    if not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a str or PathLike, got {out_dir!r}")
    episodes = _check_int("episodes", episodes, 1, 100000)
    steps = _check_int("steps", steps, 1, 10**7)
    finetune_steps = steps // 2 if finetune_steps is None else _check_int("finetune_steps", finetune_steps, 1, 10**7)
    finetune_steps = max(finetune_steps, 1)
    seed = _check_int("seed", seed, 0, 2**31 - 3)
    noise_std = _check_float("noise_std", noise_std, 0.0, 1.0)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    demo_path = out / "demos.npz"
    info = generate_demos(episodes, seed, noise_std, str(demo_path))
    data = load_demos(str(demo_path))
    demo_path.unlink()  # the demos are reproducible from (episodes, seed, noise_std); do not ship them
    if verbose:
        print(f"demos: {info['episodes']} episodes, {info['steps']} steps, expert success "
              f"{info['success_rate']:.2f} ({time.perf_counter() - t0:.0f} s)", flush=True)
    ds = chunk_dataset(data, config.horizon)
    norm = Normalizer.fit(data["obs"], data["action"])
    meta = {"episodes": episodes, "seed": seed, "noise_std": noise_std, "steps": steps,
            "finetune_steps": finetune_steps, "batch_size": batch_size}
    log = max(steps // 8, 1) if verbose else 0
    base = train_flow_policy(ds, norm, "naive", steps, seed, config=config, batch_size=batch_size, log_every=log)
    paths = {"naive": save_arm_checkpoint(out / _CKPT_FILES["naive"], base, norm, config, "naive", meta)}
    if verbose:
        print(f"base trained ({time.perf_counter() - t0:.0f} s)", flush=True)
    for i, m in enumerate(("train_hard", "train_soft")):
        ft = train_flow_policy(ds, norm, m, finetune_steps, seed + 1 + i, config=config, init=base,
                               batch_size=batch_size,
                               log_every=max(finetune_steps // 4, 1) if verbose else 0)
        paths[m] = save_arm_checkpoint(out / _CKPT_FILES[m], ft, norm, config, m,
                                       {**meta, "finetuned_from": "base"})
        if verbose:
            print(f"{m} fine-tuned ({time.perf_counter() - t0:.0f} s)", flush=True)
    return paths
