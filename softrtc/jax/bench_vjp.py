"""The pull-back ablation of the guided samplers: each VJP design choice against the shipped one ([B-12])."""

from __future__ import annotations

import dataclasses
import os
import statistics
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np

from .bench import _reporter, _stats, _time_round_robin, _window, build_rows
from .bench_config import ATOL, CHUNK_ROWS, RTOL, BenchConfig, inputs, make_policy
from .bench_report import cpu_model, format_vjp_table
from .fast_chunks import FastChunks, guided_tokens_for
from .vjp import autodiff_vjps

__all__ = ["VJP_VARIANTS", "run_vjp_ablation", "format_vjp_table"]


# [B-12] Variants of the guided soft row: label, LayerNorm VJP by autodiff ([P-17] off), GELU VJP by
# autodiff (as shipped, [P-20]; False = the recomputing VJP), stored transposed kernels ([P-19]), pull-back
# ("rule" = guided_tokens_for, "flip" = the other choice, "full" = over all tokens, [G-7]).
VJP_VARIANTS = {
    "shipped": ("as shipped", False, True, True, "rule"),
    "layer_norm_autodiff": ("LayerNorm VJP by autodiff", True, True, True, "rule"),
    "gelu_recompute": ("GELU VJP recomputing tanh", False, False, True, "rule"),
    "no_stored_transposes": ("no stored transposes", False, True, False, "rule"),
    "other_pullback": ("the other pull-back", False, True, True, "flip"),
    "plain_autodiff": ("plain autodiff, full pull-back", True, True, False, "full"),
}


def _variant_tokens(choice: str, rule: int | None, H: int, s: int) -> int | None:
    if choice == "rule":
        return rule
    if choice == "full" or s == H:
        return None
    return H - s if rule is None else None


def run_vjp_ablation(config: BenchConfig = BenchConfig(), *,
                     progress: Callable[[str], None] | None = None) -> dict:
    """Each design choice of the guided pull-back against the shipped one, side by side ([B-12]).

    The guided soft row (``inference_soft``, fast path) is compiled once per
    variant of :data:`VJP_VARIANTS` and batch size, its chunks are compared
    with the shipped variant's at every delay (they MUST agree within the
    tolerance of [B-5]), and all variants and the naive row are timed
    interleaved as in [B-6]. Uses ``calls``, ``warmup``, ``batch_sizes``,
    ``delay``, ``seed``, ``num_steps``, ``execute_horizon`` and ``arch`` of
    ``config``; the path is always the fast one.
    """
    say = _reporter(config, progress)
    t_start = time.perf_counter()
    config = dataclasses.replace(config, path="fast")
    policy = make_policy(config)
    H, s, T = policy.action_chunk_size, config.execute_horizon, config.num_steps
    method, wspec, _ = CHUNK_ROWS["inference_soft"]
    window = _window(wspec)
    naive = [r for r in build_rows(config, policy, ("naive",)) if r.path == "fast"][0]
    delays = [jnp.asarray(d, jnp.int32) for d in config.delays]
    result: dict = {
        "config": dataclasses.asdict(config),
        "environment": {"jax": jax.__version__, "backend": jax.default_backend(), "cpu_count": os.cpu_count(),
                        "cpu_model": cpu_model()},
        "tolerance": {"atol": ATOL, "rtol": RTOL},
        "variants": {k: {"label": v[0], "layer_norm_autodiff": v[1], "gelu_autodiff": v[2],
                         "stored_transposes": v[3], "pullback": v[4]} for k, v in VJP_VARIANTS.items()},
        "chunk": {}, "agreement": {}, "restricted_pullback": {}}
    for B in config.batch_sizes:
        sets = inputs(config, policy, B, 4)
        rule = guided_tokens_for(method, H, s, B)
        fns = {}
        say(f"batch {B}: compiling {len(VJP_VARIANTS)} variants of the guided soft row")
        for key, (_, ln, ge, stored, choice) in VJP_VARIANTS.items():
            tokens = _variant_tokens(choice, rule, H, s)
            fast = FastChunks(policy, method, s, T, window, guided_tokens=tokens, stored_transposes=stored)
            # The switch acts while tracing, so lower and compile inside it.
            with autodiff_vjps(layer_norm=ln, gelu=ge):
                fns[key] = fast.compile_chunk(*sets[0])
            result["restricted_pullback"].setdefault(str(B), {})[key] = tokens is not None
        agree, obs, noise, prior = {}, *sets[0]
        want = [np.asarray(fns["shipped"](obs, noise, prior, d)) for d in delays]
        for key in VJP_VARIANTS:
            worst, ok = 0.0, True
            for d, b in zip(delays, want):
                a = np.asarray(fns[key](obs, noise, prior, d))
                worst = max(worst, float(np.max(np.abs(a - b))))
                ok = ok and bool(np.all(np.abs(a - b) <= ATOL + RTOL * np.abs(b)))
            agree[key] = {"max_abs_diff": worst, "ok": ok}
        result["agreement"][str(B)] = agree

        def call(fn):
            return lambda i: fn(*sets[i % len(sets)], delays[i % len(delays)])

        timed = {"naive": call(naive.call)}
        timed.update({k: call(fns[k]) for k in VJP_VARIANTS})
        say(f"batch {B}: timing naive and {len(VJP_VARIANTS)} variants x {config.calls} calls")
        times = _time_round_robin(timed, config.calls, config.warmup, config.seed)
        stats = {k: _stats(times[k], times["naive"]) for k in timed}
        shipped = statistics.median(times["shipped"])
        for k in VJP_VARIANTS:
            stats[k]["over_shipped"] = statistics.median(times[k]) / shipped
        result["chunk"][str(B)] = stats
    result["seconds"] = time.perf_counter() - t_start
    return result
