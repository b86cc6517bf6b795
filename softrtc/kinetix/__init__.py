"""Kinetix benchmark environment and the public release's expert data (spec chapter K).

Nothing heavy is imported here: ``softrtc.kinetix.env`` (JAX + kinetix) and
``softrtc.kinetix.data`` (NumPy) load on first attribute access, so that
``import softrtc`` and ``import softrtc.kinetix`` work without JAX.
"""

from __future__ import annotations

import importlib

_ENV_NAMES = {
    "LEVEL_NAMES",
    "LARGE_ENV_PARAMS",
    "FRAME_SKIP",
    "NUM_MOTOR_BINDINGS",
    "NUM_THRUSTER_BINDINGS",
    "MAX_TIMESTEPS",
    "ACTION_NOISE_STD",
    "OBS_DIM",
    "ACTION_DIM",
    "KinetixTask",
    "make_env",
    "load_level",
    "resolve_levels_dir",
    "default_levels_dir",
    "bench_bare_env",
    "make_random_rollout",
    "random_actions",
    "check_level_name",
    "level_index",
    "package_level_names",
}
_DATA_NAMES = {
    "EXPERT_KEYS",
    "ExpertData",
    "load_expert_data",
    "save_expert_data",
    "expert_data_filename",
    "chunk_start_indices",
    "make_chunks",
    "make_training_examples",
}

__all__ = sorted(_ENV_NAMES | _DATA_NAMES)


def __getattr__(name: str):
    if name in _ENV_NAMES:
        return getattr(importlib.import_module(".env", __name__), name)
    if name in _DATA_NAMES:
        return getattr(importlib.import_module(".data", __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(__all__))
