"""`softrtc conformance rollout`: an implementation drives the arm or a Kinetix level in closed loop
([CR-1]..[CR-8], [CR-10], [CR-13], [CR-14]).

    softrtc conformance rollout --impl reference|jax|torch|torch-flipped|lerobot|module:ATTR|file.py
    softrtc conformance rollout --impl-cmd "node conformance/ports/js/rollout.js"
    softrtc conformance rollout --impl X --env kinetix [--level NAME] [--checkpoint <level>.npz | --init-seed N]
    softrtc conformance rollout --impl X --vectors [DIR] [--env arm|kinetix]   (replay the rollout vectors, [CR-10])

Each request of each episode is checked against the reference on the same
inputs; the report gives, per requirement, the cases (one per output of each
request), per episode the first request whose executed actions leave the
tolerance, and the paired differences of the episode outcomes (arm: success,
D1..D3, boundary jump; Kinetix: return, solved, delta, jerk) against the
reference's own episodes ([CR-6], [CR-7]), in the formats of
`conformance run` ([CR-8]).
"""

from __future__ import annotations

import argparse
import math
import shlex
import sys
import time

from softrtc.reference._validate import check_choice, check_int

from .._cli_util import command_error, comma_list, int_in, real_in
from .._files import write_json
from . import SPEC_VERSION
from .adapter import AdapterError
from .protocol import ChildLost, ImplementationError
from .results import RunResult, format_summary, report_dict, write_junit
from .rollout_impls import METHODS, ReferenceRollout, impl_methods, load_rollout_impl
from .rollout_loop import METRICS, Checker, Settings, run_episode

ROLLOUT_FORMAT = "rollout-1"
ENVS = ("arm", "kinetix")


class RequestLost(RuntimeError):
    """The child was lost during a request (died, hung, broke the protocol) and was replaced ([CF-30])."""


class _InProcess:
    """A Python rollout implementation called in the runner's process (``--in-process``)."""

    def __init__(self, impl, field):
        self.impl, self.name = impl, impl.name
        self.time_convention = getattr(impl, "time_convention", "data_at_1")
        self.bind(field)
        self.methods = impl_methods(impl)
        self.isolation = "in process"

    def bind(self, field) -> None:
        """Serve ``field`` (None: not yet loaded) in the implementation's time convention ([V-1])."""
        self.field = field if field is None or self.time_convention == "data_at_1" else field.flipped()

    def answer(self, c: int, args: dict) -> dict:
        return self.impl.rollout_chunk(self.field, **args)

    def close(self) -> None:
        pass


class _Child:
    """An implementation in a child process, the field served over the protocol ([CR-4])."""

    def __init__(self, argv: list, label: str, field, timeout: float, start_timeout: float,
                 memory_mb: int | None = None):
        from .rollout_child import RolloutChild

        self.child = RolloutChild(argv, start_timeout, label, memory_mb)
        self.child.start()
        self.name, self.time_convention = self.child.name, self.child.time_convention
        self.bind(field)
        self.methods = tuple(METHODS)
        self.timeout, self.rid = timeout, 0
        self.isolation = "child process"

    def answer(self, c: int, args: dict) -> dict:
        self.rid += 1
        try:
            reply = self.child.call(self.rid, args, self.field, self.timeout)
        except ChildLost as exc:
            self.child.restart()
            raise RequestLost(str(exc)) from None
        if "error" in reply:
            err = reply["error"] if isinstance(reply["error"], dict) else {"message": str(reply["error"])}
            text = f"{err.get('type', err.get('kind', 'error'))}: {err.get('message', '')}"
            if err.get("kind") == "unsupported":
                raise NotImplementedError(text)
            raise RuntimeError(text)
        return reply["result"]

    bind = _InProcess.bind

    def close(self) -> None:
        self.child.stop()


def open_impl(impl, impl_cmd, field, in_process: bool, timeout: float = 60.0, start_timeout: float = 120.0,
              memory_mb: int | None = None):
    """The implementation under test, in process or as a child ([CR-4]); AdapterError when it cannot load
    (NoRolloutChunk or LacksRolloutChunk when it loads without ``rollout_chunk``). ``field`` None: bound
    later with ``bind``, so a run loads JAX only for an implementation that has the function ([CR-10])."""
    if impl_cmd is not None:
        return _Child(shlex.split(impl_cmd), f"impl-cmd {impl_cmd!r}", field, timeout, start_timeout, memory_mb)
    if in_process:
        return _InProcess(load_rollout_impl(impl), field)
    argv = [sys.executable, "-m", "softrtc.conformance.rollout_child", "--impl", impl]
    return _Child(argv, f"impl {impl!r}", field, timeout, start_timeout, memory_mb)


def paired(impl_eps: list, ref_eps: list, metrics: tuple = METRICS) -> dict:
    """Paired differences implementation - reference per metric with 95% bootstrap intervals ([CR-7])."""
    from softrtc.arm.paired_stats import paired_difference

    out = {}
    for m in metrics:
        a = [e.metrics.get(m, math.nan) for e in impl_eps]
        b = [e.metrics.get(m, math.nan) for e in ref_eps]
        r = paired_difference([a], [b], num_resamples=2000, seed=0)
        n_impl = [x for x in a if x == x]
        n_ref = [x for x in b if x == x]
        out[m] = {"impl": sum(n_impl) / len(n_impl) if n_impl else None,
                  "reference": sum(n_ref) / len(n_ref) if n_ref else None,
                  **{k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in r.items()}}
    return out


def open_world(env: str = "arm", checkpoint=None, level=None, init_seed=None, levels_dir=None,
               max_steps: int | None = None) -> tuple:
    """``(field, world)`` of a rollout: the arm's served checkpoint and simulator ([CR-3]) or a Kinetix
    level with its served policy ([CR-13], [CR-14]). Every argument is checked before anything loads."""
    check_choice("env", env, ENVS)
    if env == "arm":
        for name, value in (("level", level), ("init_seed", init_seed), ("levels_dir", levels_dir)):
            if value is not None:
                raise ValueError(f"{name} is for env 'kinetix' only, got {value!r} with env 'arm'")
        from .rollout_field import ArmWorld, ServedField

        field = ServedField(checkpoint)
        return field, ArmWorld(field, max_steps=max_steps)
    from softrtc.kinetix.levels import check_level_name

    from .rollout_kinetix import KinetixField, KinetixWorld, default_level

    level = check_level_name(default_level() if level is None else level, "level")
    if checkpoint is not None and init_seed is not None:
        raise ValueError("give at most one of checkpoint and init_seed")
    if init_seed is not None:
        check_int("init_seed", init_seed, 0, 2**32 - 1)
    field = KinetixField(level, checkpoint, init_seed, levels_dir)
    return field, KinetixWorld(field, max_steps=max_steps)


def run(impl=None, *, impl_cmd=None, settings: Settings = Settings(), env: str = "arm", checkpoint=None,
        level=None, init_seed=None, levels_dir=None, in_process: bool = False, timeout: float = 60.0,
        progress=None) -> dict:
    """A closed-loop rollout check ([CR-5]..[CR-8], [CR-13]); returns {"result": RunResult, "episodes",
    "paired", ...}. ``env`` "kinetix" takes ``level``, ``checkpoint`` or ``init_seed`` and ``levels_dir``."""
    if (impl is None) == (impl_cmd is None):
        raise ValueError("give exactly one of impl and impl_cmd")
    if not isinstance(settings, Settings):
        raise ValueError(f"settings must be a Settings, got {type(settings).__name__}")
    t0 = time.perf_counter()
    field, world = open_world(env, checkpoint, level, init_seed, levels_dir, settings.max_steps)
    under = open_impl(impl, impl_cmd, field, in_process, timeout)
    checker = Checker(field, env)
    reference = ReferenceRollout()
    episodes, pairs = [], {}
    try:
        for method in settings.methods:
            ours, refs = [], []
            for i in range(settings.episodes):
                ep = run_episode(under.answer, field, world, settings, method, i, checker)
                episodes.append(ep)
                if ep.unsupported is not None:
                    break
                ours.append(ep)
                refs.append(run_episode(lambda c, a: reference.rollout_chunk(field, **a), field, world, settings,
                                        method, i))
                if progress:
                    progress(ep)
            if ours:
                pairs[method] = paired(ours, refs, world.metric_names)
    finally:
        under.close()
    res = RunResult(impl if impl is not None else impl_cmd, under.name, under.time_convention, ROLLOUT_FORMAT,
                    [SPEC_VERSION], checker.cases, time.perf_counter() - t0, under.isolation)
    return {"result": res, "episodes": episodes, "paired": pairs, "settings": settings.to_dict(), "env": env,
            "checkpoint": field.checkpoint, "policy": field.describe(), "metrics": world.metric_names,
            "field_calls": dict(field.calls)}


def summary_text(out: dict) -> str:
    """`conformance run`'s summary ([CF-14]), then one line per episode with a divergence and the paired
    differences per method ([CR-6], [CR-7])."""
    lines = [format_summary(out["result"])]
    for ep in out["episodes"]:
        if ep.unsupported:
            lines.append(f"  {ep.method}: unsupported ({ep.unsupported})")
        elif ep.error:
            lines.append(f"  {ep.method} episode {ep.episode}: {ep.error}")
        elif ep.first_divergence:
            fd = ep.first_divergence
            lines.append(f"  {ep.method} episode {ep.episode}: first divergence at request {fd['request']} "
                         f"(tick {fd['tick']}), {fd['ratio']:.3g} x tolerance")
    names = tuple(out.get("metrics", METRICS))
    for method, p in out["paired"].items():
        cells = []
        for m in names:
            r = p[m]
            if r["diff"] is None:
                cells.append(f"{m} -")
            elif r["lo"] is None or r["hi"] is None:
                cells.append(f"{m} {r['diff']:+.3g}")
            else:
                cells.append(f"{m} {r['diff']:+.3g} [{r['lo']:+.3g}, {r['hi']:+.3g}]")
        lines.append(f"paired {method} (impl - reference, 95% CI, n = {p[names[0]]['n']}): " + "; ".join(cells))
    return "\n".join(lines)


def report_doc(out: dict) -> dict:
    """The --report JSON: `conformance run`'s document plus the rollout's settings, episodes, pairs ([CR-8])."""
    doc = report_dict(out["result"])
    doc["rollout"] = {"env": out["env"], **out["policy"],
                      "settings": out["settings"], "episodes": [e.to_dict() for e in out["episodes"]],
                      "paired": out["paired"]}
    return doc


def add_arguments(parser: argparse.ArgumentParser) -> None:
    who = parser.add_mutually_exclusive_group(required=True)
    who.add_argument("--impl", help="reference, jax, torch, torch-flipped, lerobot, a mutant (mutant-*), "
                                    "module[:ATTR] or file.py[:ATTR] with rollout_chunk")
    who.add_argument("--impl-cmd", help="a program speaking the rollout protocol ([CR-4])")
    parser.add_argument("--env", default=None, choices=ENVS,
                        help="simulator (default arm; with --vectors, default every file the vectors' index lists)")
    parser.add_argument("--level", default=None,
                        help="Kinetix level ([K-1] or [K-20] name, see `softrtc kinetix levels`; default "
                             "s_h4_thrust_aim)")
    parser.add_argument("--init-seed", type=int_in("init_seed", 0, 2**32 - 1), default=None,
                        help="Kinetix: serve a fresh benchmark-architecture policy from this seed (default 0 "
                             "without --checkpoint)")
    parser.add_argument("--levels-dir", default=None,
                        help="Kinetix: folder of the benchmark's level files (default ../shared/kinetix-levels)")
    # ASCII digits and the library's ranges at the door ([N-11]): int() would read '١' as 1.
    parser.add_argument("--episodes", type=int_in("episodes", 1, 10_000), default=5,
                        help="episodes per method (default 5: 20 episodes with the default methods)")
    parser.add_argument("--methods", default="naive,train_hard,train_soft,inference_hard",
                        help="comma-separated methods of [S-6] (default naive,train_hard,train_soft,inference_hard)")
    parser.add_argument("--delays", type=comma_list("delay", int_in("each delay", 0, 5)), default=[0, 1, 2, 3, 4, 5],
                        help="delays drawn for requests c >= 1 (default 0..5)")
    parser.add_argument("--max-steps", type=int_in("max_steps", 1, 1000), default=400,
                        help="ticks per episode at most (default 400)")
    parser.add_argument("--seed", type=int_in("seed", 0, 2**31 - 1), default=0,
                        help="seed of environments, noise and delays (default 0)")
    parser.add_argument("--checkpoint", default=None,
                        help="policy to serve: an arm checkpoint (default the drift base) or, with --env kinetix, "
                             "a <level>.npz checkpoint of `softrtc kinetix train-bc` / `finetune`")
    parser.add_argument("--in-process", action="store_true", help="call a Python implementation in this process")
    parser.add_argument("--case-timeout", type=real_in("case_timeout", 0.0, 86_400.0, lo_open=True), default=60.0,
                        help="seconds per request (default 60)")
    parser.add_argument("--vectors", nargs="?", const="", default=None,
                        help="replay the rollout vectors open loop (DIR, default the shipped ones) instead")
    parser.add_argument("--report", help="write the JSON report here")
    parser.add_argument("--junit", help="write JUnit XML here")
    parser.add_argument("--effect", help="write the closed-loop effect (paired differences) as JSON here")


def run_from_args(args) -> int:
    prog = "softrtc conformance rollout"
    try:
        if args.vectors is not None:
            from .rollout_vectors import replay

            for name in ("level", "init_seed", "levels_dir", "checkpoint"):
                if getattr(args, name) is not None:
                    raise ValueError(f"--{name.replace('_', '-')} is not used with --vectors: the vectors' header "
                                     "names the served policy ([CR-10])")
            out = replay(args.impl, impl_cmd=args.impl_cmd, vectors_dir=args.vectors or None, env=args.env,
                         in_process=args.in_process, timeout=args.case_timeout)
        else:
            if args.level is not None:  # one clear error naming the option, before anything loads ([CR-13])
                from softrtc.kinetix.levels import check_level_name

                check_level_name(args.level, "--level")
            methods = tuple(m.strip() for m in args.methods.split(",") if m.strip())
            settings = Settings(methods, args.episodes, tuple(args.delays), args.max_steps, args.seed)
            out = run(args.impl, impl_cmd=args.impl_cmd, settings=settings, env=args.env or "arm",
                      checkpoint=args.checkpoint, level=args.level, init_seed=args.init_seed,
                      levels_dir=args.levels_dir, in_process=args.in_process, timeout=args.case_timeout)
    except (AdapterError, ImplementationError, ValueError, ImportError, OSError) as exc:
        return command_error(prog, str(exc))
    text = summary_text(out) if "episodes" in out else format_summary(out["result"])
    doc = report_doc(out) if "episodes" in out else report_dict(out["result"])
    if args.report:
        write_json(args.report, doc)
    if args.junit:
        write_junit(out["result"], args.junit)
    if args.effect and "episodes" in out:
        write_json(args.effect, effect_doc(out))
    print(text)
    return 0 if out["result"].ok else 1


def effect_doc(out: dict) -> dict:
    """The closed-loop effect of an implementation against the reference ([CR-7]): settings, paired
    differences per method and the per-episode first divergences, without the per-request cases."""
    res = out["result"]
    return {"impl": res.impl, "name": res.adapter_name, "env": out["env"], **out["policy"],
            "settings": out["settings"], "ok": res.ok,
            "requirements": {k: v["status"] for k, v in res.by_requirement().items()},
            "paired": out["paired"],
            "first_divergence": [{"method": e.method, "episode": e.episode, **(e.first_divergence or {})}
                                 for e in out["episodes"] if e.first_divergence]}
