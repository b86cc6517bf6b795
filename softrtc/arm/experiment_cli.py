"""``softrtc arm experiment`` and ``softrtc arm report`` ([AX-4], [AX-6])."""

from __future__ import annotations

import argparse
import time

from .._cli_util import command_error, comma_list, int_in, missing_extra, output_dir

__all__ = ["add_experiment_parsers"]


def _tier(text: str) -> str:
    if text not in ("main", "sweep", "tsweep"):
        raise argparse.ArgumentTypeError(f"tier must be main, sweep or tsweep, got {text!r}")
    return text


def add_experiment_parsers(sub) -> None:
    """Register ``arm experiment`` and ``arm report`` on the ``softrtc arm`` subparsers."""
    from .tasks import TASKS

    ex = sub.add_parser("experiment", help="controlled arm experiment: paired episodes, shared fine-tunes, "
                                           "resumable ([AX-1]..[AX-5])")
    ex.add_argument("--task", choices=tuple(TASKS), default="drift",
                    help="task setting (default drift, the delay-sensitive one, [AX-8])")
    ex.add_argument("--quick", action="store_true", help="tiny budget: the whole pipeline in a few minutes")
    ex.add_argument("--out", type=output_dir(), default="results/arm", help="results folder (default results/arm)")
    ex.add_argument("--work", type=output_dir(), default="arm_experiment_work",
                    help="folder for demos and fine-tuned checkpoints (default ./arm_experiment_work)")
    ex.add_argument("--rows", type=comma_list("row"), default=None, help="only these rows (comma-separated)")
    ex.add_argument("--tiers", type=comma_list("tier", _tier), default=["main", "sweep", "tsweep"],
                    help="main, sweep (window sweeps) and/or tsweep (the Euler-step sweep); default all three")
    # ASCII digits only ([N-11]): int() would read '١' as 1. The task's own range is checked by run_experiment
    # before any work; here the bound is the largest delay of any task.
    max_delay = max(t.max_delay for t in TASKS.values())
    ex.add_argument("--delays", type=comma_list("delay", int_in("each delay", 0, max_delay)), default=None,
                    help="only these delays")
    ex.add_argument("--seeds", type=comma_list("seed", int_in("each seed", 1, 2**31 - 1)), default=None,
                    help="only these fine-tuning seeds (1-based, at most the budget's number of seeds)")
    ex.add_argument("--episodes", type=int_in("value", 1, 100000), default=None,
                    help="at most this many episodes per cell (a later run with more extends the cells)")
    ex.add_argument("--workers", type=int_in("value", 1, 64), default=2, help="episode worker processes (default 2)")
    ex.add_argument("--report", action="store_true", help="write REPORT.md and plots afterwards")
    ex.set_defaults(func=_experiment)

    sc = sub.add_parser("screen", help="delay screen of a task: the scripted expert closed loop and as a chunk "
                                       "policy under each delay ([AX-8])")
    sc.add_argument("--task", choices=tuple(TASKS), default="drift", help="task setting (default drift)")
    sc.add_argument("-n", type=int_in("value", 1, 100000), default=24, help="paired env seeds (default 24)")
    sc.add_argument("--seed0", type=int_in("value", 0, 2**31 - 1), default=10_000,
                    help="first env seed (default 10000, the experiment's)")
    sc.set_defaults(func=_screen)

    rp = sub.add_parser("report", help="REPORT.md, summary.json and plots from the experiment's result files ([AX-6])")
    rp.add_argument("--results", default="results/arm", help="results folder (default results/arm)")
    rp.add_argument("--readme", default=None, help="also regenerate the arm table of this README")
    rp.add_argument("--readme-task", choices=tuple(TASKS), default="drift",
                    help="the task whose main table goes into the README (default drift)")
    rp.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    rp.set_defaults(func=_report)


def _experiment(args) -> int:
    hint = missing_extra("tqdm", "matplotlib") if args.report else missing_extra("tqdm")  # [N-13]
    if hint:
        return command_error(args._prog, hint)
    from .experiment import run_experiment

    t0 = time.perf_counter()
    r = run_experiment(args.task, "quick" if args.quick else "full", out=args.out, work=args.work, rows=args.rows,
                       delays=args.delays, seeds=args.seeds, tiers=tuple(args.tiers), workers=args.workers,
                       episodes=args.episodes)
    print(f"{r['cells']} cells, {r['ran']} run now, {time.perf_counter() - t0:.0f} s in all")
    if args.report:
        from .report import write_report

        print(write_report(args.out))
    return 0


def _screen(args) -> int:
    from .expert import run_expert_episode
    from .expert_chunks import delay_screen
    from .tasks import get_task

    task = get_task(args.task)
    seeds = range(args.seed0, args.seed0 + args.n)
    closed = sum(run_expert_episode(sd, task.env_config)["success"] for sd in seeds)
    print(f"task {task.name}: closed-loop expert solves {closed}/{args.n}")
    for d, v in delay_screen(task.env_config, task.execute_horizon, range(task.max_delay + 1), seeds).items():
        print(f"  chunked expert (s = {task.execute_horizon}) d = {d}: success {v['success']:.2f}, "
              f"completion {v['completion']:.2f}")
    return 0


def _report(args) -> int:
    hint = None if args.no_plots else missing_extra("matplotlib")  # [N-13] before any file is written
    if hint:
        return command_error(args._prog, f"{hint} (or run with --no-plots)")
    from .report import write_report

    print(write_report(args.results, readme=args.readme, readme_task=args.readme_task, plots=not args.no_plots))
    return 0
