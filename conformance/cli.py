"""`softrtc conformance run|generate|report|rollout` ([CF-19], [TP-1], [CR-8]); registered by softrtc/cli.py through add_subparsers.

Also runnable without the main CLI: ``python -m softrtc.conformance run --impl reference``.
"""

from __future__ import annotations

import argparse
import os
import sys

from .._cli_util import group_help, leaf_progs
from . import generate, report, rollout, runner


def add_subparsers(subparsers) -> None:
    """Register the `conformance` command with its `run` and `generate` subcommands."""
    _fill(subparsers.add_parser("conformance", help="conformance vectors: run an implementation against them, "
                                                    "or regenerate them from the reference"))


def _fill(conf: argparse.ArgumentParser) -> None:
    """The `run` and `generate` subcommands on ``conf`` (`softrtc conformance` or `python -m softrtc.conformance`)."""
    sub = conf.add_subparsers(dest="conformance_command", metavar="SUBCOMMAND")
    conf.set_defaults(func=group_help(conf), command="conformance")
    run_p = sub.add_parser("run", help="run the vectors against an adapter (reference, jax, torch, torch-flipped, lerobot, "
                                       "module:ATTR or file.py:ATTR)")
    runner.add_arguments(run_p)
    run_p.set_defaults(func=runner.run_from_args)
    gen_p = sub.add_parser("generate", help="regenerate the vector files from the NumPy reference")
    generate.add_arguments(gen_p)
    gen_p.set_defaults(func=generate.run_from_args)
    rep_p = sub.add_parser("report", help="compatibility report of a third-party implementation (lerobot): "
                                          "write it, --check it, or print its README --summary")
    report.add_arguments(rep_p)
    rep_p.set_defaults(func=report.run_from_args)
    roll_p = sub.add_parser("rollout", help="closed-loop rollouts on the arm or Kinetix: an implementation makes "
                                            "every chunk, checked request by request against the reference, or "
                                            "--vectors")
    rollout.add_arguments(roll_p)
    roll_p.set_defaults(func=rollout.run_from_args)


def demo() -> int:
    """Demo step of `softrtc demo`: the reference adapter against the shipped vectors."""
    return runner.run_from_args(argparse.Namespace(impl="reference", vectors=None, report=None, junit=None,
                                                   only=None))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance")
    _fill(parser)
    leaf_progs(parser)
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        # The reader of stdout went away (`... generate --check | true`): stop quietly, as softrtc's main does.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141


if __name__ == "__main__":
    sys.exit(main())
