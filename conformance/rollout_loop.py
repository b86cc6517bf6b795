"""Closed-loop rollout episodes (arm or Kinetix) and the per-request check against the reference ([CR-5]..[CR-7]).

An episode is a deterministic function of the settings, the episode index and
the implementation's answers: request ``c`` carries the observation of tick
``c s``, the implementation's previous chunk, noise and a delay drawn from
``numpy.random.default_rng((seed, episode, c))`` ([CR-5]), and the ticks it
executes are stepped in the simulator. The reference's answer on the same
inputs is the expected value, so a float32 implementation is compared request
by request on its own trajectory, without divergence compounding ([CR-5]).
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from softrtc.reference import executor as rexec
from softrtc.reference import metrics as rmetrics
from softrtc.reference._validate import check_choice, check_int
from softrtc.reference.guidance import MAX_GUIDANCE
from softrtc.reference.weights import SoftWindow

from .results import UNSUPPORTED_CASE, CaseResult
from .rollout_diagnose import TOL, diagnose_chunk, diagnose_executed, within
from .rollout_impls import METHODS, ReferenceRollout
from .compare import CaseFailure, compare

# Requirements each output of a request is checked for ([CR-2]).
_SAMPLER_REQS = {"naive": ["S-2"], "train_hard": ["S-3", "W-8"], "train_soft": ["S-3", "W-7"],
                 "inference_hard": ["G-1", "G-3"], "inference_soft": ["G-1", "G-3"]}
EXEC_REQS = ["CR-2", "X-4", "R-4"]
# smoothness on the commanded joint targets only.
JOINT_DIMS = slice(0, 3)
# The arm's paired outcomes ([CR-7]); a world names its own in ``metric_names`` (Kinetix: [CR-13]).
METRICS = ("success", "completed", "D1", "D2", "D3", "boundary")


def chunk_requirements(method: str, first: bool) -> list:
    return ["CR-2", "X-2", "S-2"] if first else ["CR-2", "X-3", "S-6", *_SAMPLER_REQS[method]]


@dataclasses.dataclass(frozen=True)
class Settings:
    """What a rollout run does ([CR-5]): episodes per method, the delays drawn for requests ``c >= 1``, the
    tick limit, the seed of environments, noise and delays."""

    methods: tuple = ("naive", "train_hard", "train_soft", "inference_hard")
    episodes: int = 20
    delays: tuple = (0, 1, 2, 3, 4, 5)
    max_steps: int = 400
    seed: int = 0

    def __post_init__(self):
        if isinstance(self.methods, str) or not self.methods:
            raise ValueError(f"methods must be a non-empty sequence of {METHODS}, got {self.methods!r}")
        for m in self.methods:
            check_choice("methods entry", m, METHODS)
        check_int("episodes", self.episodes, 1, 10_000)
        if isinstance(self.delays, str) or not self.delays:
            raise ValueError(f"delays must be a non-empty sequence of integers in [0, 5], got {self.delays!r}")
        for d in self.delays:
            check_int("delays entry", d, 0, 5)
        check_int("max_steps", self.max_steps, 1, 1000)
        check_int("seed", self.seed, 0, 2**31 - 1)

    def to_dict(self) -> dict:
        return {"methods": list(self.methods), "episodes": self.episodes, "delays": list(self.delays),
                "max_steps": self.max_steps, "seed": self.seed}


def env_seed(settings: Settings, episode: int) -> int:
    """The simulator seed of an episode: the same for every method and implementation (pairing, [CR-7])."""
    return 1_000_000 * settings.seed + episode


def request_inputs(settings: Settings, episode: int, c: int, H: int, A: int, s: int) -> tuple:
    """``(noise [H, A], d, arrival)`` of request ``c`` ([CR-5]); request 0 has ``d = arrival = 0`` ([X-2]).

    ``d`` is drawn from ``settings.delays`` (capped at ``min(s, H - s)``, [X-1]); the chunk arrives at tick
    ``d - 1``, ``d`` or ``d + 1`` after the request with probabilities 1/4, 1/2, 1/4 (kept in range), so
    early and late chunks both occur ([R-4])."""
    rng = np.random.default_rng((settings.seed, episode, c))
    noise = rng.standard_normal((H, A))
    if c == 0:
        return noise, 0, 0
    dmax = min(s, H - s)
    d = min(int(settings.delays[int(rng.integers(len(settings.delays)))]), dmax)
    u = float(rng.random())
    arrival = d - 1 if u < 0.25 and d > 0 else d + 1 if u >= 0.75 and d < dmax else d
    return noise, d, arrival


def window_for(method: str):
    """The window a request carries: the default of [W-7] for train_soft, none for the others ([S-8])."""
    return SoftWindow().to_dict() if method == "train_soft" else None


@dataclasses.dataclass
class Episode:
    """One episode's outcome: per-episode metrics, the requests made, the first divergence ([CR-6])."""

    method: str
    episode: int
    env_seed: int
    requests: int = 0
    steps: int = 0
    metrics: dict = dataclasses.field(default_factory=dict)
    first_divergence: dict | None = None
    unsupported: str | None = None
    error: str | None = None

    def to_dict(self) -> dict:
        out = dataclasses.asdict(self)
        out["metrics"] = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                          for k, v in self.metrics.items()}
        return out


def episode_metrics(world, actions: list, chunk_index: list) -> dict:
    """Success, completed parts, D1..D3 and the boundary jump on the joint commands ([A-24], [M-1], [M-3])."""
    a = np.asarray(actions, np.float64).reshape(-1, 4)[:, JOINT_DIMS]
    ci = np.asarray(chunk_index, int)
    out = {"success": float(bool(world.info.get("success"))), "completed": float(world.info.get("num_completed", 0))}
    for k in (1, 2, 3):
        out[f"D{k}"] = rmetrics.difference_norm(a, k) if a.shape[0] > k else float("nan")
    switch = a.shape[0] > 1 and np.any(ci[1:] != ci[:-1])
    out["boundary"] = rmetrics.boundary_jump(a, ci) if switch else float("nan")
    return out


class Checker:
    """Compares each answer with the reference's on the same inputs; collects the cases ([CR-5], [CR-9])."""

    def __init__(self, field, label: str):
        self.field, self.label = field, label
        self.reference = ReferenceRollout()
        self.cases: list = []

    def check(self, ep: Episode, c: int, tick, args: dict, got: dict) -> tuple:
        """Append the chunk and executed cases of request ``c``; returns (executed passed, worst, message)."""
        first = args["prev"] is None
        want = self.reference.rollout_chunk(self.field, **args)
        base = f"CR.{self.label}.{ep.method}.ep{ep.episode:03d}.r{c:03d}"
        results = []
        chunk_reqs = None
        for out, reqs in (("chunk", chunk_requirements(ep.method, first)), ("executed", EXEC_REQS)):
            t0 = time.perf_counter()
            try:
                worst, msg, status = compare(out, got[out], want[out], TOL), "", "pass"
            except CaseFailure as exc:
                worst, msg, status = exc.ratio, str(exc), "fail"
                own = None if out == "chunk" else self.reference_execution(args, got["chunk"])
                if own is not None and within(got[out], own) and chunk_reqs is not None:
                    # [CR-9] executed as says, from a wrong chunk: the chunk's requirement is the cause.
                    reqs = chunk_reqs
                    msg += "; the implementation executed its own chunk as [X-4] says: the chunk is what differs"
                else:
                    diag = diagnose_chunk(self.field, args, got[out]) if out == "chunk" \
                        else diagnose_executed(args, got["chunk"], got[out])
                    if diag is not None:  # [CR-9] the requirement the answer breaks
                        reqs = ["CR-2", diag[0]]
                        msg += f"; diagnosis [{diag[0]}]: matches the reference with {diag[1]}"
                if out == "chunk":
                    chunk_reqs = reqs
            where = "" if tick is None else f"tick {tick}, "
            msg = f"{where}d = {args['d']}, arrival {args['arrival']}: {msg}" if msg else ""
            self.cases.append(CaseResult(f"{base}.{out}", f"rollout_{ep.method}", "rollout_chunk", reqs, status,
                                         worst, msg, time.perf_counter() - t0))
            results.append((status, worst, msg))
        return results[1]

    @staticmethod
    def reference_execution(args: dict, chunk):
        """What [X-2], [X-4] and [R-4] execute from the implementation's own chunk."""
        chunk = np.asarray(chunk, np.float64)
        if args["prev"] is None:
            return chunk[:args["s"]]
        e = max(args["d"], args["arrival"])
        return rexec.segment(np.asarray(args["prev"], np.float64), chunk, args["s"], e)

    def fail_request(self, ep: Episode, c: int, message: str, status: str = "fail") -> None:
        base = f"CR.{self.label}.{ep.method}.ep{ep.episode:03d}.r{c:03d}"
        first = c == 0
        for out, reqs in (("chunk", chunk_requirements(ep.method, first)), ("executed", EXEC_REQS)):
            self.cases.append(CaseResult(f"{base}.{out}", f"rollout_{ep.method}", "rollout_chunk", reqs, status,
                                         math.inf if status == "fail" else 0.0, message))


def _answer_arrays(reply: dict, H: int, A: int, s: int) -> tuple:
    """The reply's chunk [H, A] and executed [s, A] as finite float64 arrays, else ValueError naming the fault."""
    out = []
    for key, shape in (("chunk", (H, A)), ("executed", (s, A))):
        try:
            a = np.asarray(reply[key], np.float64)
        except (KeyError, TypeError, ValueError):
            raise ValueError(f"the reply has no numeric array '{key}'") from None
        if a.shape != shape:
            raise ValueError(f"'{key}' has shape {list(a.shape)}, expected {list(shape)}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"'{key}' holds non-finite values")
        out.append(a)
    return tuple(out)


def run_episode(answer, field, world, settings: Settings, method: str, episode: int, checker=None) -> Episode:
    """One closed-loop episode ([CR-5]). ``answer(c, args)`` returns the implementation's reply dict
    ``{"chunk", "executed"}`` or raises (NotImplementedError: unsupported); ``checker`` (optional) checks
    every request against the reference and records the first divergence of the executed actions ([CR-6])."""
    ep = Episode(method, episode, env_seed(settings, episode))
    H, s, A, T = field.H, field.s, field.action_dim, field.T
    obs = world.reset(ep.env_seed)
    prev, c = None, 0
    actions, chunk_index = [], []
    while not world.done:
        noise, d, arrival = request_inputs(settings, episode, c, H, A, s)
        args = {"obs": obs, "prev": prev, "noise": noise, "method": method, "s": s, "d": d, "arrival": arrival,
                "T": T, "window": window_for(method), "max_guidance": MAX_GUIDANCE}
        try:
            chunk, executed = _answer_arrays(answer(c, args), H, A, s)
        except NotImplementedError as exc:
            ep.unsupported = str(exc) or "NotImplementedError"
            if checker is not None:
                checker.fail_request(ep, c, f"{UNSUPPORTED_CASE}: {ep.unsupported}", "unsupported")
            break
        except Exception as exc:  # noqa: BLE001 - the implementation's failure ends its episode, reported
            ep.error = f"request {c}: {type(exc).__name__}: {str(exc)[:300]}"
            if checker is not None:
                checker.fail_request(ep, c, ep.error)
            break
        if checker is not None:
            status, worst, msg = checker.check(ep, c, world.t, args, {"chunk": chunk, "executed": executed})
            if status == "fail" and ep.first_divergence is None:
                ep.first_divergence = {"request": c, "tick": world.t, "ratio": worst, "message": msg}
        e = 0 if prev is None else max(d, arrival)
        for j, a in enumerate(executed):
            if world.done:
                break
            obs = world.step(a)
            actions.append(world.physical(a))
            chunk_index.append(c - 1 if j < e else c)
        prev, c = chunk, c + 1
    ep.requests, ep.steps = c, len(actions)
    ep.metrics = world.metrics(actions, chunk_index)
    return ep
