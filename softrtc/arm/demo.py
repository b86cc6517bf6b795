"""The arm part of ``softrtc demo``: a small paired comparison on the delay-sensitive task ``drift`` ([AX-8]).

The methods the shipped ``drift`` base runs without a fine-tune (Naive, Inference Hard RTC, Inference Soft
RTC, [S-6]) each play the same few episodes at a low and a high delay in the simulated-delay executor
([X-1]..[X-6]), with the environment seeds and sampler keys of the controlled experiment's cells
(``seed0 + i`` and ``fold_in(key(key_seed), i)`` for episode ``i``, [AX-2]): on the CPU model that ran the
committed experiment its first episodes are the demo's ([AX-9]). It prints success and the smoothness metrics
side by side, beside the committed experiment's cells of the same rows and delays when a checkout's
``results/arm/<task>/episodes/`` holds them (a few episodes decide little about success; the full cells do),
and writes a plot. The experiment with intervals is ``softrtc arm experiment`` and ``results/arm/REPORT.md``.
"""

from __future__ import annotations

import os
import time

import numpy as np

from softrtc.reference._validate import check_int

from .._files import check_out_file, write_atomic

__all__ = ["DEMO_ROWS", "run_demo", "format_table"]

# The rows of the experiment ([AX-2]) that run the task's shipped base as it is, so the demo trains nothing.
DEMO_ROWS = ("naive", "inference_hard", "inference_soft")
METRICS = ("success", "D2", "boundary")


def _rows(task):
    from .experiment import rows_for

    rows = {r.name: r for r in rows_for(task)}
    return [rows[name] for name in DEMO_ROWS]


def committed_cells(results_root, task, delays) -> dict:
    """``{row: {delay: [episode rows]}}`` of the committed experiment's base-seed cells of :data:`DEMO_ROWS`
    under ``results_root/<task>/episodes`` ([AX-4]); rows or delays without a file are left out."""
    from .experiment import eval_key, read_episodes

    out: dict = {}
    folder = os.path.join(os.fspath(results_root), task.name, "episodes")
    for row in _rows(task):
        for d in delays:
            path = os.path.join(folder, f"{eval_key(row, task)}_s0_d{d}.csv")
            if os.path.isfile(path):
                out.setdefault(row.name, {})[d] = read_episodes(path)
    return out


def run_demo(plot_path, *, episodes: int = 4, delays=(1, 5), task_name: str = "drift", seed0: int = 10_000,
             key_seed: int = 0, max_steps: int | None = None, results_root="results/arm", log=print) -> dict:
    """Play ``episodes`` paired episodes per row and delay; print the table, write the plot to ``plot_path``.

    Returns ``{row: {delay: [episode metrics]}}`` (``success``, ``D2``, ``boundary``, ``steps`` of each
    episode, in episode order). ``delays`` are executable delays of the task ([X-1]); ``max_steps``
    shortens every episode (default: the task's limit of [A-11]); ``results_root`` is where the committed
    experiment's cells are looked for (absent: the table shows the demo's episodes alone).
    """
    import jax

    from .executor import episode_metrics, run_simulated_episode
    from .experiment import _load
    from .tasks import get_task

    task = get_task(task_name)
    plot_path = check_out_file("plot_path", plot_path, ".png")
    episodes = check_int("episodes", episodes, 1, 1000)
    if not isinstance(delays, (tuple, list)) or not delays:
        raise ValueError(f"delays must be a non-empty tuple of integers in [0, {task.max_delay}], got {delays!r}")
    delays = tuple(check_int(f"delays[{i}]", d, 0, task.max_delay) for i, d in enumerate(delays))
    if len(set(delays)) != len(delays):
        raise ValueError(f"delays must not repeat a delay, got {delays!r}")
    seed0 = check_int("seed0", seed0, 0, 2**31 - 1 - episodes)
    key_seed = check_int("key_seed", key_seed, 0, 2**31 - 1)
    ckpt = task.base_checkpoint()
    out: dict = {}
    t0 = time.perf_counter()
    for row in _rows(task):
        policy = _load(ckpt, task, row)
        out[row.name] = {}
        for d in delays:
            cell = []
            for i in range(episodes):
                # The experiment's pairing: env seed and sampler key depend on the episode index only.
                rec = run_simulated_episode(policy, seed0 + i, d, jax.random.fold_in(jax.random.key(key_seed), i),
                                            max_steps=max_steps, env_config=task.env_config)
                m = episode_metrics(rec)
                cell.append({"success": bool(m["success"]), "D2": float(m["D2"]), "boundary": float(m["boundary"]),
                             "steps": int(rec.steps)})
            out[row.name][d] = cell
    labels = {r.name: r.label for r in _rows(task)}
    full = committed_cells(results_root, task, delays) if results_root is not None else {}
    log(f"arm, task {task.name} (s = {task.execute_horizon}), shipped base checkpoint; {episodes} paired episodes "
        f"per method and delay (env seeds {seed0}..{seed0 + episodes - 1}, the same for every method); "
        f"{time.perf_counter() - t0:.0f} s")
    log(format_table(out, labels))
    if full:
        n = {len(c) for by_d in full.values() for c in by_d.values()}
        log(f"\nthe committed experiment's cells of these rows ({results_root}/{task.name}, "
            f"{'/'.join(map(str, sorted(n)))} paired episodes each):")
        log(format_table(full, labels))
    log("\nA few episodes decide little about success; D2 and the boundary jump (per episode, lower is smoother) "
        "separate the methods sooner. The committed experiment: success does not separate Naive from "
        "inference-time RTC, which executes smoother actions at high delay.")
    _plot(out, labels, plot_path, task.name, episodes, full)
    log(f"wrote {os.path.abspath(plot_path)}")
    log("The full experiment (fine-tuned rows too, intervals, verdicts): `softrtc arm experiment` and "
        "results/arm/REPORT.md.")
    return out


def _mean(cell, key: str) -> float:
    vals = np.asarray([e[key] for e in cell], float)
    vals = vals[np.isfinite(vals)]
    return float(vals.mean()) if vals.size else float("nan")


def format_table(out: dict, labels: dict) -> str:
    """One line per method: successes and mean ``D2`` and boundary jump ([M-1], [A-24]) at each delay."""
    delays = sorted({d for by_d in out.values() for d in by_d})
    head = f"{'method':<22}" + "".join(f"{f'd={d}: solved  D2     bound.':>30}" for d in delays)
    lines = [head, "-" * len(head)]
    for name, by_d in out.items():
        cells = []
        for d in delays:
            c = by_d.get(d, [])
            if not c:
                cells.append(f"{'-':>15}  {'-':>6} {'-':>6}")
                continue
            solved = sum(bool(e["success"]) for e in c)
            cells.append(f"{f'{solved}/{len(c)}':>15}  {_mean(c, 'D2'):6.4f} {_mean(c, 'boundary'):6.4f}")
        lines.append(f"{labels.get(name, name):<22}" + "".join(cells))
    return "\n".join(lines)


def _plot(out: dict, labels: dict, path: str, task: str, episodes: int, full: dict) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    delays = list(next(iter(out.values())))
    names = list(out)
    x = np.arange(len(delays))
    width = 0.8 / len(names)
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for k, name in enumerate(names):
        succ = [_mean(out[name][d], "success") for d in delays]
        d2 = [_mean(out[name][d], "D2") for d in delays]
        pos = x + (k - (len(names) - 1) / 2) * width
        axes[0].bar(pos, succ, width, label=labels.get(name, name))
        axes[1].bar(pos, d2, width, label=labels.get(name, name))
        if name in full:  # the committed cells' means as markers over the demo's bars
            have = [i for i, d in enumerate(delays) if full[name].get(d)]
            for ax, key in ((axes[0], "success"), (axes[1], "D2")):
                ax.plot(pos[have], [_mean(full[name][delays[i]], key) for i in have], "kD", markersize=5,
                        label="committed experiment" if k == 0 and ax is axes[0] else None)
    for ax, title in zip(axes, (f"success rate ({episodes} paired episodes)", "D2 (mean over episodes; lower is "
                                                                             "smoother)")):
        ax.set_xticks(x, [f"delay {d}" for d in delays])
        ax.set_title(title)
    axes[0].set_ylim(0, 1)
    axes[0].legend(fontsize=8)
    fig.suptitle(f"arm task {task}: naive vs inference-time RTC on the shipped base (bars: this run; "
                 f"diamonds: the committed experiment's cells)" if full else
                 f"arm task {task}: naive vs inference-time RTC on the shipped base")
    fig.tight_layout()
    write_atomic(path, lambda f: fig.savefig(f, format="png", dpi=100, metadata={"Software": None}), binary=True)
    plt.close(fig)
