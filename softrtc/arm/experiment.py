"""Controlled arm experiment: methods, shared fine-tunes, paired episodes, resumable runs ([AX-1]..[AX-6]).

Every method row of a task differs from the others only in what is compared:
all fine-tunes start from the task's one shipped base checkpoint ([A-21], [AX-8]) with the
same budget, the same seeds and therefore the same minibatch order and
per-step draws ([T-8]); all episodes of a (task, delay) use the same
environment seeds and sampler keys (paired episodes). Rows that train
identically share their fine-tunes (the key of a fine-tune is its objective
and its training weight table, so ``lam = 1`` and ``L = 0`` are Train Hard
RTC, and a window that ``clip`` and zero padding leave the same is trained
once), and rows that also sample identically share their episodes.

Results are one CSV per cell (row, fine-tuning seed, delay) under
``<out>/<task>/episodes/``; a cell whose file is complete is skipped, so a run
can be stopped and resumed, or run in parts (``--rows``, ``--delays``).
Fine-tuned checkpoints go to a work folder (not results); their digests and
final losses are recorded in ``<out>/<task>/finetunes/<fine-tune>.json``. A
cell's file is named by the row's episode key, seed and delay, so rows that
share episodes find the same file.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from softrtc._machine import cpu_model
from softrtc.reference import endpoints as rep
from softrtc.reference import weights as rw
from softrtc.reference._validate import check_int
from softrtc.reference.methods import check_method_step

from . import result_files as rf
from .tasks import ArmTask, get_task
from .workers import job_runner

__all__ = ["Row", "PAPER_WINDOW", "DEFAULT_WINDOW", "rows_for", "Budget", "BUDGETS", "run_experiment",
           "EPISODE_FIELDS", "read_episodes", "measure_prior_error", "train_key", "eval_key"]

H = 10
# The spec's default window ([W-7]) and the paper's configuration ([W-10]): same rule and schedule,
# zero padding past the overlap as the public evaluation loop does.
DEFAULT_WINDOW = rw.SoftWindow()
PAPER_WINDOW = rw.SoftWindow(rep.delay_scaled(2.0, 5), "linear", "rtc", "zeros")

EPISODE_FIELDS = ("row", "seed", "delay", "episode", "env_seed", "success", "completed", "completion", "steps",
                  "success_step", "D1", "D2", "D3", "boundary", "mean_abs_action", "cpu_model")
# [AX-9] Results are bitwise reproducible on the same CPU model only ([S-15]): every result file records it.
# Files written before it was recorded lack the column or key and still read (empty: unknown).


@dataclasses.dataclass(frozen=True)
class Row:
    """One method row: the checkpoint's objective and window, and the sampler it runs with ([AX-2]).

    ``objective``: ``None`` (the base), ``hard``, ``soft`` or ``prior_noise``
    (the project's variant, [AX-5]); ``window`` the training window (soft
    objectives); ``sampler`` a method of [S-6]; ``sampler_window`` the
    window a ``train_soft`` sampler runs with (default: ``window``);
    ``step`` the training-time sampler's solver step ([S-10], default
    Algorithm 1's); ``num_steps`` the Euler steps T of every chunk (default
    the arm policies' 5, [A-17]; the T sweep of [AX-10] varies it).
    """

    name: str
    label: str
    sampler: str
    objective: str | None = None
    window: rw.SoftWindow | None = None
    sampler_window: rw.SoftWindow | None = None
    tier: str = "main"
    origin: str = "paper"
    step: str = "algorithm1"
    num_steps: int = 5

    def __post_init__(self):
        check_method_step(self.sampler, self.step)
        check_int("num_steps", self.num_steps, 1, 64)

    @property
    def infer_window(self):
        return self.sampler_window if self.sampler_window is not None else self.window


# [AX-10] Euler step counts of the T sweep besides the main rows' T = 5, and the rows it compares at each.
TSWEEP_STEPS = (10, 20)
TIERS = ("main", "sweep", "tsweep")
TSWEEP_ROWS = ("soft2_clip", "soft2_clip_consistent", "train_hard")


def _soft(name, label, window, tier="sweep", origin="paper"):
    return Row(name, label, "train_soft", "soft", window, tier=tier, origin=origin)


def rows_for(task: ArmTask) -> list:
    """The method rows of the experiment: main comparison, cross-evaluations, project variant, sweeps."""
    ds = rep.delay_scaled
    zeros = lambda rule: rw.SoftWindow(rule, "linear", "rtc", "zeros")  # noqa: E731
    clip = lambda rule: rw.SoftWindow(rule, "linear", "rtc", "clip")  # noqa: E731
    rows = [
        Row("naive", "Naive (base)", "naive"),
        Row("inference_hard", "Inference Hard RTC", "inference_hard"),
        Row("inference_soft", "Inference Soft RTC", "inference_soft"),
        Row("train_hard", "Train Hard RTC", "train_hard", "hard"),
        _soft("soft2_clip", "Train Soft RTC lam 2 (clip, spec default)", DEFAULT_WINDOW, "main", "spec"),
        _soft("soft2_zeros", "Train Soft RTC lam 2 (zeros, paper config)", PAPER_WINDOW, "main", "paper"),
        Row("soft2_clip_hard_sampler", "Soft lam 2 (clip) weights, hard sampler", "train_hard", "soft",
            DEFAULT_WINDOW, tier="main", origin="cross"),
        Row("hard_soft_sampler", "Hard weights, soft lam 2 (clip) sampler", "train_soft", "hard", None,
            DEFAULT_WINDOW, tier="main", origin="cross"),
        Row("soft2_clip_prior_noise", "Soft lam 2 (clip) + noisy-prior training (project variant)", "train_soft",
            "prior_noise", DEFAULT_WINDOW, tier="main", origin="project"),
        # The time-consistent solver step ([S-10]) on the same checkpoints ([AX-10]).
        Row("soft2_clip_consistent", "Train Soft RTC lam 2 (clip), consistent step", "train_soft", "soft",
            DEFAULT_WINDOW, tier="main", origin="spec", step="consistent"),
        Row("hard_soft_sampler_consistent", "Hard weights, soft lam 2 (clip) sampler, consistent step", "train_soft",
            "hard", None, DEFAULT_WINDOW, tier="main", origin="cross", step="consistent"),
    ]
    # T sweep ([AX-10]): Algorithm 1, the consistent step and Hard at T = 10, 20 (T = 5 is the main rows').
    for T in TSWEEP_STEPS:
        rows += [Row(f"t{T}_soft2_clip", f"T = {T}: Soft lam 2 (clip), Algorithm 1", "train_soft", "soft",
                     DEFAULT_WINDOW, tier="tsweep", origin="spec", num_steps=T),
                 Row(f"t{T}_soft2_clip_consistent", f"T = {T}: Soft lam 2 (clip), consistent step", "train_soft",
                     "soft", DEFAULT_WINDOW, tier="tsweep", origin="spec", step="consistent", num_steps=T),
                 Row(f"t{T}_train_hard", f"T = {T}: Train Hard RTC", "train_hard", "hard", tier="tsweep",
                     origin="spec", num_steps=T)]
    for lam in (1, 3, 4):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"soft{lam}_{ov}", f"Soft lam {lam} ({ov})", f(ds(float(lam), 5))))
    for h in (3, 5):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"fixed{h}_{ov}", f"Soft fixed h {h} ({ov})", f(rep.fixed(h))))
    for L in range(0, 7):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"offset{L}_{ov}", f"Soft offset L {L} ({ov})", f(rep.offset(L, 8))))
    return rows


def _table(window, s: int, delays) -> np.ndarray:
    return np.stack([rw.soft_weights(H, d, window, s) for d in delays])


def train_key(row: Row, task: ArmTask) -> str | None:
    """The fine-tune a row's checkpoint comes from: objective and training weights ([AX-3]); None for the base."""
    if row.objective is None:
        return None
    delays = range(task.max_delay + 1)
    if row.objective == "hard":
        return "hard"
    table = _table(row.window, task.execute_horizon, delays)
    if np.array_equal(table, np.stack([rw.hard_weights(H, d) for d in delays])) and row.objective == "soft":
        return "hard"
    digest = hashlib.sha256(np.round(table, 12).tobytes()).hexdigest()[:12]
    return f"{row.objective}-{digest}"


def _sampler_table(row: Row, task: ArmTask) -> tuple:
    """The sampler family and its weights at every executable delay (zero padding included, [W-6])."""
    delays = range(task.max_delay + 1)
    if row.sampler == "train_soft":
        t = _table(row.infer_window, task.execute_horizon, delays)
        overflow = row.infer_window.overflow
        # Zero padding only matters where a window token lies past the overlap.
        past = bool(np.any(t[:, H - task.execute_horizon:] > 0))
        return ("train", np.round(t, 12).tobytes(), overflow if past else "clip")
    if row.sampler == "train_hard":
        return ("train", np.round(np.stack([rw.hard_weights(H, d) for d in delays]), 12).tobytes(), "clip")
    return (row.sampler,)


def _sampler_step(row: Row, task: ArmTask) -> str:
    """The solver step as far as it changes a chunk: "algorithm1" unless a training-time sampler has
    window tokens (0 < w < 1) at some executable delay ([S-11])."""
    if row.step == "algorithm1" or not row.sampler.startswith("train_"):
        return "algorithm1"
    t = (_table(row.infer_window, task.execute_horizon, range(task.max_delay + 1)) if row.sampler == "train_soft"
         else np.zeros((1, H)))
    return row.step if bool(np.any((t > 0) & (t < 1))) else "algorithm1"


def eval_key(row: Row, task: ArmTask) -> str:
    """Rows with equal checkpoints and equal samplers produce the same episodes and share them.

    The solver step is part of the key only where it changes a chunk, so the keys of rows with
    Algorithm 1's step (every committed cell) are those they had before steps could be chosen."""
    ident = (train_key(row, task), _sampler_table(row, task))
    step = _sampler_step(row, task)
    ident = ident if step == "algorithm1" else ident + (step,)
    # T enters the key only when it is not the arm policies' 5, so every T = 5 row keeps its key ([AX-10]).
    raw = repr(ident if row.num_steps == 5 else ident + (("T", row.num_steps),)).encode()
    return hashlib.sha256(raw).hexdigest()[:16]


@dataclasses.dataclass(frozen=True)
class Budget:
    """How much a run computes ([AX-4]): seeds, episodes and delays per tier, fine-tune steps."""

    finetune_steps: int = 800
    main_seeds: int = 3
    main_episodes: int = 100
    sweep_seeds: int = 1
    sweep_episodes: int = 50
    prior_episodes: int = 20
    max_steps: int = 1000
    demo_episodes: int = 400
    # None: every sweep row; a tuple names the sweep rows this budget runs.
    sweep_rows: tuple | None = None

    def delays(self, task: ArmTask, tier: str) -> list:
        return tier_delays(task.max_delay, tier)

    def seeds_episodes(self, tier: str) -> tuple:
        """Fine-tuning seeds and episodes per cell of a tier (the T sweep takes the sweep tier's, [AX-10])."""
        return (self.main_seeds, self.main_episodes) if tier == "main" else (self.sweep_seeds, self.sweep_episodes)


def tier_delays(max_delay: int, tier: str) -> list:
    """Delays a tier runs: every executable delay (main), 0 and the two highest (sweep), 0, 2, 4 (T sweep)."""
    if tier == "main":
        return list(range(max_delay + 1))
    if tier == "tsweep":
        return [d for d in (0, 2, 4) if d <= max_delay]
    return [0, max_delay - 1, max_delay]


BUDGETS = {
    "full": Budget(),
    "quick": Budget(finetune_steps=4, main_seeds=1, main_episodes=2, sweep_seeds=1, sweep_episodes=1,
                    prior_episodes=1, max_steps=60, demo_episodes=4,
                    sweep_rows=("soft1_clip", "offset0_zeros", "offset6_clip", "offset6_zeros")),
}


def _fmt(x):
    if isinstance(x, (bool, np.bool_)):
        return int(x)
    if x is None:
        return ""
    if isinstance(x, float):
        return repr(x) if np.isfinite(x) else "nan"
    return x


def _episode_row(name, seed, delay, i, env_seed, rec, metrics) -> dict:
    a = rec.actions[:, 0:3]
    return {"row": name, "seed": seed, "delay": delay, "episode": i, "env_seed": env_seed,
            "success": bool(metrics["success"]), "completed": int(metrics["completed"]),
            "completion": float(metrics["completion"]), "steps": int(rec.steps),
            "success_step": rec.success_step if rec.success else -1,
            **{k: float(metrics[k]) for k in ("D1", "D2", "D3", "boundary")},
            "mean_abs_action": float(np.mean(np.abs(a))) if a.size else float("nan")}


def cpu_models(manifest: dict | None) -> list:
    """Every CPU model that wrote into a results folder: ``manifest``'s (None or a manifest written before they
    were recorded: none) and this machine's ([AX-9])."""
    old = [] if manifest is None else manifest.get("cpu_models", [])
    if not isinstance(old, list) or not all(isinstance(c, str) for c in old):
        raise ValueError(f"manifest['cpu_models'] must be a list of strings, got {old!r}")
    return sorted(set(old) | {cpu_model()})


def read_episodes(path) -> list:
    """Rows of an episode CSV as dicts with typed values (the machine's ``cpu_model`` column, [AX-9], is not read:
    older files lack it)."""
    # [AX-12] A value of the wrong type is an error naming the file, the line and the field.
    return rf.read_episode_rows(path)


# --------------------------------------------------------------------------- policies


def _arm_policy(model, normalizer, task: ArmTask, sampler: str, window, step: str = "algorithm1",
                num_steps: int = 5):
    from softrtc.jax.weights import from_reference

    from .policies import ArmPolicy
    from .policy_config import ArmPolicyConfig

    cfg = ArmPolicyConfig(execute_horizon=task.execute_horizon, num_steps=num_steps)
    return ArmPolicy(model, normalizer, cfg, sampler, window=None if window is None else from_reference(window),
                     env_config=task.env_config, step=step)


def _load(path, task: ArmTask, row: Row):
    from .checkpoints import load_arm_checkpoint

    base = load_arm_checkpoint(path)
    return _arm_policy(base.model, base.normalizer, task, row.sampler,
                       row.infer_window if row.sampler == "train_soft" else None, row.step, row.num_steps)


def _run_cell(args) -> tuple:
    """Worker: the episodes of one cell, written to ``path`` (a temporary name, renamed when complete)."""
    (ckpt, task_name, row, seed, delay, episodes, seed0, key_seed, max_steps, path) = args
    import jax

    from .executor import episode_metrics, run_simulated_episode

    task = get_task(task_name)
    policy = _load(ckpt, task, row)
    t0 = time.perf_counter()
    tmp = str(path) + ".part"
    cpu = cpu_model()  # [AX-9]
    # Episode i depends on i only, so a shorter complete file is the prefix of a longer one: extend it.
    done = []
    if os.path.isfile(path):
        with open(path, newline="") as f:
            done = list(csv.DictReader(f))[:episodes]
    with open(tmp, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=EPISODE_FIELDS)
        w.writeheader()
        for r in done:
            w.writerow(r)
        for i in range(len(done), episodes):
            # Paired episodes: env seed and sampler key depend on the episode index only.
            rec = run_simulated_episode(policy, seed0 + i, delay, jax.random.fold_in(jax.random.key(key_seed), i),
                                        max_steps=max_steps, env_config=task.env_config)
            m = episode_metrics(rec)
            w.writerow({**{k: _fmt(v) for k, v in _episode_row(row.name, seed, delay, i, seed0 + i, rec, m).items()},
                        "cpu_model": cpu})
    os.replace(tmp, path)
    return str(path), time.perf_counter() - t0


# --------------------------------------------------------------------------- prior error


def measure_prior_error(base_ckpt, task: ArmTask, episodes: int, max_steps: int, seed0: int = 50_000) -> dict:
    """Error of the shifted previous chunk against the fresh plan, per delay and token ([AX-5]).

    Runs the base with the naive sampler (which ignores the prior, so the new
    chunk is the fresh plan at the request's observation) for ``episodes``
    calibration episodes per executable delay ``d >= 1`` and returns
    ``{"rms": {d: [o] per-token RMS in normalized action units (mean over the
    4 dims)}, "sigma": [H][A] pooled per token and dim (0 past the overlap)}``.
    """
    import jax

    from .executor import run_simulated_episode
    from softrtc.jax.executor import shift_prior

    row = Row("naive", "", "naive")
    pol = _load(base_ckpt, task, row)
    std = pol.normalizer.act_std
    s, o = task.execute_horizon, H - task.execute_horizon
    rms, pooled = {}, []
    for d in range(1, task.max_delay + 1):
        errs = []
        for i in range(episodes):
            rec = run_simulated_episode(pol, seed0 + i, d, jax.random.key(seed0 + i), max_steps=max_steps,
                                        env_config=task.env_config)
            for c in range(1, len(rec.chunks)):
                y = np.asarray(shift_prior(rec.chunks[c - 1], s))
                errs.append(((rec.chunks[c] - y) / std)[:o])
        e = np.asarray(errs)
        pooled.append(e)
        rms[d] = np.sqrt(np.mean(e ** 2, axis=(0, 2))).tolist() if e.size else [float("nan")] * o
    allv = np.concatenate([p for p in pooled if p.size]) if any(p.size for p in pooled) else np.zeros((1, o, 4))
    sigma = np.zeros((H, 4))
    sigma[:o] = np.sqrt(np.mean(allv ** 2, axis=0))
    return {"rms": {str(k): v for k, v in rms.items()}, "sigma": sigma.tolist(), "episodes": episodes,
            "cpu_model": cpu_model()}  # [AX-9]


# --------------------------------------------------------------------------- fine-tunes


def _demos(work: Path, budget: Budget, task: ArmTask, seed: int = 0):
    from .demos import generate_demos, load_demos
    from .env import ArmConfig

    # Tasks in the default world share one demo file; a task with its own world ([AX-8]) has its own.
    tag = "" if task.env_config == ArmConfig() else f"{task.name}_"
    path = work / f"demos_{tag}{budget.demo_episodes}_{seed}.npz"
    if not path.is_file():
        tmp = work / f"demos_{tag}.part.npz"
        generate_demos(budget.demo_episodes, seed, 0.03, str(tmp), env_config=task.env_config)
        os.replace(tmp, path)
    return load_demos(str(path))


def _finetune(key: str, row: Row, task: ArmTask, seed: int, budget: Budget, data, base, sigma, path: Path) -> dict:
    import jax
    import jax.numpy as jnp

    from softrtc.jax.training import train

    from .checkpoints import save_arm_checkpoint
    from .features import policy_features
    from .training import arm_train_config, chunk_dataset
    from .prior_noise import train_prior_noise

    cfg = base.config.__class__(execute_horizon=task.execute_horizon)
    ds = chunk_dataset(data, H)
    norm = base.normalizer
    method = "train_hard" if key == "hard" else "train_soft"
    tc = arm_train_config(method, cfg, budget.finetune_steps, learning_rate=1e-3 / 3)
    if method == "train_soft":
        tc = dataclasses.replace(tc, window=row.window)
    obs = jnp.asarray(norm.obs(policy_features(ds["obs"])), jnp.float32)
    act = jnp.asarray(norm.act(ds["chunks"]), jnp.float32)
    t0 = time.perf_counter()
    k = jax.random.key(seed)
    if row.objective == "prior_noise":
        model, losses = train_prior_noise(base.model, obs, act, tc, k, budget.finetune_steps, np.asarray(sigma))
    else:
        model, losses = train(base.model, {"obs": obs, "actions": act}, tc, k, budget.finetune_steps, progress=True)
    save_arm_checkpoint(path, model, norm, cfg, method, {"experiment_key": key, "seed": seed}, tc)
    digest = hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    return {"key": key, "seed": seed, "cpu_model": cpu_model(),  # [AX-9]
            "steps": budget.finetune_steps, "final_loss": float(np.mean(losses[-20:])),
            "seconds": round(time.perf_counter() - t0, 1), "sha256_16": digest,
            "window": None if row.window is None or key == "hard" else row.window.to_dict()}


# --------------------------------------------------------------------------- recomputed fine-tunes

# [AX-11] Episodes a recomputed fine-tune replays from a committed cell before its new cells may run, and how
# many of them may end otherwise (a long episode that diverges from a last-bit difference, [AX-9]).
REPLAY_EPISODES = 10
REPLAY_MAY_DIFFER = 1


def _finite(x):
    x = float(x)
    return x if np.isfinite(x) else None


def _by_finetune(todo) -> dict:
    """``{(train key, seed): [cell args]}`` of the cells to run that need a fine-tuned checkpoint."""
    out = {}
    for (r, sd, key, args) in todo:
        if key is not None:
            out.setdefault((key, sd), []).append(args)
    return out


def _check_recorded(out_dir: Path, task: ArmTask, budget: Budget, key: str, sd: int, cells, seed0: int,
                    key_seed: int, log) -> None:
    """A checkpoint whose digest differs from the one its folder records may only start new cells ([AX-11]).

    Another CPU model (or BLAS build) gives a fine-tune that differs in the last bits ([AX-9]). Its new
    cells are then compared with the folder's cells of the recorded checkpoint, so before they run the
    checkpoint replays the first ``REPLAY_EPISODES`` episodes of a committed cell of the same fine-tune
    (a row with Algorithm 1's sampler, highest delay): all but ``REPLAY_MAY_DIFFER`` of them must end with
    the same success and the same number of steps, else the run stops. The replay is recorded in
    ``finetunes/<tag>.recomputed.json`` with the cells the checkpoint started (``cells``); a partly
    written cell not among them came from the recorded checkpoint and is refused, since extending it
    would mix two policies in one cell.
    """
    tag = f"{key}_seed{sd}"
    rec_path = out_dir / "finetunes" / f"{tag}.json"
    ckpt = Path(cells[0][0])
    if not rec_path.is_file() or not ckpt.is_file():
        return
    digest = hashlib.sha256(ckpt.read_bytes()).hexdigest()[:16]
    recorded = rf.check_finetune(rf.read_json(rec_path, "fine-tune record"), rec_path)["sha256_16"]  # [AX-12]
    if digest == recorded:
        return
    names = [Path(c[-1]).name for c in cells]
    done_path = out_dir / "finetunes" / f"{tag}.recomputed.json"
    prev = rf.read_json(done_path, "recomputed fine-tune record") if done_path.is_file() else None
    prev = prev if isinstance(prev, dict) and prev.get("sha256_16") == digest else None
    # Cells this checkpoint started may be extended; any other partly written cell came from the recorded one.
    mine = set(prev.get("cells", [])) if prev is not None else set()
    partial = [n for n, c in zip(names, cells) if Path(c[-1]).is_file() and n not in mine]
    if partial:
        raise ValueError(f"fine-tune {tag} is checkpoint {digest}, but {rec_path} records {recorded}: its cells "
                         f"{partial} came from the recorded one; extending them would mix two policies; use "
                         "another --out")
    from softrtc._files import write_json
    if prev is not None:
        if not set(names) <= mine:
            write_json(done_path, dict(prev, cells=sorted(mine | set(names))))
        return
    import jax

    from .executor import episode_metrics, run_simulated_episode
    from softrtc._machine import cpu_model

    ep_dir = out_dir / "episodes"
    d = task.max_delay
    ref = next((r for r in rows_for(task) if train_key(r, task) == key and r.step == "algorithm1"
                and r.num_steps == 5 and (ep_dir / f"{eval_key(r, task)}_s{sd}_d{d}.csv").is_file()), None)
    if ref is None:
        raise ValueError(f"fine-tune {tag} is checkpoint {digest}, but {rec_path} records {recorded}, and no "
                         f"committed cell of it at d = {d} can be replayed to compare them; use another --out")
    old = read_episodes(ep_dir / f"{eval_key(ref, task)}_s{sd}_d{d}.csv")[:REPLAY_EPISODES]
    policy = _load(ckpt, task, ref)
    log(f"[{task.name}] fine-tune {tag}: checkpoint {digest} differs from the recorded {recorded}; replaying "
        f"{len(old)} episodes of `{ref.name}` at d = {d}")
    replay = []
    for e in old:
        i = e["episode"]
        rec = run_simulated_episode(policy, seed0 + i, d, jax.random.fold_in(jax.random.key(key_seed), i),
                                    max_steps=budget.max_steps, env_config=task.env_config)
        m = episode_metrics(rec)
        replay.append({"episode": i, "success": [e["success"], int(m["success"])], "steps": [e["steps"], rec.steps],
                       "D2": [_finite(e["D2"]), _finite(m["D2"])]})
    same = sum(r["success"][0] == r["success"][1] and r["steps"][0] == r["steps"][1] for r in replay)
    out = {"key": key, "seed": sd, "sha256_16": digest, "recorded_sha256_16": recorded, "cpu_model": cpu_model(),
           "replayed_row": ref.name, "delay": d, "episodes": len(replay), "same_success_and_steps": same,
           "max_abs_D2_difference": max((abs(r["D2"][0] - r["D2"][1]) for r in replay
                                         if None not in r["D2"]), default=None), "replay": replay,
           "cells": sorted(names)}
    if same < len(replay) - REPLAY_MAY_DIFFER:
        raise ValueError(f"fine-tune {tag}: checkpoint {digest} replays {same} of {len(replay)} committed episodes "
                         f"of `{ref.name}` with the same success and steps; its cells would not be comparable with "
                         "the folder's; use another --out")
    write_json(done_path, out)


# --------------------------------------------------------------------------- driver


def run_experiment(task_name: str = "drift", budget_name: str = "full", out="results/arm", work="arm_experiment_work",
                   rows=None, delays=None, seeds=None, tiers=("main", "sweep", "tsweep"), workers: int = 2,
                   episodes: int | None = None, seed0: int = 10_000, key_seed: int = 0, log=print) -> dict:
    """Run (or resume) the experiment of ``task_name`` under a budget; returns a summary of what ran.

    ``rows`` restricts to named rows, ``delays`` to some delays, ``seeds`` to
    some fine-tuning seeds (1-based indices), ``tiers`` to ``main``, ``tsweep`` and/or
    ``sweep``; ``episodes`` caps the episodes per cell below the budget's (a
    later run with more extends the cells). Complete cells are never recomputed.
    """

    task = get_task(task_name)
    if budget_name not in BUDGETS:
        raise ValueError(f"budget must be one of {tuple(BUDGETS)}, got {budget_name!r}")
    budget = BUDGETS[budget_name]
    if episodes is not None and (isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1):
        raise ValueError(f"episodes must be an integer >= 1 or None, got {episodes!r}")
    if isinstance(workers, bool) or not isinstance(workers, int) or not 1 <= workers <= 64:
        raise ValueError(f"workers must be an integer in [1, 64], got {workers!r}")
    all_rows = rows_for(task)
    names = [r.name for r in all_rows]
    if rows is not None:
        bad = [r for r in rows if r not in names]
        if bad:
            raise ValueError(f"rows must be among {names}, got {bad}")
    if delays is not None and any(isinstance(d, bool) or not isinstance(d, int) or not 0 <= d <= task.max_delay
                                  for d in delays):
        raise ValueError(f"delays must be integers in [0, {task.max_delay}], got {delays}")
    # [AX-4] Fine-tuning seeds are 1-based and bounded by the budget: a seed outside would select no fine-tune
    # and leave its rows out of the run without notice.
    n_seeds = max(budget.main_seeds, budget.sweep_seeds)
    if seeds is not None and any(isinstance(sd, bool) or not isinstance(sd, int) or not 1 <= sd <= n_seeds
                                 for sd in seeds):
        raise ValueError(f"seeds must be integers in [1, {n_seeds}] (the {budget_name} budget's fine-tuning "
                         f"seeds), got {seeds}")
    bad_tiers = [t for t in tiers if t not in TIERS]
    if bad_tiers:
        raise ValueError(f"tiers must be among {TIERS}, got {bad_tiers}")
    selected = [r for r in all_rows if (rows is None or r.name in rows) and r.tier in tiers
                and (r.tier == "main" or budget.sweep_rows is None or r.name in budget.sweep_rows)]
    out_dir = Path(out) / task.name
    ep_dir = out_dir / "episodes"
    ep_dir.mkdir(parents=True, exist_ok=True)
    work_dir = Path(work) / task.name / budget_name
    work_dir.mkdir(parents=True, exist_ok=True)
    from .checkpoints import load_arm_checkpoint

    # Every fine-tune of a task starts from the task's base ([AX-3], [AX-8]).
    base_path = task.base_checkpoint()
    if not base_path.is_file():
        raise ValueError(f"task {task.name!r} has no base checkpoint at {base_path}")
    manifest_path = out_dir / "manifest.json"
    manifest = {"task": task.name, "execute_horizon": task.execute_horizon, "H": H, "budget": budget_name,
                "budget_values": dataclasses.asdict(budget), "seed0": seed0, "key_seed": key_seed,
                "base_sha256_16": hashlib.sha256(base_path.read_bytes()).hexdigest()[:16],
                "rows": {r.name: {"label": r.label, "sampler": r.sampler, "objective": r.objective, "tier": r.tier,
                                  "origin": r.origin, "train_key": train_key(r, task), "eval_key": eval_key(r, task),
                                  "window": None if r.window is None else r.window.to_dict(),
                                  "sampler_window": None if r.infer_window is None else r.infer_window.to_dict(),
                                  # [S-10] named only when not Algorithm 1's, so older manifests read the same
                                  **({} if r.step == "algorithm1" else {"step": r.step})}
                         for r in all_rows},
                "order": [r.name for r in all_rows]}
    # Compared as JSON: tuples come back from the file as lists.
    manifest = json.loads(json.dumps(manifest))
    # [AX-12] A half-written manifest names itself, not only a JSON position.
    old = rf.check_manifest(rf.read_json(manifest_path, "manifest"), manifest_path) if manifest_path.is_file() \
        else None
    manifest["cpu_models"] = cpu_models(old)
    if old is not None:
        if old.get("budget_values") != manifest["budget_values"] or old.get("base_sha256_16") != \
                manifest["base_sha256_16"] or old.get("seed0") != seed0 or old.get("key_seed") != key_seed:
            raise ValueError(f"{manifest_path} was written with another budget, base or seeds; use another --out")
    manifest_path.write_text(json.dumps(manifest, indent=1, sort_keys=True) + "\n")

    # Prior error of the base (the project's variant trains with it, [AX-5]).
    prior_path = out_dir / "prior_error.json"
    if not prior_path.is_file():
        log(f"[{task.name}] measuring the prior error on {budget.prior_episodes} episodes per delay")
        pe = measure_prior_error(base_path, task, budget.prior_episodes, budget.max_steps)
        prior_path.write_text(json.dumps(pe, indent=1) + "\n")
    sigma = rf.check_prior(rf.read_json(prior_path, "prior error"), prior_path)["sigma"]

    # Cells first: a fine-tune runs only when a cell that needs its checkpoint is incomplete, so a
    # complete results folder (e.g. a fresh clone's committed one) costs no fine-tuning.
    jobs = []
    for r in selected:
        key = train_key(r, task)
        n_seeds = budget.seeds_episodes(r.tier)[0]
        seed_list = list(range(1, n_seeds + 1)) if key is not None else [0]
        if seeds is not None:
            seed_list = [s for s in seed_list if s in seeds or key is None]
        for sd in seed_list:
            ckpt = base_path if key is None else work_dir / f"{key}_seed{sd}.npz"
            n_eps = budget.seeds_episodes(r.tier)[1]
            n_eps = n_eps if episodes is None else min(n_eps, episodes)
            for d in budget.delays(task, r.tier):
                if delays is not None and d not in delays:
                    continue
                path = ep_dir / f"{eval_key(r, task)}_s{sd}_d{d}.csv"
                jobs.append((r, sd, d, n_eps, path, ckpt, key))
    # Rows that share an eval key share their episodes: run each file once.
    todo, seen = [], set()
    for (r, sd, d, n, path, ckpt, key) in jobs:
        if path in seen or (path.is_file() and len(read_episodes(path)) >= n):
            continue
        seen.add(path)
        todo.append((r, sd, key, (str(ckpt), task.name, r, sd, d, n, seed0, key_seed, budget.max_steps, str(path))))

    # Fine-tunes, one per (train key, seed), shared by every row with that key.
    base = None
    data = None
    for (r, sd, key, args) in todo:
        ckpt = Path(args[0])
        tag = f"{key}_seed{sd}"
        rec_path = out_dir / "finetunes" / f"{tag}.json"
        # [AX-13] A checkpoint is reused only with its record; without one it is fine-tuned again (the same
        # checkpoint on the same CPU model, [AX-9]) and its record rewritten, its digest checked against the
        # checkpoint it replaces.
        if key is None or (ckpt.is_file() and rec_path.is_file()):
            continue
        recorded = rf.check_finetune(rf.read_json(rec_path, "fine-tune record"), rec_path)["sha256_16"] \
            if rec_path.is_file() else hashlib.sha256(ckpt.read_bytes()).hexdigest()[:16] if ckpt.is_file() \
            else None
        source = str(rec_path) if rec_path.is_file() else f"the checkpoint {ckpt} it replaces"
        if base is None:
            base = load_arm_checkpoint(base_path)
            data = _demos(Path(work), budget, task)
        log(f"[{task.name}] fine-tune {tag} ({r.name}, {budget.finetune_steps} steps)")
        # One file per fine-tune: runs in parts may fine-tune in parallel processes.
        rec = _finetune(key, r, task, sd, budget, data, base, sigma, ckpt)
        if recorded is not None and recorded != rec["sha256_16"]:
            # The folder's episodes of this fine-tune came from another checkpoint (another machine's
            # floating point, or changed code): extending them would mix two policies in one cell.
            ckpt.unlink()
            raise ValueError(f"fine-tune {tag} gave checkpoint {rec['sha256_16']}, but {source} records "
                             f"{recorded}: its episodes in {out_dir} came from another checkpoint; use another --out")
        rec_path.parent.mkdir(exist_ok=True)
        rec_path.write_text(json.dumps(rec, indent=1, sort_keys=True) + "\n")
    for (key, sd), cells in sorted(_by_finetune(todo).items()):
        _check_recorded(out_dir, task, budget, key, sd, cells, seed0, key_seed, log)
    todo = [args for (_, _, _, args) in todo]
    log(f"[{task.name}] {len(jobs)} cells, {len(todo)} to run with {workers} worker(s)")
    t0 = time.perf_counter()
    done = 0
    if todo:
        # [AX-13] SIGTERM, SIGINT or an error ends every worker before the run exits.
        with job_runner(workers) as run:
            for p, secs in run(_run_cell, todo):
                done += 1
                log(f"[{task.name}] {done}/{len(todo)} {Path(p).name} ({secs:.0f} s, "
                    f"{time.perf_counter() - t0:.0f} s elapsed)")
    return {"cells": len(jobs), "ran": len(todo), "seconds": time.perf_counter() - t0}
