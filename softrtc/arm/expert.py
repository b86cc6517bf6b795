"""Scripted IK/waypoint expert for the arm sorting task (spec chapter A).

The expert is a stateless function of the observation ([A-13]): every control
step it re-derives the phase (approach, descend, close, lift, carry, lower,
release) from the observed gripper tip, gripper flags and object poses. Because
nothing is remembered between steps, a perturbed or noisy execution is
re-planned from wherever it ends up, which is what DART-style demonstration
collection needs ([A-15]).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from softrtc.reference._validate import check_int

from ._checks import is_real
from .env import (
    NUM_OBJECTS,
    OBJECT_TARGET_BOX,
    OBS_DIM,
    OBS_SLICES,
    ArmConfig,
    ArmSortEnv,
    inverse_kinematics,
)
from .geometry import _check_env_config, _real_array

__all__ = ["ExpertConfig", "ScriptedExpert", "run_expert_episode", "expert_success_rate"]


@dataclass(frozen=True)
class ExpertConfig:
    """Waypoint geometry and tolerances of the scripted expert ([A-13]). Metres."""

    carry_height: float = 0.15  # gripper tip height for horizontal moves
    lookahead: float = 0.04  # distance of the Cartesian carrot ahead of the tip
    align_tol: float = 0.006  # x/y error at which the gripper may close/open
    lift_tol: float = 0.03  # x error beyond which a low gripper first lifts
    grasp_clearance: float = 0.003  # tip height above the part's top when closing
    drop_clearance: float = 0.008  # part bottom height above the box floor at release

    def __post_init__(self):
        for name in ("carry_height", "lookahead", "align_tol", "lift_tol", "grasp_clearance", "drop_clearance"):
            value = getattr(self, name)
            # NumPy scalars are accepted like Python numbers (stored as float); booleans and huge integers are not.
            if not is_real(value) or value <= 0:
                raise ValueError(f"{name} must be a finite number > 0 (metres), got {value!r}")
            object.__setattr__(self, name, float(value))


class ScriptedExpert:
    """Stateless pick-and-place expert: ``act(obs) -> action`` ([A-13], [A-14]).

    Objects are handled one by one in the order blue0, blue1, silver0,
    silver1; each goes to its own slot in its box so the two parts of a box do
    not land on each other.
    """

    def __init__(self, env_config: ArmConfig | None = None, config: ExpertConfig | None = None):
        self.env_config = _check_env_config(env_config, "env_config")
        self.config = ExpertConfig() if config is None else config
        if not isinstance(self.config, ExpertConfig):
            raise ValueError("config must be an ExpertConfig")
        self._low = np.array(self.env_config.joint_low)
        self._high = np.array(self.env_config.joint_high)

    def slot_x(self, obj: int, box_x: float) -> float:
        """Release x of object ``obj`` (an integer in [0, 3]) in its box with centre ``box_x`` (finite)."""
        obj = check_int("obj", obj, 0, NUM_OBJECTS - 1)
        if not is_real(box_x):
            raise ValueError(f"box_x must be a finite real number (metres), got {box_x!r}")
        inner = self.env_config.box_inner_widths[OBJECT_TARGET_BOX[obj]]
        # Object 0/2 go to the left half, 1/3 to the right half.
        return box_x + (-1.0 if obj % 2 == 0 else 1.0) * inner / 4

    def act(self, obs) -> np.ndarray:
        """Expert action for observation ``obs`` (shape (34,)) ([A-13])."""
        o = _real_array("obs", obs, f"({OBS_DIM},)")  # booleans, strings, ragged lists are not observations
        if o.shape != (OBS_DIM,) or not np.all(np.isfinite(o)):
            raise ValueError(f"obs must be a finite array of shape ({OBS_DIM},)")
        cfg, ec = self.config, self.env_config
        q = o[OBS_SLICES["q"]]
        ee = o[OBS_SLICES["ee"]]
        closed = o[8] > 0.5
        holding = o[9] > 0.5
        objs = o[OBS_SLICES["objects"]].reshape(NUM_OBJECTS, 5)
        boxes = o[OBS_SLICES["boxes"]].reshape(2, 2)

        if holding:
            k = int(np.argmax(objs[:, 3]))
            w, h = ec.object_sizes[k]
            box = OBJECT_TARGET_BOX[k]
            # The part is welded to the tip, so move the tip by the part's error.
            want = np.array([self.slot_x(k, boxes[box, 0]),
                             boxes[box, 1] + h / 2 + cfg.drop_clearance])
            goal = ee + (want - objs[k, :2])
            at_goal = _near(ee, goal, cfg.align_tol)
            grip = 0.0 if at_goal else 1.0
            return self._action(q, ee, goal, grip)

        if closed:
            # Closed on nothing: open first so the next close can grasp.
            return self._action(q, ee, ee, 0.0)

        # A part below the table top fell beside the table and the trays, out of reach ([A-27]): skipped.
        todo = [i for i in range(NUM_OBJECTS) if objs[i, 4] < 0.5 and objs[i, 1] >= 0.0]
        if not todo:
            return self._action(q, ee, np.array([ee[0], max(ee[1], cfg.carry_height)]), 0.0)
        k = todo[0]
        w, h = ec.object_sizes[k]
        x, y, ang = objs[k, :3]
        top = y + 0.5 * (abs(w * math.sin(ang)) + abs(h * math.cos(ang)))
        goal = np.array([x, top + cfg.grasp_clearance])
        grip = 1.0 if _near(ee, goal, cfg.align_tol) else 0.0
        return self._action(q, ee, goal, grip)

    def _action(self, q, ee, goal, grip) -> np.ndarray:
        cfg = self.config
        # Lift before travelling sideways so a carried part clears walls and parts.
        if abs(ee[0] - goal[0]) > cfg.lift_tol:
            if ee[1] < cfg.carry_height - cfg.lift_tol:
                target = np.array([ee[0], cfg.carry_height])
            else:
                target = np.array([goal[0], max(cfg.carry_height, goal[1])])
        else:
            target = goal
        delta = target - ee
        dist = float(np.hypot(*delta))
        carrot = ee + delta * (min(dist, cfg.lookahead) / dist) if dist > 1e-12 else ee.copy()
        try:
            qt = inverse_kinematics(carrot, self.env_config)
        except ValueError:
            qt = np.array(q, dtype=np.float64)  # unreachable carrot: hold still
        qt = np.clip(qt, self._low, self._high)
        return np.concatenate([qt, [grip]])


def _near(a, b, tol) -> bool:
    return abs(a[0] - b[0]) <= tol and abs(a[1] - b[1]) <= tol


def run_expert_episode(seed, env_config: ArmConfig | None = None,
                       expert_config: ExpertConfig | None = None) -> dict:
    """Run the clean expert for one seeded episode ([A-14]).

    Returns ``success``, ``completed``, ``steps`` and ``success_step``.
    """
    seed = check_int("seed", seed, 0, None)
    env_config = _check_env_config(env_config, "env_config")
    if expert_config is not None and not isinstance(expert_config, ExpertConfig):
        raise ValueError(f"expert_config must be an ExpertConfig or None, got {type(expert_config).__name__}")
    env = ArmSortEnv(env_config)
    expert = ScriptedExpert(env.config, expert_config)
    obs = env.reset(seed)
    info = {"success": False, "completed": [False] * NUM_OBJECTS, "success_step": None}
    while not env.done:
        obs, info = env.step(expert.act(obs))
    return {"success": info["success"], "completed": info["completed"],
            "steps": env.t, "success_step": info["success_step"]}


def expert_success_rate(n=100, seed0=0, verbose=True) -> float:
    """Fraction of seeds ``seed0 .. seed0+n-1`` the clean expert solves ([A-14]).

    Prints the rate, mean completion time and wall time when ``verbose``.
    """
    n = check_int("n", n, 1, None)
    seed0 = check_int("seed0", seed0, 0, None)
    start = time.perf_counter()  # reporting only; the simulation never reads a clock
    results = [run_expert_episode(seed0 + i) for i in range(n)]
    elapsed = time.perf_counter() - start
    rate = sum(r["success"] for r in results) / n
    if verbose:
        steps = [r["success_step"] for r in results if r["success"]]
        mean_steps = float(np.mean(steps)) if steps else float("nan")
        failed = [seed0 + i for i, r in enumerate(results) if not r["success"]]
        print(f"expert success rate {rate:.3f} over {n} episodes (seeds {seed0}..{seed0 + n - 1}); "
              f"mean completion {mean_steps:.1f} steps; {elapsed:.1f} s total, "
              f"{elapsed / n:.3f} s/episode; failed seeds {failed}")
    return rate
