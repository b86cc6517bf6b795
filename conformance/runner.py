"""Run the conformance vectors against an implementation and report per requirement id ([CF-13]..[CF-18],
[CF-29]..[CF-31]).

    softrtc conformance run --impl NAME_OR_MODULE:ATTR | --impl-cmd "COMMAND" [--in-process]
                            [--case-timeout S] [--case-memory-mb MB] [--report FILE] [--junit FILE]
                            [--vectors DIR] [--only f1,f2] [--no-rollouts]

Every case is one call of one interface function; the rollout vectors of
``VECTORS/rollouts/`` follow, replayed on the served field as
`conformance rollout --vectors` does ([CR-10]). The implementation runs in a
child process of its own by default and answers over the protocol of
:mod:`.protocol`; this process alone reads the vectors, compares and reports, so
an implementation that hangs, exits or tampers with the runner's code fails
cases instead of deciding the run. A case passes when every expected number
agrees within its tolerance: ``|got - want| <= abs + rel * |want|`` elementwise,
integers exactly ([CF-5]). Outputs of a "noise_at_1" implementation are mapped
onto the spec (t = 1 - t', v = -u) before comparing ([CF-10], [V-1]).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path

from .._cli_util import command_error, comma_list, input_dir, output_file, real_in
from . import FORMAT_VERSION, rollout_vectors
from .adapter import ALTERNATES, INTERFACE, AdapterError, load_adapter
# The comparison lives in compare.py; its names stay importable from here.
from .compare import (CaseFailure, _decode, _flip_args, _flip_out, _number, _outputs, check_integers,  # noqa: F401
                      check_outputs, compare)
from .invoke import NONFINITE, Invoker, function_of  # noqa: F401
from .protocol import Child, ChildLost, ImplementationError
from .results import (MAX_LISTED_FAILURES, TRACE_NOT_PROVIDED, UNSUPPORTED_CASE, CaseResult, RunResult,  # noqa: F401
                      check_output_paths, format_summary, report_dict, write_junit, write_report)
from .vectors_io import VectorError, describe_vectors, load_vectors, parse_json  # noqa: F401  (re-exported)

DEFAULT_CASE_TIMEOUT = 60.0
DEFAULT_START_TIMEOUT = 120.0
# The child's address space in MB ([CF-37]): generous, since it is virtual memory (JAX's child reserves
# about 1.2 GB on two cores, and thread stacks and malloc arenas grow with the core count), but finite, so
# a runaway case fails instead of waking the system's OOM killer.
DEFAULT_CASE_MEMORY_MB = 16384
CASE_MEMORY_RANGE = (256, 1 << 20)
# The rollout vectors' function ([CR-10]): not one of the interface of [CF-7], since it needs the served field.
ROLLOUT_FUNCTION = rollout_vectors.FUNCTION
# Requests sent ahead of the replies: the child computes the next cases while this process compares.
WINDOW = 32
# A function whose cases lose this many children in a row has its remaining cases failed without running.
MAX_LOST_IN_A_ROW = 3


class CaseUnsupported(Exception):
    """The implementation declined the case (NotImplementedError, or "unsupported" over the protocol) ([CF-26])."""


# ---------------------------------------------------------------- implementations

class InProcess:
    """An adapter object called in this process (``--in-process``): no isolation, no time limit."""

    memory_mb = None  # no limit in process ([CF-37])

    def __init__(self, adapter):
        self.invoker = Invoker(adapter)
        self.name, self.time_convention = self.invoker.name, self.invoker.time_convention
        self.functions = self.invoker.functions
        self._queue: deque = deque()

    def launch(self) -> None:
        pass

    ready = restart = stop = launch

    def submit(self, request: dict) -> None:
        self._queue.append(request)

    def receive(self, deadline: float) -> dict:
        req = self._queue.popleft()
        return dict(self.invoker.call(req["function"], req["args"]), id=req["id"])


@dataclass
class _Job:
    result: CaseResult
    case: dict
    data: dict
    forms: list          # [(attr, Fn)] still to try, in order
    declined: list
    id: int = 0
    sent_at: float = 0.0


def _forms(functions, fname: str, case: dict) -> tuple[list, list]:
    """The forms of ``fname`` the implementation has that can run ``case``, and why others cannot ([CF-27])."""
    out, declined = [], []
    if fname in functions:
        out.append((fname, INTERFACE[fname]))
    alt = ALTERNATES.get(fname)
    if alt is not None and alt.name in functions:
        if alt.needs in case["args"]:
            out.append((alt.name, alt.fn))
        else:
            declined.append(f"{alt.name} needs the case's '{alt.needs}', which it does not carry")
    return out, declined


def _request(job: _Job, flipped: bool) -> dict:
    attr, fn = job.forms[0]
    args = {k: job.case["args"][k] for k in fn.args}
    if "field" in args:
        args["field"] = job.data["fields"][args["field"]]["params"]
    return {"id": job.id, "function": attr, "args": _flip_args(fn, args) if flipped else args}


def _judge(job: _Job, reply: dict, flipped: bool, memory_mb: int | None = None) -> tuple[float, str]:
    """Verdict on one reply: (worst ratio, note), or CaseFailure / CaseUnsupported ([CF-18], [CF-26]);
    a MemoryError under a memory limit says so ([CF-37])."""
    attr, fn = job.forms[0]
    is_error_case = "error" in job.case["expected"]
    if "error" in reply:
        e = reply["error"] if isinstance(reply["error"], dict) else {}
        kind, msg = e.get("kind"), str(e.get("message", ""))[:300]
        desc = f"{e.get('type', 'error')}: {msg}" if msg else str(e.get("type", "error"))
        where = f" ({e['where']})" if e.get("where") else ""
        if kind == "unsupported":
            raise CaseUnsupported(f"{attr} raised {desc}")
        if kind == "invalid_input" and is_error_case:
            return 0.0, ""
        if kind == "exception" and e.get("type") == "MemoryError" and memory_mb is not None:
            raise CaseFailure(f"{attr} ran out of memory: the case exceeded the memory limit of {memory_mb} MB "
                              f"(--case-memory-mb){where}")
        if kind in ("invalid_input", "exception"):
            raise CaseFailure(f"{'invalid input must raise ValueError, ' if is_error_case and kind == 'exception' else ''}"
                              f"{attr} raised {desc}{where}")
        if kind == "bad_result" and is_error_case:
            raise CaseFailure(f"{attr} accepted invalid input (expected ValueError, [N-7])")
        if kind in ("bad_result", "bad_call"):
            raise CaseFailure(msg)
        raise CaseFailure(f"protocol error: unknown error kind {kind!r} ([CF-29])")
    if is_error_case:
        raise CaseFailure(f"{attr} accepted invalid input (expected ValueError, [N-7])")
    got = _outputs(fn, attr, reply["result"], flipped)
    return check_outputs(INTERFACE[job.result.function], attr, got, job.case["expected"], job.case["tolerance"],
                         plain=not flipped and reply.get("_no_booleans", False))


def _run_jobs(impl, jobs: list, case_timeout: float) -> None:
    """Send the jobs' requests (up to WINDOW ahead), judge the replies in order, and replace a lost child
    ([CF-30]); each job's result is filled in place."""
    flipped = impl.time_convention == "noise_at_1"
    todo, pending = deque(jobs), deque()
    lost_in_a_row: dict[str, list] = {}
    next_id, last_event = 0, time.monotonic()
    while todo or pending:
        while todo and len(pending) < WINDOW:
            job = todo.popleft()
            lost = lost_in_a_row.get(job.result.function, [])
            if len(lost) >= MAX_LOST_IN_A_ROW:
                job.result.status, job.result.worst = "fail", math.inf
                job.result.message = (f"not run: the implementation's process was lost on {len(lost)} cases of "
                                      f"{job.result.function} in a row (last: {lost[-1]}) ([CF-30])")
                continue
            next_id += 1
            job.id, job.sent_at = next_id, time.monotonic()
            impl.submit(_request(job, flipped))
            pending.append(job)
        if not pending:
            continue
        job = pending[0]
        ready = max(job.sent_at, last_event)
        try:
            reply = impl.receive(ready + case_timeout)
            if reply.get("id") != job.id:
                raise ChildLost(f"protocol error: reply id {reply.get('id')!r}, expected {job.id} ([CF-29])")
        except ChildLost as exc:
            pending.popleft()
            last_event = time.monotonic()
            job.result.seconds += last_event - ready
            job.result.status, job.result.message, job.result.worst = "fail", str(exc), math.inf
            lost_in_a_row.setdefault(job.result.function, []).append(job.case["id"])
            todo.extendleft(reversed(pending))
            pending.clear()
            impl.restart()
            last_event = time.monotonic()
            continue
        pending.popleft()
        last_event = time.monotonic()
        job.result.seconds += last_event - ready
        lost_in_a_row.pop(job.result.function, None)
        try:
            job.result.worst, job.result.message = _judge(job, reply, flipped, impl.memory_mb)
        except CaseUnsupported as exc:
            job.declined.append(str(exc))
            job.forms.pop(0)
            if job.forms:  # the next form of the function takes the case ([CF-27])
                todo.appendleft(job)
                continue
            job.result.status, job.result.message = "unsupported", f"{UNSUPPORTED_CASE}: {'; '.join(job.declined)}"
        except CaseFailure as exc:
            job.result.status, job.result.message, job.result.worst = "fail", str(exc), exc.ratio


def _check_timeout(name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"{name} must be a finite number of seconds > 0, got {value!r}")
    return float(value)


def check_memory_mb(name: str, value) -> int:
    """A memory limit in MB: an int in CASE_MEMORY_RANGE ([CF-37], [N-7])."""
    lo, hi = CASE_MEMORY_RANGE
    if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
        raise ValueError(f"{name} must be an integer number of megabytes in [{lo}, {hi}], got {value!r}")
    return value


def run(impl=None, vectors_dir=None, only=None, files=None, *, impl_cmd=None, in_process=None,
        case_timeout=DEFAULT_CASE_TIMEOUT, start_timeout=DEFAULT_START_TIMEOUT,
        case_memory_mb=DEFAULT_CASE_MEMORY_MB, rollouts=None) -> RunResult:
    """Run every case against an implementation ([CF-13], [CF-29]), the rollout vectors included ([CR-10]).

    ``impl``: an adapter spec string (run in a child process through :mod:`.host`, or in this process with
    ``in_process=True``) or an adapter object (in this process); ``impl_cmd``: a command line of a program
    that speaks the protocol ([CF-31]). ``only``: function names to restrict the run (``rollout_chunk`` for
    the rollout vectors); ``files``: vectors already read by :func:`load_vectors`. ``rollouts``: True runs
    the rollout vectors of ``vectors_dir`` (default the shipped ones), False leaves them out, None (the
    default) runs them when this call reads the vectors itself (``files`` None); a run that leaves them out
    says why in ``RunResult.rollouts``. Raises AdapterError (ImplementationError for a child that never
    answers) or VectorError with a one-line message when nothing can run.
    """
    t0 = time.perf_counter()
    if only is not None:
        if isinstance(only, (str, bytes)) or not hasattr(only, "__iter__"):
            raise ValueError(f"only must be None or a collection of interface function names, got {only!r}")
        only = set(only)
        unknown = sorted(str(f) for f in only if f not in INTERFACE and f != ROLLOUT_FUNCTION)
        if unknown:
            raise ValueError(f"only names unknown interface functions {unknown}; known: "
                             f"{sorted(INTERFACE) + [ROLLOUT_FUNCTION]}")
    if rollouts is not None and not isinstance(rollouts, bool):
        raise ValueError(f"rollouts must be None, True or False, got {rollouts!r}")
    case_timeout = _check_timeout("case_timeout", case_timeout)
    start_timeout = _check_timeout("start_timeout", start_timeout)
    case_memory_mb = check_memory_mb("case_memory_mb", case_memory_mb)
    if (impl is None) == (impl_cmd is None):
        raise ValueError("give exactly one of impl (an adapter) and impl_cmd (a command)")
    if impl_cmd is not None:
        if not isinstance(impl_cmd, str) or not shlex.split(impl_cmd) or in_process:
            raise ValueError(f"impl_cmd must be a non-empty command line (never in process), got {impl_cmd!r}")
        runner_impl, impl_name = Child(shlex.split(impl_cmd), start_timeout, f"command {impl_cmd!r}",
                                       case_memory_mb), impl_cmd
    elif isinstance(impl, str) and not in_process:
        argv = [sys.executable, "-m", "softrtc.conformance.host", "--impl", impl]
        runner_impl, impl_name = Child(argv, start_timeout, f"impl {impl!r}", case_memory_mb), impl
    elif isinstance(impl, str):
        runner_impl, impl_name = InProcess(load_adapter(impl)), impl
    elif in_process is False:
        raise ValueError("an adapter object runs in this process; pass a spec string to run it in a child")
    else:
        runner_impl, impl_name = InProcess(impl), getattr(impl, "name", "?")
    given = files is not None
    runner_impl.launch()  # a child starts while the vectors are read
    try:
        files = load_vectors(vectors_dir) if files is None else files
        plan = _rollout_plan(rollouts, given, vectors_dir, only)
        runner_impl.ready()
        result = RunResult(impl_name, runner_impl.name, runner_impl.time_convention, FORMAT_VERSION,
                           sorted({str(d.get("spec_version")) for d in files}),
                           isolation="in process" if isinstance(runner_impl, InProcess) else "child process",
                           vectors=describe_vectors(files))
        jobs = []
        for data in files:
            for case in data["cases"]:
                fname = case.get("function")
                if only is not None and fname not in only:
                    continue
                if fname not in INTERFACE:  # load_vectors refuses such files; a hand-built list may hold one
                    raise VectorError(f"{data['_file']}: case {case.get('id')!r} names unknown interface function "
                                      f"{fname!r}")
                cr = CaseResult(case["id"], data["_file"], fname, list(case["requirements"]), "pass")
                result.cases.append(cr)
                forms, declined = _forms(runner_impl.functions, fname, case)
                if not forms and not declined:
                    cr.status, cr.message = "unsupported", f"adapter has no {fname}"
                elif not forms:
                    cr.status, cr.message = "unsupported", f"{UNSUPPORTED_CASE}: {'; '.join(declined)}"
                else:
                    jobs.append(_Job(cr, case, data, forms, declined))
        _run_jobs(runner_impl, jobs, case_timeout)
    finally:
        runner_impl.stop()
    rollout_vectors.run_part(plan, result, impl, impl_cmd=impl_cmd, in_process=bool(in_process),
                             functions=runner_impl.functions, timeout=case_timeout, start_timeout=start_timeout,
                             memory_mb=None if in_process else case_memory_mb)
    result.seconds = time.perf_counter() - t0
    return result


def _rollout_plan(rollouts, given: bool, vectors_dir, only) -> dict:
    """Whether and which rollout vectors the run replays ([CR-10]), decided before any case runs; VectorError
    for rollout vectors that are present but cannot be read."""
    if rollouts is False:
        return rollout_vectors.skipped("left out (--no-rollouts)")
    if only is not None and ROLLOUT_FUNCTION not in only:
        return rollout_vectors.skipped(f"left out (--only without {ROLLOUT_FUNCTION})")
    if rollouts is None and given:
        return rollout_vectors.skipped("left out (the vectors were passed already read; rollouts=True runs them)")
    try:
        return rollout_vectors.at_the_door(vectors_dir)
    except ValueError as exc:
        raise VectorError(str(exc)) from None


# ---------------------------------------------------------------- command line

def add_arguments(parser: argparse.ArgumentParser) -> None:
    which = parser.add_mutually_exclusive_group(required=True)
    which.add_argument("--impl", help="built-in adapter (reference, jax, torch, torch-flipped), module[:ATTR] "
                                      "or path/file.py[:ATTR]; run in a child process unless --in-process")
    which.add_argument("--impl-cmd", metavar="COMMAND",
                       help="command line of a program in any language that speaks the conformance protocol "
                            "(spec/40-conformance.md, [CF-29])")
    parser.add_argument("--in-process", action="store_true",
                        help="call the --impl adapter in the runner's own process (debugging: no time limit, "
                             "no isolation)")
    parser.add_argument("--case-timeout", type=real_in("seconds", 0.0, lo_open=True), default=DEFAULT_CASE_TIMEOUT,
                        help=f"seconds one case may take before it fails and the run goes on in a fresh child "
                             f"(default {DEFAULT_CASE_TIMEOUT:g})")
    parser.add_argument("--start-timeout", type=real_in("seconds", 0.0, lo_open=True),
                        default=DEFAULT_START_TIMEOUT,
                        help=f"seconds the child may take to write its hello line (default {DEFAULT_START_TIMEOUT:g})")
    parser.add_argument("--case-memory-mb", type=_memory_mb, default=DEFAULT_CASE_MEMORY_MB, metavar="MB",
                        help=f"address space of the implementation's child process in MB, "
                             f"{CASE_MEMORY_RANGE[0]}..{CASE_MEMORY_RANGE[1]}; a case that needs more fails "
                             f"(default {DEFAULT_CASE_MEMORY_MB}; no limit with --in-process)")
    parser.add_argument("--vectors", type=input_dir(), default=None,
                        help="vector directory (default: the vectors shipped with softrtc)")
    parser.add_argument("--report", type=output_file(), default=None, help="write a JSON report to this file")
    parser.add_argument("--junit", type=output_file(), default=None, help="write JUnit XML to this file")
    parser.add_argument("--only", type=comma_list("value", _interface_function), default=None,
                        help="comma-separated interface functions to run (default: all): "
                             + ", ".join(sorted(INTERFACE)) + f"; {ROLLOUT_FUNCTION} for the rollout vectors")
    parser.add_argument("--no-rollouts", action="store_true",
                        help="leave out the rollout vectors (VECTORS/rollouts/, spec/42-rollouts.md [CR-10]), "
                             "which load JAX to serve their field; the run says they were left out")


def _memory_mb(text: str) -> int:
    """--case-memory-mb: ASCII decimal digits only (int() would take "١" or " 8_192 ")."""
    lo, hi = CASE_MEMORY_RANGE
    if not (text.isascii() and text.isdigit()) or not lo <= int(text) <= hi:
        raise argparse.ArgumentTypeError(f"must be an integer number of megabytes in [{lo}, {hi}], got {text!r}")
    return int(text)


def _interface_function(name: str) -> str:
    if name not in INTERFACE and name != ROLLOUT_FUNCTION:
        raise argparse.ArgumentTypeError(f"{name!r} is not an interface function; choose from "
                                         f"{', '.join(sorted(INTERFACE) + [ROLLOUT_FUNCTION])}")
    return name


def run_from_args(args) -> int:
    """Exit status: 0 all supported cases pass, 1 some failed or none ran, 2 nothing could run ([CF-16])."""
    prog = getattr(args, "_prog", "softrtc conformance run")
    only = None if args.only is None else set(args.only)
    impl_cmd = getattr(args, "impl_cmd", None)
    if impl_cmd is not None and getattr(args, "in_process", False):
        return command_error(prog, "--in-process runs an --impl adapter; a --impl-cmd program is always a child")
    outputs = {"--report": args.report, "--junit": args.junit}
    try:
        check_output_paths(outputs)  # at the door: no case runs for a report that cannot be written
    except ValueError as exc:
        return command_error(prog, exc)
    try:
        res = run(args.impl, args.vectors, only, impl_cmd=impl_cmd, in_process=getattr(args, "in_process", False),
                  case_timeout=getattr(args, "case_timeout", DEFAULT_CASE_TIMEOUT),
                  start_timeout=getattr(args, "start_timeout", DEFAULT_START_TIMEOUT),
                  case_memory_mb=getattr(args, "case_memory_mb", DEFAULT_CASE_MEMORY_MB),
                  rollouts=False if getattr(args, "no_rollouts", False) else None)
    except (AdapterError, VectorError) as exc:
        return command_error(prog, exc)
    try:
        print(format_summary(res), flush=True)
        closed = None
    except BrokenPipeError as exc:  # the reader went away: the reports are still written, then main stops quietly
        closed = exc
    try:
        check_output_paths(outputs)  # again: the run took a while
        for out in (args.report, args.junit):
            if out:
                Path(out).parent.mkdir(parents=True, exist_ok=True)
        if args.report:
            write_report(res, args.report)
        if args.junit:
            write_junit(res, args.junit)
    except ValueError as exc:
        return command_error(prog, exc)
    except OSError as exc:
        return command_error(prog, f"cannot write report: {exc}")
    if closed is not None:
        raise closed
    return 0 if res.ok else 1


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m softrtc.conformance.runner",
                                     description="Run the softrtc conformance vectors against an implementation.")
    add_arguments(parser)
    parser.set_defaults(_prog=parser.prog)
    return run_from_args(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
