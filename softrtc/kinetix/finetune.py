"""Fine-tuning the public release's base policies as training-time RTC ([KE-10], [KE-11]).

The public release ships per-level expert data (``<run>/data/worlds_l_<level>.npz``,
[K-14]) and per-level base flow policies (``bc/<epoch>/policies/worlds_l_<level>.pkl``,
pickled ``nnx`` pure dicts, [P-8]). :func:`finetune_level` loads both, trains
one epoch of hard or soft training-time RTC with :mod:`softrtc.jax.training`
and writes a :mod:`softrtc.jax.checkpoint` file ``<out>/<level>.npz``.
:func:`load_level_policy` reads either kind of file back for evaluation.
"""

from __future__ import annotations

import math
import os
import pickle
import re
from pathlib import Path
from typing import Any, Mapping

import flax.nnx as nnx
import jax
import numpy as np

from softrtc._files import check_out_dir
from softrtc.jax import checkpoint as jckpt
from softrtc.jax.delays import MAX_DELAY
from softrtc.jax.params import load_pure_dict
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.jax.training import TrainConfig, train
from softrtc.reference import weights as ref_weights
from softrtc.reference.methods import METHODS

from . import data as kdata
from .env import check_level_name

__all__ = ["infer_policy_shape", "find_bc_file", "bc_policy_shape", "load_bc_policy", "find_level_policy_file",
           "load_level_policy", "read_level_policy", "check_level_role", "method_role", "ROLES", "finetune_level"]


def _check_level(level: Any) -> str:
    check_level_name(level, "level")
    return level


def _check_dir(name: str, path: Any) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"{name} must be a directory path, got {type(path).__name__}")
    p = Path(path).expanduser()
    if not p.is_dir():
        raise FileNotFoundError(f"{name} {p} is not a directory")
    return p


def _shape(tree: Mapping, *path) -> tuple:
    node: Any = tree
    for k in path:
        if not isinstance(node, Mapping):
            raise ValueError(f"pure_dict is missing key '{'/'.join(map(str, path))}'")
        # Layer indices may be ints or digit strings ([P-8]).
        node = node[k] if k in node else node.get(str(k)) if str(k) in node else None
        if node is None:
            raise ValueError(f"pure_dict is missing key '{'/'.join(map(str, path))}'")
    shape = tuple(np.shape(node))
    if len(shape) != 2:
        raise ValueError(f"pure_dict key '{'/'.join(map(str, path))}' must be a 2-D kernel [in, out], got shape {shape}")
    return shape


def infer_policy_shape(pure_dict: Mapping) -> tuple[int, int, PolicyConfig]:
    """``(obs_dim, action_dim, PolicyConfig)`` of a release pure dict, from its kernel shapes ([P-7], [KE-10]).

    ``in_proj/kernel [A + O, C]``, ``out_proj/kernel [C, A]``,
    ``mlp_stack/0/token_mix_in/kernel [H, token_hidden]``,
    ``mlp_stack/0/channel_mix_in/kernel [C, channel_hidden]``, and the number
    of ``mlp_stack`` entries. The full tree is validated when loaded.
    """
    if not isinstance(pure_dict, Mapping):
        raise ValueError(f"pure_dict must be a nested mapping of arrays, got {type(pure_dict).__name__}")
    a_in, c = _shape(pure_dict, "in_proj", "kernel")
    c2, a = _shape(pure_dict, "out_proj", "kernel")
    stack = pure_dict.get("mlp_stack")
    if not isinstance(stack, Mapping) or not stack:
        raise ValueError("pure_dict must have a non-empty 'mlp_stack' mapping")
    h, th = _shape(pure_dict, "mlp_stack", 0, "token_mix_in", "kernel")
    _, ch = _shape(pure_dict, "mlp_stack", 0, "channel_mix_in", "kernel")
    if c2 != c or a_in <= a:
        raise ValueError(f"pure_dict has inconsistent shapes: in_proj/kernel {(a_in, c)}, out_proj/kernel {(c2, a)}")
    cfg = PolicyConfig(channel_dim=c, channel_hidden_dim=ch, token_hidden_dim=th, num_layers=len(stack),
                       action_chunk_size=h)
    return a_in - a, a, cfg


def find_bc_file(bc_dir: str | os.PathLike, level: str) -> Path:
    """The release policy file of ``level`` under ``bc_dir`` ([P-8], [KE-10]).

    Looked up as ``<bc_dir>/worlds_l_<level>.pkl``, ``<bc_dir>/policies/...``
    and ``<bc_dir>/<epoch>/policies/...`` (the largest integer epoch).
    """
    _check_level(level)
    d = _check_dir("bc_dir", bc_dir)
    name = f"worlds_l_{level}.pkl"
    cands = [d / name, d / "policies" / name]
    epochs = sorted((int(p.name) for p in d.iterdir() if p.is_dir() and re.fullmatch(r"\d+", p.name)), reverse=True)
    cands += [d / str(e) / "policies" / name for e in epochs]
    for c in cands:
        if c.is_file():
            return c
    raise FileNotFoundError(f"no release policy {name} for level {level!r} under {d} "
                            f"(looked in ., policies/ and <epoch>/policies/)")


def _read_pure_dict(path: Any) -> Mapping:
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike naming a release policy .pkl file, got {type(path).__name__}")
    if not Path(path).is_file():
        raise FileNotFoundError(f"path must name an existing policy file, got {str(path)!r}")
    try:
        with open(path, "rb") as f:
            pure = pickle.load(f)
    except (pickle.UnpicklingError, EOFError, AttributeError, ImportError, IndexError, TypeError, ValueError) as e:
        raise ValueError(f"path {str(path)!r} is not a readable release policy pickle ([KE-10]): "
                         f"{type(e).__name__}: {e}") from e
    if not isinstance(pure, Mapping):
        raise ValueError(f"path {str(path)!r} must hold a pure dict (nested mapping of arrays), got {type(pure).__name__}")
    return pure


def bc_policy_shape(path: str | os.PathLike) -> tuple[int, int, PolicyConfig]:
    """``(obs_dim, action_dim, PolicyConfig)`` of a release ``.pkl`` file without building the policy ([P-7], [KE-10]).

    Used to check options against the chunk size ``H`` before any training
    starts. The file is unpickled: read only files you trust.
    """
    return infer_policy_shape(_read_pure_dict(path))


def load_bc_policy(path: str | os.PathLike) -> FlowPolicy:
    """A :class:`FlowPolicy` from a release ``.pkl`` pure dict ([P-8]); architecture inferred from it.

    The file is unpickled: load only files you trust.
    """
    pure = _read_pure_dict(path)
    obs_dim, action_dim, cfg = infer_policy_shape(pure)
    policy = FlowPolicy(obs_dim=obs_dim, action_dim=action_dim, config=cfg, rngs=nnx.Rngs(0))
    return load_pure_dict(policy, pure)


def find_level_policy_file(policy_dir: str | os.PathLike, level: str) -> Path:
    """The file :func:`load_level_policy` reads for ``level`` ([KE-11]): ``<policy_dir>/<level>.npz``
    when present, else the release file of :func:`find_bc_file`.

    ``FileNotFoundError`` names both forms when neither exists; nothing is loaded.
    """
    _check_level(level)
    d = _check_dir("policy_dir", policy_dir)
    ck = d / f"{level}.npz"
    if ck.is_file():
        return ck
    try:
        return find_bc_file(d, level)
    except FileNotFoundError:
        raise FileNotFoundError(f"no policy for level {level!r} in {d}: expected {level}.npz or a release "
                                f"worlds_l_{level}.pkl in ., policies/ or <epoch>/policies/") from None


# [KE-11] The role a policy file plays: the base (a release file, or a checkpoint without a training method)
# or a fine-tune of training-time RTC with objective "hard" or "soft" (finetune_level's "method").
ROLES = ("base", "hard", "soft")


def method_role(method: str) -> str:
    """The role of the policy a method of [S-6] runs ([KE-11]): ``train_hard`` a hard fine-tune,
    ``train_soft`` a soft one, the base for ``naive`` and the inference-time methods."""
    return {"train_hard": "hard", "train_soft": "soft"}.get(method, "base")


def read_level_policy(policy_dir: str | os.PathLike, level: str) -> tuple[FlowPolicy, dict]:
    """``(policy, about)`` for ``level`` in ``policy_dir`` ([KE-11]); ``about`` holds ``path``, ``role`` and,
    for a soft fine-tune, its training ``window`` (a reference SoftWindow, else None).

    A checkpoint must name ``level`` in its metadata (as :func:`finetune_level` writes it): a file copied
    under another level's name is refused, naming the file and both levels. Its ``method`` ("hard" or
    "soft") is its role; without one it is a base. A release ``.pkl`` file is a base.
    """
    path = find_level_policy_file(policy_dir, level)
    if path.suffix != ".npz":
        return load_bc_policy(path), {"path": path, "role": "base", "window": None}
    policy, meta = jckpt.load_checkpoint(path)
    if meta.get("level") != level:
        raise ValueError(f"checkpoint {str(path)!r} holds the policy of level {meta.get('level')!r} (its "
                         f"metadata), not of level {level!r}")
    role = meta.get("method", "base")
    if role not in ROLES:
        raise ValueError(f"checkpoint {str(path)!r} names training method {role!r}; expected 'hard', 'soft' or none")
    window = None
    if role == "soft":
        try:
            window = TrainConfig.from_dict(meta["train_config"]).window
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"checkpoint {str(path)!r}: a soft fine-tune without a valid train_config ({exc})") \
                from None
    return policy, {"path": path, "role": role, "window": window}


def check_level_role(about: Mapping, method: str, window: ref_weights.SoftWindow | None = None) -> None:
    """Raise ValueError unless the policy described by ``about`` (:func:`read_level_policy`) plays the role
    ``method`` needs ([KE-11]); for ``train_soft`` its training window must be ``window`` too ([W-7])."""
    need = method_role(method)
    name = {"base": "a base policy", "hard": "a hard fine-tune", "soft": "a soft fine-tune"}
    if about["role"] != need:
        raise ValueError(f"{str(about['path'])!r} is {name[about['role']]}, but method {method!r} runs "
                         f"{name[need]}")
    if need == "soft" and window is not None and about["window"] != window:
        raise ValueError(f"{str(about['path'])!r} was fine-tuned with window {about['window']}, but method "
                         f"{method!r} runs window {window}")


def load_level_policy(policy_dir: str | os.PathLike, level: str, method: str | None = None) -> FlowPolicy:
    """The policy of ``level`` in ``policy_dir`` ([KE-11]): a softrtc checkpoint ``<level>.npz``
    (:func:`finetune_level`'s output) or else a release file (:func:`find_bc_file`).

    A checkpoint's metadata must name ``level``; with ``method`` the file must also play that method's role
    (:func:`check_level_role`), as the arm's loaders check theirs ([A-21]).
    """
    if method is not None and method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)} or None, got {method!r}")
    policy, about = read_level_policy(policy_dir, level)
    if method is not None:
        check_level_role(about, method)
    return policy


def finetune_level(data_dir: str | os.PathLike, bc_dir: str | os.PathLike, level: str, method: str,
                   out_dir: str | os.PathLike, *, window: ref_weights.SoftWindow | None = None,
                   execute_horizon: int = 4, d_max: int = 4, delay_dist: str = "uniform",
                   batch_size: int = 256, learning_rate: float = 3e-4, epochs: int = 1, seed: int = 0,
                   progress: bool = True) -> dict:
    """Fine-tune ``level``'s release policy as training-time RTC and save it ([KE-10]).

    ``method`` is ``"hard"`` or ``"soft"`` ([T-3]; ``window`` is the soft
    window, default the paper's main setting [W-7]). Examples are the
    release's chunks ([K-16]..[K-19]); one epoch is ``floor(n / batch_size)``
    steps (at least one; the batch shrinks to ``n`` for tiny data). Delays
    are drawn from ``delay_dist`` on ``0 .. d_max`` ([D-1], [D-2]); ``d_max`` and
    ``execute_horizon`` are checked against the release policy's chunk size
    ``H`` ([D-4]) before the expert data is read. Writes
    ``<out_dir>/<level>.npz`` with metadata (level, method, train config,
    source files, steps, final loss) and returns that metadata plus ``path``.
    """
    _check_level(level)
    if method not in ("hard", "soft"):
        raise ValueError(f"method must be 'hard' or 'soft', got {method!r}")
    if window is not None and not isinstance(window, ref_weights.SoftWindow):
        raise ValueError(f"window must be a softrtc.reference.weights.SoftWindow or None, got {type(window).__name__}")
    if window is not None and method != "soft":
        raise ValueError("window is only used with method='soft'")
    for name, val, lo, hi in (("epochs", epochs, 1, 1000), ("batch_size", batch_size, 1, 1 << 20),
                              ("seed", seed, 0, 2**32 - 1), ("d_max", d_max, 0, MAX_DELAY),
                              ("execute_horizon", execute_horizon, 1, MAX_DELAY)):
        if isinstance(val, bool) or not isinstance(val, (int, np.integer)) or not lo <= val <= hi:
            raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {val!r}")
    check_out_dir("out_dir", out_dir, (f"{level}.npz",))
    data_path = _check_dir("data_dir", data_dir) / kdata.expert_data_filename(level)
    bc_path = find_bc_file(bc_dir, level)
    if not data_path.is_file():
        raise FileNotFoundError(f"data_dir {data_path.parent} has no {data_path.name}")
    policy = load_bc_policy(bc_path)
    H = policy.action_chunk_size
    for name, val in (("d_max", d_max), ("execute_horizon", execute_horizon)):
        if val > H:  # [D-4]: no weights for a delay longer than the chunk; s <= H
            raise ValueError(f"{name} must be an integer in [{0 if name == 'd_max' else 1}, {H}] "
                             f"(the chunk size H of {bc_path.name}), got {val}")
    data = kdata.load_expert_data(data_path)
    if (data.obs_dim, data.action_dim) != (policy.obs_dim, policy.action_dim):
        raise ValueError(f"expert data dims (obs {data.obs_dim}, action {data.action_dim}) differ from the policy's "
                         f"(obs {policy.obs_dim}, action {policy.action_dim}) for level {level!r}")
    obs, chunks, _ = kdata.make_training_examples(data, H)
    n = obs.shape[0]
    bs = min(batch_size, n)
    steps = max(1, n // bs) * epochs
    config = TrainConfig(method=method, window=window if window is not None else ref_weights.SoftWindow(),
                         execute_horizon=execute_horizon, delay_dist=delay_dist, d_min=0, d_max=d_max,
                         batch_size=bs, learning_rate=learning_rate)
    tuned, losses = train(policy, (obs.astype(np.float32), chunks.astype(np.float32)), config,
                          jax.random.key(seed), steps, progress=progress)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{level}.npz"
    meta = {"level": level, "method": method, "train_config": config.to_dict(), "data_file": str(data_path),
            "bc_file": str(bc_path), "examples": int(n), "steps": int(steps), "epochs": int(epochs),
            "seed": int(seed), "final_loss": float(losses[-1]) if math.isfinite(float(losses[-1])) else None}
    jckpt.save_checkpoint(path, tuned, meta)
    return meta | {"path": str(path)}
