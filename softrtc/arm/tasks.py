"""Arm task settings of the experiment: ``easy``, ``overlap4`` and ``drift`` ([AX-1], [AX-8]).

A task is an environment config plus the execute horizon ``s`` the policies
run with (the chunk horizon stays ``H = 10``, so the shipped base policy,
trained without delays, serves every task). ``easy`` is the study's setting
([A-17]: ``s = 5``, overlap ``H - s = 5``, delays ``0 .. 5``). ``overlap4``
runs ``s = 6``: the overlap is ``H - s = 4`` and the executable delays are
``0 .. 4``, the geometry of the paper's main setting (``H = 8, s = 4``:
overlap 4, delays ``0 .. 4``), so the paper's window (``lam = 2``,
``h_max = 5``) runs past the overlap at ``d = 3, 4`` exactly as there ([W-6]),
and every chunk executes six ticks open loop, more of them from an older plan
as the delay grows. Neither setting is delay-sensitive for the base policy
(measured in [AX-1]: the naive base solves about as often at the largest
delay as at ``d = 0``). ``drift`` is: its boxes are trays that hop at random
times ([A-27]), so a plan made before a hop releases the part where the tray
was, and a part that misses a tray falls out of reach ([AX-8]); it has its own
demonstrations and base (``checkpoints/drift/base.npz``). ``drift_overlap4``
runs that world and base with ``s = 6`` (overlap 4, delays ``0 .. 4``), where
zero padding and ``clip`` differ; it is less delay-sensitive ([AX-8]).
"""

from __future__ import annotations

import dataclasses

from .env import ArmConfig

__all__ = ["ArmTask", "TASKS", "DRIFT_CONFIG", "get_task"]


@dataclasses.dataclass(frozen=True)
class ArmTask:
    """A named setting: environment config and execute horizon ``s`` (``H`` is the policy's, 10)."""

    name: str
    execute_horizon: int
    env_config: ArmConfig = dataclasses.field(default_factory=ArmConfig)
    description: str = ""
    # Folder of the task's base under the shipped checkpoints ("" = the shipped base of ).
    checkpoint_subdir: str = ""

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"name must be a non-empty string, got {self.name!r}")
        if isinstance(self.execute_horizon, bool) or not isinstance(self.execute_horizon, int) \
                or not 1 <= self.execute_horizon <= 9:
            raise ValueError(f"execute_horizon must be an integer in [1, 9] (H = 10), got {self.execute_horizon!r}")
        if not isinstance(self.env_config, ArmConfig):
            raise ValueError(f"env_config must be an ArmConfig, got {type(self.env_config).__name__}")
        if not isinstance(self.checkpoint_subdir, str) or "/" in self.checkpoint_subdir \
                or self.checkpoint_subdir in (".", ".."):
            raise ValueError(f"checkpoint_subdir must be a folder name or '', got {self.checkpoint_subdir!r}")

    def base_checkpoint(self):
        """The task's shipped base checkpoint ([A-21], [AX-8]), read through the package's data folder."""
        from .checkpoints import default_checkpoint_dir

        return default_checkpoint_dir() / self.checkpoint_subdir / "base.npz" if self.checkpoint_subdir \
            else default_checkpoint_dir() / "base.npz"

    @property
    def max_delay(self) -> int:
        """Largest executable delay ``min(s, H - s)`` with ``H = 10`` ([X-1])."""
        return min(self.execute_horizon, 10 - self.execute_horizon)


# [AX-8] moving trays: the table is the pick region only, parts start nearer its middle, the trays hop.
DRIFT_CONFIG = ArmConfig(table_half_width=0.17, object_x_range=(-0.13, 0.13), object_min_gap=0.015,
                         box_center_jitter=0.0, box_inner_widths=(0.18, 0.12), box_hop_range=0.06,
                         box_hop_speed=0.3, box_hop_interval=(7, 28), tray_rim_height=0.005)

TASKS = {
    "easy": ArmTask("easy", 5, ArmConfig(), "the study's setting: s = 5, delays 0..5"),
    "overlap4": ArmTask("overlap4", 6, ArmConfig(), "s = 6, overlap 4, delays 0..4 (the paper's overlap geometry)"),
    "drift": ArmTask("drift", 5, DRIFT_CONFIG, "hopping trays: s = 5, delays 0..5, its own base", "drift"),
    "drift_overlap4": ArmTask("drift_overlap4", 6, DRIFT_CONFIG,
                              "hopping trays with s = 6, overlap 4, delays 0..4: drift's base, overlap4's geometry",
                              "drift"),
}


def get_task(name: str) -> ArmTask:
    """The task named ``name`` (one of :data:`TASKS`)."""
    if not isinstance(name, str) or name not in TASKS:
        raise ValueError(f"task must be one of {tuple(TASKS)}, got {name!r}")
    return TASKS[name]
