"""``softrtc arm`` subcommands: ``train``, ``study``, ``expert`` (spec [A-14], [A-20], [A-25])."""

from __future__ import annotations

import argparse
import tempfile

__all__ = ["add_subparsers", "demo"]


def _nonneg_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {text!r}") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"expected an integer >= 0, got {v}")
    return v


def _pos_int(text: str) -> int:
    v = _nonneg_int(text)
    if v < 1:
        raise argparse.ArgumentTypeError(f"expected an integer >= 1, got {v}")
    return v


def add_subparsers(subparsers) -> None:
    """Register ``arm train``, ``arm study`` and ``arm expert`` on the top-level CLI."""
    arm = subparsers.add_parser("arm", help="planar arm sorting study (spec/10-arm.md)")
    sub = arm.add_subparsers(dest="arm_command", metavar="ARM_COMMAND")
    arm.set_defaults(func=lambda a: (arm.print_help(), 0)[1])

    tr = sub.add_parser("train", help="demos, base BC flow policy, Train Hard / Soft RTC fine-tunes ([A-20])")
    tr.add_argument("--out", default=None, help="checkpoint folder (default: softrtc/arm/checkpoints)")
    tr.add_argument("--episodes", type=_pos_int, default=400, help="DART demo episodes (default 400)")
    tr.add_argument("--steps", type=_pos_int, default=4000, help="base training steps (default 4000)")
    tr.add_argument("--finetune-steps", type=_pos_int, default=800, help="RTC fine-tune steps (default 800)")
    tr.add_argument("--seed", type=_nonneg_int, default=0, help="seed of demos and training (default 0)")
    tr.set_defaults(func=_train)

    st = sub.add_parser("study", help="real-time study table, CSV and joint-trace plot ([A-25])")
    st.add_argument("--checkpoints", default=None, help="checkpoint folder (default: the shipped ones)")
    st.add_argument("--trials", type=_pos_int, default=10, help="trials per method (default 10)")
    st.add_argument("--latency-ms", type=float, default=55.0,
                    help="added policy latency in ms (default 55: realized delay 3-4 ticks)")
    st.add_argument("--seed0", type=_nonneg_int, default=10_000, help="first env seed (default 10000)")
    st.add_argument("--key-seed", type=_nonneg_int, default=0, help="sampler key seed (default 0)")
    st.add_argument("--max-steps", type=_pos_int, default=None, help="ticks per episode (default 1000)")
    st.add_argument("--out", default="arm_study", help="output folder (default ./arm_study)")
    st.set_defaults(func=_study)

    ex = sub.add_parser("expert", help="scripted expert success rate over seeds ([A-14])")
    ex.add_argument("-n", type=_pos_int, default=100, help="episodes (default 100)")
    ex.add_argument("--seed0", type=_nonneg_int, default=0, help="first seed (default 0)")
    ex.set_defaults(func=_expert)


def _train(args) -> int:
    from .policies import default_checkpoint_dir, train_arm_policies

    out = args.out or str(default_checkpoint_dir())
    paths = train_arm_policies(out, episodes=args.episodes, steps=args.steps, finetune_steps=args.finetune_steps,
                               seed=args.seed)
    for m, p in paths.items():
        print(f"{m}: {p}")
    return 0


def _study(args) -> int:
    from .study import run_study

    run_study(args.checkpoints, trials=args.trials, added_latency_s=args.latency_ms / 1000.0, seed0=args.seed0,
              key_seed=args.key_seed, out_dir=args.out, max_steps=args.max_steps)
    return 0


def _expert(args) -> int:
    from .expert import expert_success_rate

    expert_success_rate(n=args.n, seed0=args.seed0)
    return 0


def demo() -> int:
    """A one-trial study per method on the shipped checkpoints (about a minute), for ``softrtc demo``."""
    from .study import run_study

    with tempfile.TemporaryDirectory() as d:
        run_study(None, trials=1, out_dir=d, max_steps=250, plot=False)
    return 0
