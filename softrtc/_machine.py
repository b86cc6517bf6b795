"""The machine a benchmark ran on, framework-neutral (imports neither JAX nor torch) ([B-10], [PT-8]).

Ratios between benchmark rows depend on the CPU model, not only on the core
count, so every benchmark result records it beside ``os.cpu_count()``.
"""

from __future__ import annotations

import platform

__all__ = ["cpu_model", "cpu_features"]


def cpu_model() -> str:
    """The CPU's model name (Linux ``/proc/cpuinfo``, else ``platform.processor()``), or ``"unknown"``."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() == "model name" and value.strip():
                    return value.strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def cpu_features() -> tuple:
    """The CPU's instruction-set flags (Linux ``/proc/cpuinfo``: ``flags`` on x86, ``Features`` on Arm),
    sorted, or ``()`` where they cannot be read. Compiled programs are valid only on CPUs with the
    features they were compiled for, so a program cache keys on them ([KC-2], [KC-3])."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            for line in f:
                key, _, value = line.partition(":")
                if key.strip() in ("flags", "Features") and value.strip():
                    return tuple(sorted(set(value.split())))
    except OSError:
        pass
    return ()
