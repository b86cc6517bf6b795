"""Expert policies of the Kinetix pipeline ([KP-1]..[KP-4]).

An expert is a Gaussian actor-critic on the *expert observation*: the last
``EXPERT_HISTORY = 4`` symbolic observations of [K-5] stacked oldest first,
then the previous (pre-noise) action; after a reset the history repeats the
reset observation and the previous action is zero ([KP-1]). Actions are a
diagonal Gaussian in an unbounded space squashed per entry: ``tanh`` for the 4
motors, ``sigmoid`` for the 2 thrusters ([KP-2]). Parameters are plain nested
dicts laid out as the public release's expert files (``actor`` / ``critic``
with ``layers`` 0, 2, 4 of ``kernel`` / ``bias``, and ``logstd``), so its
``worlds_l_<level>.pkl`` experts and ours read each other ([KP-3]).

>>> params = init_expert(jax.random.key(0), obs_dim=10, action_dim=6, width=8)
>>> sorted(params), sorted(params["actor"]["layers"])
(['actor', 'critic', 'logstd'], [0, 2, 4])
"""

from __future__ import annotations

import os
import pickle
from pathlib import Path
from typing import Any, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import write_atomic
from softrtc.reference._validate import check_int

from . import env as kenv

__all__ = ["EXPERT_HISTORY", "MAX_ACTION", "LOG_STD_MIN", "LOG_STD_MAX", "MEAN_MAX", "expert_obs_dim",
           "init_expert", "expert_dims", "actor_mean_std", "critic_value", "squash", "sample_action",
           "action_log_prob", "history_reset", "history_step", "expert_input", "save_expert", "load_expert"]

# [KP-1] observations stacked into the expert's input.
EXPERT_HISTORY = 4
# [KP-2] bounds of the release's Gaussian head.
MAX_ACTION = 0.99999
LOG_STD_MIN = -10.0
LOG_STD_MAX = 2.0
MEAN_MAX = 5.0
_LAYERS = (0, 2, 4)  # indices of the Linear layers in the release's Sequential (tanh in between)


def expert_obs_dim(obs_dim: int = kenv.OBS_DIM, action_dim: int = kenv.ACTION_DIM) -> int:
    """Width of the expert input ([KP-1]): ``EXPERT_HISTORY * obs_dim + action_dim`` (2722 for the benchmark)."""
    obs_dim = check_int("obs_dim", obs_dim, 1, 1 << 20)
    action_dim = check_int("action_dim", action_dim, 1, 1 << 10)
    return EXPERT_HISTORY * obs_dim + action_dim


def _mlp_init(key, sizes, out_scale):
    ortho = jax.nn.initializers.orthogonal
    keys = jax.random.split(key, len(sizes) - 1)
    layers = {}
    for i, (k, a, b) in enumerate(zip(keys, sizes[:-1], sizes[1:])):
        scale = out_scale if i == len(sizes) - 2 else float(np.sqrt(2.0))
        layers[_LAYERS[i]] = {"kernel": ortho(scale)(k, (a, b), jnp.float32), "bias": jnp.zeros((b,), jnp.float32)}
    return {"layers": layers}


def init_expert(key: jax.Array, obs_dim: int | None = None, action_dim: int = kenv.ACTION_DIM,
                width: int = 256) -> dict:
    """Fresh expert parameters ([KP-3]): two tanh hidden layers of ``width`` per head, orthogonal
    initialisation (gain sqrt 2; 0.01 for the actor's output, 1 for the critic's), zero biases and log-std.

    ``obs_dim`` is the expert input width (default :func:`expert_obs_dim`).
    """
    if not (isinstance(key, jax.Array) and jnp.issubdtype(key.dtype, jax.dtypes.prng_key) and key.shape == ()):
        raise ValueError(f"key must be a single typed PRNG key (jax.random.key), got {key!r}")
    action_dim = check_int("action_dim", action_dim, 2, 1 << 10)
    obs_dim = expert_obs_dim(kenv.OBS_DIM, action_dim) if obs_dim is None else check_int("obs_dim", obs_dim, 1, 1 << 20)
    width = check_int("width", width, 1, 1 << 14)
    ka, kc = jax.random.split(key)
    return {"actor": _mlp_init(ka, (obs_dim, width, width, action_dim), 0.01),
            "critic": _mlp_init(kc, (obs_dim, width, width, 1), 1.0),
            "logstd": jnp.zeros((action_dim,), jnp.float32)}


def expert_dims(params: Mapping) -> tuple[int, int, int]:
    """``(input width, action_dim, width)`` of expert parameters, checked against the layout of [KP-3]."""
    try:
        a = params["actor"]["layers"]
        c = params["critic"]["layers"]
        shapes = {(h, i, k): tuple(np.shape(t[i][k])) for h, t in (("actor", a), ("critic", c))
                  for i in _LAYERS for k in ("kernel", "bias")}
        logstd = tuple(np.shape(params["logstd"]))
    except (KeyError, TypeError, IndexError) as exc:
        raise ValueError(f"params must be expert parameters with actor/critic layers 0, 2, 4 (kernel, bias) and "
                         f"logstd, missing {exc}") from None
    obs_dim, width = shapes[("actor", 0, "kernel")]
    action_dim = shapes[("actor", 4, "kernel")][1]
    want = {}
    for h, out in (("actor", action_dim), ("critic", 1)):
        for i, (a_, b_) in zip(_LAYERS, ((obs_dim, width), (width, width), (width, out))):
            want[(h, i, "kernel")] = (a_, b_)
            want[(h, i, "bias")] = (b_,)
    bad = [f"{h}/layers/{i}/{k} {shapes[(h, i, k)]} (expected {w})" for (h, i, k), w in want.items()
           if shapes[(h, i, k)] != w]
    if bad or logstd != (action_dim,):
        bad += [] if logstd == (action_dim,) else [f"logstd {logstd} (expected {(action_dim,)})"]
        raise ValueError(f"params has inconsistent shapes: {', '.join(bad)}")
    return obs_dim, action_dim, width


def _mlp(p, x):
    for j, i in enumerate(_LAYERS):
        x = x @ p["layers"][i]["kernel"] + p["layers"][i]["bias"]
        if j < len(_LAYERS) - 1:
            x = jnp.tanh(x)
    return x


def actor_mean_std(params: Mapping, obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Pre-squash Gaussian ``(mean, std)`` ([KP-2]): mean clipped to ``[-5, 5]``, log-std to ``[-10, 2]``."""
    mean = jnp.clip(_mlp(params["actor"], obs), -MEAN_MAX, MEAN_MAX)
    std = jnp.exp(jnp.clip(params["logstd"], LOG_STD_MIN, LOG_STD_MAX))
    return mean, jnp.broadcast_to(std, mean.shape)


def critic_value(params: Mapping, obs: jax.Array) -> jax.Array:
    """State value ``V(obs)`` of the critic head."""
    return _mlp(params["critic"], obs)[..., 0]


def squash(u: jax.Array) -> jax.Array:
    """``tanh`` on the motor entries, ``sigmoid`` on the thruster entries ([KP-2]), clipped into the open range."""
    m = kenv.NUM_MOTOR_BINDINGS
    motors = jnp.clip(jnp.tanh(u[..., :m]), -MAX_ACTION, MAX_ACTION)
    thrust = jnp.clip(jax.nn.sigmoid(u[..., m:]), 1.0 - MAX_ACTION, MAX_ACTION)
    return jnp.concatenate([motors, thrust], axis=-1)


def _log_det(u: jax.Array) -> jax.Array:
    m = kenv.NUM_MOTOR_BINDINGS
    um, ut = u[..., :m], u[..., m:]
    # log(1 - tanh(u)^2) and log(sigmoid(u) * sigmoid(-u)), written to stay finite for large |u|.
    tanh_part = 2.0 * (jnp.log(2.0) - um - jax.nn.softplus(-2.0 * um))
    sig_part = -jax.nn.softplus(-ut) - jax.nn.softplus(ut)
    return tanh_part.sum(-1) + sig_part.sum(-1)


def action_log_prob(mean: jax.Array, std: jax.Array, action: jax.Array) -> jax.Array:
    """Log-density of a squashed action ([KP-2]): Gaussian density of the pre-image minus the log-Jacobian."""
    m = kenv.NUM_MOTOR_BINDINGS
    u = jnp.concatenate([jnp.arctanh(action[..., :m]), jnp.log(action[..., m:]) - jnp.log1p(-action[..., m:])], -1)
    z = (u - mean) / std
    gauss = (-0.5 * z * z - jnp.log(std) - 0.5 * jnp.log(2.0 * jnp.pi)).sum(-1)
    return gauss - _log_det(u)


def sample_action(key: jax.Array, mean: jax.Array, std: jax.Array) -> jax.Array:
    """One squashed sample ``squash(mean + std * N(0, I))`` ([KP-2])."""
    return squash(mean + std * jax.random.normal(key, mean.shape, mean.dtype))


def history_reset(obs: jax.Array) -> tuple[jax.Array, jax.Array]:
    """``(history [.., 4, O], previous action [.., A] = 0)`` after a reset to ``obs`` ([KP-1])."""
    hist = jnp.repeat(obs[..., None, :], EXPERT_HISTORY, axis=-2)
    return hist, jnp.zeros(obs.shape[:-1] + (kenv.ACTION_DIM,), obs.dtype)


def history_step(hist, prev_action, obs, action, done):
    """History after a step ([KP-1]): ``obs`` appended (oldest dropped) and ``action`` kept, or, where the
    step ended the episode (``obs`` is then the reset observation, [K-9]), the reset history."""
    rolled = jnp.concatenate([hist[..., 1:, :], obs[..., None, :]], axis=-2)
    h0, a0 = history_reset(obs)
    d = done[..., None]
    return jnp.where(d[..., None], h0, rolled), jnp.where(d, a0, action)


def expert_input(hist: jax.Array, prev_action: jax.Array) -> jax.Array:
    """The expert observation ([KP-1]): flattened history (oldest first) then the previous action."""
    return jnp.concatenate([hist.reshape(hist.shape[:-2] + (-1,)), prev_action], axis=-1)


def save_expert(path: str | os.PathLike, params: Mapping) -> Path:
    """Pickle ``params`` as NumPy arrays in the release's expert layout ([KP-3]); written atomically."""
    expert_dims(params)
    host = jax.tree.map(lambda x: np.asarray(x), dict(params))
    blob = pickle.dumps(host)
    write_atomic(path, lambda f: f.write(blob), binary=True)
    return Path(path)


def load_expert(path: str | os.PathLike) -> dict:
    """Expert parameters from a ``.pkl`` file of :func:`save_expert` or the release ([KP-3]).

    Layer keys may be integers or digit strings. The file is unpickled: load only files you trust.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike naming an expert .pkl file, got {type(path).__name__}")
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"path must name an existing expert file, got {str(p)!r}")
    try:
        raw = pickle.loads(p.read_bytes())
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError, ValueError) as e:
        raise ValueError(f"path {str(p)!r} is not a readable expert pickle: {type(e).__name__}: {e}") from e

    def norm(tree: Any) -> Any:
        if isinstance(tree, Mapping):
            return {(int(k) if isinstance(k, str) and k.isdigit() else k): norm(v) for k, v in tree.items()}
        return jnp.asarray(tree, jnp.float32)

    if not isinstance(raw, Mapping):
        raise ValueError(f"path {str(p)!r} must hold a dict of expert parameters, got {type(raw).__name__}")
    params = norm(raw)
    params = {k: params[k] for k in ("actor", "critic", "logstd") if k in params}
    expert_dims(params)
    return params
