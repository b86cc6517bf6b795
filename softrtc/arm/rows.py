"""Rows, keys and budgets of the controlled arm experiment ([AX-2], [AX-3], [AX-4], [AX-10]).

A row names the checkpoint's objective and window and the sampler (method, window, solver step, Euler
steps) it runs with; :func:`train_key` names the fine-tune a row's checkpoint comes from and
:func:`eval_key` the episodes it produces, so rows that train or sample identically share them.
"""

from __future__ import annotations

import dataclasses
import hashlib

import numpy as np

from softrtc.reference import endpoints as rep
from softrtc.reference import weights as rw
from softrtc.reference._validate import check_int
from softrtc.reference.methods import check_method_step

from .tasks import ArmTask

__all__ = ["H", "Row", "PAPER_WINDOW", "DEFAULT_WINDOW", "rows_for", "train_key", "eval_key", "Budget", "BUDGETS",
           "tier_delays", "TIERS", "TSWEEP_STEPS", "TSWEEP_ROWS"]

H = 10
# The spec's default window ([W-7]) and the paper's configuration ([W-10]): same rule and schedule,
# zero padding past the overlap as the public evaluation loop does.
DEFAULT_WINDOW = rw.SoftWindow()
PAPER_WINDOW = rw.SoftWindow(rep.delay_scaled(2.0, 5), "linear", "rtc", "zeros")

@dataclasses.dataclass(frozen=True)
class Row:
    """One method row: the checkpoint's objective and window, and the sampler it runs with ([AX-2]).

    ``objective``: ``None`` (the base), ``hard``, ``soft`` or ``prior_noise``
    (the project's variant, [AX-5]); ``window`` the training window (soft
    objectives); ``sampler`` a method of [S-6]; ``sampler_window`` the
    window a ``train_soft`` sampler runs with (default: ``window``);
    ``step`` the training-time sampler's solver step ([S-10], default
    Algorithm 1's); ``num_steps`` the Euler steps T of every chunk (default
    the arm policies' 5, [A-17]; the T sweep of [AX-10] varies it).
    """

    name: str
    label: str
    sampler: str
    objective: str | None = None
    window: rw.SoftWindow | None = None
    sampler_window: rw.SoftWindow | None = None
    tier: str = "main"
    origin: str = "paper"
    step: str = "algorithm1"
    num_steps: int = 5

    def __post_init__(self):
        check_method_step(self.sampler, self.step)
        check_int("num_steps", self.num_steps, 1, 64)

    @property
    def infer_window(self):
        return self.sampler_window if self.sampler_window is not None else self.window


# [AX-10] Euler step counts of the T sweep besides the main rows' T = 5, and the rows it compares at each.
TSWEEP_STEPS = (10, 20)
TIERS = ("main", "sweep", "tsweep")
TSWEEP_ROWS = ("soft2_clip", "soft2_clip_consistent", "train_hard")


def _soft(name, label, window, tier="sweep", origin="paper"):
    return Row(name, label, "train_soft", "soft", window, tier=tier, origin=origin)


def rows_for(task: ArmTask) -> list:
    """The method rows of the experiment: main comparison, cross-evaluations, project variant, sweeps."""
    ds = rep.delay_scaled
    zeros = lambda rule: rw.SoftWindow(rule, "linear", "rtc", "zeros")  # noqa: E731
    clip = lambda rule: rw.SoftWindow(rule, "linear", "rtc", "clip")  # noqa: E731
    rows = [
        Row("naive", "Naive (base)", "naive"),
        Row("inference_hard", "Inference Hard RTC", "inference_hard"),
        Row("inference_soft", "Inference Soft RTC", "inference_soft"),
        Row("train_hard", "Train Hard RTC", "train_hard", "hard"),
        _soft("soft2_clip", "Train Soft RTC lam 2 (clip, spec default)", DEFAULT_WINDOW, "main", "spec"),
        _soft("soft2_zeros", "Train Soft RTC lam 2 (zeros, paper config)", PAPER_WINDOW, "main", "paper"),
        Row("soft2_clip_hard_sampler", "Soft lam 2 (clip) weights, hard sampler", "train_hard", "soft",
            DEFAULT_WINDOW, tier="main", origin="cross"),
        Row("hard_soft_sampler", "Hard weights, soft lam 2 (clip) sampler", "train_soft", "hard", None,
            DEFAULT_WINDOW, tier="main", origin="cross"),
        Row("soft2_clip_prior_noise", "Soft lam 2 (clip) + noisy-prior training (project variant)", "train_soft",
            "prior_noise", DEFAULT_WINDOW, tier="main", origin="project"),
        # The time-consistent solver step ([S-10]) on the same checkpoints ([AX-10]).
        Row("soft2_clip_consistent", "Train Soft RTC lam 2 (clip), consistent step", "train_soft", "soft",
            DEFAULT_WINDOW, tier="main", origin="spec", step="consistent"),
        Row("hard_soft_sampler_consistent", "Hard weights, soft lam 2 (clip) sampler, consistent step", "train_soft",
            "hard", None, DEFAULT_WINDOW, tier="main", origin="cross", step="consistent"),
    ]
    # T sweep ([AX-10]): Algorithm 1, the consistent step and Hard at T = 10, 20 (T = 5 is the main rows').
    for T in TSWEEP_STEPS:
        rows += [Row(f"t{T}_soft2_clip", f"T = {T}: Soft lam 2 (clip), Algorithm 1", "train_soft", "soft",
                     DEFAULT_WINDOW, tier="tsweep", origin="spec", num_steps=T),
                 Row(f"t{T}_soft2_clip_consistent", f"T = {T}: Soft lam 2 (clip), consistent step", "train_soft",
                     "soft", DEFAULT_WINDOW, tier="tsweep", origin="spec", step="consistent", num_steps=T),
                 Row(f"t{T}_train_hard", f"T = {T}: Train Hard RTC", "train_hard", "hard", tier="tsweep",
                     origin="spec", num_steps=T)]
    for lam in (1, 3, 4):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"soft{lam}_{ov}", f"Soft lam {lam} ({ov})", f(ds(float(lam), 5))))
    for h in (3, 5):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"fixed{h}_{ov}", f"Soft fixed h {h} ({ov})", f(rep.fixed(h))))
    for L in range(0, 7):
        for ov, f in (("clip", clip), ("zeros", zeros)):
            rows.append(_soft(f"offset{L}_{ov}", f"Soft offset L {L} ({ov})", f(rep.offset(L, 8))))
    return rows


def _table(window, s: int, delays) -> np.ndarray:
    return np.stack([rw.soft_weights(H, d, window, s) for d in delays])


def train_key(row: Row, task: ArmTask) -> str | None:
    """The fine-tune a row's checkpoint comes from: objective and training weights ([AX-3]); None for the base."""
    if row.objective is None:
        return None
    delays = range(task.max_delay + 1)
    if row.objective == "hard":
        return "hard"
    table = _table(row.window, task.execute_horizon, delays)
    if np.array_equal(table, np.stack([rw.hard_weights(H, d) for d in delays])) and row.objective == "soft":
        return "hard"
    digest = hashlib.sha256(np.round(table, 12).tobytes()).hexdigest()[:12]
    return f"{row.objective}-{digest}"


def _sampler_table(row: Row, task: ArmTask) -> tuple:
    """The sampler family and its weights at every executable delay (zero padding included, [W-6])."""
    delays = range(task.max_delay + 1)
    if row.sampler == "train_soft":
        t = _table(row.infer_window, task.execute_horizon, delays)
        overflow = row.infer_window.overflow
        # Zero padding only matters where a window token lies past the overlap.
        past = bool(np.any(t[:, H - task.execute_horizon:] > 0))
        return ("train", np.round(t, 12).tobytes(), overflow if past else "clip")
    if row.sampler == "train_hard":
        return ("train", np.round(np.stack([rw.hard_weights(H, d) for d in delays]), 12).tobytes(), "clip")
    return (row.sampler,)


def _sampler_step(row: Row, task: ArmTask) -> str:
    """The solver step as far as it changes a chunk: "algorithm1" unless a training-time sampler has
    window tokens (0 < w < 1) at some executable delay ([S-11])."""
    if row.step == "algorithm1" or not row.sampler.startswith("train_"):
        return "algorithm1"
    t = (_table(row.infer_window, task.execute_horizon, range(task.max_delay + 1)) if row.sampler == "train_soft"
         else np.zeros((1, H)))
    return row.step if bool(np.any((t > 0) & (t < 1))) else "algorithm1"


def eval_key(row: Row, task: ArmTask) -> str:
    """Rows with equal checkpoints and equal samplers produce the same episodes and share them.

    The solver step is part of the key only where it changes a chunk, so the keys of rows with
    Algorithm 1's step (every committed cell) are those they had before steps could be chosen."""
    ident = (train_key(row, task), _sampler_table(row, task))
    step = _sampler_step(row, task)
    ident = ident if step == "algorithm1" else ident + (step,)
    # T enters the key only when it is not the arm policies' 5, so every T = 5 row keeps its key ([AX-10]).
    raw = repr(ident if row.num_steps == 5 else ident + (("T", row.num_steps),)).encode()
    return hashlib.sha256(raw).hexdigest()[:16]


@dataclasses.dataclass(frozen=True)
class Budget:
    """How much a run computes ([AX-4]): seeds, episodes and delays per tier, fine-tune steps."""

    finetune_steps: int = 800
    main_seeds: int = 3
    main_episodes: int = 100
    sweep_seeds: int = 1
    sweep_episodes: int = 50
    prior_episodes: int = 20
    max_steps: int = 1000
    demo_episodes: int = 400
    # None: every sweep row; a tuple names the sweep rows this budget runs.
    sweep_rows: tuple | None = None

    def delays(self, task: ArmTask, tier: str) -> list:
        return tier_delays(task.max_delay, tier)

    def seeds_episodes(self, tier: str) -> tuple:
        """Fine-tuning seeds and episodes per cell of a tier (the T sweep takes the sweep tier's, [AX-10])."""
        return (self.main_seeds, self.main_episodes) if tier == "main" else (self.sweep_seeds, self.sweep_episodes)


def tier_delays(max_delay: int, tier: str) -> list:
    """Delays a tier runs: every executable delay (main), 0 and the two highest (sweep), 0, 2, 4 (T sweep)."""
    if tier == "main":
        return list(range(max_delay + 1))
    if tier == "tsweep":
        return [d for d in (0, 2, 4) if d <= max_delay]
    return [0, max_delay - 1, max_delay]


BUDGETS = {
    "full": Budget(),
    "quick": Budget(finetune_steps=4, main_seeds=1, main_episodes=2, sweep_seeds=1, sweep_episodes=1,
                    prior_episodes=1, max_steps=60, demo_episodes=4,
                    sweep_rows=("soft1_clip", "offset0_zeros", "offset6_clip", "offset6_zeros")),
}
