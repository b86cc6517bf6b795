"""Fine-tunes recomputed on another CPU model: when they may start new cells of a results folder ([AX-11])."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np

from . import result_files as rf
from .rows import Budget, eval_key, rows_for, train_key
from .tasks import ArmTask


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

    from softrtc._machine import cpu_model

    from .executor import episode_metrics, run_simulated_episode
    from .experiment import _load, read_episodes

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
