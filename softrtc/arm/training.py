"""Training the arm policies: chunk datasets, chapter-T configs, base and fine-tunes ([A-16], [A-20], [T-9])."""

from __future__ import annotations

import math
import os
import tempfile
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import check_out_dir
from softrtc.jax.policy import FlowPolicy
from softrtc.jax.training import TrainConfig, train
from softrtc.reference._validate import check_choice, check_int
from softrtc.reference.weights import SoftWindow as RefSoftWindow

from ._checks import check_number
from .checkpoints import CKPT_FILES, save_arm_checkpoint
from .env import ACTION_DIM, OBS_DIM
from .geometry import _check_env_config
from .features import FEATURE_DIM, Normalizer, _real_array, _rows, policy_features
from .policy_config import TRAIN_METHODS, ArmPolicyConfig, new_model

__all__ = ["chunk_dataset", "arm_train_config", "train_flow_policy", "train_arm_policies"]

# The chapter-T method of each objective ([T-3]).
_OBJECTIVE = {"naive": "none", "train_hard": "hard", "train_soft": "soft"}


def chunk_dataset(data: dict, horizon: int) -> dict:
    """Training pairs (observation, chunk of the next H clean labels) from a demo file's arrays ([A-17]).

    The chunk of row i holds the labels of rows i .. i+H-1 of its episode; past
    the episode's last row the last label is repeated (the arm holds its final
    command), so every row of every episode yields one example. ``obs`` are the
    raw observations; :func:`policy_features` maps them to the policy input.
    """
    horizon = check_int("horizon", horizon, 1, 64)
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
    method = check_choice("method", method, TRAIN_METHODS)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    steps = check_int("steps", steps, 1, 10**7)
    batch_size = check_int("batch_size", batch_size, 1, 1 << 16)
    learning_rate = check_number("learning_rate", learning_rate, 0.0, 1.0, lo_open=True)
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
    seed = check_int("seed", seed, 0, 2**31 - 1)
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
        init = new_model(config, seed)
    elif not isinstance(init, FlowPolicy):
        raise ValueError(f"init must be a FlowPolicy or None, got {type(init).__name__}")
    elif init.config != config.policy_config() or init.obs_dim != FEATURE_DIM:
        raise ValueError("init must have the architecture of config (ArmPolicyConfig.policy_config)")
    data = {"obs": jnp.asarray(obs, jnp.float32), "actions": jnp.asarray(normalizer.act(chunks), jnp.float32)}
    model, losses = train(init, data, tc, jax.random.key(seed), steps, progress=progress)
    return model, losses, tc



# Arrays of a generate_demos file that training reads ([A-16]).
_DEMO_KEYS = ("obs", "action", "episode_start", "episode_length", "seed", "noise_std")


def train_arm_policies(out_dir, episodes: int = 400, steps: int = 4000, finetune_steps: int | None = 800,
                       seed: int = 0, noise_std: float = 0.03, config: ArmPolicyConfig = ArmPolicyConfig(),
                       batch_size: int = 128, learning_rate: float = 1e-3, demos=None,
                       verbose: bool = True, env_config=None, fine_tune: bool = True) -> dict:
    """Demos, base BC policy, then Train Hard / Train Soft RTC fine-tunes, saved to ``out_dir`` ([A-20]).

    Demonstrations: ``generate_demos(episodes, seed, noise_std)`` ([A-15])
    written to a temporary folder that is removed afterwards, or the file
    ``demos`` written by it with those arguments (checked against its stored
    seed and noise level). Only ``base.npz``, ``train_hard.npz`` and
    ``train_soft.npz`` are written to ``out_dir``; nothing there is removed. The base is trained for ``steps`` steps with
    seed ``seed``; each fine-tune starts from the base and runs
    ``finetune_steps`` (``None``: ``steps // 4``) with seed ``seed + 1`` (hard)
    and ``seed + 2`` (soft), learning rate ``learning_rate / 3``. Training is
    :func:`train_flow_policy` ([T-9]). ``env_config`` is the environment the
    demonstrations are recorded in (default: the default :class:`ArmConfig`);
    ``fine_tune=False`` trains and writes the base only. Returns ``{method: path}``.
    """
    from .demos import generate_demos, load_demos

    if not isinstance(out_dir, (str, os.PathLike)):
        raise ValueError(f"out_dir must be a str or PathLike, got {out_dir!r}")
    episodes = check_int("episodes", episodes, 1, 100000)
    steps = check_int("steps", steps, 1, 10**7)
    finetune_steps = max(steps // 4, 1) if finetune_steps is None else check_int("finetune_steps", finetune_steps, 1,
                                                                                   10**7)
    seed = check_int("seed", seed, 0, 2**31 - 3)
    noise_std = check_number("noise_std", noise_std, 0.0, 1.0)
    batch_size = check_int("batch_size", batch_size, 1, 1 << 16)
    learning_rate = check_number("learning_rate", learning_rate, 0.0, 1.0, lo_open=True)
    if not isinstance(config, ArmPolicyConfig):
        raise ValueError(f"config must be an ArmPolicyConfig, got {type(config).__name__}")
    env_config = _check_env_config(env_config, "env_config")
    if not isinstance(fine_tune, bool):
        raise ValueError(f"fine_tune must be a bool, got {fine_tune!r}")
    out = check_out_dir("out_dir", out_dir)
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
            info = generate_demos(episodes, seed, noise_std, str(demo_path), env_config=env_config)
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
    paths = {"naive": save_arm_checkpoint(out / CKPT_FILES["naive"], base, norm, config, "naive", meta, tc)}
    report("naive", losses)
    for i, m in enumerate(("train_hard", "train_soft") if fine_tune else ()):
        # Fine-tuning starts from trained weights: a lower peak rate keeps it from undoing the base.
        ft, losses, tc = train_flow_policy(ds, norm, m, finetune_steps, seed + 1 + i, config=config, init=base,
                                           batch_size=batch_size, learning_rate=learning_rate / 3,
                                           progress=verbose)
        paths[m] = save_arm_checkpoint(out / CKPT_FILES[m], ft, norm, config, m,
                                       {**meta, "finetuned_from": "base"}, tc)
        report(m, losses)
    return paths
