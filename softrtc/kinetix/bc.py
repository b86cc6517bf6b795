"""Behaviour cloning of the base flow policy from expert data ([KP-11], [KP-12]).

The examples of [K-16]..[K-19] (release chunking, actions zeroed from the first
``done`` on) train a fresh :class:`~softrtc.jax.policy.FlowPolicy` with the
plain flow-matching loss (``TrainConfig(method="none")``) under the release's
optimiser settings: AdamW, learning rate 3e-4 after a linear warm-up of 1000
steps, weight decay 1e-2, global-norm clipping at 10, batch 512. An epoch
draws a fresh permutation of the examples (key ``fold_in(data key, epoch)``),
truncated to whole batches; step ``i`` uses ``fold_in(step key, i)``.

After every epoch the policy is written in the release's layout,
``<out>/<epoch>/policies/worlds_l_<level>.pkl`` (a pickled pure dict, [P-8]),
readable by ``softrtc kinetix eval --policy-dir <out>`` and ``finetune --bc``;
the curve ``curve_worlds_l_<level>.csv`` / ``.png`` gets a row; and
``resume_worlds_l_<level>.npz`` holds what the next epoch needs, so an
interrupted run continues bitwise where it stopped ([KP-12]).
"""

from __future__ import annotations

import math
import os
import pickle
import sys
import time
from pathlib import Path
from typing import Callable

import flax.nnx as nnx
import jax
import numpy as np
from tqdm.auto import tqdm

from softrtc._files import check_out_dir, write_atomic
from softrtc.jax.params import state_pure_dict
from softrtc.jax.policy import FlowPolicy, PolicyConfig
from softrtc.jax.training import TrainConfig, make_train_step
from softrtc.reference._validate import check_int

from . import data as kdata
from . import env as kenv
from .curves import plot_curves, write_curve_csv
from .resume import load_state, save_state

__all__ = ["BC_CURVE_FIELDS", "bc_train_config", "train_bc"]

BC_CURVE_FIELDS = ("epoch", "steps", "examples", "loss", "loss_last", "wall_s")


def bc_train_config(batch_size: int = 512, learning_rate: float = 3e-4, warmup_steps: int = 1000) -> TrainConfig:
    """The release's behaviour-cloning optimiser ([KP-11]) as a :class:`TrainConfig` of method ``none``."""
    return TrainConfig(method="none", execute_horizon=None, batch_size=batch_size, learning_rate=learning_rate,
                       weight_decay=1e-2, grad_clip_norm=10.0, warmup_steps=warmup_steps)


def train_bc(data_dir: str | os.PathLike, level: str, out_dir: str | os.PathLike, *, epochs: int = 32,
             policy_config: PolicyConfig | None = None, batch_size: int = 512, learning_rate: float = 3e-4,
             warmup_steps: int = 1000, seed: int = 0, resume: bool = True, progress: bool = True,
             clock: Callable[[], float] = time.monotonic) -> dict:
    """Train (or continue) the base policy of ``level`` for ``epochs`` epochs ([KP-11], [KP-12])."""
    kenv.check_level_name(level, "level")
    epochs = check_int("epochs", epochs, 1, 100000)
    seed = check_int("seed", seed, 0, 2**32 - 1)
    policy_config = PolicyConfig() if policy_config is None else policy_config
    if not isinstance(policy_config, PolicyConfig):
        raise ValueError(f"policy_config must be a PolicyConfig, got {type(policy_config).__name__}")
    if not isinstance(resume, bool) or not isinstance(progress, bool):
        raise ValueError("resume and progress must be bools")
    out = check_out_dir("out_dir", out_dir)
    data_path = Path(data_dir) / kdata.expert_data_filename(level)
    if not data_path.is_file():
        raise FileNotFoundError(f"data_dir {data_dir} has no {data_path.name}")
    data = kdata.load_expert_data(data_path)
    H = policy_config.action_chunk_size
    obs, chunks, _ = kdata.make_training_examples(data, H)
    obs, chunks = obs.astype(np.float32), chunks.astype(np.float32)
    n = obs.shape[0]
    bs = min(check_int("batch_size", batch_size, 1, 1 << 20), n)
    per_epoch = n // bs
    config = bc_train_config(bs, learning_rate, warmup_steps)
    policy = FlowPolicy(obs_dim=data.obs_dim, action_dim=data.action_dim, config=policy_config,
                        rngs=nnx.Rngs(seed))
    step = make_train_step(policy, config)
    state = step.init_state()
    k_data, k_steps = jax.random.split(jax.random.key(seed))
    name = f"worlds_l_{level}"
    resume_path, csv_path = out / f"resume_{name}.npz", out / f"curve_{name}.csv"
    meta = {"level": level, "seed": seed, "policy_config": policy_config.__dict__, "batch_size": bs,
            "learning_rate": learning_rate, "warmup_steps": warmup_steps, "examples": n,
            "data_file": str(data_path)}
    rows: list = []
    first_epoch = 0
    if resume and resume_path.is_file():
        state, saved = load_state(resume_path, state, "this policy and optimiser")
        if {k: saved.get(k) for k in meta if k != "data_file"} != {k: meta[k] for k in meta if k != "data_file"}:
            raise ValueError(f"resume file {resume_path} was written for another level, seed, policy or optimiser; "
                             f"use another --out or resume=False")
        rows, first_epoch = saved["rows"], int(saved["epochs_done"])
    out.mkdir(parents=True, exist_ok=True)
    wall0 = float(rows[-1]["wall_s"]) if rows else 0.0
    t0 = clock()
    with tqdm(total=epochs * per_epoch, initial=min(first_epoch, epochs) * per_epoch, unit="step",
              desc=f"train-bc {level}", disable=not progress, file=sys.stderr) as bar:
        for epoch in range(first_epoch, epochs):
            perm = np.asarray(jax.random.permutation(jax.random.fold_in(k_data, epoch), n))
            losses = []
            for b in range(per_epoch):
                idx = perm[b * bs:(b + 1) * bs]
                i = epoch * per_epoch + b
                state, m = step.jitted(state, obs[idx], chunks[idx], jax.random.fold_in(k_steps, i))
                losses.append(m["loss"])
                bar.update(1)
            losses = np.asarray(jax.device_get(losses), np.float64)
            rows.append({"epoch": epoch + 1, "steps": (epoch + 1) * per_epoch, "examples": n,
                         "loss": float(losses.mean()), "loss_last": float(losses[-1]),
                         "wall_s": round(wall0 + clock() - t0, 3)})
            pol_path = out / str(epoch + 1) / "policies" / f"{name}.pkl"
            pol_path.parent.mkdir(parents=True, exist_ok=True)
            pure = jax.tree.map(np.asarray, state_pure_dict(step.policy(state)))
            blob = pickle.dumps(pure)
            write_atomic(pol_path, lambda f: f.write(blob), binary=True)
            write_curve_csv(csv_path, rows, BC_CURVE_FIELDS)
            save_state(resume_path, state, dict(meta, rows=rows, epochs_done=epoch + 1))
            bar.set_postfix_str(f"loss {rows[-1]['loss']:.4g}")
    plot_curves(csv_path, out / f"curve_{name}.png", x="epoch", ys=("loss",), title=f"behaviour cloning, {level}")
    return {"level": level, "epochs": len(rows), "examples": n, "steps_per_epoch": per_epoch,
            "final_loss": rows[-1]["loss"] if rows else math.nan, "policy": str(out / str(len(rows)) / "policies"
                                                                                   / f"{name}.pkl"),
            "curve_csv": str(csv_path)}
