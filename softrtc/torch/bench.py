"""``softrtc bench torch``: the cost of Soft RTC in PyTorch, measured side by side on the CPU ([PT-8]).

Rows, each timed in the same run, round-robin (one call of every row per
round) with the median over the rounds:

* chunk generation at each batch size: the naive sampler and the training-time
  Hard and Soft RTC samplers with precomputed conditioning ([PT-6]; the naive
  row precomputes its shared-time conditioning too), the delay rotating over
  ``0 .. min(s, H - s)``; as context, the straightforward naive and soft
  samplers (time conditioning per call) and the guided soft baseline;
* training steps at one batch size: a plain flow-matching step (one flow time
  per example, the model called with ``t [B]``, mean squared velocity error),
  and Train Hard / Train Soft steps (:class:`~softrtc.torch.training.RTCObjective`,
  per-token times ``[B, H]``, masked loss); each step draws from its
  generator, runs forward and backward, clips the gradient and takes an AdamW
  step.

Targets ([PT-8]): training-time samplers at most 1.05x naive at batch 1 and
32; the soft training step at most 1.03x the hard one and at most 1.15x the
plain flow-matching step; fast and straightforward chunks within 1e-4.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import os
import statistics
import time
from typing import Callable

import torch

from softrtc._files import read_json as _read_json, write_json as _write_json
from softrtc._machine import cpu_model  # one copy for JAX and torch ([PT-8])

from . import _validate as v
from .guidance import guided_sample
from .methods import method_weights
from .policy import ARCHITECTURES, FlowPolicy, PolicyConfig
from .sampler import (conditioning_table, naive_sample, naive_sample_conditioned, rtc_sample, rtc_sample_conditioned,
                      step_conditioning)
from .training import RTCObjective
from .weights import weight_table

__all__ = ["ARCHS", "BenchConfig", "TARGETS", "run_benchmark", "format_table", "write_json", "read_json",
           "check_targets", "cpu_model"]

# The JAX runtime benchmark's sizes (obs 679, action 6, H 8, s 4) with this package's policy, and a tiny one;
# time at the token input unless BenchConfig.architecture asks for the chapter-P network ([PT-8]).
ARCHS = {
    "benchmark": dict(obs_dim=679, action_dim=6, config=PolicyConfig(horizon=8, width=256, channel_hidden=512,
                                                                      token_hidden=64, num_layers=4, time_dim=64,
                                                                      architecture="token_input")),
    "tiny": dict(obs_dim=7, action_dim=3, config=PolicyConfig(horizon=8, width=16, channel_hidden=32,
                                                              token_hidden=8, num_layers=1, time_dim=8,
                                                              architecture="token_input")),
}
CHUNK_ROWS = ("naive", "train_hard", "train_soft", "naive_straightforward", "train_soft_straightforward",
              "inference_soft")
CHUNK_LABELS = {"naive": "naive (base policy)", "train_hard": "train hard RTC", "train_soft": "train soft RTC",
                "naive_straightforward": "naive, straightforward", "inference_soft": "inference soft RTC (guided)",
                "train_soft_straightforward": "train soft RTC, straightforward"}
TRAIN_ROWS = ("plain", "hard", "soft")
# thread: CPU time of the calling thread (torch on one thread does all its work there), which a busy shared
# machine does not inflate by the time the process waits for a core; wall: elapsed time.
CLOCKS = {"thread": time.thread_time, "wall": time.perf_counter}
# (name, value key, bound) of each target ([PT-8]).
TARGETS = (
    ("train-time samplers / naive, batch 1", "samplers_b1", 1.05),
    ("train-time samplers / naive, batch 32", "samplers_b32", 1.05),
    ("soft / hard training step", "soft_over_hard", 1.03),
    ("soft / plain flow-matching step", "soft_over_plain", 1.15),
    ("fast and straightforward chunks agree", "agreement", 1e-4),
)


@dataclasses.dataclass(frozen=True)
class BenchConfig:
    """Options of ``softrtc bench torch``, validated on construction ([N-7])."""

    calls: int = 200
    warmup: int = 5
    batch_sizes: tuple = (1, 32)
    train_batch: int = 32
    train_calls: int = 50
    num_steps: int = 5
    execute_horizon: int = 4
    seed: int = 0
    arch: str = "benchmark"
    architecture: str = "token_input"
    threads: int = 1
    clock: str = "thread"

    def __post_init__(self):
        v.integer("calls", self.calls, 1, 10**7)
        v.integer("warmup", self.warmup, 0, 10**6)
        if not isinstance(self.batch_sizes, tuple) or not self.batch_sizes:
            raise ValueError(f"batch_sizes must be a non-empty tuple of integers, got {self.batch_sizes!r}")
        for b in self.batch_sizes:
            v.integer("batch_sizes entry", b, 1, 1 << 16)
        v.integer("train_batch", self.train_batch, 1, 1 << 16)
        v.integer("train_calls", self.train_calls, 0, 10**7)
        v.integer("num_steps", self.num_steps, 1, 1000)
        v.choice("arch", self.arch, tuple(ARCHS))
        v.choice("architecture", self.architecture, ARCHITECTURES)
        v.integer("execute_horizon", self.execute_horizon, 1, ARCHS[self.arch]["config"].horizon - 1)
        v.integer("seed", self.seed, 0, 2**31 - 1)
        v.integer("threads", self.threads, 1, 1024)
        v.choice("clock", self.clock, tuple(CLOCKS))
        if self.clock == "thread" and self.threads != 1:
            raise ValueError(f"clock 'thread' counts the calling thread's CPU time only and needs threads=1, "
                             f"got threads={self.threads} (use clock 'wall')")


def _timed(rows: dict, rounds: int, warmup: int, clock: Callable[[], float]) -> dict:
    """Median seconds per row over ``rounds`` round-robin rounds after ``warmup`` untimed ones."""
    times = {k: [] for k in rows}
    for r in range(warmup + rounds):
        for name, fn in rows.items():
            t0 = clock()
            fn(r)
            dt = clock() - t0
            if r >= warmup:
                times[name].append(dt)
    return {k: statistics.median(t) for k, t in times.items()}


def _plain_step(model, opt, obs, actions, g):
    """An ordinary flow-matching step: t ~ U[0, 1) per example, model(obs, x, t [B]), mean squared error."""
    tau = torch.rand(actions.shape[0], generator=g)
    eps = torch.randn(actions.shape, generator=g)
    x = tau[:, None, None] * actions + (1.0 - tau[:, None, None]) * eps
    loss = ((model(obs, x, tau) - (actions - eps)) ** 2).sum(-1).mean()
    return loss


def _rtc_step(obj):
    def loss_fn(model, opt, obs, actions, g):
        b = obj.draw(actions, g)
        return obj.loss(model(obs, b["x"], b["times"]), actions, b)
    return loss_fn


def _train_row(model, loss_fn, obs, actions, seed):
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4, weight_decay=1e-4)
    g = torch.Generator().manual_seed(seed)

    def step(_):
        opt.zero_grad(set_to_none=True)
        loss = loss_fn(model, opt, obs, actions, g)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
    return step


def run_benchmark(config: BenchConfig = BenchConfig(), clock: Callable[[], float] | None = None,
                  progress: Callable[[str], None] | None = None) -> dict:
    """Run every row side by side and return the result dict (medians in ms, ratios, targets).

    ``clock`` (seconds) defaults to the one ``config.clock`` names; tests inject their own.
    """
    if not isinstance(config, BenchConfig):
        raise ValueError(f"config must be a BenchConfig, got {type(config).__name__}")
    clock = CLOCKS[config.clock] if clock is None else clock
    if not callable(clock):
        raise ValueError("clock must be a callable returning seconds")
    say = progress or (lambda m: None)
    threads = torch.get_num_threads()
    torch.set_num_threads(config.threads)  # one thread by default: per-call overheads, not a shared pool's waits
    try:
        return _run(config, clock, say)
    finally:
        torch.set_num_threads(threads)


def _run(config: BenchConfig, clock, say) -> dict:
    arch = ARCHS[config.arch]
    H, A, O, s, T = arch["config"].horizon, arch["action_dim"], arch["obs_dim"], config.execute_horizon, config.num_steps
    dmax = min(s, H - s)
    g = torch.Generator().manual_seed(config.seed)
    pcfg = arch["config"] if config.architecture == "token_input" else \
        dataclasses.replace(arch["config"], architecture="adaln", time_dim=None)
    model = FlowPolicy(O, A, pcfg, generator=g).eval()
    tables = {"train_hard": weight_table(H, "hard"), "train_soft": weight_table(H, "soft", None, s)}
    t0 = time.perf_counter()
    chunk = {}
    agreement = 0.0
    with torch.no_grad():
        naive_cond = step_conditioning(model, torch.zeros(1, 1), T)
        ctabs = {m: conditioning_table(model, tables[m], T) for m in tables}
        for B in config.batch_sizes:
            obs, noise, prior = torch.randn(B, O, generator=g), torch.randn(B, H, A, generator=g), \
                torch.randn(B, H, A, generator=g)
            guided_w = [method_weights("inference_soft", H, s, d) for d in range(dmax + 1)]
            rows = {
                "naive": lambda r: naive_sample_conditioned(model, obs, noise, T, naive_cond),
                "train_hard": lambda r: rtc_sample_conditioned(model, obs, noise, prior, tables["train_hard"][
                    r % (dmax + 1)], T, ctabs["train_hard"][r % (dmax + 1)]),
                "train_soft": lambda r: rtc_sample_conditioned(model, obs, noise, prior, tables["train_soft"][
                    r % (dmax + 1)], T, ctabs["train_soft"][r % (dmax + 1)]),
                "naive_straightforward": lambda r: naive_sample(model, obs, noise, T),
                "train_soft_straightforward": lambda r: rtc_sample(model, obs, noise, prior,
                                                                   tables["train_soft"][r % (dmax + 1)], T),
                "inference_soft": lambda r: guided_sample(model, obs, noise, prior, guided_w[r % (dmax + 1)], T),
            }
            for d in range(dmax + 1):  # [PT-6]: the fast path gives the straightforward chunks
                w = tables["train_soft"][d]
                fast = rtc_sample_conditioned(model, obs, noise, prior, w, T, ctabs["train_soft"][d])
                agreement = max(agreement, float((fast - rtc_sample(model, obs, noise, prior, w, T)).abs().max()))
            agreement = max(agreement, float((rows["naive"](0) - rows["naive_straightforward"](0)).abs().max()))
            say(f"chunk rows, batch {B}")
            med = _timed(rows, config.calls, config.warmup, clock)
            chunk[str(B)] = {k: {"ms": med[k] * 1e3, "ratio": med[k] / med["naive"]} for k in CHUNK_ROWS}
    train = {}
    if config.train_calls:
        B = config.train_batch
        obs, actions = torch.randn(B, O, generator=g), torch.randn(B, H, A, generator=g)
        objs = {"hard": RTCObjective("hard", H, s, d_max=dmax), "soft": RTCObjective("soft", H, s, d_max=dmax)}
        model.train()
        rows = {"plain": _train_row(copy.deepcopy(model), _plain_step, obs, actions, config.seed),
                "hard": _train_row(copy.deepcopy(model), _rtc_step(objs["hard"]), obs, actions, config.seed),
                "soft": _train_row(copy.deepcopy(model), _rtc_step(objs["soft"]), obs, actions, config.seed)}
        say(f"training steps, batch {B}")
        med = _timed(rows, config.train_calls, config.warmup, clock)
        train = {k: {"ms": med[k] * 1e3, "over_hard": med[k] / med["hard"], "over_plain": med[k] / med["plain"]}
                 for k in TRAIN_ROWS}
    res = {"config": dataclasses.asdict(config), "chunk": chunk, "train": train, "agreement": agreement,
           "env": {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpu_model": cpu_model(),
                   "cpu_count": os.cpu_count()},
           "seconds": time.perf_counter() - t0}
    res["targets"] = check_targets(res)
    return res


def check_targets(res: dict) -> list:
    """[{name, value, bound, passed}] of the targets the result has rows for ([PT-8])."""
    values = {"agreement": res.get("agreement")}
    for B in ("1", "32"):
        if B in res.get("chunk", {}):
            values[f"samplers_b{B}"] = max(res["chunk"][B][m]["ratio"] for m in ("train_hard", "train_soft"))
    if res.get("train"):
        values["soft_over_hard"] = res["train"]["soft"]["over_hard"]
        values["soft_over_plain"] = res["train"]["soft"]["over_plain"]
    return [{"name": n, "value": values[k], "bound": b, "passed": bool(values[k] <= b)}
            for n, k, b in TARGETS if values.get(k) is not None]


def format_table(res: dict) -> str:
    """The side-by-side table of a result (the README's table is this text of the committed result)."""
    c, env = res["config"], res["env"]
    arch = ARCHS[c["arch"]]
    net = "" if c.get("architecture", "token_input") == "token_input" else f", {c['architecture']} network"
    lines = [f"softrtc bench torch: {c['arch']} policy{net} (obs {arch['obs_dim']}, action {arch['action_dim']}, "
             f"H {arch['config'].horizon}), s {c['execute_horizon']}, T {c['num_steps']}; median of {c['calls']} "
             f"interleaved calls after {c['warmup']} warm-up rounds, {c.get('clock', 'wall')} clock; torch {env['torch']}, {env['threads']} thread(s), "
             f"{env['cpu_model']}"]
    sizes = list(res["chunk"])
    head = f"{'chunk generation':<34s}" + "".join(f"{'b=' + b + ' ms':>11s}{'/naive':>8s}" for b in sizes)
    lines += [head, "-" * len(head)]
    for k in CHUNK_ROWS:
        lines.append(f"{CHUNK_LABELS[k]:<34s}" + "".join(
            f"{res['chunk'][b][k]['ms']:>11.3f}{res['chunk'][b][k]['ratio']:>7.2f}x" for b in sizes))
    if res["train"]:
        lines += ["", f"training step (batch {c['train_batch']}, median of {c['train_calls']} interleaved steps)",
                  f"{'objective':<34s}{'ms':>11s}{'/hard':>8s}{'/plain':>8s}"]
        for k in TRAIN_ROWS:
            r = res["train"][k]
            lines.append(f"{k:<34s}{r['ms']:>11.3f}{r['over_hard']:>7.2f}x{r['over_plain']:>7.2f}x")
    lines += ["", "targets"]
    for t in res["targets"]:
        fmt = f"{t['value']:.1e}" if t["bound"] < 0.01 else f"{t['value']:.3f}"
        lines.append(f"  {'PASS' if t['passed'] else 'FAIL'}  {t['name']:<40s}{fmt} <= {t['bound']:g}")
    return "\n".join(lines)


def write_json(res: dict, path) -> None:
    """The result as strict JSON, written whole or not at all."""
    if not isinstance(res, dict) or "chunk" not in res or "targets" not in res:
        raise ValueError("res must be a result of run_benchmark")
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path) or os.path.isdir(path):
        raise ValueError(f"path must be a file path, got {path!r}")
    _write_json(path, res, prefix=".bench-")


def read_json(path) -> dict:
    """A result written by :func:`write_json`; its targets are recomputed from its rows."""
    res = _read_json(path, "bench result file")
    if not isinstance(res, dict) or not {"config", "chunk", "train", "env", "agreement"} <= set(res):
        raise ValueError(f"{os.fspath(path)!r} is not a softrtc bench torch result")
    res["targets"] = check_targets(res)
    return res
