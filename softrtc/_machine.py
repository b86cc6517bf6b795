"""The machine a benchmark ran on, framework-neutral (imports neither JAX nor torch) ([B-10], [PT-8]).

Ratios between benchmark rows depend on the CPU model, not only on the core
count, so every benchmark result records it beside ``os.cpu_count()``.
"""

from __future__ import annotations

import platform

__all__ = ["cpu_model"]


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
