"""``softrtc kinetix {eval, finetune, bench, levels, report}`` ([KE-12], [KR-6]).

JAX, flax and kinetix are imported when a subcommand runs, so ``softrtc
--help`` stays fast; a missing dependency is reported by the top-level CLI
with its install hint.
"""

from __future__ import annotations

import importlib.util
import json
import pickle
from pathlib import Path

from .._cli_util import command_error, comma_list, group_help, input_dir, int_in, nonempty, output_dir, output_file, real_in
from .limits import EPISODES_MAX, NUM_ENVS_MAX, REPEATS_MAX

for _dep in ("jax", "flax", "kinetix"):
    if importlib.util.find_spec(_dep) is None:
        raise ModuleNotFoundError(f"softrtc kinetix needs {_dep}", name=_dep)


SEED_MAX = 2**31 - 1
# [KE-10] Release policies are pickles: loading one runs whatever code the file holds.
TRUSTED_FILES = ("The .pkl files are unpickled, which can run code stored in them: "
                 "load only files from a source you trust.")
_levels = comma_list("value")
_methods = comma_list("value")
_delays = comma_list("value", int_in("each delay", 0, 4096))

# Per command, the argument names that start the errors of the library calls, as the options that
# set them ([KE-12]): every error line names its option.
_OPTIONS = {
    "eval": {"levels": "--levels", "methods": "--methods", "method": "--methods entry", "delays": "--delays",
             "episodes": "--episodes", "seed": "--seed", "levels_dir": "--levels-dir"},
    "finetune": {"learning_rate": "--lr", "config.d_max": "--d-max", "d_max": "--d-max",
                 "batch_size": "--batch-size", "epochs": "--epochs", "seed": "--seed", "data_dir": "--data",
                 "bc_dir": "--bc", "level": "--levels entry"},
    "bench": {"level": "--level", "method": "--method", "num_envs": "--num-envs", "repeats": "--repeats",
              "seed": "--seed", "levels_dir": "--levels-dir"},
}


def _fail(cmd: str, exc: BaseException) -> int:
    msg = str(exc)
    field = msg.split(" ", 1)[0]
    if field in _OPTIONS[cmd]:
        msg = _OPTIONS[cmd][field] + msg[len(field):]
    return command_error(f"softrtc kinetix {cmd}", msg)


def add_subparsers(subparsers) -> None:
    """Register the ``kinetix`` command and its subcommands on a top-level ``subparsers``."""
    kin = subparsers.add_parser("kinetix", help="Kinetix benchmark: evaluate, fine-tune release policies, bench")
    sub = kin.add_subparsers(dest="kinetix_command", metavar="SUBCOMMAND")
    kin.set_defaults(func=group_help(kin))

    ev = sub.add_parser("eval", help="run the evaluation protocol and write CSV + Markdown results")
    ev.add_argument("--levels", type=_levels, default=None,
                    help="comma-separated level names: the benchmark's 12 (default: all 12) or kinetix-env levels "
                         "<set>_<name>[@own] (see `softrtc kinetix levels`)")
    ev.add_argument("--episodes", type=int_in("value", 1, EPISODES_MAX), default=32,
                    help="episodes per level, delay and method (default 32)")
    ev.add_argument("--methods", type=_methods, default=None,
                    help="comma-separated methods: naive, inference_hard, inference_soft, train_hard, train_soft, "
                         "train_soft:delay_scaled:LAM[:H_MAX], train_soft:offset:L[:H_MAX], train_soft:fixed:H, "
                         "train_soft:hard, each train_soft optionally followed by :zeros; a last :consistent "
                         "selects the time-consistent solver step for naive / train_hard / train_soft "
                         "(default: the paper's main-table rows)")
    ev.add_argument("--delays", type=_delays, default=[0, 1, 2, 3, 4],
                    help="comma-separated delays (default 0,1,2,3,4)")
    src = ev.add_mutually_exclusive_group()
    src.add_argument("--policy-dir", type=input_dir(), default=None,
                     help="per-level policies of every method without --method-policy: <level>.npz checkpoints "
                          "or release worlds_l_<level>.pkl files (e.g. the release's bc/24). " + TRUSTED_FILES)
    src.add_argument("--init-seed", type=int_in("value", 0, SEED_MAX), default=None,
                     help="evaluate a freshly initialised benchmark-size policy with this seed (default 0)")
    ev.add_argument("--method-policy", action="append", default=[], metavar="METHOD=DIR",
                    help="policy directory for one method (e.g. train_hard=ft/hard), overriding --policy-dir; "
                         "repeatable, once per method. " + TRUSTED_FILES)
    ev.add_argument("--levels-dir", type=input_dir(), default=None,
                    help="directory of the level JSON files (default: ../shared/kinetix-levels)")
    ev.add_argument("--seed", type=int_in("value", 0, SEED_MAX), default=0, help="rollout seed (default 0)")
    ev.add_argument("--out", type=output_dir(), required=True, help="output directory")
    ev.add_argument("--no-progress", action="store_true", help="hide progress bars")
    ev.set_defaults(func=_eval)

    ft = sub.add_parser("finetune", help="fine-tune release bc policies as hard or soft training-time RTC "
                                         "(one epoch by default)")
    ft.add_argument("--data", type=input_dir(), required=True, help="directory of worlds_l_<level>.npz expert data")
    ft.add_argument("--bc", type=input_dir(), required=True,
                    help="release bc directory (worlds_l_<level>.pkl files). " + TRUSTED_FILES)
    ft.add_argument("--method", required=True, choices=("hard", "soft"), help="training-time RTC variant")
    ft.add_argument("--window", type=nonempty(), default=None,
                    help="soft window rule: delay_scaled:LAM[:H_MAX] (default delay_scaled:2:5), offset:L[:H_MAX], "
                         "fixed:H, optionally ':zeros'")
    ft.add_argument("--levels", type=_levels, default=None, help="comma-separated levels (default: those with data files)")
    ft.add_argument("--epochs", type=int_in("value", 1, 1000), default=1, help="epochs over the data (default 1)")
    ft.add_argument("--batch-size", type=int_in("value", 1, 1 << 20), default=256,
                    help="batch size, capped at the number of examples (default 256)")
    ft.add_argument("--lr", type=real_in("value", 0.0, 10.0, lo_open=True), default=3e-4,
                    help="AdamW learning rate, > 0 (default 3e-4)")
    ft.add_argument("--d-max", type=int_in("value", 0, 4096), default=4,
                    help="largest training delay, <= H (default 4)")
    ft.add_argument("--seed", type=int_in("value", 0, 2**32 - 1), default=0, help="training seed (default 0)")
    ft.add_argument("--out", type=output_dir(), required=True, help="output directory for <level>.npz checkpoints")
    ft.add_argument("--no-progress", action="store_true", help="hide progress bars")
    ft.set_defaults(func=_finetune)

    be = sub.add_parser("bench", help="cold and warm compile time and env steps/s of each rollout family "
                                      "against the bare env, side by side")
    be.add_argument("--level", type=nonempty(), default="grasp_easy", help="level name (default grasp_easy)")
    be.add_argument("--num-envs", type=int_in("value", 1, NUM_ENVS_MAX), default=64,
                    help="parallel environments (default 64)")
    be.add_argument("--method", type=nonempty(), default=None,
                    help="measure this method's family only (default: naive and inference_soft, one per family)")
    be.add_argument("--repeats", type=int_in("value", 1, REPEATS_MAX), default=1,
                    help="timed repetitions of each rollout (default 1)")
    be.add_argument("--seed", type=int_in("value", 0, SEED_MAX), default=0, help="rollout seed (default 0)")
    be.add_argument("--levels-dir", type=input_dir(), default=None,
                    help="directory of the level JSON files (default: ../shared/kinetix-levels)")
    be.add_argument("--out", type=output_file(), default=None, help="optional JSON output file")
    be.add_argument("--no-progress", action="store_true", help="hide progress bars")
    be.set_defaults(func=_bench)

    lv = sub.add_parser("levels", help="list the level names every kinetix command accepts")
    lv.set_defaults(func=_list_levels)

    rp = sub.add_parser("report", help="the study's paper-shaped table, paired tests, plots and verdicts from its "
                                       "evaluation folders ([KR-6])")
    rp.add_argument("--study", type=input_dir(), required=True,
                    help="study folder whose eval/<level>/seed_<k>[.<part>]/ hold `kinetix eval` outputs "
                         "(e.g. results/kinetix/study)")
    rp.add_argument("--out", type=output_dir(), default=None, help="folder for the plots (default: --study)")
    rp.add_argument("--bench", type=input_dir(), default=None,
                    help="folder of `softrtc bench runtime` results runtime-<n>.json (default: results/bench "
                         "beside the study's results folder)")
    rp.add_argument("--page", type=output_file(), default=None,
                    help="Markdown page whose kinetix-table block is rewritten (e.g. docs/reports/kinetix.md)")
    rp.add_argument("--readme", type=output_file(), default=None,
                    help="README whose kinetix-table block is rewritten (the main table and verdicts)")
    rp.add_argument("--no-plots", action="store_true", help="write no PNG plots")
    rp.set_defaults(func=_report)

    from .pipeline_cli import add_cache_options, add_distributed_options, add_pipeline_subparsers

    for p in (ev, ft):
        add_cache_options(p)
    add_distributed_options(ev)
    add_pipeline_subparsers(sub)


def _list_levels(args) -> int:
    """The benchmark's 12 names, then every kinetix-env level with its sizes ([K-20], [K-21])."""
    from . import levels as klev

    print("benchmark levels (files in --levels-dir, default ../shared/kinetix-levels):")
    print("  " + ", ".join(klev.LEVEL_NAMES))
    print(f"kinetix-env levels ({klev.package_levels_dir()}), padded to the benchmark's sizes; "
          f"append {klev.OWN_SHAPES_SUFFIX} for the level's own sizes:")
    print(f"  {'name':<36} polygons circles joints thrusters")
    for name in klev.package_level_names():
        st, stem = name.split("_", 1)
        raw = json.loads((klev.package_levels_dir() / st / f"{stem}.json").read_text())["static_env_params"]
        sizes = [raw.get(f) for f in klev.LARGE_ENV_PARAMS]
        fits = all(v is not None and v <= klev.LARGE_ENV_PARAMS[f] for f, v in zip(klev.LARGE_ENV_PARAMS, sizes))
        print(f"  {name:<36} {sizes[0]:>8} {sizes[1]:>7} {sizes[2]:>6} {sizes[3]:>9}"
              + ("" if fits else f"  (only {name}{klev.OWN_SHAPES_SUFFIX})"))
    return 0


def _report(args) -> int:
    from .._cli_util import missing_extra

    hint = None if args.no_plots else missing_extra("matplotlib")  # [N-13]: at the door
    if hint:
        return command_error("softrtc kinetix report", hint)
    from .study_table import write_report

    try:
        res = write_report(args.study, out=args.out, page=args.page, readme=args.readme, bench_dir=args.bench,
                           plots=not args.no_plots)
    except (ValueError, OSError) as exc:
        return command_error("softrtc kinetix report", exc)
    print(res["block"])
    for w in res["written"]:
        print(f"wrote {w}")
    return 0


def _eval(args) -> int:
    try:
        return _eval_inner(args)
    except (ValueError, OSError) as exc:
        return _fail("eval", exc)


def _eval_inner(args) -> int:
    from .pipeline_cli import apply_cache_options, apply_distributed_options

    apply_distributed_options(args)  # [KD-1]: before any other JAX work
    apply_cache_options(args)
    import flax.nnx as nnx

    from softrtc.jax.policy import FlowPolicy, PolicyConfig

    from . import env as kenv
    from .evaluation import evaluate
    from .finetune import check_level_role, find_level_policy_file, read_level_policy
    from .methods import PAPER_METHODS
    from .protocol import EvalConfig
    from .results import write_results

    levels = tuple(args.levels) if args.levels else kenv.LEVEL_NAMES
    methods = tuple(args.methods) if args.methods else PAPER_METHODS
    delays = tuple(args.delays)
    config = EvalConfig(levels=levels, methods=methods, delays=delays, episodes=args.episodes,
                        seed=args.seed, levels_dir=args.levels_dir)
    kenv.resolve_levels_dir(args.levels_dir, config.levels)  # clear error before anything heavy
    labels = [spec.label for spec in config.methods]
    overrides: dict = {}
    for item in args.method_policy:
        m, sep, d = item.partition("=")
        if not sep or not m or not d:
            raise ValueError(f"--method-policy must be METHOD=DIR, got {item!r}")
        if m not in labels:
            raise ValueError(f"--method-policy method {m!r} is not among --methods ({', '.join(labels)})")
        if m in overrides:
            raise ValueError(f"--method-policy gives method {m!r} twice")
        if not Path(d).is_dir():
            raise FileNotFoundError(f"--method-policy {item}: {d} "
                                    f"{'is not a directory' if Path(d).exists() else 'does not exist'}")
        overrides[m] = d
    # Every (folder, level) pair is found and loaded before the first rollout ([KE-11]): a missing or
    # broken policy file stops the command at once, not after the methods before it have run.
    sources = {lab: (f"--method-policy {lab}={overrides[lab]}", overrides[lab]) if lab in overrides
               else (f"--policy-dir {args.policy_dir}", args.policy_dir) for lab in labels}
    cache: dict = {}
    for option, d in dict.fromkeys(sources.values()):
        if d is None:
            continue
        for level in config.levels:
            if (d, level) in cache:  # the same folder named by two options
                continue
            try:
                find_level_policy_file(d, level)
            except FileNotFoundError:
                raise FileNotFoundError(f"{option} has no policy for level {level!r}: expected {level}.npz or a "
                                        f"release worlds_l_{level}.pkl in ., policies/ or <epoch>/policies/") from None
            try:
                cache[(d, level)] = read_level_policy(d, level)
            except (ValueError, OSError, EOFError, pickle.UnpicklingError) as exc:
                raise ValueError(f"{option}: the policy of level {level!r} does not load: {exc}") from None
    # [KE-11] Each method gets a policy in its role (the base for naive and inference-time methods, a hard or
    # soft fine-tune of its window for train_hard / train_soft), as the arm's loaders check theirs ([A-21]).
    for spec in config.methods:
        option, d = sources[spec.label]
        for level in config.levels if d is not None else ():
            try:
                check_level_role(cache[(d, level)][1], spec.method, spec.window)
            except ValueError as exc:
                raise ValueError(f"{option}: level {level!r}: {exc}") from None
    fresh: dict = {}  # one fresh policy per observation width ([K-21]: a level at its own sizes has its own)
    if any(d is None for _, d in sources.values()):
        seed = 0 if args.init_seed is None else args.init_seed
        for level in config.levels:
            obs_dim = (kenv.OBS_DIM if kenv.level_static_env_params(level) == kenv.benchmark_static_env_params()
                       else kenv.make_env(level, args.levels_dir).obs_dim)
            if obs_dim not in fresh:
                fresh[obs_dim] = FlowPolicy(obs_dim=obs_dim, action_dim=kenv.ACTION_DIM, config=PolicyConfig(),
                                            rngs=nnx.Rngs(seed))
            fresh[level] = fresh[obs_dim]

    def policies(spec, level):
        d = sources[spec.label][1]
        return fresh[level] if d is None else cache[(d, level)][0]

    from .distributed import is_writer

    result = evaluate(config, policies, progress=not args.no_progress)
    if not is_writer():  # [KD-3]: every process holds all episodes; process 0 writes them
        return 0
    paths = write_results(result, args.out, bootstrap_resamples=config.bootstrap_resamples,
                          bootstrap_seed=config.bootstrap_seed)
    print(Path(paths["table"]).read_text(), end="")
    print("compile time per sampler family (s): " +
          ", ".join(f"{k} {v:.1f}" for k, v in result["compile_s"].items()))
    print(f"wrote {paths['episodes']}, {paths['per_level']}, {paths['pooled']}, {paths['table']}")
    return 0


def _finetune(args) -> int:
    try:
        return _finetune_inner(args)
    except (ValueError, OSError) as exc:
        return _fail("finetune", exc)


def _finetune_inner(args) -> int:
    from .pipeline_cli import apply_cache_options

    apply_cache_options(args)
    from . import data as kdata
    from . import env as kenv
    from .finetune import finetune_level
    from .methods import parse_method

    window = None
    if args.window is not None:
        if args.method != "soft":
            raise ValueError("--window is only used with --method soft")
        try:
            window = parse_method("train_soft:" + args.window).window
        except ValueError:
            raise ValueError(f"--window {args.window!r} is not a soft window: expected delay_scaled:LAM[:H_MAX], "
                             f"offset:L[:H_MAX], fixed:H or hard, optionally followed by ':zeros'") from None
    data_dir = Path(args.data)
    if not data_dir.is_dir():
        raise FileNotFoundError(f"--data {data_dir} is not a directory")
    if args.levels:
        levels = list(args.levels)
    else:
        # The benchmark's levels in their order, then package levels ([K-20]) by name.
        found = {p.name[len("worlds_l_"):-len(".npz")] for p in data_dir.glob("worlds_l_*.npz")}
        levels = [lv for lv in kenv.LEVEL_NAMES if lv in found]
        levels += sorted(lv for lv in found if kenv.is_package_level(lv))
        if not levels:
            raise FileNotFoundError(f"no worlds_l_<level>.npz expert data files in {data_dir}")
    from .finetune import bc_policy_shape, find_bc_file

    for lv in levels:  # every level's inputs exist, and fit --d-max, before the first one trains
        kenv.check_level_name(lv, "--levels entry")
        if not (data_dir / kdata.expert_data_filename(lv)).is_file():
            raise FileNotFoundError(f"--data {data_dir} has no {kdata.expert_data_filename(lv)}")
        try:
            bc_file = find_bc_file(args.bc, lv)
        except FileNotFoundError as exc:
            raise FileNotFoundError(f"--bc: {exc}") from None
        try:
            H = bc_policy_shape(bc_file)[2].action_chunk_size
        except (ValueError, OSError, EOFError, pickle.UnpicklingError) as exc:
            raise ValueError(f"--bc: {bc_file} is not a release policy file: {exc}") from None
        if args.d_max > H:  # [D-4]: a delay longer than the chunk has no weights
            raise ValueError(f"--d-max must be an integer in [0, {H}] (the chunk size H of {bc_file.name}), "
                             f"got {args.d_max}")
    for lv in levels:
        meta = finetune_level(data_dir, args.bc, lv, args.method, args.out, window=window,
                              d_max=args.d_max, batch_size=args.batch_size, learning_rate=args.lr,
                              epochs=args.epochs, seed=args.seed, progress=not args.no_progress)
        loss = "n/a" if meta["final_loss"] is None else f"{meta['final_loss']:.4g}"
        print(f"{lv}: {meta['steps']} steps on {meta['examples']} examples, final loss {loss} -> {meta['path']}")
    return 0


def _bench(args) -> int:
    try:
        from .compile_bench import FAMILY_METHODS, bench_compile, format_compile_bench
        methods = (args.method,) if args.method is not None else tuple(FAMILY_METHODS.values())
        res = bench_compile(args.level, num_envs=args.num_envs, methods=methods, seed=args.seed,
                            levels_dir=args.levels_dir, repeats=args.repeats, progress=not args.no_progress)
    except (ValueError, OSError) as exc:
        return _fail("bench", exc)
    print(format_compile_bench(res), end="")
    if args.out:
        try:
            Path(args.out).parent.mkdir(parents=True, exist_ok=True)
            Path(args.out).write_text(json.dumps(res, indent=2) + "\n")
        except OSError as exc:
            return _fail("bench", exc)
        print(f"wrote {args.out}")
    return 0
