"""Learning curves of the Kinetix pipeline as CSV and PNG ([KP-8]).

One CSV row per training iteration (PPO) or epoch (behaviour cloning); the PNG
plots every numeric column named in ``ys`` against ``x``, one panel each.
Written atomically, so an interrupted run never leaves half a file.
"""

from __future__ import annotations

import csv
import io
import math
import os
from pathlib import Path
from typing import Iterable, Sequence

from softrtc._files import write_atomic

__all__ = ["write_curve_csv", "read_curve_csv", "plot_curves"]


def write_curve_csv(path: str | os.PathLike, rows: Sequence[dict], fields: Sequence[str]) -> Path:
    """Write ``rows`` (dicts) with columns ``fields`` in that order; a missing value is an empty cell."""
    if isinstance(fields, str) or not fields:
        raise ValueError(f"fields must be a non-empty sequence of column names, got {fields!r}")
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=list(fields), extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        w.writerow({k: r.get(k, "") for k in fields})
    text = buf.getvalue()
    write_atomic(path, lambda f: f.write(text))
    return Path(path)


def read_curve_csv(path: str | os.PathLike) -> list[dict]:
    """Rows of a curve CSV with numeric cells as floats (empty or ``nan`` cells as NaN)."""
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    out = []
    for r in rows:
        out.append({k: (float(v) if v not in ("", None) else math.nan) for k, v in r.items()})
    return out


def plot_curves(csv_path: str | os.PathLike, png_path: str | os.PathLike, *, x: str = "env_steps",
                ys: Iterable[str] = ("solved", "return", "loss"), title: str = "") -> Path:
    """PNG of the columns ``ys`` of ``csv_path`` against ``x`` (columns absent from the file are skipped)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_curve_csv(csv_path)
    if not rows:
        raise ValueError(f"csv_path {csv_path} holds no rows to plot")
    if x not in rows[0]:
        raise ValueError(f"x must be a column of {csv_path} ({', '.join(rows[0])}), got {x!r}")
    ys = [y for y in ys if y in rows[0]]
    if not ys:
        raise ValueError(f"ys must name at least one column of {csv_path} ({', '.join(rows[0])})")
    fig, axes = plt.subplots(len(ys), 1, figsize=(6, 2.2 * len(ys)), sharex=True, squeeze=False)
    xs = [r[x] for r in rows]
    for ax, y in zip(axes[:, 0], ys):
        ax.plot(xs, [r[y] for r in rows], marker="." if len(rows) < 50 else None)
        ax.set_ylabel(y)
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(x)
    if title:
        axes[0, 0].set_title(title)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=80)
    plt.close(fig)
    data = buf.getvalue()
    write_atomic(png_path, lambda f: f.write(data), binary=True)
    return Path(png_path)
