"""Memory a benchmark request needs, checked against what the machine has before any work ([B-16]).

Standard library only. A training step of the flow policy (spec chapter P)
keeps, per example, the activations of every token, layer and channel for
the backward pass: XLA's memory analysis of the JAX training step of the
benchmark architecture (``H = 8``, 4 layers, ``channel_dim = 256``,
``channel_hidden_dim = 512``) gives 1.28 MB per example at batch 64 and
1.51 MB at batch 512 (0.77 GB in all), and a run at batch 65536 asked JAX
for 101 GB, 1.54 MB per example. :data:`BYTES_PER_UNIT` = 64 bytes per
(token, layer, channel unit) gives 1.57 MB there, an upper bound for those
measurements. A chunk-generation call keeps at most one forward pass and
its vector-Jacobian product, less than a training step, so the same bound
serves the batch sizes of the chunk rows.

>>> step_bytes(64, horizon=8, num_layers=4, channel_dim=256, channel_hidden_dim=512)
100663296
"""

from __future__ import annotations

import os

__all__ = ["BYTES_PER_UNIT", "step_bytes", "available_bytes", "check_fits"]

# Bytes per (example, token, layer, channel or hidden unit) of a training step: an upper bound of the measured
# 1.51-1.54 MB per example of the benchmark architecture (24576 such units per example).
BYTES_PER_UNIT = 64


def step_bytes(batch: int, horizon: int, num_layers: int, channel_dim: int, channel_hidden_dim: int) -> int:
    """Bytes a training step (or a chunk-generation call) of ``batch`` examples needs at most ([B-16])."""
    return batch * horizon * num_layers * (channel_dim + channel_hidden_dim) * BYTES_PER_UNIT


def available_bytes() -> int | None:
    """Memory the machine can give a new allocation now: ``MemAvailable`` of ``/proc/meminfo`` (Linux), else
    the free physical pages; None when neither can be read (the check is then skipped)."""
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def check_fits(option: str, batch: int, need: int, available: int | None) -> None:
    """Raise ValueError naming ``option`` when ``need`` bytes exceed ``available`` ([B-16])."""
    if available is not None and need > available:
        raise ValueError(f"{option} {batch} needs about {need / 1e9:.1f} GB ({need / batch / 1e6:.2f} MB per "
                         f"example), more than the {available / 1e9:.1f} GB this machine has available; "
                         f"use a smaller {option}")
