"""Per-level and pooled results of the Kinetix evaluation, the main table and the CSV files ([M-4], [M-5], [M-7], [KE-7], [KE-8])."""

from __future__ import annotations

import csv
import math
import numbers
import os
from pathlib import Path
from typing import Iterable, Mapping, Sequence

import numpy as np

from softrtc._files import check_out_dir
from softrtc.reference import metrics as ref_metrics
from softrtc.reference._validate import check_int

from .methods import parse_method
from .protocol import HIGH_DELAYS

__all__ = ["METRICS", "SCOPES", "summarize", "main_table", "write_results"]

METRICS = ("return", "solved", "delta", "jerk")
SCOPES = ("overall", "high")


def _check_rows(rows: list) -> None:
    """Episode rows of :func:`evaluate` ([KE-8]): str method/level, int delay, real metric values."""
    need = ("method", "level", "delay", *METRICS)
    for i, r in enumerate(rows):
        if not isinstance(r, Mapping) or any(k not in r for k in need):
            raise ValueError(f"rows[{i}] must be a mapping with keys {list(need)} (an episode row of evaluate), "
                             f"got {r if not isinstance(r, Mapping) else sorted(map(str, r))}")
        for k in ("method", "level"):
            if not isinstance(r[k], str) or not r[k]:
                raise ValueError(f"rows[{i}][{k!r}] must be a non-empty string, got {r[k]!r}")
        check_int(f"rows[{i}]['delay']", r["delay"], 0, 4096)
        for k in METRICS:
            v = r[k]
            ok = isinstance(v, (numbers.Real, np.bool_)) and not isinstance(v, np.datetime64)
            if k != "solved" and isinstance(v, (bool, np.bool_)):
                ok = False
            if ok and k in ("return", "solved") and not math.isfinite(float(v)):
                ok = False
            if not ok:
                what = "a bool or 0/1 number" if k == "solved" else (
                    "a finite real number" if k == "return" else "a real number (NaN when undefined)")
                raise ValueError(f"rows[{i}][{k!r}] must be {what}, got {v!r}")


def summarize(rows: Iterable[Mapping], *, bootstrap_resamples: int = 10000, bootstrap_seed: int = 0) -> dict:
    """Per-level and pooled metrics ([M-4], [M-5], [M-7], [KE-7]).

    Per (method, level, scope): each metric is the mean over its episodes,
    each delay of the scope weighted equally (``overall``: every delay
    evaluated, ``high``: d in {3, 4}). Pooled: the mean over levels with its
    bootstrap 95% interval over levels. Returns ``{"per_level": [...],
    "pooled": [...]}`` row lists.
    """
    if isinstance(rows, (str, bytes, Mapping)) or not isinstance(rows, Iterable):
        raise ValueError(f"rows must be an iterable of episode rows (mappings, as in evaluate()['episodes']), "
                         f"got {type(rows).__name__}")
    rows = list(rows)
    if not rows:
        raise ValueError("rows must hold at least one episode row")
    _check_rows(rows)
    check_int("bootstrap_resamples", bootstrap_resamples, 1, 10**7)
    check_int("bootstrap_seed", bootstrap_seed, 0, 2**32 - 1)
    methods = list(dict.fromkeys(r["method"] for r in rows))
    levels = list(dict.fromkeys(r["level"] for r in rows))
    per_level, pooled = [], []
    for m in methods:
        for scope in SCOPES:
            vals = {k: [] for k in METRICS}
            for lv in levels:
                sel = [r for r in rows if r["method"] == m and r["level"] == lv
                       and (scope == "overall" or r["delay"] in HIGH_DELAYS)]
                if not sel:
                    continue
                # Each delay weighted equally ([M-4]), then episodes within a delay.
                by_d = {}
                for r in sel:
                    by_d.setdefault(r["delay"], []).append(r)
                entry = {"method": m, "level": lv, "scope": scope, "episodes": len(sel)}
                for k in METRICS:
                    per_delay = [ref_metrics.defined_mean([float(r[k]) for r in rs]) for rs in by_d.values()]
                    entry[k] = ref_metrics.defined_mean(per_delay)
                    vals[k].append(entry[k])
                per_level.append(entry)
            if not vals["return"]:
                continue
            entry = {"method": m, "scope": scope, "levels": len(vals["return"])}
            for k in METRICS:
                v = ref_metrics.defined_values(vals[k])
                entry[k] = ref_metrics.defined_mean(v)
                if v.size:
                    lo, hi = ref_metrics.bootstrap_interval(v, bootstrap_resamples, bootstrap_seed)
                else:
                    lo = hi = float("nan")
                entry[k + "_lo"], entry[k + "_hi"] = lo, hi
            pooled.append(entry)
    return {"per_level": per_level, "pooled": pooled}


def _display(label: str) -> str:
    try:
        return parse_method(label).display
    except ValueError:
        return label


def main_table(summary: Mapping) -> str:
    """Markdown table in the layout of the paper's main table ([KE-8]).

    Columns: Method | Overall Return | Overall Solve | High-delay Solve |
    High-delay Jerk | Overall Delta | Overall Jerk | High-delay Delta, each
    pooled over levels with its bootstrap 95% interval.
    """
    if not isinstance(summary, Mapping) or "pooled" not in summary:
        raise ValueError("summary must be the dict returned by summarize()")
    need = ("method", "scope", *METRICS, *(k + "_lo" for k in METRICS), *(k + "_hi" for k in METRICS))
    if isinstance(summary["pooled"], (str, bytes, Mapping)) or not isinstance(summary["pooled"], Sequence):
        raise ValueError("summary['pooled'] must be the list of pooled rows returned by summarize()")
    for i, r in enumerate(summary["pooled"]):
        if not isinstance(r, Mapping):
            raise ValueError(f"summary['pooled'][{i}] must be a mapping (a pooled row of summarize()), got {r!r}")
        missing = [k for k in need if k not in r]
        if missing:
            raise ValueError(f"summary['pooled'][{i}] is missing key(s) {', '.join(missing)}")
        if not isinstance(r["method"], str) or r["scope"] not in SCOPES:
            raise ValueError(f"summary['pooled'][{i}] must have a str 'method' and 'scope' in {SCOPES}, "
                             f"got {r['method']!r}, {r['scope']!r}")
        for k in need[2:]:
            if isinstance(r[k], bool) or not isinstance(r[k], numbers.Real):
                raise ValueError(f"summary['pooled'][{i}][{k!r}] must be a real number, got {r[k]!r}")
    cols = [("overall", "return", "Overall Return"), ("overall", "solved", "Overall Solve"),
            ("high", "solved", "High-delay Solve"), ("high", "jerk", "High-delay Jerk ↓"),
            ("overall", "delta", "Overall Delta ↓"), ("overall", "jerk", "Overall Jerk ↓"),
            ("high", "delta", "High-delay Delta ↓")]
    pooled = {(r["method"], r["scope"]): r for r in summary["pooled"]}
    methods = list(dict.fromkeys(r["method"] for r in summary["pooled"]))
    lines = ["| Method | " + " | ".join(c[2] for c in cols) + " |", "|---" * (len(cols) + 1) + "|"]
    for m in methods:
        cells = []
        for scope, k, _ in cols:
            r = pooled.get((m, scope))
            if r is None or not np.isfinite(r[k]):
                cells.append("–")
            else:
                cells.append(f"{r[k]:.3f} [{r[k + '_lo']:.3f}, {r[k + '_hi']:.3f}]")
        lines.append(f"| {_display(m)} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _write_csv(path: Path, rows: list[dict]) -> None:
    if not rows:
        return
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]))
        w.writeheader()
        w.writerows(rows)


def write_results(result: Mapping, out_dir: str | os.PathLike, *, bootstrap_resamples: int = 10000,
                  bootstrap_seed: int = 0) -> dict:
    """Write ``episodes.csv``, ``per_level.csv``, ``pooled.csv`` and ``table.md`` ([KE-8]); returns the paths."""
    if not isinstance(result, Mapping) or "episodes" not in result:
        raise ValueError("result must be the dict returned by evaluate()")
    out = check_out_dir("out_dir", out_dir, ("episodes.csv", "per_level.csv", "pooled.csv", "table.md"))
    # Rows are checked and summarized before anything is created.
    summary = summarize(result["episodes"], bootstrap_resamples=bootstrap_resamples, bootstrap_seed=bootstrap_seed)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"episodes": out / "episodes.csv", "per_level": out / "per_level.csv",
             "pooled": out / "pooled.csv", "table": out / "table.md"}
    _write_csv(paths["episodes"], list(result["episodes"]))
    _write_csv(paths["per_level"], summary["per_level"])
    _write_csv(paths["pooled"], summary["pooled"])
    paths["table"].write_text(main_table(summary))
    return {k: str(v) for k, v in paths.items()} | {"summary": summary}
