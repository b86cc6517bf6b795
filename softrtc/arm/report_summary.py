"""Summaries of the arm experiment's result files: per row, delay and scope, bootstrap statistics and
paired tests against Train Hard RTC ([AX-6], [AX-7]).

:func:`load_results` reads a task folder (``manifest.json``, ``episodes/*.csv``,
``prior_error.json``, ``finetunes``); :func:`summarize` turns it into the
numbers the verdicts, tables and plots of :mod:`softrtc.arm.report` quote.
Deterministic: every bootstrap uses seed 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from . import result_files as rf
from .experiment import H
from .paired_stats import cluster_bootstrap, paired_difference, sign_flip_test

__all__ = ["load_results", "summarize", "METRICS", "RESAMPLES"]

METRICS = ("success", "completion", "D1", "D2", "D3", "boundary", "mean_abs_action", "D2_success", "D2_failure")
RESAMPLES = 2000
# Sign patterns drawn per sign-flip test ([AX-7]); 5000 resolve p down to 2e-4, below Holm's smallest threshold
# for the report's per-delay families.
PERMUTATIONS = 5000
# Derived metrics: D2 of the successful and of the failed episodes only (NaN for the others), so the jerk of a
# row is not confounded with how often it fails ([AX-7]).
_SPLIT = {"D2_success": ("D2", 1.0), "D2_failure": ("D2", 0.0)}


def load_results(folder) -> dict:
    """``{"manifest", "cells": {(row, seed, delay): [episode dicts]}, "prior", "finetunes"}`` of a task folder.

    Every file is checked as it is read ([AX-12], :mod:`softrtc.arm.result_files`): a damaged one is a
    ValueError naming it, never a changed report.
    """
    folder = Path(folder)
    if not (folder / "manifest.json").is_file():
        raise ValueError(f"folder must hold an arm experiment's results (manifest.json), got {str(folder)!r}")
    manifest = rf.check_manifest(rf.read_json(folder / "manifest.json", "manifest"), folder / "manifest.json")
    # Cells from the episode files themselves (``<eval key>_s<seed>_d<delay>.csv``): every row whose eval key
    # names a file has that cell, so rows that share episodes ([AX-3]) share them here too.
    by_key = {}
    for f in sorted((folder / "episodes").glob("*.csv")):
        episodes = rf.check_episode_file(f, rf.read_episode_rows(f), manifest)
        key, seed, delay = f.stem.rsplit("_", 2)
        by_key.setdefault(key, []).append((int(seed[1:]), int(delay[1:]), episodes))
    cells = {}
    for row, info in manifest["rows"].items():
        for seed, delay, episodes in by_key.get(info["eval_key"], []):
            cells[(row, seed, delay)] = episodes
    prior_path = folder / "prior_error.json"
    prior = rf.check_prior(rf.read_json(prior_path, "prior error"), prior_path) if prior_path.is_file() else None
    ft = rf.read_json(folder / "finetunes.json", "fine-tune records") if (folder / "finetunes.json").is_file() else {}
    if not isinstance(ft, dict):
        raise ValueError(f"fine-tune records {str(folder / 'finetunes.json')!r} must hold a JSON object")
    for tag, rec in ft.items():
        rf.check_finetune(rec, f"{folder / 'finetunes.json'}: {tag}")
    recomputed = {}
    for f in sorted((folder / "finetunes").glob("*.json")):
        # ``<tag>.recomputed.json``: a checkpoint recomputed on another CPU model and its replay check ([AX-11]).
        if f.name.endswith(".recomputed.json"):
            recomputed[f.name[:-len(".recomputed.json")]] = rf.read_json(f, "recomputed fine-tune record")
        else:
            ft[f.stem] = rf.check_finetune(rf.read_json(f, "fine-tune record"), f)
    mech = folder / "mechanism.json"
    return {"manifest": manifest, "cells": cells, "prior": prior, "finetunes": ft, "folder": str(folder),
            "recomputed": recomputed, "mechanism": rf.read_json(mech, "mechanism record") if mech.is_file() else None}


def _seeds(res, row):
    return sorted({s for (r, s, d) in res["cells"] if r == row})


def _matrix(res, row, delays, metric, seeds=None):
    """``[seeds, delays x episodes]`` of a metric (NaN where undefined); None when a delay is missing.

    ``seeds`` restricts the rows to those fine-tuning seeds (the base's seed 0 is kept whatever it says).
    """
    seeds = _seeds(res, row) if seeds is None or _seeds(res, row) == [0] else \
        [s for s in _seeds(res, row) if s in seeds]
    if not seeds:
        return None
    # A seed counts for a scope only when it ran every delay of it with the same episodes as the others.
    seeds = [s for s in seeds if all((row, s, d) in res["cells"] for d in delays)]
    if not seeds:
        return None
    n = min(len(res["cells"][(row, s, d)]) for s in seeds for d in delays)
    mats = []
    for s in seeds:
        parts = []
        for d in delays:
            eps = sorted(res["cells"][(row, s, d)], key=lambda e: e["episode"])[:n]
            if metric in _SPLIT:
                base, want = _SPLIT[metric]
                parts.append([float(e[base]) if float(e["success"]) == want else float("nan") for e in eps])
            else:
                parts.append([float(e[metric]) for e in eps])
        mats.append(np.concatenate(parts))
    return np.stack(mats)


def _delays_of(res, row):
    return sorted({d for (r, s, d) in res["cells"] if r == row})


def summarize(res) -> dict:
    """Per row: per delay, ``overall`` (every delay run) and ``high`` (two highest delays) stats of each metric.

    Each value is ``{"mean", "lo", "hi", "n"}`` (bootstrap over seeds and
    episodes); each row also has ``seeds`` and ``episodes`` (per delay), and
    ``vs_hard``: paired tests against ``train_hard`` where both ran: the
    paired bootstrap interval of the difference, and ``p_perm``, the
    sign-flip test with the environment seed as the unit (episodes of one env
    seed are not independent across fine-tuning seeds, [AX-7]).
    """
    max_d = res["manifest"]["execute_horizon"]
    max_d = min(max_d, H - max_d)
    high = [max_d - 1, max_d]
    out = {}
    done = {}
    for row, info in _rows_in_order(res["manifest"]):
        # Rows with one eval key read the same episode files ([AX-3]): their statistics are equal.
        shared = (info.get("eval_key"), row == "train_hard")
        if shared[0] is not None and shared in done:
            out[row] = done[shared]
            continue
        ds = _delays_of(res, row)
        if not ds:
            continue
        # Seeds that ran every delay of the row; the others still count in the scopes they complete.
        seeds = [s for s in _seeds(res, row) if all((row, s, d) in res["cells"] for d in ds)] or _seeds(res, row)
        n_eps = min(len(res["cells"][(row, s, d)]) for s in seeds for d in ds if (row, s, d) in res["cells"])
        entry = {"delays": ds, "seeds": len(seeds), "episodes": n_eps, "per_delay": {}, "scopes": {}, "vs_hard": {}}
        scopes = {f"d{d}": [d] for d in ds}
        scopes["overall"] = ds
        if all(d in ds for d in high):
            scopes["high"] = high
        for scope, dl in scopes.items():
            stats = {}
            for m in METRICS:
                mat = _matrix(res, row, dl, m)
                if mat is not None:
                    stats[m] = cluster_bootstrap(mat, RESAMPLES, 0)
            entry["scopes"][scope] = stats
            if row != "train_hard" and any(r == "train_hard" for (r, s, d) in res["cells"]):
                tests = {}
                # Fine-tuned rows pair seed by seed: only the seeds both ran (the base pairs with every seed).
                common = [x for x in _seeds(res, row) if x in _seeds(res, "train_hard")] or None
                for m in METRICS:
                    a, b = _matrix(res, row, dl, m, common), _matrix(res, "train_hard", dl, m, common)
                    if a is None or b is None or a.shape[1] != b.shape[1] or \
                            (a.shape[0] != b.shape[0] and 1 not in (a.shape[0], b.shape[0])):
                        continue
                    tests[m] = paired_difference(a, b, RESAMPLES, 0)
                    tests[m]["p_perm"] = sign_flip_test(a, b, PERMUTATIONS, 0)["p"]
                entry["vs_hard"][scope] = tests
        out[row] = done[shared] = entry
    return out


def _rows_in_order(manifest):
    """``(name, info)`` of every row in the experiment's order (the manifest stores it)."""
    return [(r, manifest["rows"][r]) for r in manifest.get("order", sorted(manifest["rows"]))]


def _get(summary, row, scope, metric):
    return summary.get(row, {}).get("scopes", {}).get(scope, {}).get(metric)


def _vs(summary, row, scope, metric):
    return summary.get(row, {}).get("vs_hard", {}).get(scope, {}).get(metric)
