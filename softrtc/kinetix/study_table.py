"""The Kinetix study's paper-shaped table, paired tests, plots and verdicts ([KR-1]..[KR-7]).

``softrtc kinetix report --study DIR`` reads the evaluation folders of a study
(``DIR/eval/<level>/seed_<k>/episodes.csv``, each the output of one
``softrtc kinetix eval`` run, [KR-1]) and the committed ``softrtc bench
runtime`` results (``results/bench/runtime-<n>.json``, [KR-4]), and writes
the Markdown block the Kinetix results page (and the README) shows between
``<!-- kinetix-table:begin -->`` and ``<!-- kinetix-table:end -->``: per row
return, solve, high-delay solve, high-delay jerk and delta with bootstrap
95% intervals over levels, fine-tuning seeds and paired episodes ([KR-3]),
paired differences against Train Hard RTC with the sign-flip test and Holm's
adjustment, chunk-time ratios, and the verdicts of :mod:`softrtc.verdicts`
([KR-5]). Deterministic: every bootstrap and test uses seed 0.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re
from pathlib import Path

import numpy as np

from softrtc import verdicts as shared
from softrtc._files import check_out_dir, write_atomic
from softrtc.paired_stats import holm, nested_bootstrap, sign_flip_test

__all__ = ["BEGIN", "END", "KINETIX", "METRICS", "HIGH", "read_study", "summarize_study", "read_runtime",
           "render_block", "write_plots", "write_report"]

BEGIN = "<!-- kinetix-table:begin -->"
END = "<!-- kinetix-table:end -->"
METRICS = ("return", "solved", "delta", "jerk")
HIGH = (3, 4)  # the high delays of [M-7]
RESAMPLES = 2000
PERMUTATIONS = 5000
MAX_DELAY = 64
PLOTS = ("eval_solve_by_delay.png", "eval_jerk_by_delay.png")
# What the shared claims read in this summary ([KR-5]).
KINETIX = shared.Environment(success="solved", success_word="solve", succeeds="solves", jerk="jerk",
                             fd=("delta", "jerk"), fd_label="action delta and jerk",
                             offset_row=lambda L, ov: f"train_soft:offset:{L}" + (":zeros" if ov == "zeros" else ""))
_NEED = ("method", "level", "delay", "episode", "return", "solved", "length", "delta", "jerk")
_DISPLAY = {"naive": "Base Naive", "inference_hard": "Inference Hard RTC", "inference_soft": "Inference Soft RTC",
            "train_hard": "Train Hard RTC", "train_soft": "Train Soft RTC"}
_SEED = re.compile(r"seed_(0|[1-9][0-9]{0,5})(?:\.[a-z0-9][a-z0-9_-]{0,31})?")
_INT = re.compile(r"-?[0-9]+")


# ----------------------------------------------------------------------------- reading


def _bad(path, line, field, want, got):
    return ValueError(f"results file {str(path)!r}: line {line}: field {field!r} must be {want}, got {got!r}")


def _read_episodes(path: Path, level: str) -> dict:
    """``{(method, delay): {episode: {metric: value}}}`` of one ``episodes.csv``, every value checked ([KR-1])."""
    try:
        with open(path, newline="", encoding="utf-8") as f:
            reader = csv.DictReader(f)
            header = reader.fieldnames or []
            missing = [k for k in _NEED if k not in header]
            if missing:
                raise ValueError(f"results file {str(path)!r} must have the columns {list(_NEED)} of "
                                 f"`softrtc kinetix eval` ([KE-8]); it lacks {missing}")
            rows = list(reader)
    except (UnicodeDecodeError, csv.Error) as exc:
        raise ValueError(f"results file {str(path)!r} is not a readable CSV file ({exc})") from None
    if not rows:
        raise ValueError(f"results file {str(path)!r} holds no episode")
    cells: dict = {}
    for i, r in enumerate(rows, start=2):
        if None in r or any(r.get(k) is None for k in _NEED):
            raise ValueError(f"results file {str(path)!r}: line {i} must have {len(header)} fields")
        if not r["method"].strip():
            raise _bad(path, i, "method", "a non-empty method string", r["method"])
        if r["level"] != level:
            raise _bad(path, i, "level", f"{level!r} (the folder's level)", r["level"])
        vals = {}
        for k, lo, hi in (("delay", 0, MAX_DELAY), ("episode", 0, 2**20 - 1), ("length", 1, 2**20)):
            if not _INT.fullmatch(r[k]) or not lo <= int(r[k]) <= hi:
                raise _bad(path, i, k, f"an integer in [{lo}, {hi}]", r[k])
            vals[k] = int(r[k])
        if r["solved"] not in ("True", "False", "0", "1"):
            raise _bad(path, i, "solved", "True, False, 0 or 1", r["solved"])
        vals["solved"] = 1.0 if r["solved"] in ("True", "1") else 0.0
        for k in ("return", "delta", "jerk"):
            try:
                x = float(r[k])
            except ValueError:
                raise _bad(path, i, k, "a real number", r[k]) from None
            if math.isinf(x) or (k == "return" and math.isnan(x)) or (k != "return" and x < 0):
                raise _bad(path, i, k, "a finite real number" if k == "return" else
                           "a real number >= 0 (nan when undefined)", r[k])
            vals[k] = x
        cell = cells.setdefault((r["method"], vals["delay"]), {})
        if vals["episode"] in cell:
            raise ValueError(f"results file {str(path)!r}: line {i}: episode {vals['episode']} of method "
                             f"{r['method']!r} at delay {vals['delay']} appears twice")
        cell[vals["episode"]] = {k: vals[k] for k in METRICS}
    return cells


def _is_base(row: str) -> bool:
    return row.split(":", 1)[0] in shared.BASE_ROWS


def read_study(study_dir) -> dict | None:
    """The episodes of a study's evaluation folders, or None when it has no ``eval`` folder ([KR-1]).

    Returns ``{"levels": [...], "cells": {(row, level): {seed: {delay:
    {episode: {metric: value}}}}}, "files": [...]}``. A base row (naive,
    inference-time) has one seed: it may appear in several seed folders of a
    level only with the same episodes, and counts once. ``seed_<k>.<part>``
    folders add the rows of further ``eval`` runs to seed ``k``; a trained
    row of one seed in two folders is an error. Every file is checked
    as it is read: a damaged one is a ValueError naming it.
    """
    if not isinstance(study_dir, (str, os.PathLike)) or not os.fspath(study_dir):
        raise ValueError(f"study_dir must be a str or PathLike folder path, got {study_dir!r}")
    root = Path(study_dir)
    if not root.is_dir():
        raise ValueError(f"study_dir must be an existing folder, got {str(root)!r}")
    ev = root / "eval"
    if not ev.exists():
        return None
    if not ev.is_dir():
        raise ValueError(f"study_dir's eval {str(ev)!r} must be a folder of <level>/seed_<k>/ results")
    levels, cells, files = [], {}, []
    for lv_dir in sorted(p for p in ev.iterdir() if not p.name.startswith(".")):
        if not lv_dir.is_dir():
            raise ValueError(f"{str(lv_dir)!r} must be a level folder of seed_<k> results folders")
        seeds = []
        for sd in sorted(p for p in lv_dir.iterdir() if not p.name.startswith(".")):
            m = _SEED.fullmatch(sd.name)
            if not sd.is_dir() or m is None:
                raise ValueError(f"{str(sd)!r} must be a results folder named seed_<k> or seed_<k>.<part> (k a "
                                 "fine-tuning seed, part lower-case letters, digits, _ or -)")
            if not (sd / "episodes.csv").is_file():
                raise ValueError(f"results folder {str(sd)!r} has no episodes.csv (the output of "
                                 "`softrtc kinetix eval --out`)")
            seeds.append((int(m.group(1)), sd / "episodes.csv"))
        if not seeds:
            continue
        levels.append(lv_dir.name)
        base_from: dict = {}
        row_from: dict = {}
        for seed, path in sorted(seeds):
            files.append(str(path))
            by_row: dict = {}
            for (row, d), eps in _read_episodes(path, lv_dir.name).items():
                by_row.setdefault(row, {})[d] = eps
            for row, per_d in by_row.items():
                slot = cells.setdefault((row, lv_dir.name), {})
                if _is_base(row) and slot:
                    first_seed, first_path = base_from[row]
                    if slot[first_seed] != per_d:
                        raise ValueError(f"results file {str(path)!r}: base row {row!r} differs from its episodes "
                                         f"in {str(first_path)!r}; a base row has one seed ([KR-1])")
                    continue
                if seed in slot:  # a trained row of one seed in two parts: which one counts would be a guess
                    raise ValueError(f"results file {str(path)!r}: row {row!r} of seed {seed} is also in "
                                     f"{str(row_from[(row, seed)])!r}; a row of a seed belongs to one folder ([KR-1])")
                slot[seed] = per_d
                row_from[(row, seed)] = path
                base_from.setdefault(row, (seed, path))
    if not levels:
        return None
    return {"levels": levels, "cells": cells, "files": files}


# ----------------------------------------------------------------------------- statistics


def _order(rows) -> list:
    fixed = [r for r in (*shared.BASE_ROWS, "train_hard") if r in rows]
    return fixed + sorted(r for r in rows if r not in fixed)


def _block(data, row, level, delays, metric, seeds=None, episodes=None):
    """``[seeds, delays, episodes]`` of one row and level, or None when a seed lacks a delay or an episode.

    ``seeds`` restricts fine-tuned rows to those seeds (a base row keeps its
    one); ``episodes`` are the episode indices (default: those every cell
    holds).
    """
    slot = data["cells"].get((row, level))
    if not slot:
        return None
    ss = sorted(slot) if seeds is None or _is_base(row) else [s for s in sorted(slot) if s in seeds]
    ss = [s for s in ss if all(d in slot[s] for d in delays)]
    if not ss:
        return None
    if episodes is None:
        episodes = sorted(set.intersection(*(set(slot[s][d]) for s in ss for d in delays)))
    if not episodes or any(e not in slot[s][d] for s in ss for d in delays for e in episodes):
        return None
    return np.array([[[slot[s][d][e][metric] for e in episodes] for d in delays] for s in ss], dtype=np.float64)


def _episodes(data, rows, level, delays):
    """Episode indices held by every cell of ``rows`` at ``level`` for ``delays``."""
    sets = [set(eps) for r in rows for s, per_d in data["cells"].get((r, level), {}).items()
            for d, eps in per_d.items() if d in delays]
    return sorted(set.intersection(*sets)) if sets else []


def _row_delays(data, row):
    return sorted({d for (r, _), slot in data["cells"].items() if r == row for per_d in slot.values() for d in per_d})


def _paired(data, row, scope_delays, metric):
    """Paired difference ``row - train_hard`` per level, its bootstrap interval and sign-flip test ([KR-3])."""
    blocks, deltas, seeds = [], [], []
    for lv in data["levels"]:
        a_slot, b_slot = data["cells"].get((row, lv)), data["cells"].get(("train_hard", lv))
        if not a_slot or not b_slot:
            continue
        # Fine-tuned rows pair seed by seed (only the seeds both ran at every delay of the scope); a base row
        # pairs with every seed.
        full = lambda slot: {s for s, per_d in slot.items() if all(d in per_d for d in scope_delays)}  # noqa: E731
        common = sorted(full(b_slot)) if _is_base(row) else sorted(full(a_slot) & full(b_slot))
        eps = _episodes(data, [row, "train_hard"], lv, scope_delays)
        a = _block(data, row, lv, scope_delays, metric, common, eps)
        b = _block(data, "train_hard", lv, scope_delays, metric, common, eps)
        if a is None or b is None or (a.shape[0] != b.shape[0] and a.shape[0] != 1):
            continue
        d = np.broadcast_to(a, b.shape) - b if a.shape[0] == 1 else a - b
        blocks.append(d)
        seeds.append(len(common))
        ok = np.isfinite(d)
        cnt = ok.sum(axis=(0, 1))
        with np.errstate(invalid="ignore", divide="ignore"):
            deltas.append(np.where(cnt > 0, np.where(ok, d, 0.0).sum(axis=(0, 1)) / np.maximum(cnt, 1), np.nan))
    if not blocks:
        return None
    r = nested_bootstrap(blocks, RESAMPLES, 0)
    # The sign-flip unit is the environment key (level, episode): its differences over the fine-tuning seeds
    # and the scope's delays are averaged first ([KR-3]).
    delta = np.concatenate(deltas)[None, :]
    p = sign_flip_test(delta, np.zeros_like(delta), PERMUTATIONS, 0)["p"] if np.isfinite(delta).any() \
        else float("nan")
    return {"diff": r["mean"], "lo": r["lo"], "hi": r["hi"], "n": r["n"], "p_perm": p, "levels": len(blocks),
            "seeds": min(seeds)}


def summarize_study(data: dict) -> dict:
    """Per row: ``delays``, ``levels``, ``seeds``, ``episodes``, ``scopes`` and ``vs_hard`` ([KR-3]).

    ``scopes`` holds ``overall`` (every delay the row ran) and ``high`` (d in
    {3, 4}) with the nested bootstrap of every metric, and ``d<k>`` with the
    per-delay means; ``vs_hard`` the paired differences to ``train_hard`` in
    ``overall`` and ``high``. ``seeds`` and ``episodes`` are the smallest over
    the row's levels (episodes per delay).
    """
    if not isinstance(data, dict) or "cells" not in data or "levels" not in data:
        raise ValueError("data must be the dict returned by read_study()")
    rows = _order({r for (r, _) in data["cells"]})
    out = {}
    for row in rows:
        ds = _row_delays(data, row)
        lvls = [lv for lv in data["levels"] if (row, lv) in data["cells"]]
        seeds = min(sum(all(d in per_d for d in ds) for per_d in data["cells"][(row, lv)].values()) for lv in lvls)
        eps = min(len(eps) for lv in lvls for per_d in data["cells"][(row, lv)].values() for eps in per_d.values())
        entry = {"delays": ds, "levels": len(lvls), "seeds": seeds, "episodes": eps, "scopes": {}, "vs_hard": {}}
        scopes = {"overall": ds}
        if all(d in ds for d in HIGH):
            scopes["high"] = list(HIGH)
        for scope, dl in scopes.items():
            stats = {}
            for m in METRICS:
                blocks = [b for lv in lvls if (b := _block(data, row, lv, dl, m)) is not None]
                if blocks:
                    stats[m] = nested_bootstrap(blocks, RESAMPLES, 0)
            entry["scopes"][scope] = stats
            if row != "train_hard" and any(r == "train_hard" for (r, _) in data["cells"]):
                entry["vs_hard"][scope] = {m: t for m in METRICS if (t := _paired(data, row, dl, m)) is not None}
        for d in ds:
            entry["scopes"][f"d{d}"] = {}
            for m in METRICS:
                vals = [b for lv in lvls if (b := _block(data, row, lv, [d], m)) is not None]
                means = [float(np.nanmean(b)) for b in vals if np.isfinite(b).any()]
                if means:
                    entry["scopes"][f"d{d}"][m] = {"mean": sum(means) / len(means)}
        out[row] = entry
    return out


# ----------------------------------------------------------------------------- runtime


def _delay_scaled_lam(row: str) -> int | None:
    """1 or 2 when ``row`` is a Train Soft row of the delay-scaled window with that ``lam`` (``h_max`` 5), else None."""
    parts = row.split(":")
    if parts[0] != "train_soft":
        return None
    rest = [p for p in parts[1:] if p not in ("zeros", "consistent")]
    if not rest:
        return 2  # the main window ([KE-2])
    if rest[0] == "delay_scaled" and len(rest) in (2, 3) and rest[2:] in ([], ["5"]):
        for lam in (1, 2):
            if rest[1] in (str(lam), f"{lam}.0"):
                return lam
    return None


def _runtime_key(row: str) -> str | None:
    """The ``softrtc bench runtime`` row whose sampler a Kinetix row runs, or None ([KR-4])."""
    if row in (*shared.BASE_ROWS, "train_hard"):
        return row
    lam = _delay_scaled_lam(row)
    if lam is None:
        return None
    if "consistent" in row.split(":"):
        return "train_soft_lam2_consistent" if lam == 2 else None
    return f"train_soft_lam{lam}"


def read_runtime(bench_dir) -> dict | None:
    """The newest ``runtime-<n>.json`` of ``bench_dir`` (largest ``n``), checked, or None when there is none."""
    d = Path(bench_dir)
    found = sorted((int(m.group(1)), p) for p in d.glob("runtime-*.json")
                   if (m := re.fullmatch(r"runtime-([0-9]{1,6})\.json", p.name)))
    if not found:
        return None
    path = found[-1][1]
    try:
        res = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"runtime result {str(path)!r} is not a JSON file ({exc})") from None
    try:
        env, chunk, arch = res["environment"], res["chunk"], res["architecture"]
        for b, per in chunk.items():
            for k, st in per.items():
                if isinstance(st["ratio"], bool) or not isinstance(st["ratio"], (int, float)) \
                        or not math.isfinite(st["ratio"]) or st["ratio"] <= 0:
                    raise ValueError(f"chunk[{b!r}][{k!r}]['ratio'] must be a positive real, got {st['ratio']!r}")
        machine = f"{env['backend']} ({env['cpu_count']} cores{', ' + env['cpu_model'] if env.get('cpu_model') else ''})"
        desc = (f"obs {arch['obs_dim']}, action {arch['action_dim']}, H {arch['action_chunk_size']}, "
                f"{arch['parameters']:,} parameters")
        jax_v = env["jax"]
    except (KeyError, TypeError, AttributeError, ValueError) as exc:
        raise ValueError(f"runtime result {str(path)!r} is not a `softrtc bench runtime` result ({exc})") from None
    return {"file": f"results/bench/{path.name}", "machine": machine, "jax": jax_v, "policy": desc,
            "batches": list(chunk), "chunk": chunk}


# ----------------------------------------------------------------------------- rendering


def _display(row: str) -> str:
    name = row.split(":", 1)[0]
    if name not in _DISPLAY:
        return row
    return _DISPLAY[name] if row == name else f"{_DISPLAY[name]} ({row.split(':', 1)[1]})"


def _soft_rows(summary, lam):
    return [r for r in summary if _delay_scaled_lam(r) == lam]


def _ratio(rt, row, b):
    key = _runtime_key(row)
    st = rt["chunk"][b].get(key) if rt is not None and key is not None else None
    return "–" if st is None else f"{st['ratio']:.2f}x"


def _main_table(summary, rt) -> list:
    f = shared._ci
    bs = rt["batches"] if rt is not None else []
    head = ("| Row | levels x seeds x episodes | Return | Solve | High-delay solve | High-delay jerk ↓ | "
            "High-delay delta ↓ |" + "".join(f" chunk time / naive, batch {b} |" for b in bs))
    lines = [head, "|---" * (7 + len(bs)) + "|"]
    for r, e in summary.items():
        g = lambda scope, m: e["scopes"].get(scope, {}).get(m)  # noqa: E731
        lines.append(f"| {_display(r)} | {e['levels']} x {e['seeds']} x {e['episodes']} | "
                     f"{f(g('overall', 'return'))} | {f(g('overall', 'solved'))} | {f(g('high', 'solved'))} | "
                     f"{f(g('high', 'jerk'), 4)} | {f(g('high', 'delta'), 4)} |"
                     + "".join(f" {_ratio(rt, r, b)} |" for b in bs))
    return lines


_DIFF_COLS = (("overall", "solved", "Solve", 3), ("high", "solved", "High-delay solve", 3),
              ("high", "jerk", "High-delay jerk", 4), ("high", "delta", "High-delay delta", 4),
              ("overall", "return", "Return", 3))


def _diff_table(summary) -> list:
    keys, ps = [], []
    for r, e in summary.items():
        for scope, m, _, _ in _DIFF_COLS:
            t = e["vs_hard"].get(scope, {}).get(m)
            if t is not None and math.isfinite(t["p_perm"]):
                keys.append((r, scope, m))
                ps.append(t["p_perm"])
    adj = dict(zip(keys, holm(ps))) if ps else {}
    lines = ["| Row | " + " | ".join(c[2] for c in _DIFF_COLS) + " |", "|---" * (len(_DIFF_COLS) + 1) + "|"]
    for r, e in summary.items():
        if r == "train_hard" or not e["vs_hard"]:
            continue
        cells = []
        for scope, m, _, nd in _DIFF_COLS:
            t = e["vs_hard"].get(scope, {}).get(m)
            if t is None:
                cells.append("–")
                continue
            p = adj.get((r, scope, m))
            cells.append(shared._diff(t, nd) + ("" if p is None else f" (p {p:.3f})") +
                         (" *" if p is not None and p < 0.05 else ""))
        lines.append(f"| {_display(r)} | " + " | ".join(cells) + " |")
    lines += ["", f"{len(ps)} comparisons in this table (every row against Train Hard RTC in these five columns); "
                  "p is the sign-flip test's after Holm's adjustment over them, `*` where it is below 0.05."]
    return lines


def _delay_table(summary, metric, nd) -> list:
    delays = sorted({d for e in summary.values() for d in e["delays"]})
    lines = ["| Row | " + " | ".join(f"d = {d}" for d in delays) + " |", "|---" * (len(delays) + 1) + "|"]
    for r, e in summary.items():
        cells = [shared._f(e["scopes"][f"d{d}"][metric]["mean"], nd) if metric in e["scopes"].get(f"d{d}", {})
                 else "" for d in delays]
        lines.append(f"| {_display(r)} | " + " | ".join(cells) + " |")
    return lines


def verdicts_of(summary: dict) -> list:
    """The shared claims ([KR-5]) on a study summary: its Soft N = 2 rows, its N = 1 rows measured."""
    return shared.verdicts(summary, KINETIX, soft2_rows=_soft_rows(summary, 2), n1_identical=None,
                           n1_rows=_soft_rows(summary, 1))


def render_block(data: dict | None, summary: dict | None = None, runtime: dict | None = None,
                 where: str = "page") -> str:
    """The Markdown block between the markers ([KR-6]); ``where`` is ``"page"`` (with the per-delay tables, paired
    differences and plots) or ``"readme"`` (the main table and the verdicts, linking to the page)."""
    if where not in ("page", "readme"):
        raise ValueError(f"where must be 'page' or 'readme', got {where!r}")
    cmd = "`softrtc kinetix report --study results/kinetix/study`"
    if data is None:
        return "\n".join([BEGIN, "", f"The study has no evaluation yet: its `eval/` folder holds no results "
                          f"folder (`eval/<level>/seed_<k>/`, [KR-1]). Generated by {cmd}.", "", END])
    summary = summarize_study(data) if summary is None else summary
    seeds = sorted({s for slot in data["cells"].values() for s in slot})
    out = [BEGIN, "", f"Generated by {cmd} from `results/kinetix/study/eval/`; do not edit by hand. "
           f"{len(data['levels'])} level(s) ({', '.join(f'`{lv}`' for lv in data['levels'])}), fine-tuning seeds "
           f"{', '.join(map(str, seeds))}. Intervals are bootstrap 95% intervals over levels, then fine-tuning seeds "
           f"and paired episodes within each level ({RESAMPLES} resamples, seed 0); high delay = d in "
           f"{{{', '.join(map(str, HIGH))}}}; jerk and delta are those of the commanded actions ([KE-7]).", ""]
    out += _main_table(summary, runtime)
    if runtime is not None:
        out += ["", f"Chunk time / naive: the median time of one chunk request over the naive sampler's, from "
                f"`softrtc bench runtime` ({runtime['file']}: {runtime['machine']}, jax {runtime['jax']}, the "
                f"benchmark-size policy, {runtime['policy']}). A zero-padded window runs the clip row's sampler "
                f"(its weight table is an argument of the same program); `–`: no such row in that run."]
    else:
        out += ["", "Chunk time / naive: no `softrtc bench runtime` result (results/bench/runtime-<n>.json)."]
    out += ["", "### Verdicts", ""]
    for v in verdicts_of(summary):
        out.append(f"- **{v['claim']}** Verdict: **{v['verdict']}**"
                   + (f" ({v['reason']})" if v.get("reason") else "") + f". {v['evidence']}.")
    if where == "readme":
        out += ["", "Paired differences, per-delay tables and plots: [Kinetix results](docs/reports/kinetix.md).",
                "", END]
        return "\n".join(out)
    out += ["", "### Paired differences against Train Hard RTC", "",
            "Same levels, environment keys and fine-tuning seeds (a base row pairs with every seed); the sign-flip "
            "test takes the environment key (level, episode) as its unit, its differences averaged over seeds and "
            "delays first ([KR-3]).", ""]
    out += _diff_table(summary)
    out += ["", "### Solve per delay", ""] + _delay_table(summary, "solved", 3)
    out += ["", "### Jerk per delay", ""] + _delay_table(summary, "jerk", 4)
    out += ["", f"![Solve per delay](kinetix/{PLOTS[0]})", "", f"![Jerk per delay](kinetix/{PLOTS[1]})", "", END]
    return "\n".join(out)


def write_plots(summary: dict, out_dir) -> list:
    """Solve and jerk per delay, one line per row, as PNG files in ``out_dir`` ([KR-6])."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = check_out_dir("out_dir", out_dir, PLOTS)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for name, metric, label in ((PLOTS[0], "solved", "solve rate"), (PLOTS[1], "jerk", "jerk (D2)")):
        fig, ax = plt.subplots(figsize=(9.5, 4.5))
        n_levels = max(e["levels"] for e in summary.values())
        colors = plt.get_cmap("tab20").colors
        for i, (r, e) in enumerate(summary.items()):
            ds = [d for d in e["delays"] if metric in e["scopes"].get(f"d{d}", {})]
            # A row run on fewer levels is a mean over fewer levels: its label says so.
            few = f" ({e['levels']} of {n_levels} levels)" if e["levels"] < n_levels else ""
            # 20 colours, then the same colours dashed, then dotted: up to 60 rows each get their own style.
            ax.plot(ds, [e["scopes"][f"d{d}"][metric]["mean"] for d in ds], marker="o" if r == "train_hard" else ".",
                    color=colors[i % 20], linestyle=("-", "--", ":")[i // 20 % 3], label=_display(r) + few)
        ax.set_xticks(sorted({d for e in summary.values() for d in e["delays"]}))
        ax.set_xlabel("delay d (control steps)")
        ax.set_ylabel(f"{label}, mean over the row's levels")
        ax.legend(fontsize=6, loc="center left", bbox_to_anchor=(1.01, 0.5))
        fig.tight_layout()
        path = out / name
        # No software tag, so the bytes depend on the figure only; written whole or not at all.
        write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=100, metadata={"Software": None}),
                     binary=True)
        plt.close(fig)
        paths.append(str(path))
    return paths


def _rewrite(path, block: str, what: str) -> None:
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"{what} must name an existing Markdown file, got {str(p)!r}")
    txt = p.read_text(encoding="utf-8")
    i, j = txt.find(BEGIN), txt.find(END)
    if i < 0 or j < i:
        raise ValueError(f"{what} {str(p)!r} has no {BEGIN} ... {END} markers")
    new = txt[:i] + block + txt[j + len(END):]
    write_atomic(p, lambda f: f.write(new))


def write_report(study_dir, *, out=None, page=None, readme=None, bench_dir=None, plots: bool = True) -> dict:
    """Read the study, print-ready block and optional rewrites ([KR-6]); returns ``{"block", "written"}``.

    ``out`` (default ``study_dir``) receives the plots when the study has
    results; ``page`` and ``readme`` are Markdown files whose block between
    the markers is replaced; ``bench_dir`` (default ``results/bench`` beside
    the study's ``results`` folder) holds the runtime results.
    """
    if not isinstance(plots, bool):
        raise ValueError(f"plots must be a bool, got {plots!r}")
    data = read_study(study_dir)
    bench = Path(bench_dir) if bench_dir is not None else Path(study_dir).resolve().parent.parent / "bench"
    runtime = read_runtime(bench) if bench.is_dir() else None
    summary = summarize_study(data) if data is not None else None
    written = []
    if plots and data is not None:
        written += write_plots(summary, study_dir if out is None else out)
    block = render_block(data, summary, runtime, "page")
    if page is not None:
        _rewrite(page, block, "page")
        written.append(str(page))
    if readme is not None:
        _rewrite(readme, render_block(data, summary, runtime, "readme"), "readme")
        written.append(str(readme))
    return {"block": block, "written": written}
