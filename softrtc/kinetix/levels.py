"""Kinetix levels: names, settings and level files (spec chapter K, [K-1]..[K-4], [K-20]..[K-23]).

The benchmark's 12 levels: where their files are found ([K-2], [K-3]) and
how one is loaded and checked against the benchmark's static settings
([K-4]). The levels shipped inside kinetix-env, named ``<set>_<file>``
(``m_h5_angry_birds``) and loaded padded to the benchmark's shapes, or at
their own with the ``@own`` suffix ([K-20]..[K-23]). The environment built
from a level is :mod:`softrtc.kinetix.env`, which re-exports these names.

This module imports kinetix at import time; ``softrtc.kinetix`` loads it
lazily so that ``import softrtc`` stays free of it.
"""

from __future__ import annotations

import functools
import hashlib
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
from kinetix.util.saving import expand_env_state, load_from_json_file  # noqa: E402

__all__ = [
    "LEVEL_NAMES", "LARGE_ENV_PARAMS", "FRAME_SKIP", "NUM_MOTOR_BINDINGS", "NUM_THRUSTER_BINDINGS",
    "MAX_TIMESTEPS", "project_root", "default_levels_dir", "resolve_levels_dir", "benchmark_static_env_params",
    "load_level", "PACKAGE_SETS", "OWN_SHAPES_SUFFIX", "package_levels_dir", "package_level_names",
    "check_level_name", "is_package_level", "level_index", "level_static_env_params", "LEVELS_HINT",
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

# [K-20] the size sets of the levels kinetix-env ships (kinetix/levels/<set>/<file>.json).
PACKAGE_SETS: tuple[str, ...] = ("s", "m", "l")
# [K-21] a package level name with this suffix runs at the file's own static sizes.
OWN_SHAPES_SUFFIX = "@own"
# [K-20] where an unknown name's error sends the user.
LEVELS_HINT = "list the valid names with `softrtc kinetix levels`"


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
    # [K-20]: package levels come from the kinetix package, never from the levels directory.
    names = tuple(n for n in names if n in LEVEL_NAMES)
    if not names:
        if levels_dir is None:
            return package_levels_dir()
        if not isinstance(levels_dir, (str, os.PathLike)):
            raise ValueError(f"levels_dir must be a path or None, got {type(levels_dir).__name__}")
        d = Path(levels_dir).expanduser().resolve()
        if not d.is_dir():
            raise FileNotFoundError(f"levels_dir must be a directory; {d} "
                                    f"{'is not a directory' if d.exists() else 'does not exist'}")
        return d
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


def package_levels_dir() -> Path:
    """The ``levels`` folder of the installed kinetix-env package, which holds ``s/``, ``m/`` and ``l/`` [K-20]."""
    import kinetix

    return Path(kinetix.__file__).resolve().parent / "levels"


def package_level_names() -> tuple[str, ...]:
    """Every level kinetix-env ships, as ``<set>_<file stem>`` sorted by set (s, m, l) then name [K-20]."""
    root = package_levels_dir()
    return tuple(f"{st}_{p.stem}" for st in PACKAGE_SETS for p in sorted((root / st).glob("*.json")))


def _split_package_name(name: str) -> tuple[str, str, bool] | None:
    """``(set, file stem, own shapes)`` of a package level name, or ``None`` when ``name`` is not one [K-20]."""
    own = name.endswith(OWN_SHAPES_SUFFIX)
    base = name[:-len(OWN_SHAPES_SUFFIX)] if own else name
    st, sep, stem = base.partition("_")
    if not sep or st not in PACKAGE_SETS or not stem or "/" in stem or "\\" in stem or stem.startswith("."):
        return None
    if not (package_levels_dir() / st / f"{stem}.json").is_file():
        return None
    return st, stem, own


def is_package_level(name: Any) -> bool:
    """True when ``name`` is a kinetix-env package level (``<set>_<file>`` or ``<set>_<file>@own``) [K-20]."""
    return isinstance(name, str) and name not in LEVEL_NAMES and _split_package_name(name) is not None


def check_level_name(level_name: Any, arg: str = "level_name") -> str:
    """``level_name`` when it names a level ([K-1] or [K-20]); else a ``ValueError`` naming ``arg``,
    the benchmark's 12 names, the package form and how to list the package's names."""
    if isinstance(level_name, str) and (level_name in LEVEL_NAMES or is_package_level(level_name)):
        return level_name
    raise ValueError(f"{arg} must be one of the benchmark's levels ({', '.join(LEVEL_NAMES)}) or a level shipped "
                     f"with kinetix-env as <set>_<name>[{OWN_SHAPES_SUFFIX}] with set s, m or l (e.g. "
                     f"m_h5_angry_birds); {LEVELS_HINT}; got {level_name!r}")


def level_index(level_name: str) -> int:
    """The integer folded into a level's PRNG keys [K-22]: the position in ``LEVEL_NAMES`` for the
    benchmark's 12, else the first 31 bits of SHA-256 of the name (stable across kinetix versions)."""
    check_level_name(level_name)
    if level_name in LEVEL_NAMES:
        return LEVEL_NAMES.index(level_name)
    return int.from_bytes(hashlib.sha256(level_name.encode()).digest()[:4], "big") & 0x7FFFFFFF


def level_static_env_params(level_name: str) -> StaticEnvParams:
    """Static params a level runs with: the benchmark's [K-4], or a ``@own`` level's file sizes [K-21]."""
    check_level_name(level_name)
    split = _split_package_name(level_name) if level_name not in LEVEL_NAMES else None
    if split is None or not split[2]:
        return benchmark_static_env_params()
    path = package_levels_dir() / split[0] / f"{split[1]}.json"
    return _load_package_file(path)[1]


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
    return check_level_name(level_name)


def benchmark_static_env_params() -> StaticEnvParams:
    """Static params of the benchmark [K-4]."""
    return StaticEnvParams(
        **LARGE_ENV_PARAMS,
        frame_skip=FRAME_SKIP,
        num_motor_bindings=NUM_MOTOR_BINDINGS,
        num_thruster_bindings=NUM_THRUSTER_BINDINGS,
    )


def load_level(level_name: str, levels_dir: str | os.PathLike | None = None):
    """Load one level file as a kinetix ``EnvState`` [K-1]..[K-4], [K-20], [K-21].

    A package level ([K-20]) is read from the kinetix package (``levels_dir``
    is not used) and padded to the benchmark's sizes, or kept at its own with
    the ``@own`` suffix ([K-21]).

    The file's static and dynamic params are checked against the benchmark's
    (screen size aside, which affects rendering only); a mismatch is a
    ``ValueError`` because the compiled env would silently differ.
    """
    _check_level_name(level_name)
    if level_name not in LEVEL_NAMES:
        return _load_package_level(level_name)
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


def _load_package_file(path: Path):
    """``(level, static params, env params)`` of a kinetix-env level file, checked against the settings
    the benchmark fixes besides the sizes ([K-4]: frame skip, bindings, ``max_timesteps``) [K-21]."""
    try:
        raw = json.loads(path.read_text())
        raw_static, raw_params = raw["static_env_params"], raw["env_params"]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"level file {path} is not a kinetix level JSON: {e}") from e
    fixed = {"frame_skip": FRAME_SKIP, "num_motor_bindings": NUM_MOTOR_BINDINGS,
             "num_thruster_bindings": NUM_THRUSTER_BINDINGS}
    for field, value in fixed.items():
        if raw_static.get(field, value) != value:
            raise ValueError(f"level file {path} has {field}={raw_static[field]}, expected {value}")
    if raw_params.get("max_timesteps", MAX_TIMESTEPS) != MAX_TIMESTEPS:
        raise ValueError(f"level file {path} has max_timesteps={raw_params['max_timesteps']}, "
                         f"expected {MAX_TIMESTEPS}")
    try:
        return load_from_json_file(str(path))
    except (KeyError, TypeError, AttributeError, IndexError) as e:
        raise ValueError(f"level file {path} is not a valid kinetix level JSON: {type(e).__name__}: {e}") from e


@functools.lru_cache(maxsize=None)
def _load_package_level(level_name: str):
    # Cached per process: kinetix's padding runs op by op (about 10 s on 2 cores), and a level's
    # arrays are immutable, so every env built from the name shares one loaded level.
    st, stem, own = _split_package_name(level_name)
    path = package_levels_dir() / st / f"{stem}.json"
    level, file_static, _ = _load_package_file(path)
    if own:
        return level
    want = benchmark_static_env_params()
    sizes = {f: getattr(file_static, f) for f in LARGE_ENV_PARAMS}
    over = [f"{f}={v} > {LARGE_ENV_PARAMS[f]}" for f, v in sizes.items() if v > LARGE_ENV_PARAMS[f]]
    if over:
        raise ValueError(f"level_name {level_name!r} does not fit the benchmark's sizes ({', '.join(over)}); "
                         f"use {level_name}{OWN_SHAPES_SUFFIX} for its own sizes")
    # [K-21]: kinetix's own padding (the loader of its evaluation levels): inactive shapes, joints and
    # thrusters appended, joint and thruster indices shifted past the added polygons, the collision
    # matrix recomputed for the larger sizes.
    return expand_env_state(level, want)
