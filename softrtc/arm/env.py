"""Planar pymunk arm that sorts four parts into two boxes (spec chapter A).

The scene lives in a vertical plane (x to the right, y up, metres, gravity
-9.81 m/s^2 along y). A three-link arm is mounted on a static pedestal; its
revolute joints are driven by rate-controlled motors that track commanded
joint position targets. A virtual gripper at the tip of the last link welds an
object to the link when it closes with the object within reach. Two large blue
parts belong in the blue box and two small silver parts in the gray box.

Requirement ids cited below refer to ``spec/10-arm.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pymunk

from softrtc.reference._validate import check_int, real_array

from ._checks import is_real

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

NUM_JOINTS = 3
NUM_OBJECTS = 4
# object order in observations and info: blue0, blue1, silver0, silver1.
OBJECT_NAMES = ("blue0", "blue1", "silver0", "silver1")
# Box index per object: 0 = blue box, 1 = gray box.
OBJECT_TARGET_BOX = (0, 0, 1, 1)
_OBJ_FIELDS = 5  # x, y, angle, held, placed
# attempts of the part placement before reset gives up.
PLACEMENT_ATTEMPTS = 10_000

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

# Collision categories: arm links collide with nothing ([A-3]).
_CAT_WORLD = 0b01
_CAT_OBJECT = 0b10
_ARM_FILTER = pymunk.ShapeFilter(categories=0b100, mask=0)
_WORLD_FILTER = pymunk.ShapeFilter(categories=_CAT_WORLD, mask=_CAT_OBJECT)
_OBJECT_FILTER = pymunk.ShapeFilter(categories=_CAT_OBJECT, mask=_CAT_WORLD | _CAT_OBJECT)


@dataclass(frozen=True)
class ArmConfig:
    """Geometry, dynamics and episode constants of the arm scene ([A-1]..[A-12]).

    All lengths are metres, masses kilograms, angles radians, times seconds.
    """

    control_hz: int = 50
    substeps: int = 10
    max_steps: int = 1000
    base: tuple[float, float] = (0.0, 0.45)
    link_lengths: tuple[float, float, float] = (0.30, 0.28, 0.10)
    link_masses: tuple[float, float, float] = (1.0, 0.8, 0.3)
    link_radius: float = 0.012
    joint_low: tuple[float, float, float] = (-math.pi, -3.0, -math.pi)
    joint_high: tuple[float, float, float] = (math.pi, 3.0, math.pi)
    motor_gain: float = 12.0  # 1/s: commanded joint rate per rad of error
    motor_max_rate: float = 4.0  # rad/s
    motor_max_force: float = 2000.0  # N*m torque limit of each motor
    grasp_radius: float = 0.015
    table_half_width: float = 0.75
    object_sizes: tuple[tuple[float, float], ...] = (
        (0.07, 0.04), (0.07, 0.04), (0.035, 0.03), (0.035, 0.03))
    object_masses: tuple[float, ...] = (0.3, 0.3, 0.1, 0.1)
    object_friction: float = 0.8
    object_x_range: tuple[float, float] = (-0.18, 0.18)
    object_min_gap: float = 0.03
    box_centers: tuple[float, float] = (-0.34, 0.32)
    box_center_jitter: float = 0.02
    box_inner_widths: tuple[float, float] = (0.20, 0.14)
    box_wall_height: float = 0.05
    box_wall_thickness: float = 0.01
    home_ee: tuple[float, float] = (0.0, 0.25)

    def __post_init__(self):
        _validate_config(self)  # every field at construction, like the other config classes ([A-12])

    @property
    def dt(self) -> float:
        """Control period in seconds ([A-4])."""
        return 1.0 / self.control_hz

    @property
    def physics_dt(self) -> float:
        """Fixed physics substep in seconds ([A-4])."""
        return 1.0 / (self.control_hz * self.substeps)


def _real_array(name: str, value, shape_desc: str) -> np.ndarray:
    """``value`` as a float64 array: integer/float dtype only ([N-7]); ragged, boolean, string and complex
    inputs raise ValueError naming ``name`` (no conversion). Shape and finiteness are the caller's checks."""
    try:
        return real_array(name, value).astype(np.float64)
    except ValueError as exc:
        raise ValueError(f"{exc} (expected a finite real array of shape {shape_desc})") from None


def _check_env_config(env_config, name: str = "env_config") -> "ArmConfig":
    """``env_config`` checked (an :class:`ArmConfig`), or the default for None; errors name ``name``."""
    if env_config is None:
        return ArmConfig()
    if not isinstance(env_config, ArmConfig):
        raise ValueError(f"{name} must be an ArmConfig or None, got {type(env_config).__name__}")
    _validate_config(env_config)
    return env_config


def _reals(name: str, values, n: int, low: float | None = None, strict: bool = False) -> tuple:
    """``n`` finite real numbers (no booleans), each > low (strict) or >= low."""
    ok = isinstance(values, (tuple, list)) and len(values) == n and all(
        is_real(x) and (low is None or (x > low if strict else x >= low)) for x in values)
    if not ok:
        bound = "" if low is None else f" {'>' if strict else '>='} {low}"
        raise ValueError(f"config.{name} must be {n} finite numbers{bound}, got {values!r}")
    return tuple(values)


def _real(name: str, value, low: float, strict: bool = False) -> None:
    """One finite real number (no boolean) > low (strict) or >= low."""
    try:
        _reals(name, (value,), 1, low, strict)
    except ValueError:
        raise ValueError(f"config.{name} must be a finite number {'>' if strict else '>='} {low}, "
                         f"got {value!r}") from None


def _validate_config(cfg: ArmConfig) -> None:
    """Every field of an :class:`ArmConfig` ([A-1]..[A-12], [N-7]); NaN, booleans and wrong lengths are errors."""
    if not isinstance(cfg, ArmConfig):
        raise ValueError(f"config must be an ArmConfig, got {type(cfg).__name__}")
    check_int("config.control_hz", cfg.control_hz, 1, 10_000)
    check_int("config.substeps", cfg.substeps, 1, 1_000)
    check_int("config.max_steps", cfg.max_steps, 1, None)
    for name in ("motor_gain", "motor_max_rate", "motor_max_force", "grasp_radius", "link_radius",
                 "object_friction", "box_wall_height", "box_wall_thickness", "table_half_width"):
        _real(name, getattr(cfg, name), 0.0, strict=True)
    for name in ("object_min_gap", "box_center_jitter"):
        _real(name, getattr(cfg, name), 0.0)
    _reals("link_lengths", cfg.link_lengths, NUM_JOINTS, 0.0, strict=True)
    _reals("link_masses", cfg.link_masses, NUM_JOINTS, 0.0, strict=True)
    low = _reals("joint_low", cfg.joint_low, NUM_JOINTS)
    high = _reals("joint_high", cfg.joint_high, NUM_JOINTS)
    if any(lo >= hi for lo, hi in zip(low, high)):
        raise ValueError("config.joint_low must be < config.joint_high for every joint")
    _reals("object_masses", cfg.object_masses, NUM_OBJECTS, 0.0, strict=True)
    if not isinstance(cfg.object_sizes, (tuple, list)) or len(cfg.object_sizes) != NUM_OBJECTS:
        raise ValueError(f"config.object_sizes must hold {NUM_OBJECTS} (width, height) pairs, got {cfg.object_sizes!r}")
    for i, size in enumerate(cfg.object_sizes):
        _reals(f"object_sizes[{i}]", size, 2, 0.0, strict=True)
    lo, hi = _reals("object_x_range", cfg.object_x_range, 2)
    if not lo < hi:
        raise ValueError("config.object_x_range must satisfy low < high")
    _reals("base", cfg.base, 2)
    _reals("box_centers", cfg.box_centers, 2)
    _reals("box_inner_widths", cfg.box_inner_widths, 2, 0.0, strict=True)
    _reals("home_ee", cfg.home_ee, 2)
    _validate_layout(cfg)


def _validate_layout(cfg: ArmConfig) -> None:
    """Cross-field geometry of [A-5] and [A-12]: every check names the field it rejects."""
    half = cfg.table_half_width
    # Parts rest on the table: every centre in object_x_range keeps the widest part on it.
    lo, hi = cfg.object_x_range
    widths = sorted(float(s[0]) for s in cfg.object_sizes)
    if lo - widths[-1] / 2 < -half or hi + widths[-1] / 2 > half:
        raise ValueError(f"config.object_x_range must keep every part on the table: low - {widths[-1] / 2!r} >= "
                         f"{-half!r} and high + {widths[-1] / 2!r} <= {half!r}, got {cfg.object_x_range!r}")
    # Some placement meets object_min_gap: the two widest parts at the ends gives the shortest row of centres.
    need = sum(widths) - (widths[-1] + widths[-2]) / 2 + (NUM_OBJECTS - 1) * cfg.object_min_gap
    if hi - lo < need:
        raise ValueError(f"config.object_x_range is too narrow: high - low must be >= {need!r} for the parts of "
                         f"config.object_sizes with config.object_min_gap, got {cfg.object_x_range!r}")
    # Boxes stand on the table for every jitter draw, and the two never overlap.
    spans = []
    for i, (c, inner) in enumerate(zip(cfg.box_centers, cfg.box_inner_widths)):
        reach = inner / 2 + cfg.box_wall_thickness + cfg.box_center_jitter
        if c - reach < -half or c + reach > half:
            raise ValueError(f"config.box_centers[{i}] = {c!r} puts box {i} off the table: |centre| + inner width / 2 "
                             f"+ wall thickness + jitter must be <= table_half_width = {half!r}")
        spans.append((c - reach, c + reach))
    if spans[0][0] < spans[1][1] and spans[1][0] < spans[0][1]:
        raise ValueError(f"config.box_centers {cfg.box_centers!r} make the two boxes overlap (walls and jitter "
                         f"included)")
    # The arm starts at rest with its tip above the table, at a reachable point ([A-2]).
    if not cfg.home_ee[1] > 0.0:
        raise ValueError(f"config.home_ee must lie above the table top (y > 0), got {cfg.home_ee!r}")
    try:
        _ik(np.asarray(cfg.home_ee, np.float64), cfg, -math.pi / 2)
    except ValueError:
        raise ValueError(f"config.home_ee {cfg.home_ee!r} is outside the reachable workspace of the arm "
                         f"([A-2]: tip with link 3 pointing down)") from None


def _config(config) -> ArmConfig:
    """``config`` checked, or the default for None (not for other falsy values)."""
    if config is None:
        return ArmConfig()
    _validate_config(config)
    return config


def forward_kinematics(q, config: ArmConfig | None = None) -> np.ndarray:
    """End-effector (gripper tip) position for joint positions ``q`` ([A-2]).

    Link 1 points at world angle ``-pi/2 + q[0]`` (``q[0] = 0`` hangs straight
    down from the overhead base); each later link adds its joint angle to the
    previous link's world angle.
    """
    cfg = _config(config)
    q = _real_array("q", q, f"({NUM_JOINTS},)")
    if q.shape != (NUM_JOINTS,) or not np.all(np.isfinite(q)):
        raise ValueError(f"q must be a finite array of shape ({NUM_JOINTS},), got {q!r}")
    theta = -math.pi / 2 + np.cumsum(q)
    pos = np.array(cfg.base, dtype=np.float64)
    for length, th in zip(cfg.link_lengths, theta):
        pos = pos + length * np.array([math.cos(th), math.sin(th)])
    return pos


def inverse_kinematics(ee_xy, config: ArmConfig | None = None, tool_angle: float = -math.pi / 2) -> np.ndarray:
    """Joint positions that put the gripper tip at ``ee_xy`` ([A-2]).

    The last link points at world angle ``tool_angle`` (straight down by
    default) and the elbow uses the branch with ``q[1] <= 0``. Targets below
    the base keep every joint angle continuous (no wrap-around), so straight
    Cartesian paths map to continuous joint paths. Unreachable targets raise
    ValueError.
    """
    cfg = _config(config)
    p = _real_array("ee_xy", ee_xy, "(2,)")  # booleans, strings and ragged lists are not coordinates
    if p.shape != (2,) or not np.all(np.isfinite(p)):
        raise ValueError(f"ee_xy must be a finite array of shape (2,), got {ee_xy!r}")
    if not is_real(tool_angle):
        raise ValueError(f"tool_angle must be a finite real number (radians), got {tool_angle!r}")
    return _ik(p, cfg, float(tool_angle))


def _ik(p: np.ndarray, cfg: ArmConfig, tool_angle: float) -> np.ndarray:
    """:func:`inverse_kinematics` on checked arguments ([A-2])."""
    l1, l2, l3 = cfg.link_lengths
    wx = p[0] - l3 * math.cos(tool_angle) - cfg.base[0]
    wy = p[1] - l3 * math.sin(tool_angle) - cfg.base[1]
    d = math.hypot(wx, wy)
    if d > l1 + l2 - 1e-9 or d < abs(l1 - l2) + 1e-9:
        raise ValueError(f"ee_xy {tuple(p)} is outside the reachable workspace")
    alpha = math.atan2(wy, wx)
    cos_b = (d * d + l1 * l1 - l2 * l2) / (2 * d * l1)
    beta = math.acos(max(-1.0, min(1.0, cos_b)))
    cos_e = (l1 * l1 + l2 * l2 - d * d) / (2 * l1 * l2)
    elbow = math.acos(max(-1.0, min(1.0, cos_e)))
    theta1 = alpha + beta
    q1 = theta1 + math.pi / 2
    q2 = -(math.pi - elbow)
    q3 = tool_angle - (theta1 + q2)
    return np.array([q1, q2, q3])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2 * math.pi) - math.pi


@dataclass
class _Scene:
    space: pymunk.Space
    links: list
    motors: list
    objects: list
    box_centers: np.ndarray
    grasp: list = field(default_factory=list)
    held: int = -1


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
        self._scene: _Scene | None = None
        self._t = 0
        self._done = True
        self._closed = False
        self._success_step = None
        self._targets = np.zeros(NUM_JOINTS)

    # ------------------------------------------------------------------ reset
    def reset(self, seed) -> np.ndarray:
        """Build a fresh scene with seeded object placement ([A-5], [A-6])."""
        seed = check_int("seed", seed, 0, None)
        rng = np.random.default_rng(seed)
        space = pymunk.Space()
        space.gravity = (0.0, -9.81)
        # Metre-scale scene: the default 0.1 slop would let parts sink 10 cm.
        space.collision_slop = 0.0005
        space.iterations = 20
        self._build_world(space, rng)
        self._t = 0
        self._done = False
        self._closed = False
        self._success_step = None
        return self._observe()

    def _build_world(self, space: pymunk.Space, rng: np.random.Generator) -> None:
        cfg = self.config
        static = space.static_body
        table = pymunk.Segment(static, (-cfg.table_half_width, -0.01), (cfg.table_half_width, -0.01), 0.01)
        table.friction = 1.0
        table.filter = _WORLD_FILTER
        space.add(table)
        # Boxes: two walls standing on the table; the table is the box floor.
        centers = np.array(cfg.box_centers, dtype=np.float64) + rng.uniform(
            -cfg.box_center_jitter, cfg.box_center_jitter, size=2)
        for cx, inner in zip(centers, cfg.box_inner_widths):
            for side in (-1.0, 1.0):
                x = cx + side * (inner / 2 + cfg.box_wall_thickness / 2)
                wall = pymunk.Poly(static, [
                    (x - cfg.box_wall_thickness / 2, 0.0), (x + cfg.box_wall_thickness / 2, 0.0),
                    (x + cfg.box_wall_thickness / 2, cfg.box_wall_height),
                    (x - cfg.box_wall_thickness / 2, cfg.box_wall_height)])
                wall.friction = 0.8
                wall.filter = _WORLD_FILTER
                space.add(wall)

        # Arm: each link body has its origin at its proximal joint.
        q0 = inverse_kinematics(np.array(cfg.home_ee), cfg)
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
        xs = self._sample_object_x(rng)
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
        self._scene = _Scene(space, links, motors, objects, centers)
        self._targets = q0.copy()

    def _sample_object_x(self, rng: np.random.Generator) -> np.ndarray:
        cfg = self.config
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
        # Plain floats here: this loop dominates the cost of an episode.
        for _ in range(cfg.substeps):
            prev = -math.pi / 2
            for body, motor, target in pairs:
                angle = body.angle
                rate = kp * (target - (angle - prev))
                prev = angle
                rate = vmax if rate > vmax else (-vmax if rate < -vmax else rate)
                # pymunk's SimpleMotor drives b.w - a.w to -rate.
                motor.rate = -rate
            space.step(h)
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
        import matplotlib.pyplot as plt

        if self._scene is None:
            raise RuntimeError("call reset(seed) first")
        cfg = self.config
        sc = self._scene
        if ax is None:
            _, ax = plt.subplots(figsize=(8, 4))
        ax.plot([-cfg.table_half_width, cfg.table_half_width], [0, 0], "k-")
        for cx, inner, color in zip(sc.box_centers, cfg.box_inner_widths, ("tab:blue", "gray")):
            for side in (-1, 1):
                x = cx + side * (inner / 2 + cfg.box_wall_thickness / 2)
                ax.plot([x, x], [0, cfg.box_wall_height], color=color, lw=3)
        pts = [np.array(cfg.base)]
        for b, length in zip(sc.links, cfg.link_lengths):
            p = b.local_to_world((length, 0))
            pts.append(np.array([p.x, p.y]))
        pts = np.array(pts)
        ax.plot(pts[:, 0], pts[:, 1], "o-", color="k")
        for i, (body, shape) in enumerate(sc.objects):
            v = np.array([body.local_to_world(p) for p in shape.get_vertices()])
            ax.fill(v[:, 0], v[:, 1], color="tab:blue" if OBJECT_TARGET_BOX[i] == 0 else "silver",
                    ec="k")
        ax.set_aspect("equal")
        return ax
