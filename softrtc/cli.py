"""The ``softrtc`` command line.

Subcommands register themselves through an ``add_subparsers(subparsers)``
function in their package's ``cli`` module; a subpackage whose optional
dependencies are missing is listed with the install hint instead.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys

from ._cli_util import command_error, leaf_progs

# (module, extra that provides its dependencies)
_SUBCOMMAND_MODULES = [
    ("softrtc.reference.cli", None),
    ("softrtc.conformance.cli", None),
    ("softrtc.jax.cli", "jax"),
    ("softrtc.arm.cli", "arm"),
    ("softrtc.kinetix.cli", "kinetix"),
]


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="softrtc",
        description="Reference semantics of real-time chunking (RTC) and Soft RTC.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser("demo", help="the main job: worked examples, weights table, and every "
                                       "available check on built-in defaults")
    demo.set_defaults(func=_demo)
    for mod_name, extra in _SUBCOMMAND_MODULES:
        try:
            mod = importlib.import_module(mod_name)
        except ModuleNotFoundError as exc:
            if exc.name and exc.name.startswith("softrtc"):
                continue  # subcommand not present in this build
            hint = f" (pip install 'softrtc[{extra}]')" if extra else ""
            sub.add_parser(mod_name.split(".")[1], help=f"unavailable: missing {exc.name}{hint}")
            continue
        mod.add_subparsers(sub)
    leaf_progs(parser)
    return parser


def _demo(args) -> int:
    """Run every demo step that is available, in order; fail if any fails."""
    steps = []
    for mod_name, _ in _SUBCOMMAND_MODULES:
        try:
            mod = importlib.import_module(mod_name)
        except ModuleNotFoundError:
            continue
        if hasattr(mod, "demo"):
            steps.append((mod_name, mod.demo))
    status = 0
    for name, fn in steps:
        print(f"\n=== {name.rsplit('.', 2)[1]} ===", flush=True)
        rc = fn()
        if rc:
            print(f"demo step {name} failed with status {rc}", file=sys.stderr)
            status = rc
    return status


def main(argv=None) -> int:
    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:  # reported by the parser of the command they were given to, with its usage line
        args._parser.error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "func", None):
        # [N-11] Like a command group without its subcommand: the help, and the status of a usage error.
        parser.print_help()
        return 2
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        # The reader of stdout went away (`softrtc weights | head`): stop quietly, as other Unix tools do.
        # Point stdout at devnull so the interpreter's final flush does not raise a second time.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, the status a shell reports for a tool killed by a closed pipe
    except (ValueError, OSError, OverflowError) as exc:
        # Invalid input ([N-7]) or an unusable file: one line naming the problem, no traceback.
        # SOFTRTC_TRACEBACK=1 shows the traceback when debugging softrtc itself.
        return command_error(args._prog, exc)


if __name__ == "__main__":
    sys.exit(main())
