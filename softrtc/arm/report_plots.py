"""Plots of the arm experiment ([AX-6]): success / jerk frontier, window sweeps, success per delay and the
sampler windows' weights, written as PNG files beside a task's summary."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from softrtc.reference import endpoints as rep
from softrtc.reference import weights as rw

from .experiment import H
from .report_summary import _get, _rows_in_order, summarize

__all__ = ["plot_all"]


def _window_from(d):
    rule = d["rule"]
    kind = rule["kind"]
    if kind == "delay_scaled":
        r = rep.delay_scaled(float(rule["lam"]), int(rule["h_max"]))
    elif kind == "offset":
        r = rep.offset(int(rule["length"]), int(rule["h_max"]))
    elif kind == "fixed":
        r = rep.fixed(int(rule["length"]))
    else:
        r = rep.hard()
    return rw.SoftWindow(r, d["schedule"], d["parametrization"], d["overflow"])


def _save(plt, fig, path: Path) -> Path:
    """``fig`` as a PNG at ``path`` (no software tag, so the bytes depend on the figure only), then closed."""
    fig.tight_layout()
    fig.savefig(path, dpi=100, metadata={"Software": None})
    plt.close(fig)
    return path


def plot_all(res, out_dir, summary: dict | None = None) -> list:
    """PNG plots: frontier, sweeps, success per delay, window weights ([AX-6]); ``summary`` is
    ``summarize(res)`` when already computed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    summary = summarize(res) if summary is None else summary
    m = res["manifest"]
    out_dir = Path(out_dir)
    paths = []
    # Frontier: overall success vs high-delay D2.
    fig, ax = plt.subplots(figsize=(7, 5))
    for r, info in _rows_in_order(m):
        a, b = _get(summary, r, "overall", "success"), _get(summary, r, "high", "D2")
        if not a or not b or not math.isfinite(b["mean"]):
            continue
        xe = [[max(a["mean"] - a["lo"], 0) if math.isfinite(a["lo"]) else 0],
              [max(a["hi"] - a["mean"], 0) if math.isfinite(a["hi"]) else 0]]
        ye = [[max(b["mean"] - b["lo"], 0) if math.isfinite(b["lo"]) else 0],
              [max(b["hi"] - b["mean"], 0) if math.isfinite(b["hi"]) else 0]]
        ax.errorbar(a["mean"], b["mean"], xerr=xe, yerr=ye, fmt="o" if info["tier"] == "main" else ".",
                    capsize=2, alpha=1.0 if info["tier"] == "main" else 0.5)
        if info["tier"] == "main":
            ax.annotate(r, (a["mean"], b["mean"]), fontsize=6)
    ax.set_xlabel("overall success")
    ax.set_ylabel("high-delay D2 (jerk)")
    ax.set_title(f"task {m['task']}: success / high-delay jerk frontier")
    paths.append(_save(plt, fig, out_dir / "frontier.png"))
    # Sweeps.
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ov, mk in (("clip", "o-"), ("zeros", "s--")):
        Ls = [L for L in range(7) if f"offset{L}_{ov}" in summary and _get(summary, f"offset{L}_{ov}", "high", "success")]
        if Ls:
            axes[0].plot(Ls, [_get(summary, f"offset{L}_{ov}", "high", "success")["mean"] for L in Ls], mk,
                         label=f"offset {ov}")
            axes[1].plot(Ls, [_get(summary, f"offset{L}_{ov}", "high", "D2")["mean"] for L in Ls], mk,
                         label=f"offset {ov}")
    axes[0].set_xlabel("L")
    axes[0].set_ylabel("high-delay success")
    axes[1].set_xlabel("L")
    axes[1].set_ylabel("high-delay D2")
    axes[0].legend(fontsize=7)
    paths.append(_save(plt, fig, out_dir / "sweeps.png"))
    # Success per delay.
    fig, ax = plt.subplots(figsize=(7, 4))
    for r, info in _rows_in_order(m):
        if info["tier"] != "main" or r not in summary:
            continue
        ds = summary[r]["delays"]
        ax.plot(ds, [_get(summary, r, f"d{d}", "success")["mean"] for d in ds], "o-", label=r)
    ax.set_xlabel("delay d (ticks)")
    ax.set_ylabel("success")
    ax.legend(fontsize=6)
    paths.append(_save(plt, fig, out_dir / "success_by_delay.png"))
    # Window weights.
    s = m["execute_horizon"]
    maxd = min(s, H - s)
    wrows = [(r, i) for r, i in _rows_in_order(m) if i["sampler_window"] is not None]
    fig, axes = plt.subplots(1, len(wrows), figsize=(1.2 * len(wrows), 2.6), squeeze=False)
    for ax, (r, info) in zip(axes[0], wrows):
        win = _window_from(info["sampler_window"])
        ax.imshow(np.stack([rw.soft_weights(H, d, win, s) for d in range(maxd + 1)]), vmin=0, vmax=1, cmap="viridis")
        ax.axvline(H - s - 0.5, color="r", lw=0.8)
        ax.set_title(r, fontsize=5)
        ax.set_xticks([])
        ax.set_yticks(range(maxd + 1))
        ax.tick_params(labelsize=5)
    paths.append(_save(plt, fig, out_dir / "window_weights.png"))
    return paths
