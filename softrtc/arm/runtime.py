"""Real-time runtime for the arm: fixed-rate control thread, inference worker thread (spec chapter R).

The control loop ticks at ``control_hz`` on the wall clock in the calling
thread; policy inference runs in a worker thread. The delay passed to the
sampler is predicted from recent realized delays ([R-3]); the realized delay
of each chunk is measured in ticks ([R-2]) and decides how many ticks run
from the previous chunk ([R-4]). A chunk that misses the buffered actions is
rejected and the arm holds its last command ([R-5], [R-6]); a crashed worker
ends the episode cleanly ([R-7]).

Every read of time and every wait goes through a clock ([R-10]): the wall
clock by default, or :class:`softrtc.arm.clock.SimulatedClock`, on which the
timeline is deterministic. The simulation itself never reads a clock ([A-4]).
"""

from __future__ import annotations

import dataclasses
import math
import queue
import threading
import traceback

import jax
import numpy as np

from softrtc.jax import executor as jexec

from ._checks import check_number
from .clock import WallClock
from .env import ACTION_DIM, ArmConfig, ArmSortEnv
from .geometry import _check_env_config
from .executor import EpisodeRecord

__all__ = ["RuntimeConfig", "run_realtime_episode", "predict_delay", "jitter_summary"]


# Upper bound of an added latency ([R-8]): far beyond any deadline of at a sensible control rate.
MAX_ADDED_LATENCY_S = 10.0


def checked_chunk(chunk, H: int, low, high) -> tuple:
    """``(chunk as float64, None)`` for a chunk the runtime may execute, else ``(None, reason)`` ([R-7]).

    Executable: a real (integer or float) array of shape ``(H, ACTION_DIM)``,
    finite and within the action bounds ``[low, high]`` of [A-8]. The dtype is
    checked before any cast, so a complex, string or boolean chunk is refused,
    not converted (NumPy would drop an imaginary part, parse strings, read
    booleans as 0 and 1). Never raises.
    """
    try:
        raw = np.asarray(chunk)
    except Exception as exc:  # noqa: BLE001 - a ragged or exotic return value is the model's fault
        return None, f"is not an array ({type(exc).__name__})"
    if raw.dtype.kind not in "iuf":
        return None, f"has dtype {raw.dtype} (not a real number type)"
    if raw.shape != (H, ACTION_DIM):
        return None, f"has shape {list(raw.shape)}, not [{H}, {ACTION_DIM}]"
    a = raw.astype(np.float64)
    if not np.all(np.isfinite(a)):
        return None, "has non-finite values"
    out = (a < low) | (a > high)
    if np.any(out):
        j, i = (int(x) for x in np.argwhere(out)[0])
        return None, (f"has token {j} action[{i}] = {float(a[j, i])!r} outside its range "
                      f"[{float(low[i])!r}, {float(high[i])!r}]")
    return a, None


@dataclasses.dataclass(frozen=True)
class RuntimeConfig:
    """Runtime parameters ([R-1]..[R-8]).

    ``added_latency_s``: extra seconds the worker waits after each policy
    call, to play a slower model ([R-8]); ``latency_window``: k of the delay
    prediction rule ([R-3]); ``max_hold_ticks``: consecutive hold ticks after
    which the episode ends with a ``stall`` fault ([R-6]); ``join_timeout_s``:
    how long the runtime waits for the worker at the end ([R-7]).
    """

    added_latency_s: float = 0.055
    latency_window: int = 5
    max_hold_ticks: int = 50
    join_timeout_s: float = 2.0

    def __post_init__(self):
        # NumPy scalars are accepted like Python ones (and stored as Python numbers); booleans are not numbers.
        for name, lo, hi in (("added_latency_s", 0.0, MAX_ADDED_LATENCY_S), ("join_timeout_s", 0.0, 60.0)):
            object.__setattr__(self, name, check_number(name, getattr(self, name), lo, hi))
        for name, lo, hi in (("latency_window", 1, 1000), ("max_hold_ticks", 1, 10**6)):
            v = getattr(self, name)
            if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, np.integer)) or not lo <= v <= hi:
                raise ValueError(f"{name} must be an integer in [{lo}, {hi}], got {v!r}")
            object.__setattr__(self, name, int(v))


def predict_delay(recent_delays, max_delay: int) -> int:
    """[R-3] Predicted delay: max of the recent realized delays, at least 1, at most ``max_delay``.

    A realized delay above ``max_delay`` cannot be conditioned on ([X-1]); it
    makes the prediction ``max_delay`` and the chunk will be late ([R-5]).
    """
    if isinstance(max_delay, bool) or not isinstance(max_delay, (int, np.integer)) or max_delay < 1:
        raise ValueError(f"max_delay must be an integer >= 1, got {max_delay!r}")
    try:
        r = list(recent_delays)
    except TypeError:
        raise ValueError(f"recent_delays must be a non-empty sequence of integers >= 0, got {recent_delays!r}") from None
    if not r or any(isinstance(x, bool) or not isinstance(x, (int, np.integer)) or x < 0 for x in r):
        raise ValueError(f"recent_delays must be a non-empty sequence of integers >= 0, got {r!r}")
    return int(min(max(max(r), 1), max_delay))


def jitter_summary(periods_s) -> dict:
    """p50, p99 and max of control-loop periods in ms, and the share of periods over 1.5 dt is left to callers."""
    try:
        raw = np.asarray(periods_s)
    except (ValueError, TypeError):
        raise ValueError("periods_s must be a non-empty 1-D array of finite periods >= 0 (seconds), "
                         "got a ragged or non-numeric sequence") from None
    if raw.dtype.kind not in "iuf":
        raise ValueError(f"periods_s must be real numbers, got dtype {raw.dtype}")
    p = raw.astype(np.float64)
    if p.ndim != 1 or p.size < 1 or not np.all(np.isfinite(p)) or np.any(p < 0):
        raise ValueError("periods_s must be a non-empty 1-D array of finite periods >= 0 (seconds)")
    return {"p50_ms": float(np.percentile(p, 50) * 1e3), "p99_ms": float(np.percentile(p, 99) * 1e3),
            "max_ms": float(p.max() * 1e3), "mean_ms": float(p.mean() * 1e3), "n": int(p.size)}


class _Worker(threading.Thread):
    """Inference thread: one request at a time; results and exceptions go to ``out`` ([R-1], [R-7])."""

    def __init__(self, policy, out: queue.Queue, clock, H: int, low, high):
        super().__init__(daemon=True, name="softrtc-arm-inference")
        self.policy, self.out, self.clock = policy, out, clock
        self.s, self.H, self.low, self.high = policy.s, H, low, high
        self.requests: queue.Queue = queue.Queue()

    def warm(self, H: int) -> None:
        # Compile the key and prior ops before the clock starts: a first-use compilation
        # inside the loop would read as a late chunk.
        jax.block_until_ready(jax.random.fold_in(jax.random.key(0), 1))
        jax.block_until_ready(jexec.shift_prior(np.zeros((H, ACTION_DIM)), self.s))

    def run(self):
        while True:
            req = self.requests.get()
            if req is None:
                return
            c, obs, prev, d, key, t_req, extra = req
            try:
                # Keys and priors are computed here so the control thread never dispatches JAX work.
                key = jax.random.fold_in(key, c)
                prior = None if prev is None else np.asarray(jexec.shift_prior(prev, self.s), np.float64)
                # checked before any cast: the chunk or why it cannot run.
                chunk, problem = checked_chunk(self.policy.generate(obs, prior, d, key), self.H, self.low,
                                               self.high)
                t_compute = self.clock.now() - t_req
                # Holding the result back plays a slower model; it does not block the control loop.
                if extra > 0:
                    self.clock.sleep(extra)
                self.out.put(("chunk", c, (chunk, problem), self.clock.now(), t_compute))
            except BaseException as exc:  # noqa: BLE001 - any failure of the worker is reported, never raised here
                self.out.put(("error", c, f"{type(exc).__name__}: {exc}", self.clock.now(),
                              traceback.format_exc()))
                return
            finally:
                self.clock.task_done()  # after the answer is posted


# How often the control thread looks for the first chunk while it waits for it ([R-2]).
_FIRST_POLL_S = 0.001
_CLOCK_METHODS = ("now", "sleep_until", "sleep", "task_started", "task_done", "join")


def run_realtime_episode(policy, env_seed: int, key, config: RuntimeConfig = RuntimeConfig(), *,
                         max_steps: int | None = None, env_config: ArmConfig | None = None,
                         added_latency=None, clock=None) -> EpisodeRecord:
    """One arm episode in the real-time runtime ([R-1]..[R-9]).

    ``policy`` has ``H``, ``s`` and ``generate(obs, prior, d, key)``; request
    ``c`` uses ``jax.random.fold_in(key, c)``. ``added_latency`` (optional)
    overrides ``config.added_latency_s`` with a callable ``c -> seconds`` (to
    inject stalls, [R-8]); it is called in the control thread when request
    ``c`` is made, and a result that is not a finite number of seconds in
    ``[0, 10]`` raises ``ValueError`` naming ``added_latency`` from this call
    (after the worker is stopped). An exception raised by ``generate`` is a
    worker crash ([R-7]). The episode ends when the environment is done
    ([A-11]), after ``max_steps`` ticks, or at a fault ([R-6], [R-7]).
    ``clock`` (default :class:`~softrtc.arm.clock.WallClock`) is what the
    runtime reads time from and waits on ([R-10]); on the wall clock outcomes
    depend on timing and are not bitwise reproducible, on a
    :class:`~softrtc.arm.clock.SimulatedClock` they are.
    """
    H = getattr(policy, "H", None)
    s = getattr(policy, "s", None)
    is_int = lambda v: isinstance(v, (int, np.integer)) and not isinstance(v, (bool, np.bool_))  # noqa: E731
    if not (is_int(H) and is_int(s) and 1 <= s < H) or not callable(getattr(policy, "generate", None)):
        raise ValueError("policy must provide integers H, s (1 <= s < H) and generate(obs, prior, d, key)")
    H, s = int(H), int(s)
    if isinstance(env_seed, bool) or not isinstance(env_seed, (int, np.integer)) or env_seed < 0:
        raise ValueError(f"env_seed must be an integer >= 0, got {env_seed!r}")
    if not isinstance(key, jax.Array) or not jax.numpy.issubdtype(key.dtype, jax.dtypes.prng_key):
        raise ValueError("key must be a typed JAX PRNG key (jax.random.key(seed))")
    if key.shape != ():
        raise ValueError(f"key must be a single typed JAX PRNG key of shape (), got shape {tuple(key.shape)}")
    if not isinstance(config, RuntimeConfig):
        raise ValueError(f"config must be a RuntimeConfig, got {type(config).__name__}")
    if added_latency is not None and not callable(added_latency):
        raise ValueError("added_latency must be None or a callable c -> seconds")
    clock = WallClock() if clock is None else clock
    if isinstance(clock, type) or not all(callable(getattr(clock, m, None)) for m in _CLOCK_METHODS):
        raise ValueError(f"clock must provide {', '.join(_CLOCK_METHODS)} (softrtc.arm.clock), "
                         f"got {type(clock).__name__}")
    env = ArmSortEnv(_check_env_config(env_config, "env_config"))
    limit = env.config.max_steps if max_steps is None else max_steps
    if isinstance(limit, bool) or not isinstance(limit, (int, np.integer)) or not 1 <= limit <= env.config.max_steps:
        raise ValueError(f"max_steps must be an integer in [1, {env.config.max_steps}], got {max_steps!r}")
    dt = env.config.dt
    d_max = min(s, H - s)

    results: queue.Queue = queue.Queue()
    worker = _Worker(policy, results, clock, H, env.action_low, env.action_high)

    def extra_latency(c: int) -> float:
        # the caller's per-request latency, checked here: a bad value is the caller's error, not a worker crash.
        if added_latency is None:
            return config.added_latency_s
        return check_number(f"added_latency({c})", added_latency(c), 0.0, MAX_ADDED_LATENCY_S)
    worker.warm(H)
    worker.start()

    # Per-chunk log.
    chunks, req_step, d_pred, d_exec, d_real, lat, accepted = [], [], [], [], [], [], []
    # Per-tick log.
    actions, ci, ti, qs, hold, periods = [], [], [], [], [], []
    events: list = []
    fault = None
    info = {"success": False, "num_completed": 0, "success_step": None}

    t_req_of: dict = {}
    in_flight: set = set()

    def request(c, obs, prev, d, tick):
        extra = extra_latency(c)
        t_req = clock.now()
        t_req_of[c] = t_req
        in_flight.add(c)
        chunks.append(None)
        req_step.append(tick)
        d_pred.append(d)
        d_exec.append(-1)
        d_real.append(-1)
        lat.append(float("nan"))
        accepted.append(False)
        clock.task_started()  # before the hand-over, so a simulated clock never runs ahead of the worker
        worker.requests.put((c, np.array(obs), None if prev is None else np.array(prev), d, key, t_req, extra))

    obs = env.reset(int(env_seed))
    try:
        # [X-2] / [R-2] start: request 0 (d = 0, no prior); the clock starts when it is back.
        request(0, obs, None, 0, 0)
        while True:
            try:
                msg = results.get_nowait()
                break
            except queue.Empty:
                clock.sleep_until(clock.now() + _FIRST_POLL_S)
        in_flight.discard(0)
        if msg[0] == "error":
            fault = f"worker_error: {msg[2]}"
            events.append((0, "worker_error", msg[4]))
            raise _End
        _, _, (chunk0, problem), t_done, _ = msg
        lat[0] = t_done - t_req_of[0]
        if problem is not None:
            # a chunk the runtime cannot execute is a model fault: recorded, never raised.
            fault = f"worker_error: chunk 0 {problem}"
            events.append((0, "bad_chunk", 0))
            raise _End
        chunks[0] = chunk0
        d_real[0] = d_exec[0] = 0
        accepted[0] = True
        recent = [int(math.ceil(lat[0] / dt))]  # the first latency, in ticks
        cur, cur_base = 0, 0          # the executing chunk and the tick of its request
        pending = None                # (c, request tick, predicted d) in flight
        ready = None                  # (c, request tick, exec delay) accepted, waiting for its switch tick
        restart = False               # a rejected chunk: the next request starts afresh
        last_cmd = None
        holds_in_row = 0
        next_c = 1
        T0 = clock.now()
        last_tick_time = None
        k = 0
        while not env.done and k < limit:
            clock.sleep_until(T0 + k * dt)
            now = clock.now()
            if last_tick_time is not None:
                periods.append(now - last_tick_time)
            last_tick_time = now

            # Collect a finished request ([R-2]).
            while True:
                try:
                    msg = results.get_nowait()
                except queue.Empty:
                    break
                if msg[0] == "error":
                    fault = f"worker_error: {msg[2]}"
                    events.append((k, "worker_error", msg[4]))
                    break
                _, c, (chunk, problem), t_done, _ = msg
                in_flight.discard(c)
                lat[c] = t_done - t_req_of[c]
                good = problem is None
                if good:
                    chunks[c] = chunk
                if pending is None or pending[0] != c:
                    continue  # already declared late and rejected at its deadline
                _, r, dp = pending
                pending = None
                dr = k - r
                d_real[c] = dr
                recent = (recent + [dr])[-config.latency_window:]
                if not good:
                    fault = f"worker_error: chunk {c} {problem}"
                    events.append((k, "bad_chunk", c))
                    break
                # execute from the previous chunk for max(predicted, realized) ticks.
                de = max(dp, dr)
                d_exec[c] = de
                accepted[c] = True
                ready = (c, r, de)
            if fault is not None:
                raise _End

            # deadline: a chunk not back by tick r + d_max is late (prev[s + d_max] may not exist).
            if pending is not None and k - pending[1] >= d_max:
                c_late = pending[0]
                events.append((k, "late_reject", c_late))
                # [R-9] -2 marks "rejected late" in both delays (nothing of it ran); its latency is logged on arrival.
                d_real[c_late] = d_exec[c_late] = -2
                pending = None
                cur = None
                restart = True
            # Switch to the ready chunk at its switch tick ([R-4], [X-4]).
            if ready is not None and k >= ready[1] + ready[2]:
                cur, cur_base = ready[0], ready[1]
                ready = None
                events.append((k, "switch", cur))

            # Issue the next request ([X-1], [X-3], [R-3]).
            if pending is None and ready is None and not (cur is None and not restart):
                if restart and not in_flight:
                    # Only once the worker is idle: the restart must see a fresh observation.
                    c = next_c
                    next_c += 1
                    request(c, obs, None, 0, k)
                    pending = (c, k, 0)
                    restart = False
                    events.append((k, "restart_request", c))
                elif not restart and k == cur_base + s:
                    dp = predict_delay(recent, d_max)
                    c = next_c
                    next_c += 1
                    request(c, obs, chunks[cur], dp, k)  # the worker shifts it into the prior ([X-3])
                    pending = (c, k, dp)

            # [R-4] / [R-5] choose the command: an aligned token, else hold.
            j = None if cur is None else k - cur_base
            if j is not None and j < H:
                a = chunks[cur][j]
                ci.append(cur)
                ti.append(j)
                hold.append(False)
                holds_in_row = 0
            else:
                if last_cmd is None:
                    fault = "hold_before_first_command"
                    raise _End
                a = last_cmd
                ci.append(-1)
                ti.append(-1)
                hold.append(True)
                holds_in_row += 1
                if holds_in_row == 1:
                    events.append((k, "hold_start", None))
            qs.append(obs[0:3].copy())
            obs, info = env.step(a)
            actions.append(np.asarray(a, np.float64))
            last_cmd = actions[-1]
            k += 1
            if holds_in_row >= config.max_hold_ticks:
                fault = f"stall: {holds_in_row} consecutive hold ticks"
                events.append((k, "stall", None))
                break
    except _End:
        pass
    finally:
        worker.requests.put(None)
        if not clock.join(worker, config.join_timeout_s):
            events.append((len(actions), "worker_not_joined", None))

    n = len(actions)
    keep = [i for i, ch in enumerate(chunks) if ch is not None]
    full = np.full((len(chunks), H, ACTION_DIM), np.nan)
    for i in keep:
        full[i] = chunks[i]
    return EpisodeRecord(
        method=str(getattr(policy, "method", "unknown")), env_seed=int(env_seed),
        actions=np.asarray(actions, np.float64).reshape(n, ACTION_DIM), chunk_index=np.asarray(ci, int),
        token_index=np.asarray(ti, int), joint_pos=np.asarray(qs).reshape(n, 3), chunks=full,
        request_step=np.asarray(req_step, int), delays=np.asarray(d_pred, int), exec_delays=np.asarray(d_exec, int),
        realized_delays=np.asarray(d_real, int), latencies_s=np.asarray(lat, np.float64),
        success=bool(info["success"]), num_completed=int(info["num_completed"]),
        success_step=info["success_step"], steps=n, dt=dt, step_limit=int(limit), hold=np.asarray(hold, bool),
        periods_s=np.asarray(periods, np.float64), accepted=np.asarray(accepted, bool), fault=fault, events=events)


class _End(Exception):
    """Internal: leave the control loop at a fault."""
