"""The arm study: the paper's hardware table on the simulated arm in the real-time runtime ([A-25], [A-26]).

Each method (Base, Train Hard RTC, Train Soft RTC) runs ``trials`` episodes
with environment seeds ``seed0 .. seed0 + trials - 1`` (the same seeds for
every method) in :func:`softrtc.arm.runtime.run_realtime_episode`, with added
policy latency that puts the realized delay at 3-4 control ticks. The table
has the paper's columns (Succ., Compl., Obj., Thr., D1, D2, D3, Bound., Lat.)
with standard errors over trials ([M-6]).
"""

from __future__ import annotations

import csv
import os

import jax
import numpy as np

from softrtc._files import check_out_dir, check_out_file
from softrtc.reference._validate import check_int
from softrtc.reference.metrics import defined_mean, defined_values, standard_error

from ._checks import check_number
from .checkpoints import load_policies
from .env import NUM_OBJECTS, ArmConfig
from .executor import EpisodeRecord, episode_metrics
from .policy_config import METHOD_LABELS, STUDY_METHODS
from .runtime import RuntimeConfig, jitter_summary, run_realtime_episode

__all__ = ["run_study", "summarize", "format_table", "read_results", "table_from_results", "plot_traces",
           "DEFAULT_ADDED_LATENCY_S", "DEFAULT_SEED0"]

# 55 ms on top of a few ms of compute: 60-80 ms per call, a realized delay of 3-4 ticks at 50 Hz.
DEFAULT_ADDED_LATENCY_S = 0.055
# Evaluation seeds, disjoint in practice from the demo seeds (SeedSequence-derived 32-bit words).
DEFAULT_SEED0 = 10_000

_COLUMNS = ("Method", "Succ.", "Compl.", "Obj.", "Thr.", "D1", "D2", "D3", "Bound.", "Lat.")


def _se(values) -> float:
    v = defined_values(values)
    return standard_error(v) if v.size >= 2 else float("nan")


def summarize(per_trial: list[dict]) -> dict:
    """One table row from per-trial metrics ([A-25], [M-6]): counts, means and standard errors."""
    if not isinstance(per_trial, list) or not per_trial or not all(isinstance(m, dict) for m in per_trial):
        raise ValueError("per_trial must be a non-empty list of episode_metrics dicts")
    need = ("success", "completed", "completion", "throughput", "D1", "D2", "D3", "boundary", "latency_ms",
            "hold_ticks", "fault")
    for i, m in enumerate(per_trial):
        missing = [k for k in need if k not in m]
        if missing:
            raise ValueError(f"per_trial[{i}] must be an episode_metrics dict; missing keys {missing}")
        for k in need[:-1]:
            v = m[k]
            if isinstance(v, (bool, np.bool_)) and k not in ("success",):
                raise ValueError(f"per_trial[{i}][{k!r}] must be a real number, got {v!r}")
            if not isinstance(v, (bool, np.bool_, int, float, np.integer, np.floating)):
                raise ValueError(f"per_trial[{i}][{k!r}] must be a real number, got {v!r}")
    n = len(per_trial)
    row = {"trials": n, "successes": sum(m["success"] for m in per_trial),
           "objects": sum(m["completed"] for m in per_trial), "objects_total": NUM_OBJECTS * n}
    for k in ("completion", "throughput", "D1", "D2", "D3", "boundary", "latency_ms", "hold_ticks"):
        vals = [float(m[k]) for m in per_trial]
        row[k] = defined_mean(vals)
        row[k + "_se"] = _se(vals)
    row["faults"] = sum(m["fault"] is not None for m in per_trial)
    return row


def format_table(rows: dict) -> str:
    """The paper's hardware table as text: ``{method: summarize(...)}`` -> aligned columns ([A-25])."""
    if not isinstance(rows, dict) or not rows:
        raise ValueError("rows must be a non-empty dict {method: summary row}")
    need = ("successes", "trials", "objects", "objects_total")
    for m, r in rows.items():
        if not isinstance(r, dict):
            raise ValueError(f"rows[{m!r}] must be a summarize() dict, got {type(r).__name__}")
        missing = [k for k in need if k not in r] + [k2 for k in ("completion", "throughput", "D1", "D2", "D3",
                                                                  "boundary", "latency_ms")
                                                     for k2 in (k, k + "_se") if k2 not in r]
        if missing:
            raise ValueError(f"rows[{m!r}] must be a summarize() dict; missing keys {missing}")

    def pm(r, k, fmt):
        # A single trial has no standard error ([M-6] needs n >= 2): print a dash, not nan.
        se = r[k + "_se"]
        return f"{r[k]:{fmt}} ± " + ("-" if se != se else f"{se:{fmt}}")

    lines = [[*_COLUMNS]]
    for m, r in rows.items():
        lines.append([METHOD_LABELS.get(m, m), f"{r['successes']}/{r['trials']}", pm(r, "completion", ".3f"),
                      f"{r['objects']}/{r['objects_total']}", pm(r, "throughput", ".2f"), pm(r, "D1", ".4f"),
                      pm(r, "D2", ".4f"), pm(r, "D3", ".4f"), pm(r, "boundary", ".4f"), pm(r, "latency_ms", ".1f")])
    widths = [max(len(row[i]) for row in lines) for i in range(len(_COLUMNS))]
    out = ["  ".join(c.ljust(w) for c, w in zip(row, widths)) for row in lines]
    out.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(out)


_INT_FIELDS = ("completed", "hold_ticks")
_REAL_FIELDS = ("completion", "throughput", "D1", "D2", "D3", "boundary", "latency_ms")


def read_results(path) -> dict:
    """``{method: [per-trial metrics]}`` from a study's ``results.csv`` ([A-25]), methods in first-seen order.

    The inverse of what :func:`run_study` writes: ``success`` is ``True`` /
    ``False``, ``fault`` is empty for none, reals may be ``nan``.
    """
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must be an existing results.csv file, got {path!r}")
    out: dict = {}
    with open(path, newline="") as f:
        for i, r in enumerate(csv.DictReader(f)):
            try:
                if r["success"] not in ("True", "False"):
                    raise ValueError(f"success {r['success']!r}")
                m = {"success": r["success"] == "True", "fault": r["fault"] or None,
                     **{k: int(r[k]) for k in _INT_FIELDS}, **{k: float(r[k]) for k in _REAL_FIELDS}}
            except (KeyError, ValueError, TypeError) as e:
                raise ValueError(f"path {os.fspath(path)!r}: row {i + 1} is not a study result row ({e})") from None
            out.setdefault(r["method"], []).append(m)
    if not out:
        raise ValueError(f"path {os.fspath(path)!r} holds no result rows")
    return out


def table_from_results(path) -> str:
    """The study table ([A-25]) recomputed from a committed ``results.csv`` (the README's block)."""
    return format_table({m: summarize(trials) for m, trials in read_results(path).items()})


def plot_traces(records: dict, path) -> str:
    """Commanded joint targets over time, one panel per method (the paper's teaser, bottom) ([A-26])."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not isinstance(records, dict) or not records:
        raise ValueError("records must be a non-empty dict {method: EpisodeRecord}")
    for m, rec in records.items():
        if not isinstance(rec, EpisodeRecord):
            raise ValueError(f"records[{m!r}] must be an EpisodeRecord, got {type(rec).__name__}")
    check_out_file("path", path, ".png")
    fig, axes = plt.subplots(len(records), 1, figsize=(9, 2.4 * len(records)), sharex=True, squeeze=False)
    for ax, (m, rec) in zip(axes[:, 0], records.items()):
        t = np.arange(rec.steps) * rec.dt
        for i, name in enumerate(("q1", "q2", "q3")):
            ax.plot(t, rec.actions[:, i], lw=1.0, label=f"{name} target")
        sw = np.nonzero(rec.chunk_index[1:] != rec.chunk_index[:-1])[0] + 1
        for x in sw * rec.dt:
            ax.axvline(x, color="0.85", lw=0.5, zorder=0)
        status = "success" if rec.success else f"{rec.num_completed}/4 parts"
        ax.set_title(f"{METHOD_LABELS.get(m, m)} (seed {rec.env_seed}, {status})", fontsize=9)
        ax.set_ylabel("rad")
    axes[0, 0].legend(fontsize=7, ncol=3, loc="upper right")
    axes[-1, 0].set_xlabel("time [s] (grey: chunk switches)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return os.fspath(path)


def run_study(checkpoint_dir=None, trials: int = 10, methods=STUDY_METHODS,
              added_latency_s: float = DEFAULT_ADDED_LATENCY_S, seed0: int = DEFAULT_SEED0, key_seed: int = 0,
              out_dir="arm_study", max_steps: int | None = None, plot: bool = True, verbose: bool = True,
              announce_files: bool = True) -> dict:
    """Run the arm study and write ``results.csv``, ``summary.csv`` and ``traces.png`` to ``out_dir`` ([A-25]).

    Trial ``i`` of every method uses env seed ``seed0 + i`` and key
    ``fold_in(key(key_seed), i)``; the methods run interleaved, trial by
    trial, in an order rotated by ``i``. Returns ``{"rows", "per_trial", "jitter",
    "table", "paths"}``; ``jitter`` pools the control-loop periods of all
    trials of a method ([R-9]). ``verbose`` prints the table and the jitter
    lines, and with ``announce_files`` the paths written.
    """
    trials = check_int("trials", trials, 1, 10000)
    seed0 = check_int("seed0", seed0, 0, 2**31 - 1)
    key_seed = check_int("key_seed", key_seed, 0, 2**31 - 1)
    added_latency_s = check_number("added_latency_s", added_latency_s, 0.0, 10.0)
    out = check_out_dir("out_dir", out_dir)
    for name in ("results.csv", "summary.csv", "traces.png"):
        if (out / name).is_dir():
            raise ValueError(f"out_dir {str(out)!r} holds a folder {name!r} where the study writes a file")
    limit_max = ArmConfig().max_steps
    if max_steps is not None:
        max_steps = check_int("max_steps", max_steps, 1, limit_max)
    for name, flag in (("plot", plot), ("verbose", verbose), ("announce_files", announce_files)):
        if not isinstance(flag, bool):
            raise ValueError(f"{name} must be True or False, got {flag!r}")
    methods = tuple(methods)
    if not methods:
        raise ValueError("methods must not be empty")
    policies = load_policies(checkpoint_dir, methods)
    for p in policies.values():
        p.warmup()
    out.mkdir(parents=True, exist_ok=True)
    cfg = RuntimeConfig(added_latency_s=added_latency_s)
    base_key = jax.random.key(key_seed)
    per_trial, rows, jitter, first_records, delay_hist = {}, {}, {}, {}, {}
    periods = {m: [] for m in methods}
    delays = {m: [] for m in methods}
    for m in methods:
        per_trial[m] = []
    csv_rows = []
    # Interleaved ([A-25]): trial i runs every method in turn, the order rotated by i, so that a change in
    # the machine's load during the study falls on every method alike.
    for i in range(trials):
        for m in methods[i % len(methods):] + methods[:i % len(methods)]:
            rec = run_realtime_episode(policies[m], seed0 + i, jax.random.fold_in(base_key, i), cfg,
                                       max_steps=max_steps)
            met = episode_metrics(rec)
            per_trial[m].append(met)
            periods[m].append(rec.periods_s)
            delays[m].extend(int(x) for x in rec.realized_delays[1:])
            if i == 0:
                first_records[m] = rec
            csv_rows.append({"method": m, "trial": i, "env_seed": seed0 + i, **met,
                             "mean_realized_delay": defined_mean([x for x in rec.realized_delays[1:] if x >= 0])})
            if verbose:
                print(f"  {METHOD_LABELS.get(m, m):15s} trial {i}: success={met['success']} "
                      f"parts={met['completed']}/4 t={met['duration_s']:.1f}s lat={met['latency_ms']:.1f}ms "
                      f"fault={met['fault']}", flush=True)
    for m in methods:
        rows[m] = summarize(per_trial[m])
        ps = [p for p in periods[m] if p.size]
        allp = np.concatenate(ps) if ps else np.zeros(1)
        jitter[m] = jitter_summary(allp)
        jitter[m]["late_rejects"] = sum(x == -2 for x in delays[m])
        vals, counts = np.unique([x for x in delays[m] if x >= 0], return_counts=True)
        delay_hist[m] = {int(v): int(c) for v, c in zip(vals, counts)}
    table = format_table(rows)
    paths = {"results": str(out / "results.csv"), "summary": str(out / "summary.csv")}
    with open(paths["results"], "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(csv_rows[0]))
        w.writeheader()
        w.writerows(csv_rows)
    with open(paths["summary"], "w", newline="") as f:
        keys = list(next(iter(rows.values())))
        w = csv.DictWriter(f, fieldnames=["method", *keys, "period_p50_ms", "period_p99_ms"])
        w.writeheader()
        for m, r in rows.items():
            w.writerow({"method": m, **r, "period_p50_ms": jitter[m]["p50_ms"], "period_p99_ms": jitter[m]["p99_ms"]})
    if plot:
        paths["traces"] = plot_traces(first_records, out / "traces.png")
    if verbose:
        print()
        print(table)
        print()
        for m in methods:
            j = jitter[m]
            print(f"{METHOD_LABELS.get(m, m):15s} control period p50 {j['p50_ms']:.2f} ms, p99 {j['p99_ms']:.2f} ms, "
                  f"max {j['max_ms']:.1f} ms; realized delays (ticks: count) {delay_hist[m]}; "
                  f"late chunks {j['late_rejects']}")
        if announce_files:
            print("wrote " + ", ".join(paths.values()))
    return {"rows": rows, "per_trial": per_trial, "jitter": jitter, "delays": delay_hist, "table": table,
            "paths": paths}


if __name__ == "__main__":  # python -m softrtc.arm.study results/arm/realtime/results.csv
    import sys

    if len(sys.argv) != 2:
        sys.exit("usage: python -m softrtc.arm.study RESULTS_CSV")
    print(table_from_results(sys.argv[1]))
