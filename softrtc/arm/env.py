"""Planar pymunk arm that sorts four parts into two boxes: the environment (spec chapter A).

The scene lives in a vertical plane (x to the right, y up, metres, gravity
-9.81 m/s^2 along y). A three-link arm is mounted on a static pedestal; its
revolute joints are driven by rate-controlled motors that track commanded
joint position targets. A virtual gripper at the tip of the last link welds an
object to the link when it closes with the object within reach. Two large blue
parts belong in the blue box and two small silver parts in the gray box.

This module holds the environment: ``reset``, the control step, the gripper,
completion and the observation. The scene's configuration and kinematics are
in :mod:`softrtc.arm.geometry`, the building of the pymunk scene in
:mod:`softrtc.arm.scene`, drawing in :mod:`softrtc.arm.render`; their public
names are importable from here too.

Requirement ids cited below refer to ``spec/10-arm.md``.
"""

from __future__ import annotations

import math

import numpy as np
import pymunk

from softrtc.reference._validate import check_int

from .geometry import (
    NUM_JOINTS,
    NUM_OBJECTS,
    OBJECT_NAMES,
    OBJECT_TARGET_BOX,
    ArmConfig,
    _real_array,
    _validate_config,
    forward_kinematics,
    inverse_kinematics,
)
from .render import render_scene
from .scene import Scene, build_scene

__all__ = [
    "ArmConfig",
    "ArmSortEnv",
    "OBJECT_NAMES",
    "OBJECT_TARGET_BOX",
    "NUM_JOINTS",
    "NUM_OBJECTS",
    "OBS_DIM",
    "ACTION_DIM",
    "OBS_SLICES",
    "forward_kinematics",
    "inverse_kinematics",
]

_OBJ_FIELDS = 5  # x, y, angle, held, placed

# observation layout (half-open index ranges into the flat vector).
OBS_SLICES = {
    "q": slice(0, 3),
    "qdot": slice(3, 6),
    "ee": slice(6, 8),
    "gripper_closed": slice(8, 9),
    "holding": slice(9, 10),
    "objects": slice(10, 10 + NUM_OBJECTS * _OBJ_FIELDS),
    "boxes": slice(30, 34),
}
OBS_DIM = 34
ACTION_DIM = NUM_JOINTS + 1


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi



class ArmSortEnv:
    """Arm sorting environment ([A-1]..[A-12]).

    ``reset(seed) -> obs`` and ``step(action) -> (obs, info)``; see
    ``spec/10-arm.md`` for the observation and action layouts.
    """

    obs_dim = OBS_DIM
    action_dim = ACTION_DIM

    def __init__(self, config: ArmConfig | None = None):
        cfg = ArmConfig() if config is None else config
        _validate_config(cfg)
        self.config = cfg
        self.joint_low = np.array(cfg.joint_low, dtype=np.float64)
        self.joint_high = np.array(cfg.joint_high, dtype=np.float64)
        self.action_low = np.concatenate([self.joint_low, [0.0]])
        self.action_high = np.concatenate([self.joint_high, [1.0]])
        self._scene: Scene | None = None
        self._t = 0
        self._done = True
        self._closed = False
        self._success_step = None
        self._targets = np.zeros(NUM_JOINTS)

    # ------------------------------------------------------------------ reset
    def reset(self, seed) -> np.ndarray:
        """Build a fresh scene with seeded object placement ([A-5], [A-6])."""
        seed = check_int("seed", seed, 0, None)
        self._scene, q0 = build_scene(self.config, np.random.default_rng(seed))
        self._targets = q0.copy()
        self._t = 0
        self._done = False
        self._closed = False
        self._success_step = None
        return self._observe()

    # ------------------------------------------------------------------- step
    def step(self, action):
        """Apply one control step ([A-4], [A-8], [A-9], [A-10], [A-11])."""
        if self._scene is None:
            raise RuntimeError("call reset(seed) before step(action)")
        if self._done:
            raise RuntimeError("episode is done; call reset(seed)")
        a = self.validate_action(action)
        cfg = self.config
        sc = self._scene
        self._targets = a[:NUM_JOINTS].copy()
        close = bool(a[NUM_JOINTS] > 0.5)
        if close and not self._closed:
            self._try_grasp()
        elif not close and self._closed:
            self._release()
        self._closed = close

        h = cfg.physics_dt
        kp, vmax = cfg.motor_gain, cfg.motor_max_rate
        targets = [float(x) for x in self._targets]
        pairs = list(zip(sc.links, sc.motors, targets))
        space = sc.space
        boxes = sc.box_bodies
        for b, hops in enumerate(sc.hops):
            # a hop starting at this step's tick sets the box's new destination.
            if self._t in hops:
                sc.box_goals[b] = hops[self._t]
        # Plain floats here: this loop dominates the cost of an episode.
        for _ in range(cfg.substeps):
            for b, body in enumerate(boxes):
                # Toward the destination at box_hop_speed, landing on it exactly within a substep.
                v = (sc.box_goals[b] - body.position.x) / h
                speed = cfg.box_hop_speed
                body.velocity = (speed if v > speed else (-speed if v < -speed else v), 0.0)
            prev = -math.pi / 2
            for body, motor, target in pairs:
                angle = body.angle
                rate = kp * (target - (angle - prev))
                prev = angle
                rate = vmax if rate > vmax else (-vmax if rate < -vmax else rate)
                # pymunk's SimpleMotor drives b.w - a.w to -rate.
                motor.rate = -rate
            space.step(h)
        for b, body in enumerate(boxes):
            sc.box_centers[b] = body.position.x
        self._t += 1
        completed = self.completed()
        success = bool(all(completed))
        if success and self._success_step is None:
            self._success_step = self._t
        self._done = success or self._t >= cfg.max_steps
        info = {
            "t": self._t,
            "time_s": self._t * cfg.dt,
            "success": success,
            "completed": completed,
            "num_completed": int(sum(completed)),
            "done": self._done,
            "success_step": self._success_step,
            "success_time_s": None if self._success_step is None else self._success_step * cfg.dt,
            "holding": sc.held,
        }
        return self._observe(), info

    def validate_action(self, action) -> np.ndarray:
        """Return ``action`` as float64 or raise ValueError ([A-8])."""
        a = _real_array("action", action, f"({ACTION_DIM},)")  # booleans, strings, ragged lists are not actions
        if a.shape != (ACTION_DIM,):
            raise ValueError(f"action must have shape ({ACTION_DIM},), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a!r}")
        bad = np.nonzero((a < self.action_low) | (a > self.action_high))[0]
        if bad.size:
            i = int(bad[0])
            raise ValueError(
                f"action[{i}] = {a[i]!r} is outside its allowed range "
                f"[{self.action_low[i]!r}, {self.action_high[i]!r}]")
        return a

    # --------------------------------------------------------------- gripper
    def _ee_position(self) -> np.ndarray:
        last = self._scene.links[-1]
        p = last.local_to_world((self.config.link_lengths[-1], 0.0))
        return np.array([p.x, p.y])

    def _try_grasp(self) -> None:
        # pick the object whose surface is nearest the tip, within reach.
        sc = self._scene
        tip = tuple(self._ee_position())
        best, best_d = -1, math.inf
        for i, (_, shape) in enumerate(sc.objects):
            d = shape.point_query(tip).distance
            # reach is inclusive (<=); strict < keeps the lowest index on ties.
            if d <= self.config.grasp_radius and d < best_d:
                best, best_d = i, d
        if best < 0:
            return
        body = sc.objects[best][0]
        last = sc.links[-1]
        pin = pymunk.PivotJoint(last, body, tip)
        lock = pymunk.GearJoint(last, body, body.angle - last.angle, 1.0)
        sc.space.add(pin, lock)
        sc.grasp = [pin, lock]
        sc.held = best

    def _release(self) -> None:
        sc = self._scene
        if sc.grasp:
            sc.space.remove(*sc.grasp)
        sc.grasp = []
        sc.held = -1

    # ----------------------------------------------------------- measurement
    def completed(self) -> list[bool]:
        """Per-object completion: object in its own box and not held ([A-10])."""
        return [self._in_box(i, OBJECT_TARGET_BOX[i]) for i in range(NUM_OBJECTS)]

    def _in_box(self, i: int, box: int) -> bool:
        sc = self._scene
        if sc.held == i:
            return False
        cfg = self.config
        body = sc.objects[i][0]
        x, y = body.position
        half = cfg.box_inner_widths[box] / 2
        cx = sc.box_centers[box]
        return bool(abs(x - cx) < half and 0.0 <= y <= cfg.box_wall_height)

    def _joint_state(self):
        links = self._scene.links
        q = np.empty(NUM_JOINTS)
        qd = np.empty(NUM_JOINTS)
        prev_a, prev_w = -math.pi / 2, 0.0
        for i, b in enumerate(links):
            q[i] = b.angle - prev_a
            qd[i] = b.angular_velocity - prev_w
            prev_a, prev_w = b.angle, b.angular_velocity
        return q, qd

    def joint_positions(self) -> np.ndarray:
        """Current joint positions ``q`` (rad), shape (3,) ([A-2])."""
        if self._scene is None:
            raise RuntimeError("call reset(seed) first")
        return self._joint_state()[0]

    def box_centers(self) -> np.ndarray:
        """x of the blue and gray box centres (m), shape (2,) ([A-5])."""
        if self._scene is None:
            raise RuntimeError("call reset(seed) first")
        return self._scene.box_centers.copy()

    @property
    def t(self) -> int:
        """Control steps taken since reset."""
        return self._t

    @property
    def done(self) -> bool:
        return self._done

    def _observe(self) -> np.ndarray:
        sc = self._scene
        q, qd = self._joint_state()
        obs = np.empty(OBS_DIM, dtype=np.float64)
        obs[OBS_SLICES["q"]] = q
        obs[OBS_SLICES["qdot"]] = qd
        obs[OBS_SLICES["ee"]] = self._ee_position()
        obs[8] = 1.0 if self._closed else 0.0
        obs[9] = 1.0 if sc.held >= 0 else 0.0
        completed = self.completed()
        k = OBS_SLICES["objects"].start
        for i, (body, _) in enumerate(sc.objects):
            obs[k:k + 5] = (body.position.x, body.position.y, _wrap(body.angle),
                            1.0 if sc.held == i else 0.0, 1.0 if completed[i] else 0.0)
            k += 5
        obs[30:34] = (sc.box_centers[0], 0.0, sc.box_centers[1], 0.0)
        return obs

    def render(self, ax=None):
        """Draw the scene with matplotlib (optional, for inspection)."""
        if self._scene is None:
            raise RuntimeError("call reset(seed) first")
        return render_scene(self._scene, self.config, ax)
