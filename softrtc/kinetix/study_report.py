"""The reduced Kinetix study's report: measured expert learning curves and the full study's cost ([KP-14]).

``python -m softrtc.kinetix.study_report [--results DIR]`` reads the committed
files of ``results/kinetix/study/``: ``curve_worlds_l_<level>.csv`` (one row per
PPO iteration, from ``softrtc kinetix train-expert``) and ``study.json`` (the
command and configuration that produced them), and ``results/kinetix/bench.json``
(``softrtc kinetix bench --out``), and prints the Markdown block the README shows between
its ``kinetix-study`` markers. The cost of the full study is the public
release's budget divided by the rates measured here.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from .curves import read_curve_csv

__all__ = ["RELEASE_EXPERT_STEPS", "RELEASE_SEEDS", "NUM_LEVELS", "DATA_STEPS", "EVAL_ENV_STEPS", "SOLVE_TARGET",
           "curve_summary", "report", "main"]

# The release's expert budget per (level, seed): 1000 iterations of 256 envs x 256 steps.
RELEASE_EXPERT_STEPS = 1000 * 256 * 256
RELEASE_SEEDS = 8
NUM_LEVELS = 12
# Expert data per level (the release's default) and the evaluation of [KE-1]: 12 levels x 5 delays x 32
# episodes x 6 methods x 256 steps.
DATA_STEPS = 1_000_000
EVAL_ENV_STEPS = 12 * 5 * 32 * 6 * 256
SOLVE_TARGET = 0.5
LAST_ROWS = 5


def _finite(xs):
    return [x for x in xs if isinstance(x, float) and math.isfinite(x)]


def curve_summary(rows: list[dict]) -> dict:
    """Iterations, env steps, wall time, steady env steps/s (first iteration, which compiles, left out),
    solve rate over the last ``LAST_ROWS`` iterations with episodes, and the best iteration's."""
    if not rows:
        raise ValueError("rows must hold at least one curve row")
    first, last = rows[0], rows[-1]
    rate = math.nan
    if len(rows) > 1 and last["wall_s"] > first["wall_s"]:
        rate = (last["env_steps"] - first["env_steps"]) / (last["wall_s"] - first["wall_s"])
    solved = _finite([r["solved"] for r in rows])
    tail = solved[-LAST_ROWS:]
    return {"iterations": int(last["update"]), "env_steps": int(last["env_steps"]), "wall_s": float(last["wall_s"]),
            "steps_per_s": rate, "solved_last": sum(tail) / len(tail) if tail else math.nan,
            "solved_max": max(solved) if solved else math.nan,
            "episodes": int(sum(r["episodes"] for r in rows if math.isfinite(r["episodes"])))}


def _fmt(x, spec=".3f"):
    return "–" if not (isinstance(x, (int, float)) and math.isfinite(x)) else format(x, spec)


def report(results_dir: str | Path) -> str:
    """The README block of [KP-14] from the files in ``results_dir``."""
    d = Path(results_dir)
    study = json.loads((d / "study.json").read_text())
    bench = json.loads((d.parent / "bench.json").read_text())
    curves = sorted(d.glob("curve_worlds_l_*.csv"))
    if not curves:
        raise FileNotFoundError(f"results_dir {d} holds no curve_worlds_l_<level>.csv")
    lines = ["| Level | PPO iterations | Env steps | Wall time (min) | Env steps/s | Episodes | "
             "Return, first -> last iteration | Solve rate, last 5 iterations | Best iteration's solve rate |",
             "|---|---|---|---|---|---|---|---|---|"]
    rates, reached = [], []
    for f in curves:
        level = f.stem[len("curve_worlds_l_"):]
        rows = read_curve_csv(f)
        s = curve_summary(rows)
        if math.isfinite(s["steps_per_s"]):
            rates.append(s["steps_per_s"])
        if math.isfinite(s["solved_max"]) and s["solved_max"] >= SOLVE_TARGET:
            reached.append(level)
        lines.append(f"| {level} | {s['iterations']} | {s['env_steps']:,} | {s['wall_s'] / 60:.1f} | "
                     f"{_fmt(s['steps_per_s'], '.0f')} | {s['episodes']} | {_fmt(rows[0]['return'])} -> "
                     f"{_fmt(rows[-1]['return'])} | {_fmt(s['solved_last'])} | "
                     f"{_fmt(s['solved_max'])} |")
    rate = sum(rates) / len(rates) if rates else math.nan
    progs = bench["programs"]
    eval_rate = min(v["steps_per_s"] for k, v in progs.items() if k != "bare")
    expert_h = RELEASE_EXPERT_STEPS * RELEASE_SEEDS * NUM_LEVELS / rate / 3600 if rates else math.nan
    one_h = RELEASE_EXPERT_STEPS / rate / 3600 if rates else math.nan
    data_h = DATA_STEPS * NUM_LEVELS / progs["bare"]["steps_per_s"] / 3600
    eval_h = EVAL_ENV_STEPS / eval_rate / 3600
    out = ["\n".join(lines), "",
           f"Configuration: {study['config_text']}; each level stopped after the first iteration that ended past "
           f"{study['max_minutes']} minutes of wall clock, both levels at once, on {study['machine']}. The first "
           f"iteration includes compiling; the rates leave it out. Command: `{study['command']}`.",
           ""]
    if reached:
        out.append(f"Levels reaching a solve rate of {SOLVE_TARGET}: {', '.join(reached)}.")
    else:
        out.append(f"No level reached a solve rate of {SOLVE_TARGET} within this budget, so the study stops at "
                   f"the curves (data, base policies, fine-tuning and the evaluation table are not run).")
    out += ["",
            f"Cost of the full study at the rates measured here: the release trains each expert for "
            f"{RELEASE_EXPERT_STEPS:,} env steps ({RELEASE_SEEDS} seeds x {NUM_LEVELS} levels); at "
            f"{_fmt(rate, '.0f')} PPO env steps/s (mean over the levels above, learning included) one expert takes "
            f"{_fmt(one_h, ',.0f')} h and all of them {_fmt(expert_h, ',.0f')} h. Expert data "
            f"({DATA_STEPS:,} steps per level) take about {_fmt(data_h, '.1f')} h at the bare env's "
            f"{progs['bare']['steps_per_s']:.0f} env steps/s, and the evaluation of [KE-1] "
            f"({EVAL_ENV_STEPS:,} env steps) {_fmt(eval_h, '.1f')} h at the slowest rollout's "
            f"{eval_rate:.0f} env steps/s (bench of {bench['num_envs']} envs). Expert training dominates: the "
            f"full study needs about {_fmt(expert_h / 24, ',.0f')} machine-days of this machine at the PPO rate "
            f"measured under the conditions stated above, or the accelerators the release used. The data and "
            f"evaluation rates come from `softrtc kinetix bench` (results/kinetix/bench.json) and hold for the "
            f"conditions of that run; where the PPO runs shared the machine with other jobs, an idle machine "
            f"trains faster, by up to the ratio of the bare env's rate there to the PPO rate here."]
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="python -m softrtc.kinetix.study_report", description=__doc__.split("\n")[0])
    ap.add_argument("--results", default=str(Path(__file__).resolve().parents[2] / "results" / "kinetix" / "study"),
                    help="folder of the study's result files (default results/kinetix/study)")
    args = ap.parse_args(argv)
    try:
        sys.stdout.write(report(args.results))
    except (OSError, ValueError, KeyError) as exc:
        print(f"study_report: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
