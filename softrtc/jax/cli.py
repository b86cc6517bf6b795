"""`softrtc bench runtime`, `vjp`, `table` and the JAX step of `softrtc demo`; registered by softrtc/cli.py.

``add_subparsers(subparsers)`` adds ``bench`` with the subcommands ``runtime``,
``vjp`` and ``table`` (spec/32-runtime-bench.md, chapter B). ``demo()`` is a quick check of the JAX
twin: the conformance vectors of the samplers and guidance against the JAX
adapter, and fast against straightforward chunks of a small flow policy.
"""

from __future__ import annotations

import argparse
import sys
import time

from .._cli_util import command_error, comma_list, group_help, int_in, missing_extra, output_file


_size_list = comma_list("value", int_in("each batch size", 1, 1 << 16))


def _batch_sizes(text: str) -> tuple:
    return tuple(_size_list(text))

# BenchConfig's field names as the options that set them, for its error messages.
_OPTIONS = {"calls": "--calls", "warmup": "--warmup", "batch_sizes": "--batch-sizes", "delay": "--delay",
            "seed": "--seed", "num_steps": "--steps", "execute_horizon": "--execute-horizon", "path": "--path",
            "train_batch": "--train-batch", "train_calls": "--train-calls", "arch": "--arch"}


def _as_options(message: str) -> str:
    field = message.split(" ", 1)[0]
    return _OPTIONS[field] + message[len(field):] if field in _OPTIONS else message


def _delay(text: str):
    if text == "rotate":
        return None
    try:
        # ASCII digits only, as every integer option ([N-11]): int() would read "1_0" or full-width digits.
        return int_in("value", 0, 4096)(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"value must be 'rotate' or an integer in [0, 4096], got {text!r}") from None


def _common_options(parser, noun: str, out: str) -> None:
    """Options that `bench runtime` and `bench vjp` share, with the same meaning ([B-10], [B-12])."""
    parser.add_argument("--calls", type=int_in("value", 1, 10**7), default=200, help=f"timed calls per {noun} and batch size, 1 .. 10^7 (default 200)")
    parser.add_argument("--warmup", type=int_in("value", 1, 10**6), default=5, help="untimed warm-up rounds after compilation, 1 .. 10^6 (default 5)")
    parser.add_argument("--batch-sizes", type=_batch_sizes, default=(1, 32), help="comma-separated (default 1,32)")
    parser.add_argument("--delay", type=_delay, default=None,
                        help="'rotate' (default: d = 0 .. min(s, H - s) in turn across calls) or a fixed delay")
    parser.add_argument("--seed", type=int_in("value", 0, 2**31 - 1), default=0, help="seed of the policy parameters and inputs (default 0)")
    parser.add_argument("--steps", type=int_in("value", 1, 1000), default=5, help="Euler steps T, 1 .. 1000 (default 5)")
    parser.add_argument("--execute-horizon", type=int_in("value", 1, 4096), default=4, help="execute horizon s, 1 .. H (default 4)")
    parser.add_argument("--arch", choices=("benchmark", "tiny"), default="benchmark",
                        help="policy size: the benchmark's (obs 679, action 6, H 8; default) or a tiny smoke-test one")
    parser.add_argument("--out", type=output_file(), default=out, help=f"JSON output (default {out})")


def add_subparsers(subparsers) -> None:
    """Register `bench runtime` ([B-1], [B-10]) and `bench vjp` ([B-12])."""
    bench = subparsers.add_parser("bench", help="benchmarks of the JAX implementation")
    sub = bench.add_subparsers(dest="bench_command", metavar="SUBCOMMAND")
    bench.set_defaults(func=group_help(bench))
    rt = sub.add_parser(
        "runtime", help="chunk-generation latency per method (ratio to naive) and training-step time "
                        "(spec/32-runtime-bench.md)")
    _common_options(rt, "row", "runs/bench_runtime.json")
    rt.add_argument("--path", choices=("fast", "straightforward"), default="fast",
                    help="implementation of the method rows (default fast, which also measures the straightforward "
                         "naive and train-soft samplers and the public-style guided soft sampler as rows of their "
                         "own; straightforward measures the seven method rows on that path only)")
    rt.add_argument("--train-batch", type=int_in("value", 1, 1 << 16), default=32, help="batch size of the training steps, 1 .. 65536 (default 32)")
    rt.add_argument("--train-calls", type=int_in("value", 0, 10**7), default=50,
                    help="timed training steps per method (default 50; 0 skips them)")
    rt.add_argument("--strict", action="store_true", help="exit with status 1 when a timing target fails")
    rt.set_defaults(func=run_runtime)
    vj = sub.add_parser(
        "vjp", help="each design choice of the guided samplers' pull-back against the shipped one, side by side "
                    "(spec/32-runtime-bench.md, [B-12])")
    _common_options(vj, "variant", "runs/bench_vjp.json")
    vj.set_defaults(func=run_vjp)
    tb = sub.add_parser(
        "table", help="the table of a `bench runtime` result file, and the ratio ranges over several "
                      "(spec/32-runtime-bench.md, [B-15])")
    tb.add_argument("results", nargs="+", metavar="RESULT.json",
                    help="result files written by `softrtc bench runtime --out`; the first one's table is printed")
    tb.set_defaults(func=run_table)


def _check_memory(config) -> None:
    """[B-16] The largest chunk batch and the training batch fit in the memory JAX computes in (the host's,
    or an accelerator's own), estimated from the sizes before anything is compiled."""
    import jax

    from softrtc._memory import available_bytes, check_fits, step_bytes

    from .bench_config import ARCHS

    available = available_bytes()
    if jax.default_backend() != "cpu":
        stats = jax.devices()[0].memory_stats() or {}
        if "bytes_limit" in stats:
            available = stats["bytes_limit"] - stats.get("bytes_in_use", 0)
    pc = ARCHS[config.arch]["config"]

    def need(batch):
        return step_bytes(batch, pc.action_chunk_size, pc.num_layers, pc.channel_dim, pc.channel_hidden_dim)

    largest = max(config.batch_sizes)
    check_fits("--batch-sizes entry", largest, need(largest), available)
    if config.train_calls:
        check_fits("--train-batch", config.train_batch, need(config.train_batch), available)


def _run(args, run, fmt, **extra):
    """Build the BenchConfig from ``args``, run, print the table and write the JSON.

    Returns the result, or the exit status 2 when the options are invalid or
    the JSON cannot be written ([B-10]).
    """
    prog = getattr(args, "_prog", "softrtc bench")
    hint = missing_extra("tqdm")  # [N-13] the training rows' progress bar: checked before any work
    if hint:
        return command_error(prog, hint)
    from .bench_config import BenchConfig
    from .bench_report import write_json

    try:
        config = BenchConfig(
            calls=args.calls, warmup=args.warmup, batch_sizes=tuple(args.batch_sizes), delay=args.delay,
            seed=args.seed, num_steps=args.steps, execute_horizon=args.execute_horizon, arch=args.arch, **extra)
    except ValueError as exc:
        return command_error(prog, _as_options(str(exc)))
    try:
        _check_memory(config)
    except ValueError as exc:
        return command_error(prog, exc)
    res = run(config, progress=lambda m: print(f"[bench] {m}", file=sys.stderr, flush=True))
    print(fmt(res))
    try:
        write_json(res, args.out)
    except OSError as exc:
        return command_error(prog, f"cannot write {args.out}: {exc}")
    print(f"wrote {args.out}")
    return res


def run_runtime(args) -> int:
    """Exit status: 0 done (timing targets only count with --strict), 1 paths disagree or strict failure,
    2 invalid options ([B-10])."""
    from .bench import run_benchmark
    from .bench_report import format_table

    res = _run(args, run_benchmark, format_table, path=args.path, train_batch=args.train_batch,
               train_calls=args.train_calls)
    if isinstance(res, int):
        return res
    agree = all(t["pass"] for t in res["targets"] if t["id"] == "B-5")
    timing = all(t["pass"] for t in res["targets"] if t["id"] != "B-5")
    return 0 if agree and (timing or not args.strict) else 1


def run_vjp(args) -> int:
    """Exit status: 0 done, 1 a variant's chunks disagree with the shipped ones, 2 invalid options ([B-12])."""
    from .bench_vjp import format_vjp_table, run_vjp_ablation

    res = _run(args, run_vjp_ablation, format_vjp_table, train_calls=0)
    if isinstance(res, int):
        return res
    return 0 if all(a["ok"] for per_b in res["agreement"].values() for a in per_b.values()) else 1


def run_table(args) -> int:
    """Print the table of the last result file and the ratio ranges over all of them ([B-15]); no JAX work."""
    from .bench_report import format_ranges, format_table, read_result

    prog = getattr(args, "_prog", "softrtc bench table")
    try:
        results = [read_result(p) for p in args.results]
        print(format_table(results[-1]))
        print()
        print(format_ranges(results))
    except ValueError as exc:
        return command_error(prog, str(exc))
    return 0


def demo() -> int:
    """Demo step of `softrtc demo`: JAX against the conformance vectors, and fast vs straightforward chunks."""
    t0 = time.perf_counter()
    status = 0
    try:
        from softrtc.conformance import runner
    except ModuleNotFoundError:
        runner = None
    if runner is not None:
        print("JAX implementation against every conformance vector (softrtc conformance run --impl jax)")
        res = runner.run("jax")
        print(runner.format_summary(res))
        status = 0 if res.ok else 1

    from . import bench

    cfg = bench.BenchConfig(arch="tiny", batch_sizes=(2,), calls=1, warmup=1, train_calls=0)
    print("\nFast vs straightforward chunks, tiny flow policy, batch 2, d = 0 .. 4 ([B-5]):")
    agree = bench.check_agreement(cfg, bench.make_policy(cfg), 2, ("naive", "inference_soft", "train_soft_lam2"))
    for name, a in agree.items():
        print(f"  {bench.CHUNK_ROWS[name][2]:<24s} max |fast - straightforward| = {a['max_abs_diff']:.1e}  "
              f"{'PASS' if a['ok'] else 'FAIL'}")
        status = status or (0 if a["ok"] else 1)
    print(f"JAX demo: {time.perf_counter() - t0:.0f} s; runtime benchmark: softrtc bench runtime")
    return status
