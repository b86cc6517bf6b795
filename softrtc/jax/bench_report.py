"""Printing and storing benchmark results, and the machine they ran on ([B-10], [B-12])."""

from __future__ import annotations

import json
import math
import numbers
import os
from typing import Any, Callable, Mapping

import jax
import numpy as np

from softrtc._files import write_atomic
from softrtc._machine import cpu_model  # one copy for JAX and torch ([B-10])

from .bench_config import (ARCHS, GUIDED_VS_PUBLIC_LIMIT, NAIVE_VS_STRAIGHTFORWARD_LIMIT, SOFT_STEP_LIMIT,
                           TRAIN_METHODS, TRAIN_ROWS, TRAIN_SAMPLER_LIMIT)

__all__ = ["cpu_model", "format_table", "format_ranges", "format_vjp_table", "read_result", "write_json"]



def _formatted(producer: str, fmt: Callable[[dict], str], res: Any, keys: tuple) -> str:
    """``fmt(res)``, with a result that lacks a key it reads reported as ``ValueError`` naming the key ([N-7])."""
    if not isinstance(res, Mapping):
        raise ValueError(f"res must be a result of {producer}, got {type(res).__name__}")
    missing = [k for k in keys if k not in res]
    if missing:
        raise ValueError(f"res must be a result of {producer}; it lacks the key(s) {missing}")
    try:
        return fmt(res)
    except KeyError as exc:
        raise ValueError(f"res must be a complete result of {producer}; it lacks the key {exc.args[0]!r}") from None
    except (TypeError, AttributeError, IndexError, ValueError) as exc:
        raise ValueError(f"res must be a result of {producer}; an entry has the wrong type or form ({exc})") from None


def _machine(env: Mapping) -> str:
    # Results written before the CPU model was recorded lack the key.
    model = env.get("cpu_model")
    return f"{env['backend']} ({env['cpu_count']} cores{', ' + model if model else ''})"


_VJP_KEYS = ("config", "environment", "variants", "chunk", "agreement", "restricted_pullback", "seconds")
_RUNTIME_KEYS = ("config", "architecture", "environment", "rows", "chunk", "agreement", "targets", "seconds")


def format_vjp_table(res: dict) -> str:
    """The printed table of [B-12]: per batch size, every variant's median, ratio to naive and to shipped.

    A result without a key the table reads raises ``ValueError`` naming the key.
    """
    return _formatted("run_vjp_ablation", _format_vjp_table, res, _VJP_KEYS)


def _format_vjp_table(res: dict) -> str:
    cfg = res["config"]
    lines = [f"softrtc bench vjp: guided soft RTC (fast path), {cfg['arch']} network, s {cfg['execute_horizon']}, "
             f"T {cfg['num_steps']}; median of {cfg['calls']} interleaved calls after {cfg['warmup']} warm-up "
             f"rounds; {_machine(res['environment'])}, "
             f"jax {res['environment']['jax']}"]
    for b, stats in res["chunk"].items():
        head = f"{'variant':<32s} {'pull-back':<10s} {'ms':>9s} {'/naive':>7s} {'/shipped':>9s} {'max|v-shipped|':>15s}"
        lines += ["", f"batch {b}", head, "-" * len(head),
                  f"{'naive (base policy)':<32s} {'-':<10s} {stats['naive']['median_ms']:>9.3f} {1.0:>6.2f}x"]
        for k, v in res["variants"].items():
            st, ag = stats[k], res["agreement"][b][k]
            pb = "j < H - s" if res["restricted_pullback"][b][k] else "all"
            lines.append(f"{v['label']:<32s} {pb:<10s} {st['median_ms']:>9.3f} {st['ratio']:>6.2f}x "
                         f"{st['over_shipped']:>8.3f}x {ag['max_abs_diff']:>10.1e} {'ok' if ag['ok'] else 'FAIL'}")
    lines.append(f"total {res['seconds']:.0f} s")
    return "\n".join(lines)


# --------------------------------------------------------------------------- output


def format_table(res: dict) -> str:
    """The printed table of [B-10]: rows x batch sizes (median ms, ratio to naive), agreement, targets.

    A result without a key the table reads raises ``ValueError`` naming the key.
    """
    return _formatted("run_benchmark", _format_table, res, _RUNTIME_KEYS)


def _format_table(res: dict) -> str:
    cfg, arch = res["config"], res["architecture"]
    bs = list(res["chunk"])
    d = "rotating " + "..".join(map(str, (0, max(0, len(_delays_of(cfg)) - 1)))) \
        if cfg["delay"] is None else str(cfg["delay"])
    lines = [f"softrtc bench runtime: obs {arch['obs_dim']}, action {arch['action_dim']}, "
             f"H {arch['action_chunk_size']}, s {cfg['execute_horizon']}, T {cfg['num_steps']}, d {d}; "
             f"median of {cfg['calls']} interleaved calls after {cfg['warmup']} warm-up rounds; "
             f"{_machine(res['environment'])}, "
             f"jax {res['environment']['jax']}"]
    # The method column is as wide as the longest label (at least 26, the width of the older tables).
    w = max([26] + [len(r["label"]) for r in res["rows"]])
    head = f"{'method':<{w}s} {'path':<15s}" + "".join(f" {'b=' + b + ' ms':>10s} {'/naive':>7s}" for b in bs) \
        + f" {'max|fast-sf|':>12s}"
    lines += [head, "-" * len(head)]
    for r in res["rows"]:
        k = r["key"]
        cells = "".join(f" {res['chunk'][b][k]['median_ms']:>10.3f} {res['chunk'][b][k]['ratio']:>6.2f}x"
                        for b in bs)
        # Fast rows are checked under their name, public-style rows ([B-14]) under their key.
        ak = r["name"] if r["path"] == "fast" else r["key"]
        diffs = [res["agreement"][b][ak]["max_abs_diff"] for b in bs
                 if r["path"] != "straightforward" and ak in res["agreement"][b]]
        path = "public-style" if r["path"] == "public" else r["path"]
        lines.append(f"{r['label']:<{w}s} {path:<15s}{cells} {(f'{max(diffs):.1e}' if diffs else '-'):>12s}")
    if res.get("vjp_cost"):
        lines += ["", "context (not targets)"]
        for b in bs:
            ch, vc = res["chunk"][b], res["vjp_cost"][b]
            guided = max(ch[k]["median_ms"] for k in ("inference_hard", "inference_soft"))
            if "naive/straightforward" in ch:
                lines.append(f"  guided / straightforward naive, batch {b:<6s} "
                             f"{guided / ch['naive/straightforward']['median_ms']:>6.2f}x")
            restricted = res.get("restricted_pullback", {}).get(b)
            lines.append(f"  one forward + VJP / one forward, batch {b:<4s} {vc['ratio']:>6.2f}x "
                         f"({vc['forward_vjp_ms']:.3f} / {vc['forward_ms']:.3f} ms)"
                         + ("" if restricted is None else
                            f"; pull-back {'restricted to j < H - s' if restricted else 'over all tokens'}"))
    ts = res.get("train_step")
    if ts:
        lines += ["", f"training step (batch {ts['batch']}, delays 0..{ts['d_max']}, "
                      f"median of {ts['none']['calls']} interleaved calls)",
                  f"{'method':<26s} {'ms':>10s} {'/hard':>7s} {'/none':>7s}"]
        for m in TRAIN_METHODS:
            lines.append(f"{m:<26s} {ts[m]['median_ms']:>10.2f} "
                         f"{ts[m]['median_ms'] / ts['hard']['median_ms']:>6.2f}x "
                         f"{ts[m]['median_ms'] / ts['none']['median_ms']:>6.2f}x")
    if res["targets"]:
        lines += ["", "targets"]
        for t in res["targets"]:
            val = f"{t['value']:.1e} (tol {res['tolerance']['atol']:.0e})" if t["limit"] is None \
                else f"{t['value']:.3f} <= {t['limit']:.2f}"
            lines.append(f"  {'PASS' if t['pass'] else 'FAIL'}  [{t['id']}] {t['target']:<44s} {val}")
    lines.append(f"total {res['seconds']:.0f} s")
    return "\n".join(lines)


def format_ranges(results: list) -> str:
    """The ratios of [B-9] over several runs of ``run_benchmark`` as a Markdown table ([B-15]).

    Per ratio and batch size the smallest and largest value over the runs
    (a single value for one run), and the target; the guided samplers over
    naive is context, not a target ([B-9]). Every result must hold the batch
    sizes of the first; a result without a key the table reads raises
    ``ValueError`` naming the key.
    """
    if not isinstance(results, (list, tuple)) or not results:
        raise ValueError("results must be a non-empty list of run_benchmark results")
    for i, res in enumerate(results):
        _formatted("run_benchmark", lambda r: "", res, _RUNTIME_KEYS)
        if list(res["chunk"]) != list(results[0]["chunk"]):
            raise ValueError(f"results[{i}] must have the batch sizes of results[0] {list(results[0]['chunk'])}, "
                             f"got {list(res['chunk'])}")
    return _formatted("run_benchmark", lambda _: _format_ranges(results), results[0], _RUNTIME_KEYS)


def _ratio_rows() -> list:
    """(label, function of a batch size's chunk stats -> ratio, target) of the range table."""
    def largest(ch, keys, over):
        return max(ch[k]["median_ms"] for k in keys) / ch[over]["median_ms"]
    return [
        ("training-time samplers / naive", lambda ch: largest(ch, tuple(k for k in TRAIN_ROWS if k in ch), "naive"),
         f"{TRAIN_SAMPLER_LIMIT:.2f}"),
        ("naive / straightforward naive", lambda ch: largest(ch, ("naive",), "naive/straightforward"),
         f"{NAIVE_VS_STRAIGHTFORWARD_LIMIT:.2f}"),
        ("guided samplers / public-style guided", lambda ch: largest(ch, ("inference_hard", "inference_soft"),
                                                                     "inference_soft/public"),
         f"{GUIDED_VS_PUBLIC_LIMIT:.2f}"),
        ("guided samplers / naive (context)", lambda ch: largest(ch, ("inference_hard", "inference_soft"), "naive"),
         "-"),
    ]


def _span(values: list) -> str:
    lo, hi = min(values), max(values)
    return f"{lo:.2f}" if f"{lo:.2f}" == f"{hi:.2f}" else f"{lo:.2f}-{hi:.2f}"


def _format_ranges(results: list) -> str:
    bs = list(results[0]["chunk"])
    env = results[0]["environment"]
    lines = [f"| ratio over {len(results)} run{'s' if len(results) > 1 else ''} ({_machine(env)}) | "
             + " | ".join(f"batch {b}" for b in bs) + " | target |",
             "|---|" + "---|" * len(bs) + "---|"]
    for label, ratio, target in _ratio_rows():
        cells = [_span([ratio(r["chunk"][b]) for r in results]) for b in bs]
        lines.append(f"| {label} | " + " | ".join(cells) + f" | {target} |")
    steps = [r["train_step"]["soft_over_hard"] for r in results if r.get("train_step")]
    if steps:
        lines.append(f"| soft / hard training step (batch {results[0]['train_step']['batch']}) | {_span(steps)} | "
                     + " | " * (len(bs) - 1) + f"{SOFT_STEP_LIMIT:.2f} |")
    return "\n".join(lines)


def read_result(path: str | os.PathLike) -> dict:
    """A result file written by :func:`write_json` ([B-10]), checked to be one of ``run_benchmark``."""
    if not isinstance(path, (str, os.PathLike)) or not os.path.isfile(path):
        raise ValueError(f"path must name an existing result file, got {path!r}")
    try:
        with open(path, encoding="utf-8") as f:
            res = json.load(f)
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{os.fspath(path)} is not a JSON result file ({exc})") from None
    if not isinstance(res, dict) or any(k not in res for k in _RUNTIME_KEYS):
        raise ValueError(f"{os.fspath(path)} is not a result of softrtc bench runtime "
                         f"(it lacks some of the keys {list(_RUNTIME_KEYS)})")
    return res


def _delays_of(cfg: dict) -> list:
    H = ARCHS[cfg["arch"]]["config"].action_chunk_size
    s = cfg["execute_horizon"]
    return list(range(min(s, H - s) + 1))


def _json_value(value: Any, where: str) -> Any:
    """``value`` as plain JSON data ([B-10]): NumPy and JAX scalars and arrays become numbers and lists,
    tuples lists, and every non-finite float (NaN, inf) ``None`` (JSON ``null``)."""
    if value is None or isinstance(value, (str, bool, np.bool_)):
        return bool(value) if isinstance(value, np.bool_) else value
    if isinstance(value, Mapping):
        out = {}
        for k, x in value.items():
            if not isinstance(k, str):
                raise ValueError(f"res{where} must have string keys, got {k!r}")
            out[k] = _json_value(x, f"{where}[{k!r}]")
        return out
    if isinstance(value, (list, tuple)):
        return [_json_value(x, f"{where}[{i}]") for i, x in enumerate(value)]
    if isinstance(value, (np.ndarray, np.generic, jax.Array)):
        arr = np.asarray(value)
        if arr.dtype.kind not in "biuf":
            raise ValueError(f"res{where} must hold JSON values (numbers, strings, bools, None, lists, dicts), "
                             f"got an array of dtype {arr.dtype}")
        return _json_value(arr.tolist(), where)
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        f = float(value)
        return f if math.isfinite(f) else None
    raise ValueError(f"res{where} must hold JSON values (numbers, strings, bools, None, lists, dicts), "
                     f"got {type(value).__name__}")


def write_json(res: dict, path: str | os.PathLike) -> None:
    """Write the result of :func:`run_benchmark` ([B-10]) or :func:`run_vjp_ablation` ([B-12]) as JSON.

    The output is strict JSON: NumPy and JAX numbers are written as plain
    numbers and non-finite ones (NaN, inf) as ``null`` ([B-10]). The text is
    built first and then written to a temporary file in the target folder and
    renamed, so a failure never leaves a partial file at ``path``. Creates the
    parent folder; ``path`` must not be a directory.
    """
    if not isinstance(res, Mapping) or "chunk" not in res:
        raise ValueError("res must be a result of run_benchmark or run_vjp_ablation")
    if not isinstance(path, (str, os.PathLike)) or not os.fspath(path):
        raise ValueError(f"path must be a file path, got {path!r}")
    if os.path.isdir(path):
        raise ValueError(f"path must be a file path, got the directory {os.fspath(path)!r}")
    text = json.dumps(_json_value(res, ""), indent=1, sort_keys=True, allow_nan=False) + "\n"
    os.makedirs(os.path.dirname(os.path.abspath(os.fspath(path))), exist_ok=True)
    write_atomic(path, lambda f: f.write(text), prefix=".bench-")
