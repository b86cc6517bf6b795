"""Loader for the public RTC Kinetix release's per-level expert data [K-14]..[K-19].

Each level's file is an uncompressed ``.npz`` written with ``np.savez`` from
the rollout recorder's state dict: arrays ``obs``, ``action``, ``done``,
``solved``, ``return_`` and ``length``, all shaped ``[steps, envs, ...]``
(see ``spec/20-kinetix.md`` for the meaning of each). This module needs only
NumPy.
"""

from __future__ import annotations

import dataclasses
import os
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from softrtc.reference._validate import real_array

# [K-14] keys and their rank (number of dimensions) in a release file.
EXPERT_KEYS: dict[str, int] = {
    "obs": 3,
    "action": 3,
    "done": 2,
    "solved": 2,
    "return_": 2,
    "length": 2,
}


@dataclasses.dataclass(frozen=True)
class ExpertData:
    """One level's validated expert rollouts, arrays ``[steps, envs, ...]`` [K-14], [K-15]."""

    obs: np.ndarray  # [S, E, obs_dim] float
    action: np.ndarray  # [S, E, action_dim] float
    done: np.ndarray  # [S, E] bool
    solved: np.ndarray  # [S, E] float
    return_: np.ndarray  # [S, E] float
    length: np.ndarray  # [S, E] float

    def __post_init__(self):
        # [K-15], [N-7]: the constructor validates like load_expert_data (done becomes bool).
        checked = _check_expert_arrays({f.name: getattr(self, f.name) for f in dataclasses.fields(self)})
        for k, v in checked.items():
            object.__setattr__(self, k, v)

    @property
    def num_steps(self) -> int:
        return int(self.obs.shape[0])

    @property
    def num_envs(self) -> int:
        return int(self.obs.shape[1])

    @property
    def obs_dim(self) -> int:
        return int(self.obs.shape[2])

    @property
    def action_dim(self) -> int:
        return int(self.action.shape[2])

    def episode_stats(self) -> dict[str, float]:
        """Mean solved/return/length over completed episodes (rows where ``done``) [K-14]."""
        n = int(self.done.sum())
        if n == 0:
            return {"num_episodes": 0, "solved": float("nan"), "return_": float("nan"), "length": float("nan")}
        d = self.done
        return {
            "num_episodes": n,
            "solved": float(self.solved[d].mean()),
            "return_": float(self.return_[d].mean()),
            "length": float(self.length[d].mean()),
        }


def expert_data_filename(level_name: str) -> str:
    """Release file name of a level: ``worlds_l_<level>.npz`` [K-14]."""
    if not isinstance(level_name, str) or not level_name or "/" in level_name or level_name.endswith(".json"):
        raise ValueError(f"level_name must be a bare level name such as 'grasp_easy', got {level_name!r}")
    return f"worlds_l_{level_name}.npz"


def _check_expert_arrays(arrays: dict[str, Any]) -> dict[str, np.ndarray]:
    """Validate the six arrays of [K-14] / [K-15]; returns them with ``done`` as bool.

    Real numeric dtypes only ([N-7]): ``obs``, ``action``, ``return_`` and
    ``length`` must be integer or float; ``solved`` and ``done`` are flags and
    may also be boolean; ``done`` must hold 0/1 only. Boolean float keys,
    strings, complex numbers, datetimes and timedeltas are rejected, not cast.
    """
    missing = [k for k in EXPERT_KEYS if k not in arrays]
    if missing:
        raise ValueError(f"expert data is missing key(s) {', '.join(missing)}; required keys: {', '.join(EXPERT_KEYS)}")
    out: dict[str, np.ndarray] = {}
    for k, rank in EXPERT_KEYS.items():
        v = arrays[k]
        flag = k in ("done", "solved")
        allowed = "biuf" if flag else "iuf"
        a = real_array(f"expert data key {k!r}", v, allowed)
        if a.ndim != rank:
            want = "[steps, envs, dim]" if rank == 3 else "[steps, envs]"
            raise ValueError(f"expert data key {k!r} must have rank {rank} {want}, got shape {a.shape}")
        out[k] = a
    lead = out["obs"].shape[:2]
    for k, a in out.items():
        if a.shape[:2] != lead:
            raise ValueError(
                f"expert data key {k!r} has leading dims {a.shape[:2]}, expected [steps, envs] = {lead} (from 'obs')"
            )
    if lead[0] < 1 or lead[1] < 1:
        raise ValueError(f"expert data key 'obs' must have steps >= 1 and envs >= 1, got shape {out['obs'].shape}")
    for k in ("obs", "action"):
        if out[k].shape[2] < 1:
            raise ValueError(f"expert data key {k!r} must have a last dimension >= 1, got shape {out[k].shape}")
    # done is a flag; accept bool or 0/1 numbers, nothing else.
    done = out["done"]
    if done.dtype != np.bool_:
        if not np.all(np.isin(done, (0, 1))):
            raise ValueError(f"expert data key 'done' must be boolean (or 0/1), got dtype {done.dtype} with other values")
        done = done.astype(bool)
    out["done"] = done
    for k in ("obs", "action", "solved", "return_", "length"):
        a = out[k]
        if a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise ValueError(f"expert data key {k!r} contains non-finite values (NaN or inf)")
    if np.any(out["length"] < 0):
        raise ValueError("expert data key 'length' must be >= 0")
    return out


def _validate_arrays(arrays: dict[str, Any]) -> ExpertData:
    return ExpertData(**_check_expert_arrays(arrays))


def load_expert_data(path: str | os.PathLike) -> ExpertData:
    """Load and validate one release ``.npz`` file [K-14], [K-15].

    Raises ``FileNotFoundError`` when ``path`` does not exist and
    ``ValueError`` naming the key for a missing key, a wrong rank, mismatched
    ``[steps, envs]`` leading dims or non-finite values. Extra keys are ignored.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike to a .npz file, got {type(path).__name__}")
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"expert data file {p} does not exist")
    try:
        # allow_pickle=False: the release holds plain numeric arrays only.
        z = np.load(p, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a .npy file loads as one array, not an archive
            raise ValueError(f"path {p} is a single .npy array, expected an .npz archive with keys {list(EXPERT_KEYS)}")
        with z:
            arrays = {k: z[k] for k in z.files if k in EXPERT_KEYS}
    except (zipfile.BadZipFile, OSError, EOFError) as e:
        raise ValueError(f"path {p} is not a readable .npz archive: {e}") from e
    except ValueError as e:
        if "pickle" in str(e).lower():
            raise ValueError(f"path {p} holds object arrays; expert data must be numeric: {e}") from e
        raise
    return _validate_arrays(arrays)


def save_expert_data(path: str | os.PathLike, data: ExpertData | dict[str, Any]) -> Path:
    """Write ``data`` in the release format (``np.savez``, keys of [K-14])."""
    if not isinstance(path, (str, os.PathLike)):
        raise ValueError(f"path must be a str or os.PathLike, got {type(path).__name__}")
    p = Path(path)
    target = p if p.suffix == ".npz" else p.with_name(p.name + ".npz")
    if target.is_dir():
        raise ValueError(f"path must name a file, but {target} is a directory")
    if not target.parent.is_dir():
        raise ValueError(f"path's folder {target.parent} does not exist or is not a directory")
    if isinstance(data, ExpertData):
        arrays = dataclasses.asdict(data)
    elif isinstance(data, dict):
        arrays = dataclasses.asdict(_validate_arrays(data))
    else:
        raise ValueError(f"data must be an ExpertData or a dict of arrays, got {type(data).__name__}")
    np.savez(target, **arrays)
    return target


# ----------------------------------------------------------------------------
# chunking [K-16]..[K-19]
# ----------------------------------------------------------------------------


def _check_data(data: Any) -> ExpertData:
    if not isinstance(data, ExpertData):
        raise ValueError(f"data must be an ExpertData (from load_expert_data), got {type(data).__name__}")
    return data


def _check_horizon(horizon: Any) -> int:
    if isinstance(horizon, bool) or not isinstance(horizon, (int, np.integer)) or int(horizon) < 1:
        raise ValueError(f"horizon must be an integer >= 1, got {horizon!r}")
    return int(horizon)


def flatten_env_major(x: np.ndarray) -> np.ndarray:
    """``[steps, envs, ...] -> [envs * steps, ...]``, each env's steps contiguous [K-16]."""
    x = np.asarray(x)
    if x.ndim < 2:
        raise ValueError(f"x must have rank >= 2 [steps, envs, ...], got shape {x.shape}")
    return np.swapaxes(x, 0, 1).reshape((x.shape[0] * x.shape[1],) + x.shape[2:])


def chunk_start_indices(data: ExpertData, horizon: int, cross_env: bool = True) -> np.ndarray:
    """Flat (env-major) indices at which training chunks start [K-17].

    ``cross_env=True`` (the public rule) gives every ``i`` in
    ``0 .. E*S - horizon``; ``cross_env=False`` keeps only starts whose chunk
    stays inside one env's recording (``step <= S - horizon``).
    """
    data = _check_data(data)
    horizon = _check_horizon(horizon)
    if not isinstance(cross_env, bool):
        raise ValueError(f"cross_env must be a bool, got {cross_env!r}")
    S, E = data.num_steps, data.num_envs
    if cross_env:
        if horizon > S * E:
            raise ValueError(f"horizon must be <= envs * steps = {S * E}, got {horizon}")
        return np.arange(S * E - horizon + 1, dtype=np.int64)
    if horizon > S:
        raise ValueError(f"horizon must be <= steps = {S} when cross_env=False, got {horizon}")
    per_env = np.arange(S - horizon + 1, dtype=np.int64)
    return (np.arange(E, dtype=np.int64)[:, None] * S + per_env[None, :]).reshape(-1)


def make_chunks(
    data: ExpertData, starts: Any, horizon: int, keep_done_action: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(obs [B, obs_dim], chunks [B, H, A], valid [B, H])`` for flat ``starts`` [K-16], [K-18].

    ``chunks[b, j] = action[starts[b] + j]`` in the env-major flat order; with
    ``k`` the first ``j`` where ``done[starts[b] + j]`` holds, every
    ``j >= k`` is set to 0 (the public rule), or every ``j > k`` when
    ``keep_done_action`` [K-18]. ``valid`` marks the entries kept.
    """
    data = _check_data(data)
    horizon = _check_horizon(horizon)
    if not isinstance(keep_done_action, bool):
        raise ValueError(f"keep_done_action must be a bool, got {keep_done_action!r}")
    starts = np.asarray(starts)
    n = data.num_steps * data.num_envs
    if starts.ndim != 1 or not (np.issubdtype(starts.dtype, np.integer)):
        raise ValueError(f"starts must be a 1-D integer array, got dtype {starts.dtype} shape {starts.shape}")
    if starts.size == 0:
        raise ValueError("starts must hold at least one start index (no empty axis, [N-12])")
    if horizon > n:
        raise ValueError(f"horizon must be <= envs * steps = {n}, got {horizon}")
    if starts.size and (starts.min() < 0 or starts.max() > n - horizon):
        raise ValueError(f"starts must lie in [0, {n - horizon}] (envs * steps - horizon), got range [{starts.min()}, {starts.max()}]")
    obs = flatten_env_major(data.obs)
    act = flatten_env_major(data.action)
    done = flatten_env_major(data.done)
    idx = starts[:, None] + np.arange(horizon)[None, :]
    chunks = act[idx]
    dchunk = done[idx]
    first = np.where(dchunk.any(axis=1), dchunk.argmax(axis=1), horizon)
    if keep_done_action:
        first = np.minimum(first + 1, horizon)
    valid = np.arange(horizon)[None, :] < first[:, None]
    chunks = np.where(valid[:, :, None], chunks, np.zeros((), chunks.dtype))
    return obs[starts], chunks, valid


def make_training_examples(
    data: ExpertData, horizon: int, cross_env: bool = True, keep_done_action: bool = False
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """All ``(obs, action chunk, valid)`` training examples of one level [K-16]..[K-19].

    Defaults reproduce the public training code: env-major flattening, every
    start ``0 .. E*S - H``, actions zeroed from the first ``done`` on.
    """
    starts = chunk_start_indices(data, horizon, cross_env)
    return make_chunks(data, starts, horizon, keep_done_action)
