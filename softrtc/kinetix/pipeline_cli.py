"""``softrtc kinetix {train-expert, generate-data, train-bc, screen}``: the release's pipeline ([KP-13])
and the level screen ([KS-1]),
and the options every Kinetix command shares: the compile cache ([KC-1]) and, for ``eval``, the
process group of ``jax.distributed`` ([KD-1]).

Parsers only import the standard library; JAX loads when a command runs.
"""

from __future__ import annotations

from pathlib import Path

from .._cli_util import command_error, comma_list, input_dir, int_in, output_dir, real_in
from .limits import EPISODES_MAX

__all__ = ["add_cache_options", "apply_cache_options", "add_distributed_options", "apply_distributed_options",
           "add_pipeline_subparsers"]

SEED_MAX = 2**31 - 1
_levels = comma_list("value")


def add_cache_options(p) -> None:
    """``--compile-cache DIR`` / ``--no-compile-cache`` ([KC-1])."""
    g = p.add_mutually_exclusive_group()
    g.add_argument("--compile-cache", type=output_dir(), default=None, metavar="DIR",
                   help="compile cache folder (default: $SOFTRTC_JAX_CACHE, else ~/.cache/softrtc/jax)")
    g.add_argument("--no-compile-cache", action="store_true", help="compile everything afresh, store nothing")


def apply_cache_options(args) -> None:
    from . import cache

    if getattr(args, "no_compile_cache", False):
        cache.enable_compile_cache(None)
    elif getattr(args, "compile_cache", None):
        cache.enable_compile_cache(args.compile_cache)
    else:
        cache.enable_compile_cache(True)


def add_distributed_options(p) -> None:
    """``--coordinator HOST:PORT --num-processes N --process-id I [--local-devices K]`` ([KD-1])."""
    g = p.add_argument_group("scale-out (jax.distributed): run the same command once per process")
    g.add_argument("--coordinator", default=None, metavar="HOST:PORT",
                   help="address of process 0 (enables multi-process mode)")
    g.add_argument("--num-processes", type=int_in("value", 1, 4096), default=None, help="processes in the run")
    g.add_argument("--process-id", type=int_in("value", 0, 4095), default=None, help="this process, 0-based")
    g.add_argument("--local-devices", type=int_in("value", 1, 1024), default=None,
                   help="CPU devices of this process (default: JAX's, one)")


def apply_distributed_options(args) -> None:
    """Join the process group when ``--coordinator`` is given; the three options go together ([KD-1])."""
    given = [args.coordinator is not None, args.num_processes is not None, args.process_id is not None]
    if not any(given):
        if args.local_devices is not None:
            import jax

            jax.config.update("jax_num_cpu_devices", args.local_devices)
        return
    if not all(given):
        raise ValueError("--coordinator, --num-processes and --process-id go together (one process per id)")
    if args.process_id >= args.num_processes:
        raise ValueError(f"--process-id must be an integer in [0, {args.num_processes - 1}], got {args.process_id}")
    from . import distributed

    distributed.initialize(args.coordinator, args.num_processes, args.process_id, args.local_devices)


def add_pipeline_subparsers(sub) -> None:
    """Register ``train-expert``, ``generate-data`` and ``train-bc`` on the ``kinetix`` subparsers."""
    te = sub.add_parser("train-expert", help="train PPO experts on the symbolic observations (release layout)")
    te.add_argument("--levels", type=_levels, required=True, help="comma-separated level names")
    te.add_argument("--out", type=output_dir(), required=True, help="run folder (seed_<s>/<update>/...)")
    te.add_argument("--seeds", type=comma_list("value", int_in("each seed", 0, SEED_MAX)), default=[0],
                    help="comma-separated seeds (default 0)")
    te.add_argument("--updates", type=int_in("value", 1, 1 << 24), default=1000,
                    help="PPO iterations per expert (default 1000, the release's)")
    te.add_argument("--num-envs", type=int_in("value", 1, 1 << 16), default=256, help="envs (default 256)")
    te.add_argument("--num-steps", type=int_in("value", 1, 1 << 16), default=256,
                    help="steps per env and iteration (default 256)")
    te.add_argument("--num-minibatches", type=int_in("value", 1, 1 << 20), default=8, help="default 8")
    te.add_argument("--num-epochs", type=int_in("value", 1, 1000), default=4, help="default 4")
    te.add_argument("--layer-width", type=int_in("value", 1, 1 << 14), default=256, help="default 256")
    te.add_argument("--lr", type=real_in("value", 0.0, 10.0, lo_open=True), default=3e-4, help="default 3e-4")
    te.add_argument("--log-interval", type=int_in("value", 1, 1 << 20), default=20,
                    help="iterations between checkpoints (default 20)")
    te.add_argument("--max-minutes", type=real_in("value", 0.0, 1e7, lo_open=True), default=None,
                    help="stop each expert after the first block past this wall-clock budget")
    te.add_argument("--no-resume", action="store_true", help="start afresh even if a resume file exists")
    _common(te, seed=False)
    te.set_defaults(func=_train_expert)

    gd = sub.add_parser("generate-data", help="record expert data as the release's worlds_l_<level>.npz")
    gd.add_argument("--run", type=input_dir(), required=True, help="expert run folder (train-expert --out)")
    gd.add_argument("--levels", type=_levels, required=True, help="comma-separated level names")
    gd.add_argument("--out", type=output_dir(), default=None, help="data folder (default RUN/data)")
    gd.add_argument("--num-envs", type=int_in("value", 1, 1 << 16), default=128, help="default 128")
    gd.add_argument("--num-steps", type=int_in("value", 1, 1 << 40), default=1_000_000,
                    help="total steps, rounded up to whole blocks per env (default 1000000)")
    gd.add_argument("--batch-size", type=int_in("value", 1, 1 << 20), default=256,
                    help="steps per env and block (default 256)")
    gd.add_argument("--solve-rate-threshold", type=real_in("value", 0.0, 1.0), default=0.65, help="default 0.65")
    gd.add_argument("--no-resume", action="store_true",
                    help="record again even if the level's data and meta files match these settings")
    _common(gd)
    gd.set_defaults(func=_generate_data)

    tb = sub.add_parser("train-bc", help="behaviour-clone the base flow policy (release bc/<epoch>/policies)")
    tb.add_argument("--data", type=input_dir(), required=True, help="folder of worlds_l_<level>.npz")
    tb.add_argument("--levels", type=_levels, required=True, help="comma-separated level names")
    tb.add_argument("--out", type=output_dir(), required=True, help="output folder (<epoch>/policies/...)")
    tb.add_argument("--epochs", type=int_in("value", 1, 100000), default=32, help="default 32")
    tb.add_argument("--batch-size", type=int_in("value", 1, 1 << 20), default=512, help="default 512")
    tb.add_argument("--lr", type=real_in("value", 0.0, 10.0, lo_open=True), default=3e-4, help="default 3e-4")
    tb.add_argument("--warmup-steps", type=int_in("value", 0, 1 << 30), default=1000, help="default 1000")
    tb.add_argument("--channel-dim", type=int_in("value", 2, 8192), default=256, help="default 256")
    tb.add_argument("--channel-hidden-dim", type=int_in("value", 1, 65536), default=512, help="default 512")
    tb.add_argument("--token-hidden-dim", type=int_in("value", 1, 65536), default=64, help="default 64")
    tb.add_argument("--num-layers", type=int_in("value", 1, 256), default=4, help="default 4")
    tb.add_argument("--chunk-size", type=int_in("value", 1, 1024), default=8, help="H (default 8)")
    tb.add_argument("--no-resume", action="store_true", help="start afresh even if a resume file exists")
    _common(tb, levels_dir=False)
    tb.set_defaults(func=_train_bc)

    sc = sub.add_parser("screen", help="screen candidate levels: constant and random actions, a short PPO run, "
                                       "the expert under delay; keep or drop each, with reasons")
    sc.add_argument("--levels", type=_levels, required=True,
                    help="comma-separated level names (e.g. m_h5_angry_birds; see `softrtc kinetix levels`)")
    sc.add_argument("--out", type=output_dir(), required=True,
                    help="output folder (<level>/..., screen.json, screen.md); a rerun continues where it stopped")
    sc.add_argument("--ppo-steps", type=int_in("value", 1, 1 << 40), default=200_000,
                    help="PPO env steps per level, rounded up to whole iterations (default 200000)")
    sc.add_argument("--episodes", type=int_in("value", 1, EPISODES_MAX), default=64,
                    help="episodes per constant action, for random actions and per delay (default 64)")
    sc.add_argument("--delays", type=comma_list("value", int_in("each delay", 0, 64)), default=[0, 1, 2, 4],
                    help="delays of the expert, increasing from 0 (default 0,1,2,4)")
    sc.add_argument("--hold", type=int_in("value", 1, 64), default=4,
                    help="steps the expert's delayed input is held, the study's execution horizon s (default 4; "
                         "1: observation delay alone)")
    sc.add_argument("--const-threshold", type=real_in("value", 0.0, 1.0), default=0.5,
                    help="a constant action solving at least this rate drops the level (default 0.5)")
    sc.add_argument("--expert-threshold", type=real_in("value", 0.0, 1.0), default=0.8,
                    help="the expert's solve rate at d = 0 a kept level needs (default 0.8)")
    sc.add_argument("--min-drop", type=real_in("value", 0.0, 1.0), default=0.2,
                    help="least fall of the expert's solve rate from d = 0 to the largest delay (default 0.2)")
    sc.add_argument("--ppo-envs", type=int_in("value", 1, 1 << 16), default=32, help="PPO envs (default 32)")
    sc.add_argument("--ppo-num-steps", type=int_in("value", 1, 1 << 16), default=256,
                    help="PPO steps per env and iteration (default 256)")
    sc.add_argument("--ppo-minibatches", type=int_in("value", 1, 1 << 20), default=4, help="default 4")
    _common(sc)
    sc.set_defaults(func=_screen)


def _common(p, *, seed: bool = True, levels_dir: bool = True) -> None:
    if seed:
        p.add_argument("--seed", type=int_in("value", 0, SEED_MAX), default=0, help="seed (default 0)")
    if levels_dir:
        p.add_argument("--levels-dir", type=input_dir(), default=None,
                       help="directory of the level JSON files (default: ../shared/kinetix-levels)")
    add_cache_options(p)
    p.add_argument("--no-progress", action="store_true", help="hide progress bars")


def _levels_checked(levels) -> list:
    from .env import check_level_name

    for lv in levels:
        check_level_name(lv, "--levels entry")
    if len(set(levels)) != len(levels):
        raise ValueError("--levels names a level twice")
    return list(levels)


def _run(cmd: str, body, args) -> int:
    try:
        apply_cache_options(args)
        return body(args)
    except (ValueError, OSError) as exc:
        return command_error(f"softrtc kinetix {cmd}", exc)


def _train_expert(args) -> int:
    def body(args):
        from .ppo import PPOConfig, train_expert

        levels = _levels_checked(args.levels)
        config = PPOConfig(num_envs=args.num_envs, num_steps=args.num_steps, num_minibatches=args.num_minibatches,
                           num_epochs=args.num_epochs, layer_width=args.layer_width, lr=args.lr)
        for lv in levels:
            for seed in args.seeds:
                r = train_expert(lv, args.out, updates=args.updates, seed=seed, config=config,
                                 log_interval=args.log_interval, max_minutes=args.max_minutes,
                                 levels_dir=args.levels_dir, resume=not args.no_resume,
                                 progress=not args.no_progress)
                last = r["last"]
                print(f"{lv} seed {seed}: {r['updates']} iterations, {r['env_steps']} env steps"
                      + (" (stopped at --max-minutes)" if r["stopped_early"] else "")
                      + (f", last solve rate {last.get('solved', float('nan')):.3f}" if last else "")
                      + f" -> {r['curve_csv']}")
        return 0

    return _run("train-expert", body, args)


def _generate_data(args) -> int:
    def body(args):
        from .recorder import generate_data

        for lv in _levels_checked(args.levels):
            r = generate_data(args.run, lv, out_dir=args.out, num_envs=args.num_envs, num_steps=args.num_steps,
                              batch_size=args.batch_size, seed=args.seed,
                              solve_rate_threshold=args.solve_rate_threshold, levels_dir=args.levels_dir,
                              progress=not args.no_progress, resume=not args.no_resume)
            st = r["episode_stats"]
            below = sum(not e["good"] for e in r["experts"])
            print(f"{lv}: {r['steps_per_env'] * r['num_envs']} steps, {st['num_episodes']} episodes, solve rate "
                  f"{st['solved']:.3f}, {len(r['experts'])} expert(s)"
                  + (f", {below} below the threshold {args.solve_rate_threshold}" if below else "")
                  + f" -> {r['path']}" + (" (already recorded, read back)" if r["resumed"] else ""))
        return 0

    return _run("generate-data", body, args)


def _screen(args) -> int:
    def body(args):
        from .ppo import PPOConfig
        from .screen import ScreenConfig, screen_levels

        levels = _levels_checked(args.levels)
        ppo = PPOConfig(num_envs=args.ppo_envs, num_steps=args.ppo_num_steps, num_minibatches=args.ppo_minibatches)
        config = ScreenConfig(ppo_steps=args.ppo_steps, episodes=args.episodes, delays=tuple(args.delays),
                              seed=args.seed, const_threshold=args.const_threshold,
                              expert_threshold=args.expert_threshold, min_drop=args.min_drop, ppo=ppo,
                              hold=args.hold)
        results = screen_levels(levels, args.out, config, levels_dir=args.levels_dir, progress=not args.no_progress)
        for r in results:
            print(f"{r['level']}: {'kept' if r['kept'] else 'dropped'}: " + "; ".join(r["reasons"]))
        print(f"wrote {Path(args.out) / 'screen.json'} and {Path(args.out) / 'screen.md'}")
        return 0

    return _run("screen", body, args)


def _train_bc(args) -> int:
    def body(args):
        from softrtc.jax.policy import PolicyConfig

        from .bc import train_bc

        cfg = PolicyConfig(channel_dim=args.channel_dim, channel_hidden_dim=args.channel_hidden_dim,
                           token_hidden_dim=args.token_hidden_dim, num_layers=args.num_layers,
                           action_chunk_size=args.chunk_size)
        for lv in _levels_checked(args.levels):
            r = train_bc(args.data, lv, args.out, epochs=args.epochs, policy_config=cfg,
                         batch_size=args.batch_size, learning_rate=args.lr, warmup_steps=args.warmup_steps,
                         seed=args.seed, resume=not args.no_resume, progress=not args.no_progress)
            print(f"{lv}: {r['epochs']} epochs of {r['steps_per_epoch']} steps on {r['examples']} examples, "
                  f"final loss {r['final_loss']:.4g} -> {Path(r['policy'])}")
        return 0

    return _run("train-bc", body, args)
