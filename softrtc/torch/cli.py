"""``softrtc bench torch`` ([PT-8]) and ``softrtc arm torch`` ([PT-9]); registered by softrtc/cli.py."""

from __future__ import annotations

import argparse
import importlib.util
import sys

from softrtc._cli_util import command_error, comma_list, int_in, output_dir, output_file

HINT = "needs the 'torch' extra (missing module torch): pip install 'softrtc[torch]'"


def _group(subparsers, name: str, help_text: str, create: bool = True):
    """The sub-subparsers action of group ``name`` (``bench``, ``arm``); when the group is absent or stands for
    a missing extra, a new group (``create``) or None."""
    parser = subparsers.choices.get(name)
    if parser is not None:
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction):
                return action
    if not create:
        return None
    parser = argparse.ArgumentParser(prog=f"{subparsers._prog_prefix} {name}", description=help_text)
    subparsers.choices[name] = parser
    return parser.add_subparsers(dest=f"{name}_command", metavar="SUBCOMMAND")


def add_subparsers(subparsers) -> None:
    """Add ``torch`` to the ``bench`` and ``arm`` groups."""
    bench = _group(subparsers, "bench", "benchmarks")
    p = bench.add_parser("torch", help="softrtc.torch: training-time samplers vs naive, soft vs hard vs plain "
                                       "flow-matching training step, side by side ([PT-8])")
    p.add_argument("--calls", type=int_in("value", 1, 10**7), default=200,
                   help="timed chunk calls per row and batch size, 1 .. 10^7 (default 200)")
    p.add_argument("--warmup", type=int_in("value", 0, 10**6), default=5, help="untimed rounds first (default 5)")
    p.add_argument("--batch-sizes", type=comma_list("value", int_in("each entry", 1, 1 << 16)), default=[1, 32],
                   help="comma-separated chunk batch sizes (default 1,32)")
    p.add_argument("--train-batch", type=int_in("value", 1, 1 << 16), default=32, help="training batch (default 32)")
    p.add_argument("--train-calls", type=int_in("value", 0, 10**7), default=50,
                   help="timed training steps per objective (default 50; 0 skips them)")
    p.add_argument("--steps", type=int_in("value", 1, 1000), default=5, help="Euler steps T (default 5)")
    p.add_argument("--execute-horizon", type=int_in("value", 1, 4096), default=4, help="s (default 4)")
    p.add_argument("--seed", type=int_in("value", 0, 2**31 - 1), default=0, help="seed (default 0)")
    p.add_argument("--arch", choices=("benchmark", "tiny"), default="benchmark", help="policy size (default benchmark)")
    p.add_argument("--architecture", choices=("token_input", "adaln"), default="token_input",
                   help="policy network: time at the token input (default) or chapter P's adaLN modulation")
    p.add_argument("--threads", type=int_in("value", 1, 1024), default=1, help="torch threads (default 1)")
    p.add_argument("--clock", choices=("thread", "wall"), default="thread",
                   help="thread: the calling thread's CPU time (default; needs --threads 1), wall: elapsed time")
    p.add_argument("--out", type=output_file(), default="runs/bench_torch.json", help="JSON output")
    p.add_argument("--table", metavar="RESULT_JSON", default=None,
                   help="print the table of a result file and exit (no measurement)")
    p.add_argument("--strict", action="store_true", help="exit with status 1 when a target fails")
    p.set_defaults(func=run_bench)

    # `arm torch` needs the arm extra too: without it the arm group keeps saying so
    arm = _group(subparsers, "arm", "pymunk arm sorting study", create=False)
    if arm is None:
        return
    a = arm.add_parser("torch", help="train the PyTorch arm policies with the JAX recipe and evaluate them beside "
                                     "the shipped JAX policies in the simulated-delay executor ([PT-9])")
    a.add_argument("--out", type=output_file(), default="results/torch/arm.json", help="result JSON")
    a.add_argument("--work", type=output_dir(), default="arm_torch_work",
                   help="folder of the trained policies (default arm_torch_work)")
    a.add_argument("--retrain", action="store_true", help="train even when --work holds the three policies")
    a.add_argument("--demos", default=None, help="an existing generate_demos file made with the recipe's arguments")
    a.add_argument("--episodes", type=int_in("value", 1, 100000), default=400, help="demo episodes (default 400)")
    a.add_argument("--steps", type=int_in("value", 1, 10**7), default=4000, help="base steps (default 4000)")
    a.add_argument("--finetune-steps", type=int_in("value", 1, 10**7), default=800, help="fine-tune steps (default 800)")
    a.add_argument("--seed", type=int_in("value", 0, 2**31 - 3), default=0, help="training seed (default 0)")
    a.add_argument("--delays", type=comma_list("value", int_in("each entry", 0, 5)), default=[1, 3, 5],
                   help="constant delays of the evaluation (default 1,3,5)")
    a.add_argument("--eval-episodes", type=int_in("value", 1, 100000), default=20,
                   help="paired episodes per delay (default 20)")
    a.add_argument("--seed0", type=int_in("value", 0, 2**31 - 100001), default=10_000,
                   help="first evaluation env seed (default 10000)")
    # an episode is at most the scene's 1000 ticks (ArmConfig.max_steps): a larger limit is refused here,
    # before any training, not by the executor afterwards.
    a.add_argument("--max-steps", type=int_in("value", 1, 1000), default=None,
                   help="episode step limit, at most 1000 (the scene's episode length)")
    a.add_argument("--threads", type=int_in("value", 1, 1024), default=1, help="torch threads (default 1)")
    a.add_argument("--table", metavar="RESULT_JSON", default=None,
                   help="print the table of a result file and exit (no training or evaluation)")
    a.set_defaults(func=run_arm)


_OPTIONS = {"execute_horizon": "--execute-horizon", "num_steps": "--steps", "train_batch": "--train-batch",
            "train_calls": "--train-calls", "batch_sizes": "--batch-sizes", "finetune_steps": "--finetune-steps",
            "delays": "--delays", "seed0": "--seed0"}


def _as_option(message: str) -> str:
    """A config field's error in terms of the command's option ([N-11])."""
    field = message.split(" ", 1)[0]
    return _OPTIONS.get(field, "--" + field.replace("_", "-")) + message[len(field):]


def _check_memory(bench, cfg) -> None:
    """[B-16] The largest chunk batch and the training batch fit in the host's memory, estimated from the
    sizes before any tensor is made (the rows run on the CPU)."""
    from softrtc._memory import available_bytes, check_fits, step_bytes

    pc = bench.ARCHS[cfg.arch]["config"]
    available = available_bytes()

    def need(batch):
        return step_bytes(batch, pc.horizon, pc.num_layers, pc.width, pc.channel_hidden)

    largest = max(cfg.batch_sizes)
    check_fits("--batch-sizes entry", largest, need(largest), available)
    if cfg.train_calls:
        check_fits("--train-batch", cfg.train_batch, need(cfg.train_batch), available)


def run_bench(args) -> int:
    prog = getattr(args, "_prog", "softrtc bench torch")
    if importlib.util.find_spec("torch") is None:
        return command_error(prog, HINT)
    from . import bench

    if args.table is not None:
        try:
            res = bench.read_json(args.table)
        except (ValueError, OSError) as exc:
            return command_error(prog, f"--table: {exc}")
        print(bench.format_table(res))
        return 0
    try:
        cfg = bench.BenchConfig(calls=args.calls, warmup=args.warmup, batch_sizes=tuple(args.batch_sizes),
                                train_batch=args.train_batch, train_calls=args.train_calls, num_steps=args.steps,
                                execute_horizon=args.execute_horizon, seed=args.seed, arch=args.arch,
                                architecture=args.architecture, threads=args.threads, clock=args.clock)
    except ValueError as exc:
        return command_error(prog, _as_option(str(exc)))
    try:
        _check_memory(bench, cfg)
    except ValueError as exc:
        return command_error(prog, exc)
    res = bench.run_benchmark(cfg, progress=lambda m: print(f"[bench] {m}", file=sys.stderr, flush=True))
    print(bench.format_table(res))
    try:
        bench.write_json(res, args.out)
    except (OSError, ValueError) as exc:
        return command_error(prog, f"cannot write {args.out}: {exc}")
    print(f"wrote {args.out}")
    return 1 if args.strict and not all(t["passed"] for t in res["targets"]) else 0


def run_arm(args) -> int:
    prog = getattr(args, "_prog", "softrtc arm torch")
    for mod, extra in (("torch", "torch"), ("pymunk", "arm"), ("jax", "arm")):
        if importlib.util.find_spec(mod) is None:
            return command_error(prog, f"needs the '{extra}' extra (missing module {mod}): pip install 'softrtc[{extra}]'")
    import torch

    from . import arm

    if args.table is not None:
        try:
            res = arm.read_results(args.table)
        except (ValueError, OSError) as exc:
            return command_error(prog, f"--table: {exc}")
        print(arm.format_table(res["summary"]))
        return 0
    try:
        recipe = arm.TrainRecipe(episodes=args.episodes, steps=args.steps, finetune_steps=args.finetune_steps,
                                 seed=args.seed)
        protocol = arm.Protocol(delays=tuple(args.delays), episodes=args.eval_episodes, seed0=args.seed0,
                                max_steps=args.max_steps)
    except ValueError as exc:
        return command_error(prog, _as_option(str(exc)))
    torch.set_num_threads(args.threads)
    res = arm.run_experiment(args.out, args.work, recipe, protocol, args.demos, args.retrain,
                             progress=lambda m: print(m, file=sys.stderr, flush=True))
    print(arm.format_table(res["summary"]))
    print(f"wrote {args.out}")
    return 0
