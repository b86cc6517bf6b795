"""The ``softrtc`` command line.

Subcommands register themselves through an ``add_subparsers(subparsers)``
function in their package's ``cli`` module; a subpackage whose optional
dependencies are missing is listed with the install hint instead.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import os
import sys

from ._cli_util import command_error, extra_hint, leaf_progs, missing_subcommand

# (module, the name its demo step and missing-extra line go by, extra that provides its dependencies)
_SUBCOMMAND_MODULES = [
    ("softrtc.reference_cli", "reference", None),
    ("softrtc.conformance.cli", "conformance", None),
    ("softrtc.jax.cli", "bench", "jax"),
    ("softrtc.arm.cli", "arm", "arm"),
    ("softrtc.torch.cli", "torch", None),  # adds `bench torch` and `arm torch`; checks its modules itself
    ("softrtc.kinetix.cli", "kinetix", "kinetix"),
]

# The modules each extra installs that its commands import (lazily, when they run).
_EXTRA_MODULES = {
    "jax": ("jax", "flax", "optax"),
    "arm": ("jax", "flax", "optax", "pymunk"),
    "kinetix": ("jax", "flax", "optax", "kinetix"),
}


def _missing_module(extra: str | None) -> str | None:
    """The first module of ``extra`` that is not installed, or None."""
    for name in _EXTRA_MODULES.get(extra, ()):
        if importlib.util.find_spec(name) is None:
            return name
    return None


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="softrtc",
        description="Reference semantics of real-time chunking (RTC) and Soft RTC.")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    demo = sub.add_parser("demo", help="the main job: worked examples, weights table, and every "
                                       "available check on built-in defaults")
    demo.set_defaults(func=_demo)
    unavailable = {}
    for mod_name, label, extra in _SUBCOMMAND_MODULES:
        missing = _missing_module(extra)
        if missing:
            unavailable[label] = f"the '{extra}' extra (missing module {missing}): pip install 'softrtc[{extra}]'"
            _unavailable(sub, label, f"needs {unavailable[label]}")
            continue
        importlib.import_module(mod_name).add_subparsers(sub)
    for label, message in unavailable.items():
        # Another module may have added its own subcommands to the same group (`bench torch` beside the
        # missing `bench runtime`): the group's unknown subcommands then name the missing extra.
        if sub.choices[label].get_default("func") is None:
            _hint_unknown_subcommands(sub.choices[label], message)
    leaf_progs(parser)
    return parser


def _unavailable(sub, label: str, message: str) -> None:
    """A command whose extra is not installed: listed in the help, and run it says which extra in one line."""
    parser = sub.add_parser(label, help=f"unavailable: {message}", add_help=False)
    parser.add_argument("rest", nargs=argparse.REMAINDER)
    parser.set_defaults(func=lambda args: command_error(f"softrtc {label}", message))


def _hint_unknown_subcommands(group: argparse.ArgumentParser, message: str) -> None:
    """An unknown subcommand of ``group`` is reported in one line that also names the missing extra."""
    usage_error = group.error

    def error(text: str):
        if "invalid choice" in text:
            sys.exit(command_error(group.prog, f"{text}; the others need {message}"))
        usage_error(text)

    group.error = error


def _demo(args) -> int:
    """Run every demo step that is available, in order; fail if any fails."""
    steps = []
    for mod_name, label, extra in _SUBCOMMAND_MODULES:
        if _missing_module(extra):
            print(f"(skipping the {label} demo: the '{extra}' extra is not installed)", flush=True)
            continue
        mod = importlib.import_module(mod_name)
        if hasattr(mod, "demo"):
            steps.append((label, mod.demo))
    status = 0
    for name, fn in steps:
        print(f"\n=== {name} ===", flush=True)
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
        # [N-11] Like a command group without its subcommand: a usage error on stderr, status 2.
        return missing_subcommand(parser)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        # The reader of stdout went away (`softrtc weights | head`): stop quietly, as other Unix tools do.
        # Point stdout at devnull so the interpreter's final flush does not raise a second time.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # 128 + SIGPIPE, the status a shell reports for a tool killed by a closed pipe
    except ModuleNotFoundError as exc:
        # [N-13] An optional module a command imports only when it runs: one line naming the extra. The
        # commands check theirs at the door; this catches any import deeper down.
        hint = extra_hint(exc.name)
        if hint is None:
            raise
        return command_error(args._prog, hint)
    except (ValueError, OSError, OverflowError) as exc:
        # Invalid input ([N-7]) or an unusable file: one line naming the problem, no traceback.
        # SOFTRTC_TRACEBACK=1 shows the traceback when debugging softrtc itself.
        return command_error(args._prog, exc)


if __name__ == "__main__":
    sys.exit(main())
