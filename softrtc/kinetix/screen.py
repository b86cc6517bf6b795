"""Screening candidate Kinetix levels for the delay study ([KS-1]..[KS-7]).

Per level, four measurements, each written as soon as it is done so a
restarted screen continues where it stopped ([KS-6]):

1. ``baselines.json``: the solve rate of every constant action of a grid over
   the action entries the level uses, and of uniform random actions ([KS-2]);
2. ``ppo/``: a short PPO run (:func:`softrtc.kinetix.ppo.train_expert`, its
   curve CSV and PNG, resumable by itself, [KS-3]);
3. ``delays.json``: the final expert's solve rate when it acts on delayed
   observations, at each delay of the screen ([KS-4]);

   2 and 3 are skipped for a level that a constant action already drops:
   no expert could keep it ([KS-5], [KS-6]).
4. ``screen.json``: the verdict, kept or dropped, with every reason ([KS-5]).

:func:`screen_levels` runs them for several levels and writes the table of
all of them (``screen.json`` and ``screen.md`` in the output folder, [KS-7]).
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import time
from pathlib import Path
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from softrtc._files import check_out_dir, read_json, write_atomic, write_json
from softrtc.reference._validate import check_int

from . import env as kenv
from . import expert as kexp
from .limits import EPISODES_MAX
from .ppo import PPOConfig, expert_paths, train_expert

__all__ = ["SCREEN_PPO", "ScreenConfig", "used_action_entries", "constant_actions", "episode_outcomes",
           "expert_mode", "delayed_expert_outcomes", "screen_verdict", "screen_level", "screen_levels", "format_screen"]

# [KS-3] the screen's PPO: 32 envs x 256 steps per iteration (8,192 env steps), so a short run has a curve.
SCREEN_PPO = PPOConfig(num_envs=32, num_steps=256, num_minibatches=4, num_epochs=4)
# [KS-2] grid values of a used motor entry and a used thruster entry; the coarse grid past GRID_MAX actions.
MOTOR_GRID, THRUSTER_GRID = (-1.0, -0.5, 0.0, 0.5, 1.0), (0.0, 0.5, 1.0)
COARSE_MOTOR_GRID, COARSE_THRUSTER_GRID = (-1.0, 0.0, 1.0), (0.0, 1.0)
GRID_MAX = 243
PPO_BLOCK = 4  # PPO iterations per checkpoint and resume point
BATCH = 128  # envs per call of the baseline program (one compile for every level at the same sizes)
FORMAT = 1


def _check_rate(name: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)) \
            or not math.isfinite(float(value)) or not 0.0 <= float(value) <= 1.0:
        raise ValueError(f"{name} must be a real number in [0, 1], got {value!r}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class ScreenConfig:
    """Settings of a screen ([KS-1]); every field is checked ([N-7])."""

    ppo_steps: int = 200_000
    episodes: int = 64
    delays: tuple = (0, 1, 2, 4)
    seed: int = 0
    const_threshold: float = 0.5
    expert_threshold: float = 0.8
    min_drop: float = 0.2
    ppo: PPOConfig = SCREEN_PPO
    hold: int = 4  # [KS-4] steps the expert's input is held: the study's execution horizon s

    def __post_init__(self):
        check_int("ppo_steps", self.ppo_steps, 1, 1 << 40)
        check_int("episodes", self.episodes, 1, EPISODES_MAX)
        check_int("seed", self.seed, 0, 2**31 - 1)
        if isinstance(self.delays, (str, bytes)) or not isinstance(self.delays, (list, tuple)):
            raise ValueError(f"delays must be a sequence of distinct integers in [0, 64] starting at 0, "
                             f"got {self.delays!r}")
        ds = tuple(check_int("delays entry", d, 0, 64) for d in self.delays)
        if len(ds) < 2 or ds[0] != 0 or list(ds) != sorted(set(ds)):
            raise ValueError(f"delays must be increasing distinct integers in [0, 64], starting at 0, at least two, "
                             f"got {self.delays!r}")
        object.__setattr__(self, "delays", ds)
        _check_rate("const_threshold", self.const_threshold)
        _check_rate("expert_threshold", self.expert_threshold)
        _check_rate("min_drop", self.min_drop)
        if not isinstance(self.ppo, PPOConfig):
            raise ValueError(f"ppo must be a PPOConfig, got {type(self.ppo).__name__}")
        check_int("hold", self.hold, 1, 64)

    @classmethod
    def from_dict(cls, d: dict) -> "ScreenConfig":
        """The configuration of a ``screen.json``; one without ``hold`` was screened with ``hold = 1`` ([KS-6])."""
        if not isinstance(d, dict):
            raise ValueError(f"screen config must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        ppo = d.pop("ppo", None)
        if not isinstance(ppo, dict):
            raise ValueError(f"screen config's ppo must be a JSON object, got {ppo!r}")
        d.setdefault("hold", 1)
        fields = {f.name for f in dataclasses.fields(cls)} - {"ppo"}
        ppo_fields = {f.name for f in dataclasses.fields(PPOConfig)}
        if set(d) - fields or set(ppo) - ppo_fields:
            raise ValueError(f"screen config has unknown keys {sorted(set(d) - fields)}, ppo "
                             f"{sorted(set(ppo) - ppo_fields)}; known: {sorted(fields)}, ppo {sorted(ppo_fields)}")
        return cls(**d, ppo=PPOConfig(**ppo))

    @property
    def ppo_updates(self) -> int:
        """PPO iterations: ``ceil(ppo_steps / (num_envs * num_steps))`` ([KS-3])."""
        return -(-self.ppo_steps // self.ppo.batch_size)

    def to_dict(self) -> dict:
        """JSON form; ``hold = 1`` is left out, as in screens written before the option existed ([KS-6])."""
        d = dataclasses.asdict(self)
        d["delays"] = list(self.delays)
        if self.hold == 1:
            del d["hold"]
        return d


def used_action_entries(level) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """``(motor entries, thruster entries)`` of the action that move something in ``level`` ([KS-2]):
    motor bindings of active joints with a motor that is not automatic, thruster bindings of active
    thrusters (thruster entries counted from ``NUM_MOTOR_BINDINGS``)."""
    j_on = np.asarray(level.joint.active) & np.asarray(level.joint.motor_on) & ~np.asarray(level.motor_auto)
    motors = sorted({int(b) for b in np.asarray(level.motor_bindings)[j_on]})
    t_on = np.asarray(level.thruster.active)
    thrusters = sorted({kenv.NUM_MOTOR_BINDINGS + int(b) for b in np.asarray(level.thruster_bindings)[t_on]})
    return tuple(motors), tuple(thrusters)


def constant_actions(motors: tuple[int, ...], thrusters: tuple[int, ...]) -> np.ndarray:
    """The grid of constant actions over the used entries, zero elsewhere ([KS-2]): ``[K, 6]`` float32.

    Motors take ``MOTOR_GRID``, thrusters ``THRUSTER_GRID``; when that grid has more than
    ``GRID_MAX`` actions the coarse grid (motors -1, 0, 1; thrusters 0, 1) is used instead.
    """
    grids = [MOTOR_GRID] * len(motors) + [THRUSTER_GRID] * len(thrusters)
    if math.prod(len(g) for g in grids) > GRID_MAX:
        grids = [COARSE_MOTOR_GRID] * len(motors) + [COARSE_THRUSTER_GRID] * len(thrusters)
    out = []
    for values in itertools.product(*grids):
        a = np.zeros(kenv.ACTION_DIM, np.float32)
        a[list(motors) + list(thrusters)] = values
        out.append(a)
    return np.stack(out)


def _first_episode(step_fn, task, keys, extra, init_extra):
    """Run each env until its first episode ends (at most ``max_timesteps`` steps); ``(solved, return, length)``."""
    n = keys.shape[0]
    k_reset, k_run = jax.vmap(lambda k: tuple(jax.random.split(k)))(keys)
    obs, state = jax.vmap(task.reset)(k_reset)
    carry0 = (state, k_run, init_extra(obs), jnp.zeros(n, bool), jnp.zeros(n, bool), jnp.zeros(n, jnp.float32),
              jnp.zeros(n, jnp.int32))

    def body(c, _):
        state, keys, ex, ended, solved, ret, length = c
        ks = jax.vmap(lambda k: tuple(jax.random.split(k, 3)))(keys)
        keys, k_act, k_env = ks
        action, ex_pre = step_fn(k_act, ex, extra)
        obs, state, reward, done, info = jax.vmap(task.step)(k_env, state, action)
        live = ~ended
        ret = ret + jnp.where(live, reward, 0.0)
        length = length + live.astype(jnp.int32)
        solved = solved | (live & info["solved"])
        ex = ex_pre(obs, action, done)
        return (state, keys, ex, ended | done, solved, ret, length), None

    c, _ = jax.lax.scan(body, carry0, None, length=int(task.env_params.max_timesteps))
    return {"solved": c[4], "return": c[5], "length": c[6]}


def _baseline_program(task):
    """Jitted ``fn(keys [B], actions [B, 6], random [B]) -> outcomes``: each env holds its constant action,
    or draws uniform random actions ([K-13]) where ``random`` is set ([KS-2])."""

    def step_fn(k_act, ex, extra):
        const, rand = extra
        r = jax.vmap(lambda k: kenv.random_actions(k, (1,))[0])(k_act)
        return jnp.where(rand[:, None], r, const), lambda obs, action, done: ex

    def fn(keys, const, rand):
        return _first_episode(step_fn, task, keys, (const, rand), lambda obs: jnp.zeros((), jnp.int32))

    return jax.jit(fn)


def episode_outcomes(task, keys, actions, random_mask, program=None) -> dict:
    """First-episode ``solved``, ``return``, ``length`` per row ([KS-2]), in calls of ``min(BATCH, rows)``
    envs (the last one padded with copies of its first row, whose results are dropped)."""
    actions, random_mask = np.asarray(actions), np.asarray(random_mask)
    if actions.ndim != 2 or actions.shape[0] < 1 or actions.shape[1] != task.action_dim:
        raise ValueError(f"actions must have shape [n >= 1, {task.action_dim}], got {actions.shape}")
    n = int(actions.shape[0])
    if random_mask.shape != (n,) or random_mask.dtype != bool:
        raise ValueError(f"random_mask must be a bool array of shape ({n},), got {random_mask.dtype} {random_mask.shape}")
    if tuple(getattr(keys, "shape", ())) != (n,):
        raise ValueError(f"keys must be {n} PRNG keys (shape ({n},)), got shape {getattr(keys, 'shape', None)}")
    actions = actions.astype(np.float32)
    program = _baseline_program(task) if program is None else program
    B = min(BATCH, n)
    outs = []
    for lo in range(0, n, B):
        idx = np.arange(lo, min(lo + B, n))
        idx = np.concatenate([idx, np.full(B - idx.size, idx[0])])
        out = jax.device_get(program(keys[idx], jnp.asarray(actions[idx]), jnp.asarray(random_mask[idx])))
        outs.append({k: np.asarray(v)[:min(B, n - lo)] for k, v in out.items()})
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def expert_mode(params, x):
    """The expert's deterministic action ([KS-4]): ``squash(mean)`` of [KP-2]."""
    return kexp.squash(kexp.actor_mean_std(params, x)[0])


def _delay_program(task, max_delay: int, act: Callable = expert_mode, hold: int = 1):
    """Jitted ``fn(params, keys [B], delays [B]) -> outcomes`` of the expert acting on delayed inputs ([KS-4]).

    Each env keeps its last ``max_delay + hold`` expert inputs ([KP-1]), newest first; the action executed
    at step ``t`` is ``act(params, input of step c - d)``, where ``c = t - (t mod hold)`` is the step at
    which the current block of ``hold`` steps began (``hold = 1``: ``c = t``). At a reset every slot holds
    the reset input, so the first ``d`` steps of an episode act on it.
    """
    D = max_delay + hold

    def init_extra(obs):
        hist, prev = kexp.history_reset(obs)
        x = kexp.expert_input(hist, prev)
        return hist, prev, jnp.repeat(x[:, None, :], D, axis=1), jnp.zeros(x.shape[0], jnp.int32)

    def step_fn(k_act, ex, extra):
        params, delays = extra
        hist, prev, buf, t = ex
        x_del = jnp.take_along_axis(buf, (delays + t % hold)[:, None, None], axis=1)[:, 0]
        action = act(params, x_del)

        def after(obs, action, done):
            h, p = kexp.history_step(hist, prev, obs, action, done)
            x = kexp.expert_input(h, p)
            rolled = jnp.concatenate([x[:, None, :], buf[:, :-1]], axis=1)
            return (h, p, jnp.where(done[:, None, None], jnp.repeat(x[:, None, :], D, axis=1), rolled),
                    jnp.where(done, 0, t + 1))

        return action, after

    def fn(params, keys, delays):
        return _first_episode(step_fn, task, keys, (params, delays), init_extra)

    return jax.jit(fn)


def delayed_expert_outcomes(task, params, keys, delays, act: Callable = expert_mode, hold: int = 1) -> dict:
    """Per env, the first episode of ``act`` (default the expert's mode) at its delay, its input held for
    ``hold`` steps ([KS-4]); one call of ``len(keys)`` envs."""
    delays = np.asarray(delays)
    if delays.ndim != 1 or delays.size < 1 or not np.issubdtype(delays.dtype, np.integer) or delays.min() < 0 \
            or delays.max() > 64:
        raise ValueError(f"delays must be a non-empty 1-D integer array with values in [0, 64], got {delays!r}")
    if tuple(getattr(keys, "shape", ())) != delays.shape:
        raise ValueError(f"keys must be one PRNG key per delay (shape {delays.shape}), got "
                         f"{getattr(keys, 'shape', None)}")
    check_int("hold", hold, 1, 64)
    delays = delays.astype(np.int32)
    fn = _delay_program(task, int(delays.max()), act, int(hold))
    return {k: np.asarray(v) for k, v in jax.device_get(fn(params, keys, jnp.asarray(delays))).items()}


def screen_verdict(baselines: dict, delays: dict | None, config: ScreenConfig) -> dict:
    """``{"kept": bool, "reasons": [...]}`` from the measurements ([KS-5]); every failed rule is a reason,
    and a kept level's one reason says what it passed. ``delays`` is ``None`` for a level the constant-action
    rule drops before its expert is trained ([KS-6]); then that rule is the one reason."""
    reasons = []
    best = max(baselines["constant"], key=lambda r: r["solved"])
    if _constant_drops(baselines, config):
        reasons.append(f"a constant action solves it: {best['action']} solves {best['solved']:.2f} "
                       f">= {config.const_threshold}")
    if delays is None:
        if not reasons:
            raise ValueError("delays must be the delay measurements of the expert unless a constant action "
                             "drops the level, got None")
        return {"kept": False, "reasons": reasons}
    rates = {int(r["delay"]): r["solved"] for r in delays["rows"]}
    d0, dmax = config.delays[0], config.delays[-1]
    if rates[d0] < config.expert_threshold:
        reasons.append(f"the expert solves {rates[d0]:.2f} < {config.expert_threshold} at d = {d0}")
    drop = rates[d0] - rates[dmax]
    if drop < config.min_drop:
        reasons.append(f"its solve rate does not fall with delay: {rates[d0]:.2f} at d = {d0}, {rates[dmax]:.2f} "
                       f"at d = {dmax} (drop {drop:.2f} < {config.min_drop})")
    if reasons:
        return {"kept": False, "reasons": reasons}
    return {"kept": True, "reasons": [f"no constant action solves it (best {best['solved']:.2f}), the expert solves "
                                      f"{rates[d0]:.2f} at d = {d0} and {rates[dmax]:.2f} at d = {dmax}"]}


def _constant_drops(baselines: dict, config: ScreenConfig) -> bool:
    return max(r["solved"] for r in baselines["constant"]) >= config.const_threshold


def _stage(path: Path, meta: dict, compute: Callable[[], dict]) -> tuple[dict, bool]:
    """A stage's result: read back when ``path`` holds one for ``meta``, else computed and written ([KS-6])."""
    if path.is_file():
        saved = read_json(path, "screen stage file")
        if saved.get("meta") != meta:
            raise ValueError(f"out holds {path} from another screen configuration ({saved.get('meta')}); "
                             f"use another --out folder")
        return saved, True
    t0 = time.perf_counter()
    res = dict(compute(), meta=meta)
    res["wall_s"] = round(time.perf_counter() - t0, 3)
    write_json(path, res)
    return res, False


def _keys(config: ScreenConfig, level: str, stage: int, n: int):
    base = jax.random.fold_in(jax.random.fold_in(jax.random.key(config.seed), kenv.level_index(level)), stage)
    return jax.random.split(base, n)


def screen_level(level: str, out: str | Path, config: ScreenConfig, *, levels_dir=None,
                 progress: bool = True, log: Callable[[str], None] | None = None) -> dict:
    """Screen one level into ``<out>/<level>/`` ([KS-1]..[KS-6]); returns its ``screen.json`` content."""
    kenv.check_level_name(level, "level")
    if not isinstance(config, ScreenConfig):
        raise ValueError(f"config must be a ScreenConfig, got {type(config).__name__}")
    log = log or (lambda msg: print(msg, file=sys.stderr, flush=True))
    folder = Path(out) / level
    folder.mkdir(parents=True, exist_ok=True)
    meta = {"level": level, "config": config.to_dict(), "format": FORMAT}
    # Each stage is keyed by what it depends on only, so a rerun with more PPO steps or other thresholds
    # keeps the baselines, and other thresholds keep the delay measurements too.
    base_meta = {"level": level, "episodes": config.episodes, "seed": config.seed, "format": FORMAT}
    delay_meta = dict(base_meta, delays=list(config.delays), ppo_steps=config.ppo_steps,
                      ppo=config.ppo.to_dict(), **({} if config.hold == 1 else {"hold": config.hold}))
    task = kenv.make_env(level, levels_dir)
    E = config.episodes

    def baselines():
        motors, thrusters = used_action_entries(task.level)
        consts = constant_actions(motors, thrusters)
        K = consts.shape[0]
        actions = np.concatenate([np.repeat(consts, E, axis=0), np.zeros((E, kenv.ACTION_DIM), np.float32)])
        rand = np.concatenate([np.zeros(K * E, bool), np.ones(E, bool)])
        log(f"{level}: {K} constant actions and random actions, {E} episodes each")
        o = episode_outcomes(task, _keys(config, level, 0, actions.shape[0]), actions, rand)
        rows = [{"action": [round(float(v), 3) for v in consts[k]],
                 "solved": float(o["solved"][k * E:(k + 1) * E].mean()),
                 "return": float(o["return"][k * E:(k + 1) * E].mean())} for k in range(K)]
        return {"motor_entries": list(motors), "thruster_entries": list(thrusters), "constant": rows,
                "random": {"solved": float(o["solved"][K * E:].mean()), "return": float(o["return"][K * E:].mean())},
                "env_steps": int(o["length"].sum())}

    base, cached = _stage(folder / "baselines.json", base_meta, baselines)
    log(f"{level}: constant actions best solve {max(r['solved'] for r in base['constant']):.2f}, random "
        f"{base['random']['solved']:.2f}" + (" (read back)" if cached else f" ({base['wall_s']:.0f} s)"))
    def result(verdict, ppo_steps, ppo_wall, curve, rows, wall, steps):
        return {"level": level, "kept": verdict["kept"], "reasons": verdict["reasons"],
                "constant_best": max(base["constant"], key=lambda r: r["solved"]),
                "constant_count": len(base["constant"]), "random_solved": base["random"]["solved"],
                "ppo_env_steps": ppo_steps, "ppo_wall_s": ppo_wall, "ppo_curve": curve, "expert_by_delay": rows,
                "wall_s": dict(baselines=base["wall_s"], **wall),
                "env_steps": dict(baselines=base["env_steps"], **steps),
                "meta": meta}

    if _constant_drops(base, config):
        # [KS-5]'s first rule already drops the level: no expert can keep it, so none is trained ([KS-6]).
        log(f"{level}: dropped by a constant action; no PPO run and no delay measurement")
        res = result(screen_verdict(base, None, config), 0, 0.0, [], None, {"ppo": 0.0, "delays": 0.0},
                     {"ppo": 0, "delays": 0})
        write_json(folder / "screen.json", res)
        return res
    t0 = time.perf_counter()
    ppo = train_expert(level, folder / "ppo", updates=config.ppo_updates, seed=config.seed, config=config.ppo,
                       log_interval=PPO_BLOCK, levels_dir=levels_dir, progress=progress)
    ppo_wall = float(ppo["last"].get("wall_s", time.perf_counter() - t0))
    log(f"{level}: PPO {ppo['env_steps']} env steps, last training solve {ppo['last'].get('solved', float('nan')):.2f}")

    def delays():
        # The final expert: the checkpoint of the last block ([KP-6] names a block by its first iteration).
        seed_dir = expert_paths(folder / "ppo", config.seed, level)["seed_dir"]
        last = max(int(p.name) for p in seed_dir.iterdir() if p.name.isdigit())
        path = expert_paths(folder / "ppo", config.seed, level, last)["policy"]
        params = kexp.load_expert(path)
        ds = np.repeat(np.asarray(config.delays, np.int32), E)
        keys = jnp.tile(_keys(config, level, 1, E), len(config.delays))  # the same E episodes at every delay
        o = delayed_expert_outcomes(task, params, keys, ds, hold=config.hold)
        rows = [{"delay": d, "solved": float(o["solved"][i * E:(i + 1) * E].mean()),
                 "return": float(o["return"][i * E:(i + 1) * E].mean())} for i, d in enumerate(config.delays)]
        return {"expert": str(path.relative_to(folder)), "rows": rows, "env_steps": int(o["length"].sum())}

    dl, cached = _stage(folder / "delays.json", delay_meta, delays)
    log(f"{level}: expert solve by delay " + ", ".join(f"d={r['delay']} {r['solved']:.2f}" for r in dl["rows"])
        + (" (read back)" if cached else f" ({dl['wall_s']:.0f} s)"))
    verdict = screen_verdict(base, dl, config)
    # An iteration in which no episode ended has no solve rate or return: null in the JSON.
    curve = [{k: (None if isinstance(r[k], float) and not math.isfinite(r[k]) else r[k])
              for k in ("env_steps", "solved", "return")} for r in _read_curve(Path(ppo["curve_csv"]))]
    res = result(verdict, ppo["env_steps"], ppo_wall, curve, dl["rows"], {"ppo": ppo_wall, "delays": dl["wall_s"]},
                 {"ppo": ppo["env_steps"], "delays": dl["env_steps"]})
    write_json(folder / "screen.json", res)
    return res


def _read_curve(path: Path) -> list[dict]:
    import csv

    with open(path, newline="") as f:
        return [{k: float(v) if v not in ("", "nan") else float("nan") for k, v in row.items()}
                for row in csv.DictReader(f)]


def format_screen(results: list[dict], config: ScreenConfig) -> str:
    """Markdown table of a screen with the reasons per level ([KS-7])."""
    ds = config.delays
    head = ("| level | kept | best constant | random | PPO steps | PPO min | "
            + " | ".join(f"expert d={d}" for d in ds) + " |")
    lines = [f"# Kinetix level screen", "",
             f"Rules ([KS-5]): kept when no constant action solves >= {config.const_threshold}, the expert solves "
             f">= {config.expert_threshold} at d = 0, and its solve rate falls by >= {config.min_drop} from d = 0 "
             f"to d = {ds[-1]}, its input held for {config.hold} step{'s' if config.hold > 1 else ''} ([KS-4]); "
             f"a level a constant action solves gets no PPO run (-). {config.episodes} episodes per row; "
             f"PPO {config.ppo_steps} env steps requested "
             f"({config.ppo.num_envs} envs x {config.ppo.num_steps} steps per iteration), seed {config.seed}.", "",
             head, "|" + "---|" * (6 + len(ds))]
    for r in results:
        if r["expert_by_delay"] is None:  # dropped by a constant action before PPO ([KS-6])
            ppo, expert = "- | -", ["-"] * len(ds)
        else:
            by = {int(x["delay"]): x["solved"] for x in r["expert_by_delay"]}
            ppo, expert = f"{r['ppo_env_steps']} | {r['ppo_wall_s'] / 60:.1f}", [f"{by[d]:.2f}" for d in ds]
        lines.append(f"| {r['level']} | {'yes' if r['kept'] else 'no'} | {r['constant_best']['solved']:.2f} | "
                     f"{r['random_solved']:.2f} | {ppo} | " + " | ".join(expert) + " |")
    lines += ["", "## Why", ""]
    for r in results:
        lines.append(f"- **{r['level']}** ({'kept' if r['kept'] else 'dropped'}): " + "; ".join(r["reasons"]) + ".")
    return "\n".join(lines) + "\n"


def screen_levels(levels, out: str | Path, config: ScreenConfig | None = None, *, levels_dir=None,
                  progress: bool = True, log: Callable[[str], None] | None = None) -> list[dict]:
    """Screen ``levels`` one after the other ([KS-1]); a level whose ``screen.json`` matches ``config`` is
    read back, not rerun ([KS-6]). Writes ``<out>/screen.json`` and ``<out>/screen.md`` after each level."""
    config = ScreenConfig() if config is None else config
    if not isinstance(config, ScreenConfig):
        raise ValueError(f"config must be a ScreenConfig, got {type(config).__name__}")
    if isinstance(levels, str) or not isinstance(levels, (list, tuple)) or not levels:
        raise ValueError(f"levels must be a non-empty list of level names, got {levels!r}")
    if len(set(levels)) != len(levels):
        raise ValueError(f"levels must name each level once, got {list(levels)!r}")
    for lv in levels:
        kenv.check_level_name(lv, "levels entry")
    out = check_out_dir("out", out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for lv in levels:
        done = out / lv / "screen.json"
        meta = {"level": lv, "config": config.to_dict(), "format": FORMAT}
        if done.is_file() and read_json(done, "screen file").get("meta") == meta:
            results.append(read_json(done, "screen file"))
        else:
            results.append(screen_level(lv, out, config, levels_dir=levels_dir, progress=progress, log=log))
        write_json(out / "screen.json", {"config": config.to_dict(), "levels": results})
        text = format_screen(results, config)
        write_atomic(out / "screen.md", lambda f: f.write(text))
    return results
