"""The benchmark's 12 Kinetix levels: names, settings and level files (spec chapter K, [K-1]..[K-4]).

Where the level files are found ([K-2], [K-3]) and how one is loaded and
checked against the benchmark's static settings ([K-4]). The environment
built from a level is :mod:`softrtc.kinetix.env`, which re-exports these names.

This module imports kinetix at import time; ``softrtc.kinetix`` loads it
lazily so that ``import softrtc`` stays free of it.
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path
from typing import Any

# kinetix imports grain, which warns on every start that its worker profiling needs a newer jaxlib;
# softrtc never uses grain workers, so that one notice is dropped (other absl warnings still show).
logging.getLogger("absl").addFilter(
    lambda record: not str(record.msg).startswith("Grain multiprocess worker profiling"))

from kinetix.environment.env_state import StaticEnvParams  # noqa: E402
from kinetix.util.saving import load_from_json_file  # noqa: E402

__all__ = [
    "LEVEL_NAMES", "LARGE_ENV_PARAMS", "FRAME_SKIP", "NUM_MOTOR_BINDINGS", "NUM_THRUSTER_BINDINGS",
    "MAX_TIMESTEPS", "project_root", "default_levels_dir", "resolve_levels_dir", "benchmark_static_env_params",
    "load_level",
]

# [K-1] the benchmark's level set, in the order the public release lists it.
LEVEL_NAMES: tuple[str, ...] = (
    "grasp_easy",
    "catapult",
    "cartpole_thrust",
    "hard_lunar_lander",
    "mjc_half_cheetah",
    "mjc_swimmer",
    "mjc_walker",
    "h17_unicycle",
    "chain_lander",
    "catcher_v3",
    "trampoline",
    "car_launch",
)

# [K-4] static sizes of the "large" Kinetix levels and the benchmark's extras.
LARGE_ENV_PARAMS: dict[str, int] = {
    "num_polygons": 12,
    "num_circles": 4,
    "num_joints": 6,
    "num_thrusters": 2,
}
FRAME_SKIP = 2
NUM_MOTOR_BINDINGS = 4
NUM_THRUSTER_BINDINGS = 2
MAX_TIMESTEPS = 256


def project_root() -> Path | None:
    """Directory holding ``pyproject.toml``, found upward from this file; ``None`` outside a source checkout [K-2]."""
    here = Path(__file__).resolve().parent
    for cand in (here, *here.parents):
        if (cand / "pyproject.toml").is_file():
            return cand
    # An installed package has no project root, hence no default levels directory [K-2].
    return None


def default_levels_dir() -> Path | None:
    """``<project root>/../shared/kinetix-levels`` when it exists, else ``None`` (also outside a checkout) [K-2]."""
    root = project_root()
    if root is None:
        return None
    cand = (root.parent / "shared" / "kinetix-levels").resolve()
    return cand if cand.is_dir() else None


def resolve_levels_dir(levels_dir: str | os.PathLike | None = None, names=LEVEL_NAMES) -> Path:
    """Absolute levels directory holding ``<name>.json`` for every name [K-2], [K-3].

    Raises ``FileNotFoundError`` naming the missing files and the directory
    searched (or saying why there is no default); ``ValueError`` for an
    unknown level name or a ``levels_dir`` that is not a path.
    """
    names = _check_names(names)
    files = ", ".join(n + ".json" for n in names)
    if levels_dir is None:
        d = default_levels_dir()
        if d is None:
            root = project_root()
            if root is None:
                raise FileNotFoundError(
                    f"no Kinetix levels directory given, and softrtc runs from an installed package "
                    f"(no pyproject.toml above {Path(__file__).resolve().parent}), which has no default; "
                    f"pass levels_dir= (command line: --levels-dir) a directory holding {files}"
                )
            searched = root.parent / "shared" / "kinetix-levels"
            raise FileNotFoundError(
                f"no Kinetix levels directory given and the default {searched} does not exist; "
                f"pass levels_dir= (command line: --levels-dir) a directory holding {files}"
            )
    else:
        if not isinstance(levels_dir, (str, os.PathLike)):
            raise ValueError(f"levels_dir must be a path or None, got {type(levels_dir).__name__}")
        d = Path(levels_dir).expanduser().resolve()
        if not d.is_dir():
            why = "is not a directory" if d.exists() else "does not exist"
            raise FileNotFoundError(f"levels_dir must be a directory holding the Kinetix level files ({files}); "
                                    f"{d} {why}")
    missing = [f"{n}.json" for n in names if not (d / f"{n}.json").is_file()]
    if missing:
        raise FileNotFoundError(f"Kinetix level files missing from {d}: {', '.join(missing)}")
    return d


def _check_names(names: Any) -> tuple[str, ...]:
    # A single str is one level name, not a sequence of characters.
    if isinstance(names, str):
        return (_check_level_name(names),)
    if not isinstance(names, (list, tuple)):
        raise ValueError(f"names must be a level name or a non-empty list/tuple of level names, got {type(names).__name__}")
    if not names:
        raise ValueError("names must hold at least one level name, got an empty sequence")
    for n in names:
        _check_level_name(n)
    return tuple(names)


def _check_level_name(level_name: Any) -> str:
    if not isinstance(level_name, str) or level_name not in LEVEL_NAMES:
        raise ValueError(f"level_name must be one of {', '.join(LEVEL_NAMES)}; got {level_name!r}")
    return level_name


def benchmark_static_env_params() -> StaticEnvParams:
    """Static params of the benchmark [K-4]."""
    return StaticEnvParams(
        **LARGE_ENV_PARAMS,
        frame_skip=FRAME_SKIP,
        num_motor_bindings=NUM_MOTOR_BINDINGS,
        num_thruster_bindings=NUM_THRUSTER_BINDINGS,
    )


def load_level(level_name: str, levels_dir: str | os.PathLike | None = None):
    """Load one level file as a kinetix ``EnvState`` [K-1]..[K-4].

    The file's static and dynamic params are checked against the benchmark's
    (screen size aside, which affects rendering only); a mismatch is a
    ``ValueError`` because the compiled env would silently differ.
    """
    _check_level_name(level_name)
    d = resolve_levels_dir(levels_dir, (level_name,))
    path = (d / f"{level_name}.json").resolve()
    # kinetix's loader keeps its own defaults for static fields, so the raw
    # file is checked first to catch a level built for other settings.
    try:
        raw = json.loads(path.read_text())
        raw_static, raw_params = raw["static_env_params"], raw["env_params"]
    except (ValueError, KeyError, TypeError) as e:
        raise ValueError(f"level file {path} is not a kinetix level JSON: {e}") from e
    for field, value in (("static_env_params", raw_static), ("env_params", raw_params)):
        if not isinstance(value, dict):
            raise ValueError(f"level file {path} field {field!r} must be a JSON object, got {type(value).__name__}")
    try:
        level, file_static, _ = _load_level_file(path, raw_static, raw_params)
    except (KeyError, TypeError, AttributeError, IndexError) as e:
        raise ValueError(f"level file {path} is not a valid kinetix level JSON: {type(e).__name__}: {e}") from e
    want = benchmark_static_env_params()
    got = file_static.replace(screen_dim=want.screen_dim, downscale=want.downscale)
    if got != want:
        raise ValueError(f"level file {path} has static params {file_static}, expected {want}")
    return level


def _load_level_file(path: Path, raw_static: dict, raw_params: dict):
    for field, value in {**LARGE_ENV_PARAMS, "frame_skip": FRAME_SKIP}.items():
        if field in raw_static and raw_static[field] != value:
            raise ValueError(f"level file {path} has {field}={raw_static[field]}, expected {value}")
    if raw_params.get("max_timesteps", MAX_TIMESTEPS) != MAX_TIMESTEPS:
        raise ValueError(
            f"level file {path} has max_timesteps={raw_params['max_timesteps']}, expected {MAX_TIMESTEPS}"
        )
    # kinetix resolves relative paths inside its own package, so pass absolute.
    return load_from_json_file(str(path))
