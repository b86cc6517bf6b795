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

from . import result_files as rf
from .recomputed import _by_finetune, _check_recorded
from .rows import (BUDGETS, DEFAULT_WINDOW, H, PAPER_WINDOW, TIERS, TSWEEP_ROWS, TSWEEP_STEPS, Budget, Row,  # noqa: F401
                   _sampler_step, _sampler_table, _soft, _table, eval_key, rows_for, tier_delays, train_key)
from .tasks import ArmTask, get_task
from .workers import job_runner

# Rows, keys and budgets live in rows.py ([AX-2]..[AX-4]); re-exported here, where the experiment's users find them.
__all__ = ["Row", "PAPER_WINDOW", "DEFAULT_WINDOW", "rows_for", "Budget", "BUDGETS", "run_experiment",
           "EPISODE_FIELDS", "read_episodes", "measure_prior_error", "train_key", "eval_key", "tier_delays", "H",
           "TIERS", "TSWEEP_STEPS", "TSWEEP_ROWS"]

EPISODE_FIELDS = ("row", "seed", "delay", "episode", "env_seed", "success", "completed", "completion", "steps",
                  "success_step", "D1", "D2", "D3", "boundary", "mean_abs_action", "cpu_model")
# [AX-9] Results are bitwise reproducible on the same CPU model only ([S-15]): every result file records it.
# Files written before it was recorded lack the column or key and still read (empty: unknown).


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
