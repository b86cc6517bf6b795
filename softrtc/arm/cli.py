"""``softrtc arm`` subcommands: ``train``, ``study``, ``expert``, ``mechanism``, ``experiment``, ``report`` (spec [A-14],
[A-20], [A-25], [AX-4], [AX-5])."""

from __future__ import annotations

import os

from .._cli_util import (command_error, comma_list, group_help, input_dir, int_in, missing_extra, output_dir,
                         output_file, real_in)

__all__ = ["add_subparsers", "demo"]


SEED_MAX = 2**31 - 1
# [A-20] `arm train` writes to a folder of the current directory unless told otherwise: a trial run never
# replaces the shipped checkpoints of the installed package.
DEFAULT_TRAIN_OUT = "arm_checkpoints"


def add_subparsers(subparsers) -> None:
    """Register ``arm train``, ``arm study`` and ``arm expert`` on the top-level CLI."""
    arm = subparsers.add_parser("arm", help="planar arm sorting study (spec/10-arm.md)")
    sub = arm.add_subparsers(dest="arm_command", metavar="ARM_COMMAND")
    arm.set_defaults(func=group_help(arm))

    tr = sub.add_parser("train", help="demos, base BC flow policy, Train Hard / Soft RTC fine-tunes ([A-20])")
    tr.add_argument("--out", type=output_dir(), default=DEFAULT_TRAIN_OUT,
                    help=f"checkpoint folder (default ./{DEFAULT_TRAIN_OUT}; the shipped checkpoints in "
                         "softrtc/arm/checkpoints are replaced only when named here)")
    tr.add_argument("--episodes", type=int_in("value", 1, 100000), default=400,
                    help="DART demo episodes, 1 .. 100000 (default 400)")
    tr.add_argument("--steps", type=int_in("value", 1, 10**7), default=4000, help="base training steps (default 4000)")
    tr.add_argument("--finetune-steps", type=int_in("value", 1, 10**7), default=800,
                    help="RTC fine-tune steps (default 800)")
    tr.add_argument("--seed", type=int_in("value", 0, SEED_MAX - 2), default=0,
                    help=f"seed of demos and training, 0 .. {SEED_MAX - 2} (default 0)")
    from .tasks import TASKS

    tr.add_argument("--task", choices=tuple(TASKS), default="easy",
                    help="the world the demonstrations are recorded in (default easy, the default world)")
    tr.add_argument("--base-only", action="store_true", help="train and write base.npz only (no fine-tunes)")
    tr.set_defaults(func=_train)

    st = sub.add_parser("study", help="real-time study table, CSV and joint-trace plot ([A-25])")
    st.add_argument("--checkpoints", type=input_dir(), default=None,
                    help="checkpoint folder (default: the shipped ones)")
    st.add_argument("--trials", type=int_in("value", 1, 10000), default=10, help="trials per method, 1 .. 10000 "
                                                                                 "(default 10)")
    st.add_argument("--latency-ms", type=real_in("value", 0.0, 10000.0), default=55.0,
                    help="added policy latency in ms, 0 .. 10000 (default 55: realized delay 3-4 ticks)")
    st.add_argument("--seed0", type=int_in("value", 0, SEED_MAX), default=10_000, help="first env seed (default 10000)")
    st.add_argument("--key-seed", type=int_in("value", 0, SEED_MAX), default=0, help="sampler key seed (default 0)")
    st.add_argument("--max-steps", type=int_in("value", 1, 1000), default=None,
                    help="ticks per episode, 1 .. 1000 (default 1000)")
    st.add_argument("--out", type=output_dir(), default="arm_study", help="output folder (default ./arm_study)")
    st.set_defaults(func=_study)

    ex = sub.add_parser("expert", help="scripted expert success rate over seeds ([A-14])")
    ex.add_argument("-n", type=int_in("value", 1, 100000), default=100, help="episodes (default 100)")
    ex.add_argument("--seed0", type=int_in("value", 0, SEED_MAX), default=0, help="first seed (default 0)")
    ex.set_defaults(func=_expert)

    from .tasks import TASKS

    me = sub.add_parser("mechanism", help="where a soft checkpoint's executed window tokens go under each solver "
                                          "step: pull toward the prior ([AX-5])")
    me.add_argument("--checkpoint", required=True, help="arm checkpoint of a soft fine-tune (an .npz file)")
    me.add_argument("--task", choices=tuple(TASKS), default="drift", help="task setting (default drift)")
    me.add_argument("--delays", type=comma_list("delay", int_in("each delay", 1, 5)), default=[1, 2, 3, 4, 5],
                    help="delays d >= 1 (default 1,2,3,4,5)")
    me.add_argument("--episodes", type=int_in("episodes", 1, 10_000), default=20,
                    help="closed-loop episodes per delay and step (default 20)")
    me.add_argument("--max-steps", type=int_in("max_steps", 1, 1000), default=1000,
                    help="ticks per episode at most (default 1000)")
    me.add_argument("--out", type=output_file(), default=os.path.join("runs", "mechanism.json"),
                    help="JSON output (default runs/mechanism.json; the committed one is "
                         "results/arm/drift/mechanism.json)")
    me.set_defaults(func=_mechanism)

    from .experiment_cli import add_experiment_parsers

    add_experiment_parsers(sub)


def _train(args) -> int:
    from .training import train_arm_policies

    from .tasks import get_task

    paths = train_arm_policies(args.out, episodes=args.episodes, steps=args.steps, finetune_steps=args.finetune_steps,
                               seed=args.seed, env_config=get_task(args.task).env_config,
                               fine_tune=not args.base_only)
    for m, p in paths.items():
        print(f"{m}: {p}")
    return 0


def _study(args) -> int:
    hint = missing_extra("matplotlib")  # [N-13] the trace plot comes after the trials: check it first
    if hint:
        return command_error(args._prog, hint)
    from .study import run_study

    run_study(args.checkpoints, trials=args.trials, added_latency_s=args.latency_ms / 1000.0, seed0=args.seed0,
              key_seed=args.key_seed, out_dir=args.out, max_steps=args.max_steps)
    return 0


def _mechanism(args) -> int:
    from .mechanism import measure_pull, write_pull

    res = measure_pull(args.checkpoint, args.task, tuple(args.delays), args.episodes, max_steps=args.max_steps)
    write_pull(res, args.out)
    print(f"wrote {args.out}")
    return 0


def _expert(args) -> int:
    from .expert import expert_success_rate

    expert_success_rate(n=args.n, seed0=args.seed0)
    return 0


# Where `softrtc demo` writes its arm plot, relative to the current folder (runs/ as the other commands' outputs).
DEMO_PLOT = os.path.join("runs", "demo", "arm_drift.png")


def demo() -> int:
    """Paired simulated-delay episodes of Naive and inference-time RTC on ``drift`` at a low and a high delay,
    success and D2 side by side, and a plot (about a minute), for ``softrtc demo``."""
    from .demo import run_demo

    os.makedirs(os.path.dirname(DEMO_PLOT), exist_ok=True)
    run_demo(DEMO_PLOT)
    return 0
