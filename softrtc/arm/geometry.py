"""Geometry of the arm scene: counts, :class:`ArmConfig` with its checks, and the arm's kinematics.

The scene lives in a vertical plane (x to the right, y up, metres). A
three-link arm hangs from an overhead base; its tip is the gripper. Every
length, mass and limit of the scene is a field of :class:`ArmConfig`, checked
at construction ([A-12]); :func:`forward_kinematics` and
:func:`inverse_kinematics` map joint positions to the tip and back ([A-2]).

Requirement ids cited below refer to ``spec/10-arm.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from softrtc.reference._validate import check_int, real_array

from ._checks import is_real

__all__ = [
    "ArmConfig",
    "OBJECT_NAMES",
    "OBJECT_TARGET_BOX",
    "NUM_JOINTS",
    "NUM_OBJECTS",
    "forward_kinematics",
    "inverse_kinematics",
]

NUM_JOINTS = 3
NUM_OBJECTS = 4
# object order in observations and info: blue0, blue1, silver0, silver1.
OBJECT_NAMES = ("blue0", "blue1", "silver0", "silver1")
# Box index per object: 0 = blue box, 1 = gray box.
OBJECT_TARGET_BOX = (0, 0, 1, 1)


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
    # moving boxes: 0 keeps them static (every task but ``drift``).
    box_hop_range: float = 0.0  # m: each hop's destination lies within +-range of the box's start centre
    box_hop_speed: float = 0.5  # m/s: speed of a box while it hops
    box_hop_interval: tuple[int, int] = (25, 75)  # control ticks between hop starts, drawn uniformly inclusive
    tray_rim_height: float = 0.005  # m: wall height of a moving tray (static boxes use box_wall_height)

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
    for name in ("object_min_gap", "box_center_jitter", "box_hop_range"):
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
    _real("box_hop_speed", cfg.box_hop_speed, 0.0, strict=True)
    _real("tray_rim_height", cfg.tray_rim_height, 0.0, strict=True)
    gap = cfg.box_hop_interval
    if not isinstance(gap, (tuple, list)) or len(gap) != 2:
        raise ValueError(f"config.box_hop_interval must be 2 integers 1 <= low <= high (ticks), got {gap!r}")
    check_int("config.box_hop_interval[0]", gap[0], 1, None)
    check_int("config.box_hop_interval[1]", gap[1], gap[0], None)
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
    # Static boxes stand on the table for every jitter draw; moving trays stay beside it ([A-27]); the two
    # never overlap.
    spans = []
    for i, (c, inner) in enumerate(zip(cfg.box_centers, cfg.box_inner_widths)):
        reach = inner / 2 + cfg.box_wall_thickness + cfg.box_center_jitter + cfg.box_hop_range
        if cfg.box_hop_range == 0 and (c - reach < -half or c + reach > half):
            raise ValueError(f"config.box_centers[{i}] = {c!r} puts box {i} off the table: |centre| + inner width / 2 "
                             f"+ wall thickness + jitter must be <= table_half_width = {half!r}")
        if cfg.box_hop_range > 0 and abs(c) - reach < half:
            raise ValueError(f"config.box_centers[{i}] = {c!r} lets moving tray {i} reach over the table: |centre| - "
                             f"inner width / 2 - wall thickness - jitter - hop range must be >= table_half_width = "
                             f"{half!r}")
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
