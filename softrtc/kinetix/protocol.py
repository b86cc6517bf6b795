"""The Kinetix evaluation protocol ([KE-1]): its constants and :class:`EvalConfig`.

Every method of chapter S ([S-6]) is run in closed loop on the benchmark
levels with the asynchronous executor of chapter X: execute horizon
``s = 4``, delays ``d in {0, .., 4}``, 5 flow steps, ``N`` episodes per
(level, delay, method), 256 control steps per episode, metrics of chapter M
on the executed actions up to the end of each env's first episode.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Any

from softrtc.reference import metrics as ref_metrics
from softrtc.reference._validate import check_int

from . import env as kenv
from .limits import EPISODE_STEPS_MAX, EPISODE_STEPS_MIN, EPISODES_MAX
from .methods import PAPER_METHODS, MethodSpec, parse_method

__all__ = ["EXECUTE_HORIZON", "DELAYS", "NUM_FLOW_STEPS", "EPISODES", "EPISODE_STEPS", "HIGH_DELAYS", "EvalConfig"]

# [KE-1] the protocol of the paper's Experimental Setup.
EXECUTE_HORIZON = 4
DELAYS = (0, 1, 2, 3, 4)
NUM_FLOW_STEPS = 5
EPISODES = 32
EPISODE_STEPS = kenv.MAX_TIMESTEPS
HIGH_DELAYS = ref_metrics.HIGH_DELAYS

@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """The evaluation protocol ([KE-1]); every field is validated.

    ``methods`` holds method strings (:func:`parse_method`) or
    :class:`MethodSpec`s. ``seed`` fixes every random draw ([KE-5]).
    """

    levels: tuple = kenv.LEVEL_NAMES
    methods: tuple = PAPER_METHODS
    delays: tuple = DELAYS
    episodes: int = EPISODES
    execute_horizon: int = EXECUTE_HORIZON
    num_flow_steps: int = NUM_FLOW_STEPS
    episode_steps: int = EPISODE_STEPS
    seed: int = 0
    levels_dir: str | None = None
    bootstrap_resamples: int = 10000
    bootstrap_seed: int = 0

    def __post_init__(self):
        levels = _as_tuple("levels", self.levels, "distinct level names", single=(str,))
        for lv in levels:
            if not isinstance(lv, str):
                kenv.check_level_name(lv, "levels entries")
        if not levels or len(set(levels)) != len(levels):
            raise ValueError(f"levels must be a non-empty sequence of distinct level names, got {self.levels!r}")
        for lv in levels:
            kenv.check_level_name(lv, "levels entries")
        object.__setattr__(self, "levels", levels)
        meths = tuple(m if isinstance(m, MethodSpec) else parse_method(m) for m in
                      _as_tuple("methods", self.methods, "distinct methods", single=(str, MethodSpec)))
        if not meths or len({m.label for m in meths}) != len(meths):
            raise ValueError(f"methods must be a non-empty sequence of distinct methods, got {self.methods!r}")
        seen: dict = {}
        for m in meths:  # [KE-2] two spellings of one method, window and step (lam 2 and 2.0) are one method
            same = seen.setdefault((m.method, m.window, m.step), m.label)
            if same != m.label:
                raise ValueError(f"methods must be distinct methods: {same!r} and {m.label!r} are the same method "
                                 f"and window, with the same solver step")
        object.__setattr__(self, "methods", meths)
        s = check_int("execute_horizon", self.execute_horizon, 1, 1 << 12)
        ds = _as_tuple("delays", self.delays, f"distinct integers in [0, {s}]")
        for d in ds:
            check_int("delays entries", d, 0, s)
        if not ds or len(set(ds)) != len(ds):
            raise ValueError(f"delays must be a non-empty sequence of distinct integers in [0, {s}], "
                             f"got {self.delays!r}")
        for d in ds:
            check_int("delays entries", d, 0, s)
        object.__setattr__(self, "delays", tuple(int(d) for d in ds))
        check_int("episodes", self.episodes, 1, EPISODES_MAX)
        check_int("num_flow_steps", self.num_flow_steps, 1, 1024)
        check_int("episode_steps", self.episode_steps, EPISODE_STEPS_MIN, EPISODE_STEPS_MAX)
        check_int("seed", self.seed, 0, 2**32 - 1)
        check_int("bootstrap_resamples", self.bootstrap_resamples, 1, 10**7)
        check_int("bootstrap_seed", self.bootstrap_seed, 0, 2**32 - 1)
        if self.levels_dir is not None and not isinstance(self.levels_dir, (str, os.PathLike)):
            raise ValueError(f"levels_dir must be a path or None, got {type(self.levels_dir).__name__}")


def _as_tuple(name: str, value: Any, what: str, single: tuple = ()) -> tuple:
    """``value`` as a tuple ([N-7]): an instance of ``single`` is a one-entry sequence; any other
    non-iterable (``delays=3``) or a string where a string is no entry is a ``ValueError`` naming ``name``."""
    if single and isinstance(value, single):
        return (value,)
    if not isinstance(value, (str, bytes)):
        try:
            return tuple(value)
        except TypeError:  # not iterable, e.g. a bare integer or a 0-d array
            pass
    raise ValueError(f"{name} must be a non-empty sequence of {what}, got {value!r}")
