"""`softrtc conformance run|generate` ([CF-19]); registered by softrtc/cli.py through add_subparsers.

Also runnable without the main CLI: ``python -m softrtc.conformance run --impl reference``.
"""

from __future__ import annotations

import argparse
import sys

from . import generate, runner


def add_subparsers(subparsers) -> None:
    """Register the `conformance` command with its `run` and `generate` subcommands."""
    conf = subparsers.add_parser("conformance", help="conformance vectors: run an implementation against them, "
                                                     "or regenerate them from the reference")
    sub = conf.add_subparsers(dest="conformance_command", metavar="SUBCOMMAND")
    conf.set_defaults(func=lambda args: (conf.print_help(), 2)[1])
    run_p = sub.add_parser("run", help="run the vectors against an adapter (reference, jax, torch, torch-flipped, "
                                       "module:ATTR or file.py:ATTR)")
    runner.add_arguments(run_p)
    run_p.set_defaults(func=runner.run_from_args)
    gen_p = sub.add_parser("generate", help="regenerate the vector files from the NumPy reference")
    generate.add_arguments(gen_p)
    gen_p.set_defaults(func=generate.run_from_args)


def demo() -> int:
    """Demo step of `softrtc demo`: the reference adapter against the shipped vectors."""
    return runner.run_from_args(argparse.Namespace(impl="reference", vectors=None, report=None, junit=None,
                                                   only=None))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance")
    add_subparsers(parser.add_subparsers(dest="command", metavar="COMMAND"))
    args = parser.parse_args(["conformance", *(argv if argv is not None else sys.argv[1:])])
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
