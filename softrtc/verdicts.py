"""Verdicts on the paper's qualitative claims, one rule set for every environment ([AX-7], [KR-5]).

The rules read an environment-neutral summary: per row name, ``seeds``
(fine-tuning seeds), ``episodes`` (paired episodes per delay), ``scopes``
(``{scope: {metric: {"mean", "lo", "hi", ...}}}``, with at least the scopes
``overall`` and ``high``) and ``vs_hard`` (``{scope: {metric: {"diff", "lo",
"hi", ...}}}``, the paired difference to Train Hard RTC and its bootstrap
interval). An :class:`Environment` names the metrics that play each part in
the claims (success, jerk, the finite-difference family) and the rows that
form each comparison, so the arm report ([AX-7]) and the Kinetix study table
([KR-5]) state the same claims under the same rules. Each claim is
*supported*, *not supported* or *inconclusive* (with the reason): enough
seeds and episodes, and a paired interval against Train Hard RTC that
excludes 0 in the stated direction. The formatting helpers here also write
the reports' intervals.

>>> _diff({"diff": 0.1, "lo": 0.05, "hi": 0.15}, 2)
'+0.10 [0.05, 0.15]'
"""

from __future__ import annotations

import dataclasses
import math
from typing import Callable

__all__ = ["Environment", "verdicts", "MIN_SEEDS", "MIN_EPISODES", "SMALL_COST", "BASE_ROWS"]

# Below these a claim gets no verdict, whatever its interval ([AX-7]).
MIN_SEEDS = 3
MIN_EPISODES = 20
# A "small" success cost, and "nearly matches": 10 points of success rate.
SMALL_COST = 0.10
# Rows evaluated from the base policy, without fine-tuning: one seed by construction.
BASE_ROWS = ("naive", "inference_hard", "inference_soft")


@dataclasses.dataclass(frozen=True)
class Environment:
    """What the claims read in one environment's summary.

    ``success`` and ``jerk`` are metric keys of the summary; ``success_word``
    / ``succeeds`` are how the claims write the success metric; ``fd`` is the
    finite-difference family of the smoothness claim, written ``fd_label``;
    ``offset_row(L, overflow)`` names the row of the offset sweep with length
    ``L`` and overflow ``"clip"`` / ``"zeros"``.
    """

    success: str
    success_word: str
    succeeds: str
    jerk: str
    fd: tuple
    fd_label: str
    offset_row: Callable[[int, str], str]
    hard: str = "train_hard"
    naive: str = "naive"
    inference: tuple = ("inference_hard", "inference_soft")
    base_rows: tuple = BASE_ROWS

    def __post_init__(self):
        for name in ("success", "success_word", "succeeds", "jerk", "fd_label", "hard", "naive"):
            if not isinstance(getattr(self, name), str) or not getattr(self, name):
                raise ValueError(f"{name} must be a non-empty string, got {getattr(self, name)!r}")
        for name in ("fd", "inference", "base_rows"):
            v = getattr(self, name)
            if not isinstance(v, tuple) or not v or not all(isinstance(x, str) and x for x in v):
                raise ValueError(f"{name} must be a non-empty tuple of non-empty strings, got {v!r}")
        if not callable(self.offset_row):
            raise ValueError(f"offset_row must be a callable (L, overflow) -> row name, got {self.offset_row!r}")


def _f(x, nd=3):
    return "nan" if x is None or not math.isfinite(x) else f"{x:.{nd}f}"


def _ci(st, nd=3):
    if st is None:
        return "n/a"
    return f"{_f(st['mean'], nd)} [{_f(st['lo'], nd)}, {_f(st['hi'], nd)}]"


def _diff(t, nd=3):
    if t is None:
        return "n/a"
    return f"{'+' if t['diff'] >= 0 else ''}{_f(t['diff'], nd)} [{_f(t['lo'], nd)}, {_f(t['hi'], nd)}]"


def _diff_vs(summary, t, hard):
    """``_diff`` plus, when the pairing used fewer fine-tuning seeds than Train Hard's quoted value pools, how
    many: the quoted means and the paired difference then cover different seeds ([KR-3])."""
    k, n = (t or {}).get("seeds"), summary.get(hard, {}).get("seeds")
    note = f", paired on the {k} seed{'s' if k != 1 else ''} both ran" if k is not None and n is not None and k < n \
        else ""
    return _diff(t) + note


def _get(summary, row, scope, metric):
    return summary.get(row, {}).get("scopes", {}).get(scope, {}).get(metric)


def _vs(summary, row, scope, metric):
    return summary.get(row, {}).get("vs_hard", {}).get(scope, {}).get(metric)


def _enough(summary, rows, env):
    """A reason why the rows are too small for a verdict, or None."""
    for r in rows:
        e = summary.get(r)
        if e is None:
            return f"`{r}` was not run"
        trained = r not in env.base_rows
        if trained and e["seeds"] < MIN_SEEDS:
            return f"`{r}` has {e['seeds']} fine-tuning seed(s), fewer than {MIN_SEEDS}"
        if e["episodes"] < MIN_EPISODES:
            return f"`{r}` has {e['episodes']} episodes per delay, fewer than {MIN_EPISODES}"
    return None


def _config(row: str) -> str:
    """Which configuration and solver step ([S-10]) a Soft row's verdict applies to."""
    pad = "paper config, zero padding" if "zeros" in row else "spec default, clip"
    step = "consistent step" if "consistent" in row else "Algorithm 1 step"
    return f"{pad}; {step}"


def _sign(t):
    """+1 / -1 when the paired interval excludes 0, else 0."""
    if t is None or not math.isfinite(t.get("lo", float("nan"))):
        return 0
    return 1 if t["lo"] > 0 else (-1 if t["hi"] < 0 else 0)


def verdicts(summary: dict, env: Environment, soft2_rows=(), n1_identical: bool | None = None,
             n1_rows=()) -> list:
    """The paper's qualitative claims with a verdict each: supported / not supported / inconclusive.

    ``soft2_rows`` are the Soft ``N = 2`` rows the experiment ran (one claim
    of jerk and one of smoothness each). The claim "Soft N = 1 nearly
    matches Hard" is *identical by construction* when ``n1_identical`` is
    True (its rows share Train Hard's files), inconclusive when False; when
    None it is measured on each row of ``n1_rows``: supported when the paired
    overall success difference's interval lies within ``SMALL_COST`` of 0, not
    supported when it lies wholly beyond. Returns ``[{"claim", "verdict",
    "evidence", "reason"}]``.
    """
    if not isinstance(summary, dict):
        raise ValueError(f"summary must be a dict row -> entry, got {type(summary).__name__}")
    if not isinstance(env, Environment):
        raise ValueError(f"env must be a softrtc.verdicts.Environment, got {type(env).__name__}")
    for name, rows in (("soft2_rows", soft2_rows), ("n1_rows", n1_rows)):
        if isinstance(rows, str) or not all(isinstance(r, str) and r for r in rows):
            raise ValueError(f"{name} must be a sequence of row names, got {rows!r}")
    if n1_identical not in (True, False, None):
        raise ValueError(f"n1_identical must be True, False or None, got {n1_identical!r}")
    S, w, J, hard = env.success, env.success_word, env.jerk, env.hard
    out = []
    # 1. Training-time RTC beats inference-time RTC at high delay (success).
    ih, is_ = env.inference
    why = _enough(summary, [hard, ih, is_], env)
    t_ih = _vs(summary, ih, "high", S)
    t_is = _vs(summary, is_, "high", S)
    ev = (f"high-delay {w}: Train Hard {_ci(_get(summary, hard, 'high', S))}, "
          f"Inference Hard {_ci(_get(summary, ih, 'high', S))} "
          f"(vs Train Hard {_diff(t_ih)}), Inference Soft {_ci(_get(summary, is_, 'high', S))} "
          f"(vs Train Hard {_diff(t_is)})")
    if why:
        v = "inconclusive"
    else:
        signs = {_sign(t_ih), _sign(t_is)}
        v = "supported" if signs == {-1} else ("not supported" if 1 in signs else "inconclusive")
        if v == "not supported":
            why = f"an inference-time method {env.succeeds} more often than Train Hard at high delay"
        elif v == "inconclusive":
            why = "the paired intervals include 0"
    out.append({"claim": f"Training-time RTC beats inference-time RTC at high delay ({w}).", "verdict": v,
                "evidence": ev, "reason": why})
    # 2. Soft N = 2 has the lowest high-delay jerk at a small solve cost: under the paper's step (Algorithm 1) and
    # under the consistent step of [S-10], each a claim of its own.
    pts = round(SMALL_COST * 100)
    for row in soft2_rows:
        why = _enough(summary, [row, hard], env)
        tj = _vs(summary, row, "high", J)
        ts = _vs(summary, row, "overall", S)
        ev = (f"`{row}` high-delay {J} {_ci(_get(summary, row, 'high', J))} vs Train Hard "
              f"{_ci(_get(summary, hard, 'high', J))} (diff {_diff(tj)}); overall {w} "
              f"{_ci(_get(summary, row, 'overall', S))} vs {_ci(_get(summary, hard, 'overall', S))}"
              f" (diff {_diff_vs(summary, ts, hard)})")
        if why:
            v = "inconclusive"
        elif _sign(tj) == 1 or (ts is not None and ts["hi"] < -SMALL_COST):
            v = "not supported"
            why = "jerk is higher than Train Hard's" if _sign(tj) == 1 else f"the {w} cost exceeds {pts} points"
        elif _sign(tj) == -1 and ts is not None and ts["lo"] > -SMALL_COST:
            v = "supported"
        else:
            v = "inconclusive"
            why = f"the paired intervals do not separate the jerk from Train Hard's or bound the {w} cost"
        out.append({"claim": f"Soft N = 2 ({_config(row)}) has lower high-delay jerk than Train Hard at a small "
                             f"(< {pts} points) {w} cost.",
                    "verdict": v, "evidence": ev, "reason": why})
    # 3. N = 1 nearly matches Hard.
    if n1_identical is not None:
        same = n1_identical
        out.append({"claim": f"Soft N = 1 nearly matches Hard RTC in {w}.",
                    # Equal by construction is not evidence for the claim: the verdict says so instead of "supported".
                    "verdict": "identical by construction" if same else "inconclusive",
                    "evidence": ("`lam = 1` gives `e(d) = d` under the ceiling rule: its training weights, fine-tunes "
                                 "and sampler are those of Train Hard RTC (same files in this experiment), so it "
                                 "matches Hard exactly; any difference between the two in a paper table comes from "
                                 "separate training runs" if same else "the rows were not shared"),
                    "reason": None if same else "rows differ"})
    for row in n1_rows if n1_identical is None else ():
        why = _enough(summary, [row, hard], env)
        t = _vs(summary, row, "overall", S)
        ev = (f"`{row}` overall {w} {_ci(_get(summary, row, 'overall', S))} vs Train Hard "
              f"{_ci(_get(summary, hard, 'overall', S))} (diff {_diff_vs(summary, t, hard)})")
        v = "inconclusive"
        if why is None:
            if t is None or not math.isfinite(t["lo"]):
                why = "no paired interval against Train Hard"
            elif -SMALL_COST < t["lo"] and t["hi"] < SMALL_COST:
                v = "supported"
            elif t["lo"] > SMALL_COST or t["hi"] < -SMALL_COST:
                v = "not supported"
                why = f"the {w} difference exceeds {pts} points"
            else:
                why = f"the paired interval is not within {pts} points of 0"
        out.append({"claim": f"Soft N = 1 ({_config(row)}) nearly matches Hard RTC in {w} (paired difference "
                             f"within {pts} points).", "verdict": v, "evidence": ev, "reason": why})
    # 4. The offset sweep trades solve for smoothness steeply.
    for ov in ("zeros", "clip"):
        name = {L: env.offset_row(L, ov) for L in range(7)}
        need = [name[0], name[6]]
        ok = all(r in summary for r in need)
        ev = "; ".join(f"L {L}: {w} {_ci(_get(summary, name[L], 'high', S), 2)}, {J} "
                       f"{_ci(_get(summary, name[L], 'high', J), 3)}"
                       for L in range(7) if name[L] in summary) or "no row of the sweep in the results"
        why = None if ok else "the offset rows L = 0 and L = 6 were not both run"
        if ok:
            e0 = summary[name[0]]
            e6 = summary[name[6]]
            if min(e0["episodes"], e6["episodes"]) < MIN_EPISODES:
                why = f"fewer than {MIN_EPISODES} episodes per delay"
        v = "inconclusive"
        if why is None:
            a = _get(summary, name[6], "high", S)
            b = _get(summary, name[0], "high", S)
            ja = _get(summary, name[6], "high", J)
            jb = _get(summary, name[0], "high", J)
            if a and b and ja and jb:
                if a["hi"] < b["lo"] and ja["hi"] < jb["lo"]:
                    v = "supported"
                elif a["lo"] > b["hi"] or ja["lo"] > jb["hi"]:
                    v = "not supported"
                else:
                    why = "the high-delay intervals of L = 0 and L = 6 overlap"
        out.append({"claim": f"The offset sweep ({ov}) trades high-delay {w} for smoothness (L = 6 vs L = 0).",
                    "verdict": v, "evidence": ev, "reason": why})
    # 5. Soft RTC has the lowest finite-difference metrics among Base, Hard and Soft (the hardware claim).
    for row in soft2_rows:
        why = _enough(summary, [row, hard, env.naive], env)
        ev = ", ".join(f"{m}: soft {_ci(_get(summary, row, 'overall', m))}, hard "
                       f"{_ci(_get(summary, hard, 'overall', m))}, base {_ci(_get(summary, env.naive, 'overall', m))}"
                       for m in env.fd)
        tests = [_vs(summary, row, "overall", m) for m in env.fd]
        if why:
            v = "inconclusive"
        elif all(_sign(t) == -1 for t in tests):
            v = "supported"
        elif any(_sign(t) == 1 for t in tests):
            v = "not supported"
            why = "at least one finite-difference metric is higher than Train Hard's"
        else:
            v = "inconclusive"
            why = "the paired intervals against Train Hard include 0"
        out.append({"claim": f"Soft RTC ({_config(row)}) has lower {env.fd_label} than Train Hard RTC over all delays.",
                    "verdict": v, "evidence": ev, "reason": why})
    return out
