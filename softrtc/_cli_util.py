"""Argument types shared by the ``softrtc`` subcommands ([N-7] for the command line).

Each factory returns an ``argparse`` type whose error names the option and its
allowed range, so a bad value stops the command before any work starts. Output
paths are checked up front too: a command that runs for minutes must not fail
only when it writes its result.

>>> int_in("value", 1, 10)("3")
3
>>> comma_list("value", int_in("each entry", 0, 8))("0,2,4")
[0, 2, 4]
>>> real_in("value", 0.0, 10.0)("2.5e0")
2.5
"""

from __future__ import annotations

import argparse
import math
import os
import re
import sys
from pathlib import Path
from typing import Callable

from ._files import unwritable_reason


def _range(lo, hi) -> str:
    if lo is not None and hi is not None:
        return f" in [{lo}, {hi}]"
    if lo is not None:
        return f" >= {lo}"
    return f" <= {hi}" if hi is not None else ""


def command_error(prog: str, message) -> int:
    """[N-11] One line ``PROG: error: MESSAGE`` on stderr; returns the exit status 2.

    Called while an exception is being handled, ``SOFTRTC_TRACEBACK=1``
    re-raises that exception (with its traceback) instead.
    """
    active = sys.exc_info()[1]
    if active is not None and os.environ.get("SOFTRTC_TRACEBACK") == "1":
        raise active
    print(f"{prog}: error: {message}", file=sys.stderr)
    return 2


# Plain ASCII decimal integers: Python's int() would also take "1_0", " 7 " or full-width digits.
_INT = re.compile(r"[+-]?[0-9]+")
# Plain ASCII decimal reals (an optional exponent): float() would also take "1_0", " 2 ", "２" or "٣".
_REAL = re.compile(r"[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def int_in(what: str, lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An integer in [lo, hi] (either bound may be None); ``what`` names it in the message (argparse adds the option)."""
    def parse(text: str) -> int:
        try:
            if not _INT.fullmatch(text):
                raise ValueError(text)
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be an integer{_range(lo, hi)}, got {text!r}") from None
        if (lo is not None and value < lo) or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(f"{what} must be an integer{_range(lo, hi)}, got {value}")
        return value
    return parse


def real_in(what: str, lo: float | None = None, hi: float | None = None, *,
            lo_open: bool = False) -> Callable[[str], float]:
    """A finite real number in [lo, hi], or in (lo, hi] with ``lo_open``."""
    def parse(text: str) -> float:
        try:
            value = float(text) if _REAL.fullmatch(text) else math.nan
        except (ValueError, OverflowError):
            value = math.nan
        below = lo is not None and (value <= lo if lo_open else value < lo)
        if not math.isfinite(value) or below or (hi is not None and value > hi):
            where = f" in ({lo}, {hi}]" if lo_open and lo is not None and hi is not None else _range(lo, hi)
            raise argparse.ArgumentTypeError(f"{what} must be a finite number{where}, got {text!r}")
        return value
    return parse


def comma_list(what: str, item: Callable[[str], object] = str, *, unique: bool = True) -> Callable[[str], list]:
    """A non-empty comma-separated list; empty entries (``1,,2``, ``2,``) and, with ``unique``, repeats are errors."""
    def parse(text: str) -> list:
        parts = [p.strip() for p in text.split(",")]
        if not text.strip() or any(not p for p in parts):
            raise argparse.ArgumentTypeError(f"{what} must be a comma-separated list without empty entries, "
                                             f"got {text!r}")
        values = [item(p) for p in parts]
        if unique and len(set(values)) != len(values):
            raise argparse.ArgumentTypeError(f"{what} must not repeat an entry, got {text!r}")
        return values
    return parse


def _writable(text: str, folder: Path) -> str:
    """``text`` when ``folder``, or its nearest existing ancestor (the command creates the rest), takes new files."""
    reason = unwritable_reason(folder)
    if reason:
        raise argparse.ArgumentTypeError(f"{text} {reason}")
    return text


def output_file() -> Callable[[str], str]:
    """A file the command will write: not empty, not a directory, inside a writable (or creatable) directory."""
    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("must be a file path, got an empty string")
        path = Path(text)
        if path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a directory; expected a file path")
        return _writable(text, path.parent)
    return parse


def output_dir() -> Callable[[str], str]:
    """A directory the command will write into: not empty, not an existing file, creatable or writable."""
    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("must be a directory path, got an empty string")
        path = Path(text)
        if path.exists() and not path.is_dir():
            raise argparse.ArgumentTypeError(f"{text} is a file; expected a directory")
        return _writable(text, path)
    return parse


def input_dir() -> Callable[[str], str]:
    """An existing directory to read from."""
    def parse(text: str) -> str:
        if not text:
            raise argparse.ArgumentTypeError("must be a directory path, got an empty string")
        if not Path(text).is_dir():
            what = "is not a directory" if Path(text).exists() else "does not exist"
            raise argparse.ArgumentTypeError(f"{text} {what}")
        return text
    return parse


def nonempty() -> Callable[[str], str]:
    """Any non-empty string."""
    def parse(text: str) -> str:
        if not text.strip():
            raise argparse.ArgumentTypeError("must not be empty")
        return text
    return parse


# [N-13] The extra that installs each optional top-level module a command imports.
MODULE_EXTRAS = {"jax": "jax", "flax": "jax", "optax": "jax", "tqdm": "jax", "pymunk": "arm", "matplotlib": "arm",
                 "kinetix": "kinetix", "torch": "torch"}


def extra_hint(module: str) -> str | None:
    """``needs the 'X' extra (missing module M): pip install 'softrtc[X]'`` for an optional module, else None."""
    root = (module or "").split(".")[0]
    extra = MODULE_EXTRAS.get(root)
    return None if extra is None else f"needs the '{extra}' extra (missing module {root}): pip install 'softrtc[{extra}]'"


def missing_extra(*modules: str) -> str | None:
    """[N-13] The :func:`extra_hint` of the first of ``modules`` that cannot be imported, or None.

    A command calls it before any work for the modules it imports only when it gets there (tqdm for a
    training loop, matplotlib for plots), so a missing one ends it at the door, not after minutes of work.
    """
    import importlib.util

    for name in modules:
        try:
            found = importlib.util.find_spec(name) is not None
        except (ImportError, ValueError):  # a parent package missing, or a module without a spec
            found = False
        if not found:
            return extra_hint(name) or f"needs the module {name}, which is not installed"
    return None


def leaf_progs(parser: argparse.ArgumentParser) -> None:
    """Give every parser below ``parser`` the default ``_prog`` (e.g. "softrtc bench runtime") and ``_parser``,
    so that errors raised inside a command name the whole command ([N-11])."""
    parser.set_defaults(_prog=parser.prog, _parser=parser)
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for child in action.choices.values():
                leaf_progs(child)


def group_help(parser: argparse.ArgumentParser) -> Callable[[argparse.Namespace], int]:
    """``func`` of a command group run without a subcommand: a usage error ([N-11]), see :func:`missing_subcommand`."""
    def show(args) -> int:
        return missing_subcommand(parser)
    return show


def missing_subcommand(parser: argparse.ArgumentParser) -> int:
    """[N-11] The usage line and ``PROG: error: a subcommand is needed (one of: ...)`` on stderr; returns 2.

    As argparse reports every other usage error: stdout stays empty, so a script that captures it gets
    nothing, and the status says the invocation was wrong. ``--help`` still prints the help on stdout.
    """
    names = [name for action in parser._actions if isinstance(action, argparse._SubParsersAction)
             for name in action.choices]
    parser.print_usage(sys.stderr)
    print(f"{parser.prog}: error: a subcommand is needed (one of: {', '.join(names)})", file=sys.stderr)
    return 2
