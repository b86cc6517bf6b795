"""Simulated-delay executor on the arm and the arm study's episode metrics (spec [A-22]..[A-24], chapter X).

The delay ``d`` is given in control ticks and no wall clock is read, so a
rollout is a deterministic function of (policy, env seed, delays, key):
request ``c`` is made at step ``c s`` with that step's observation and the
prior ``shift_prior(previous chunk, s)`` ([X-3]); the ``s`` steps that follow
execute ``previous[s .. s + d_c - 1]`` then ``new[d_c .. s - 1]`` ([X-4]).
The prior is shifted by the JAX executor (``softrtc.jax.executor``); chunks
come from the JAX samplers through :class:`softrtc.arm.policies.ArmPolicy`
([S-6]). The recorded (chunks, delays) reproduce the executed actions through
either ``execute_chunks`` (JAX or reference) — a conformance test checks it.
"""

from __future__ import annotations

import dataclasses

import jax
import numpy as np

from softrtc.jax import executor as jexec
from softrtc.reference import executor as rexec
from softrtc.reference import metrics as rmetrics
from softrtc.reference._validate import check_int

from .env import ACTION_DIM, ArmConfig, ArmSortEnv, NUM_OBJECTS
from .geometry import _check_env_config

# One dispatch per request instead of one per primitive (same keys as jax.random.fold_in).
_fold_in = jax.jit(jax.random.fold_in)


def _shift_prior(prev: np.ndarray, s: int) -> np.ndarray:
    """[X-3] on the host (the reference's shift), rounded through float32 like the JAX twin
    ``softrtc.jax.executor.shift_prior`` (the policies' inputs are float32)."""
    return rexec.shift_prior(prev, s).astype(np.float32).astype(np.float64)

__all__ = ["EpisodeRecord", "run_simulated_episode", "episode_metrics", "JOINT_DIMS"]

# smoothness metrics use the commanded joint targets only.
JOINT_DIMS = slice(0, 3)


@dataclasses.dataclass
class EpisodeRecord:
    """Everything one arm episode produced, for either executor ([A-23], [R-9]).

    Per control tick ``n``: ``actions[n]`` (the command sent), ``chunk_index[n]``
    and ``token_index[n]`` (its source; ``-1`` for a hold tick of [R-5]),
    ``joint_pos[n]`` (the observed joint positions before the command).
    Per chunk ``c``: ``chunks[c]``, ``request_step[c]``, ``delays[c]`` (the ``d``
    passed to the sampler), ``exec_delays[c]`` (ticks executed from the previous
    chunk), ``realized_delays[c]``, ``latencies_s[c]`` (runtime only; the
    simulated executor reports NaN latency). ``step_limit`` is the number of
    ticks the trial was run for at most (``max_steps``), whatever ended it
    ([A-24]). Runtime-only per-tick fields are ``periods_s`` and ``hold``.
    """

    method: str
    env_seed: int
    actions: np.ndarray
    chunk_index: np.ndarray
    token_index: np.ndarray
    joint_pos: np.ndarray
    chunks: np.ndarray
    request_step: np.ndarray
    delays: np.ndarray
    exec_delays: np.ndarray
    realized_delays: np.ndarray
    latencies_s: np.ndarray
    success: bool
    num_completed: int
    success_step: int | None
    steps: int
    dt: float
    step_limit: int
    hold: np.ndarray | None = None
    periods_s: np.ndarray | None = None
    accepted: np.ndarray | None = None
    fault: str | None = None
    events: list = dataclasses.field(default_factory=list)


def _delay_fn(delays, max_delay: int):
    """A callable c -> d_c for requests c >= 1 from an int, a sequence or a callable ([X-1], [X-5])."""
    if callable(delays):
        return lambda c: check_int(f"delays({c})", delays(c), 0, max_delay)
    if isinstance(delays, (int, np.integer)) and not isinstance(delays, (bool, np.bool_)):
        d = check_int("delays", delays, 0, max_delay)
        return lambda c: d
    try:
        seq = [check_int(f"delays[{i}]", x, 0, max_delay) for i, x in enumerate(delays)]
    except TypeError:
        raise ValueError(f"delays must be an int, a sequence of ints or a callable, got {delays!r}") from None
    if not seq:
        raise ValueError("delays must not be empty")
    if seq[0] != 0:
        raise ValueError(f"delays[0] must be an integer in [0, 0] (first chunk, [X-2]), got {seq[0]}")
    # Past the end of the sequence the last delay is kept.
    return lambda c: seq[min(c, len(seq) - 1)]


def run_simulated_episode(policy, env_seed: int, delays, key, *, max_steps: int | None = None,
                          env_config: ArmConfig | None = None) -> EpisodeRecord:
    """One closed-loop arm episode under simulated delay ([X-1]..[X-6], [A-22]).

    ``policy`` has ``H``, ``s``, ``method`` and ``generate(obs, prior, d, key)``
    (an :class:`~softrtc.arm.policies.ArmPolicy`). ``delays`` is a constant
    ``d`` for every request ``c >= 1``, a sequence ``d_0 = 0, d_1, ...`` (the
    last entry repeats) or a callable ``c -> d_c``; each must satisfy [X-1]
    ``0 <= d <= min(s, H - s)``. Request ``c`` uses the key
    ``jax.random.fold_in(key, c)`` ([N-9]). The episode ends when the
    environment is done ([A-11]) or after ``max_steps`` steps; metrics are on
    the truncated sequence ([X-6]).
    """
    H, s = check_int("policy.H", getattr(policy, "H", None), 1), check_int("policy.s", getattr(policy, "s", None), 1)
    if s > H or not callable(getattr(policy, "generate", None)):
        raise ValueError("policy must provide H, s (1 <= s <= H) and generate(obs, prior, d, key)")
    env_seed = check_int("env_seed", env_seed, 0)
    if not isinstance(key, jax.Array) or not jax.numpy.issubdtype(key.dtype, jax.dtypes.prng_key):
        raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed))")
    if key.shape != ():
        raise ValueError(f"key must be a single typed JAX PRNG key of shape (), got shape {tuple(key.shape)}")
    env = ArmSortEnv(_check_env_config(env_config, "env_config"))
    limit = env.config.max_steps if max_steps is None else check_int("max_steps", max_steps, 1, env.config.max_steps)
    dfn = _delay_fn(delays, min(s, H - s))

    obs = env.reset(env_seed)
    actions, ci, ti, qs = [], [], [], []
    chunks, req, used = [], [], []
    info = {"success": False, "num_completed": 0, "success_step": None}
    prev = None
    c = 0
    while not env.done and env.t < limit:
        d = 0 if c == 0 else dfn(c)
        req.append(env.t)
        sub = _fold_in(key, c)
        if prev is None:
            new = np.asarray(policy.generate(obs, None, 0, sub), np.float64)
        else:
            prior = _shift_prior(prev, s)
            new = np.asarray(policy.generate(obs, prior, d, sub), np.float64)
        # prev[s .. s + d - 1], then new[d .. s - 1] (d = 0 for the first chunk, [X-2]).
        from_prev, token = jexec.segment_sources(H, s, d)
        src = [(c - 1 if p else c, int(t)) for p, t in zip(from_prev, token)]
        if new.shape != (H, ACTION_DIM):
            raise ValueError(f"policy.generate must return a chunk of shape [{H}, {ACTION_DIM}], "
                             f"got {list(new.shape)}")
        chunks.append(new)
        used.append(d)
        for cc, tt in src:
            if env.done or env.t >= limit:
                break
            qs.append(obs[0:3].copy())
            a = (prev if cc == c - 1 else new)[tt]
            obs, info = env.step(a)
            actions.append(np.asarray(a, np.float64))
            ci.append(cc)
            ti.append(tt)
        prev = new
        c += 1
    n = len(actions)
    return EpisodeRecord(
        method=str(getattr(policy, "method", "unknown")), env_seed=env_seed,
        actions=np.asarray(actions).reshape(n, 4), chunk_index=np.asarray(ci, int), token_index=np.asarray(ti, int),
        joint_pos=np.asarray(qs).reshape(n, 3), chunks=np.asarray(chunks), request_step=np.asarray(req, int),
        delays=np.asarray(used, int), exec_delays=np.asarray(used, int), realized_delays=np.asarray(used, int),
        latencies_s=np.full(len(chunks), np.nan), success=bool(info["success"]),
        num_completed=int(info["num_completed"]), success_step=info["success_step"], steps=n,
        dt=env.config.dt, step_limit=int(limit), hold=np.zeros(n, bool))


def episode_metrics(record: EpisodeRecord) -> dict:
    """Per-trial values of the arm study table ([A-24], [M-1], [M-3]).

    ``success``, ``completion`` (completed parts / 4), ``completed``,
    ``duration_s`` (the episode time actually run, ``steps * dt``),
    ``throughput`` (completed parts per minute of trial time: the success time
    for a solved episode, else the full trial of ``step_limit`` ticks, so a
    trial cut short by a stall, a crash or a fault never scores higher than
    running on would have), ``D1``..``D3`` and ``boundary`` on the commanded
    joint targets, ``latency_ms`` (mean policy-call latency, NaN if not
    measured), ``hold_ticks``.
    """
    if not isinstance(record, EpisodeRecord):
        raise ValueError(f"record must be an EpisodeRecord, got {type(record).__name__}")
    steps = check_int("record.steps", record.steps, 0)
    check_int("record.step_limit", record.step_limit, max(steps, 1))
    check_int("record.num_completed", record.num_completed, 0, NUM_OBJECTS)
    dt = record.dt
    if isinstance(dt, (bool, np.bool_)) or not isinstance(dt, (int, float, np.integer, np.floating)) \
            or not np.isfinite(float(dt) if abs(dt) < 1e308 else np.inf) or dt <= 0:
        raise ValueError(f"record.dt must be a finite number > 0 (seconds), got {dt!r}")
    if not isinstance(record.success, (bool, np.bool_)):
        raise ValueError(f"record.success must be a boolean, got {record.success!r}")
    if record.success:
        check_int("record.success_step (required when record.success)", record.success_step, 1, record.step_limit)
    acts = record.actions
    if not isinstance(acts, np.ndarray) or acts.dtype.kind not in "iuf" or acts.ndim != 2 \
            or acts.shape[1] != ACTION_DIM or acts.shape[0] != steps:
        raise ValueError(f"record.actions must be a real array of shape (record.steps, {ACTION_DIM}) = "
                         f"({steps}, {ACTION_DIM}), got {getattr(acts, 'shape', type(acts).__name__)}")
    if not isinstance(record.chunk_index, np.ndarray) or record.chunk_index.shape != (steps,):
        raise ValueError(f"record.chunk_index must be an integer array of shape ({steps},)")
    if not isinstance(record.latencies_s, np.ndarray) or record.latencies_s.dtype.kind not in "iuf":
        raise ValueError("record.latencies_s must be a real array")
    a = record.actions[:, JOINT_DIMS]
    out = {"success": bool(record.success), "completed": int(record.num_completed),
           "completion": record.num_completed / NUM_OBJECTS}
    out["duration_s"] = record.steps * record.dt
    trial_steps = record.success_step if record.success else record.step_limit
    out["throughput"] = record.num_completed / (trial_steps * record.dt / 60.0)
    for k in (1, 2, 3):
        out[f"D{k}"] = rmetrics.difference_norm(a, k) if a.shape[0] > k else float("nan")
    has_switch = a.shape[0] > 1 and np.any(record.chunk_index[1:] != record.chunk_index[:-1])
    out["boundary"] = rmetrics.boundary_jump(a, record.chunk_index) if has_switch else float("nan")
    lat = record.latencies_s[np.isfinite(record.latencies_s)]
    out["latency_ms"] = float(np.mean(lat) * 1e3) if lat.size else float("nan")
    out["hold_ticks"] = int(np.sum(record.hold)) if record.hold is not None else 0
    out["fault"] = record.fault
    return out
