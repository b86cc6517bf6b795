"""Scale-out over several JAX processes with ``jax.distributed`` ([KD-1]..[KD-4]).

Every process runs the same command with its own ``process_id``; after
:func:`initialize` ``jax.devices()`` lists the devices of every process, so the
env axis of a rollout ([KE-4]) is sharded over all of them. Each process builds
the same arguments (same seed, same keys) and places them as global arrays
(:class:`softrtc.kinetix.cache.CompiledProgram`); the rollout's outputs are
replicated, which gathers the episodes once per rollout call, and every process
then holds the full results. Only process 0 writes files ([KD-3]).

On CPUs the collectives run over gloo (several processes on one machine, or
machines on a network); on GPUs and TPUs JAX uses the accelerator's own.
"""

from __future__ import annotations

import re

import jax

from softrtc.reference._validate import check_int

__all__ = ["PROCESSES_MAX", "parse_coordinator", "initialize", "is_writer", "process_index", "process_count"]

PROCESSES_MAX = 4096


def parse_coordinator(text: str) -> str:
    """``HOST:PORT`` of the coordinator (process 0's address), checked ([KD-1])."""
    if not isinstance(text, str) or not re.fullmatch(r"[A-Za-z0-9_.\-\[\]:]+:[0-9]{1,5}", text.strip()):
        raise ValueError(f"coordinator must be HOST:PORT (e.g. localhost:12355 or 10.0.0.1:12355), got {text!r}")
    port = int(text.strip().rsplit(":", 1)[1])
    if not 1 <= port <= 65535:
        raise ValueError(f"coordinator port must lie in [1, 65535], got {port}")
    return text.strip()


def initialize(coordinator: str, num_processes: int, process_id: int, local_devices: int | None = None,
               timeout_s: int = 300) -> None:
    """Join a run of ``num_processes`` processes ([KD-1]); call before any other JAX work.

    ``local_devices`` sets the number of CPU devices of this process (JAX's ``jax_num_cpu_devices``);
    on CPU the cross-process collectives use gloo. ``timeout_s`` bounds the wait for the others.
    """
    coordinator = parse_coordinator(coordinator)
    num_processes = check_int("num_processes", num_processes, 1, PROCESSES_MAX)
    process_id = check_int("process_id", process_id, 0, num_processes - 1)
    timeout_s = check_int("timeout_s", timeout_s, 1, 86400)
    if local_devices is not None:
        local_devices = check_int("local_devices", local_devices, 1, 1024)
        jax.config.update("jax_num_cpu_devices", local_devices)
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=coordinator, num_processes=num_processes,
                               process_id=process_id, initialization_timeout=timeout_s)


def process_index() -> int:
    return jax.process_index()


def process_count() -> int:
    return jax.process_count()


def is_writer() -> bool:
    """True in the process that writes results and prints tables: process 0 ([KD-3])."""
    return jax.process_index() == 0
