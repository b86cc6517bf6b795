"""Building the pymunk scene of the arm task: table, boxes, arm and parts ([A-1], [A-3], [A-5], [A-6]).

:func:`build_scene` makes a fresh space from an :class:`ArmConfig` and a
seeded generator: the table, the two boxes at jittered centres, the arm at
rest with its tip at ``home_ee``, and the four parts placed on the table by
rejection sampling. The environment (:mod:`softrtc.arm.env`) steps it.

Requirement ids cited below refer to ``spec/10-arm.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pymunk

from .geometry import NUM_JOINTS, NUM_OBJECTS, ArmConfig, _ik

__all__ = ["Scene", "build_scene", "hop_schedule", "sample_part_x", "PLACEMENT_ATTEMPTS", "BIN_Y"]

# top of the bin under a table with moving trays (m): below the arm's reach.
BIN_Y = -0.4

# attempts of the part placement before reset gives up.
PLACEMENT_ATTEMPTS = 10_000

# Collision categories: arm links collide with nothing ([A-3]).
_CAT_WORLD = 0b01
_CAT_OBJECT = 0b10
_ARM_FILTER = pymunk.ShapeFilter(categories=0b100, mask=0)
_WORLD_FILTER = pymunk.ShapeFilter(categories=_CAT_WORLD, mask=_CAT_OBJECT)
_OBJECT_FILTER = pymunk.ShapeFilter(categories=_CAT_OBJECT, mask=_CAT_WORLD | _CAT_OBJECT)


@dataclass
class Scene:
    """The pymunk space of one episode and the handles the environment steps and reads."""

    space: pymunk.Space
    links: list
    motors: list
    objects: list
    box_centers: np.ndarray
    grasp: list = field(default_factory=list)
    held: int = -1
    # moving boxes: a kinematic body per box, its hop schedule (start tick -> destination x) and the
    # destination it is moving to; empty and unused while the boxes are static.
    box_bodies: list = field(default_factory=list)
    hops: list = field(default_factory=list)
    box_goals: np.ndarray | None = None


def build_scene(cfg: ArmConfig, rng: np.random.Generator) -> tuple[Scene, np.ndarray]:
    """A fresh scene of a checked ``cfg``, and the arm's joint positions at rest ([A-1], [A-5], [A-6])."""
    space = pymunk.Space()
    space.gravity = (0.0, -9.81)
    # Metre-scale scene: the default 0.1 slop would let parts sink 10 cm.
    space.collision_slop = 0.0005
    space.iterations = 20
    static = space.static_body
    table = pymunk.Segment(static, (-cfg.table_half_width, -0.01), (cfg.table_half_width, -0.01), 0.01)
    table.friction = 1.0
    table.filter = _WORLD_FILTER
    space.add(table)
    # Boxes: two walls standing on the table; the table is the box floor.
    centers = np.array(cfg.box_centers, dtype=np.float64) + rng.uniform(
        -cfg.box_center_jitter, cfg.box_center_jitter, size=2)
    moving = cfg.box_hop_range > 0
    box_bodies = []
    for cx, inner in zip(centers, cfg.box_inner_widths):
        # Static boxes keep their walls on the static body, so the default scene is unchanged by.
        if moving:
            # A tray: kinematic body carrying its own floor (top at y = 0) and walls ([A-27]).
            body = pymunk.Body(body_type=pymunk.Body.KINEMATIC)
            body.position = (float(cx), 0.0)
            reach = inner / 2 + cfg.box_wall_thickness
            floor = pymunk.Segment(body, (-reach, -0.01), (reach, -0.01), 0.01)
            floor.friction = 1.0
            floor.filter = _WORLD_FILTER
            space.add(body, floor)
            box_bodies.append(body)
            owner, x0, top = body, 0.0, cfg.tray_rim_height
        else:
            owner, x0, top = static, cx, cfg.box_wall_height
        for side in (-1.0, 1.0):
            x = x0 + side * (inner / 2 + cfg.box_wall_thickness / 2)
            wall = pymunk.Poly(owner, [
                (x - cfg.box_wall_thickness / 2, 0.0), (x + cfg.box_wall_thickness / 2, 0.0),
                (x + cfg.box_wall_thickness / 2, top),
                (x - cfg.box_wall_thickness / 2, top)])
            wall.friction = 0.8
            wall.filter = _WORLD_FILTER
            space.add(wall)

    # Arm: each link body has its origin at its proximal joint; the tip starts at home_ee, link 3 down ([A-2]).
    q0 = _ik(np.array(cfg.home_ee, dtype=np.float64), cfg, -math.pi / 2)
    links, motors = [], []
    prev = static
    theta = -math.pi / 2
    origin = np.array(cfg.base, dtype=np.float64)
    for i in range(NUM_JOINTS):
        theta += q0[i]
        length = cfg.link_lengths[i]
        body = pymunk.Body()
        body.position = tuple(origin)
        body.angle = theta
        seg = pymunk.Segment(body, (0, 0), (length, 0), cfg.link_radius)
        seg.mass = cfg.link_masses[i]
        seg.filter = _ARM_FILTER
        pivot = pymunk.PivotJoint(prev, body, tuple(origin))
        motor = pymunk.SimpleMotor(prev, body, 0.0)
        motor.max_force = cfg.motor_max_force
        space.add(body, seg, pivot, motor)
        links.append(body)
        motors.append(motor)
        prev = body
        origin = origin + length * np.array([math.cos(theta), math.sin(theta)])

    objects = []
    xs = sample_part_x(cfg, rng)
    for i in range(NUM_OBJECTS):
        w, h = cfg.object_sizes[i]
        body = pymunk.Body()
        body.position = (float(xs[i]), h / 2)
        shape = pymunk.Poly.create_box(body, (w, h), radius=0.0)
        shape.mass = cfg.object_masses[i]
        shape.friction = cfg.object_friction
        shape.filter = _OBJECT_FILTER
        space.add(body, shape)
        objects.append((body, shape))
    scene = Scene(space, links, motors, objects, centers)
    if moving:
        # Beside the table and the trays there is nothing: a part that misses falls into a bin out of reach.
        bin_ = pymunk.Segment(static, (-2.0, BIN_Y - 0.01), (2.0, BIN_Y - 0.01), 0.01)
        bin_.friction = 1.0
        bin_.filter = _WORLD_FILTER
        space.add(bin_)
        scene.box_bodies = box_bodies
        scene.hops = hop_schedule(cfg, centers, rng)
        scene.box_goals = centers.copy()
    return scene, q0


def hop_schedule(cfg: ArmConfig, centers: np.ndarray, rng: np.random.Generator) -> list:
    """Per box, the hops of a whole episode: ``{start tick: destination x}`` ([A-27]).

    Drawn after the part placement, box 0 first: each gap to the next hop start
    is an integer uniform on ``box_hop_interval`` (inclusive), then its
    destination is uniform on ``centre +- box_hop_range``; draws stop at the
    first start at or past ``max_steps``.
    """
    lo, hi = cfg.box_hop_interval
    out = []
    for c in centers:
        hops, t = {}, 0
        while True:
            t += int(rng.integers(lo, hi + 1))
            if t >= cfg.max_steps:
                break
            hops[t] = float(c + rng.uniform(-cfg.box_hop_range, cfg.box_hop_range))
        out.append(hops)
    return out


def sample_part_x(cfg: ArmConfig, rng: np.random.Generator) -> np.ndarray:
    """Centres x of the four parts on the table, at least ``object_min_gap`` apart ([A-5])."""
    lo, hi = cfg.object_x_range
    widths = np.array([s[0] for s in cfg.object_sizes])
    # rejection sampling: each attempt redraws all four centres in one call; the configuration check
    # guarantees a valid placement exists, and a range so tight that 10,000 attempts miss it raises.
    for _ in range(PLACEMENT_ATTEMPTS):
        xs = rng.uniform(lo, hi, size=NUM_OBJECTS)
        ok = True
        for i in range(NUM_OBJECTS):
            for j in range(i + 1, NUM_OBJECTS):
                if abs(xs[i] - xs[j]) < (widths[i] + widths[j]) / 2 + cfg.object_min_gap:
                    ok = False
        if ok:
            return xs
    raise ValueError(f"config.object_x_range {cfg.object_x_range!r} is too narrow: {PLACEMENT_ATTEMPTS} "
                     f"placements of the parts with config.object_min_gap failed for this seed ([A-5])")
