"""Worker processes of the arm experiment that end with the run that started them ([AX-13]).

:func:`job_runner` maps a function over jobs in ``workers`` spawned
processes and yields the results in job order. When the run stops early (SIGTERM,
SIGINT, an error in a job or in the caller's loop), no worker outlives it:
queued jobs are cancelled and the worker processes are terminated, then
killed if they do not exit within a grace period. A worker whose parent dies
without that cleanup (SIGKILL) is ended by the kernel on Linux
(``PR_SET_PDEATHSIG``) and, elsewhere, ends itself when it finds that its
parent changed. A job already running when the run stops leaves only its
temporary file (the cells are written under a temporary name and renamed
when complete, [AX-4]).
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
from typing import Callable, Iterable, Iterator

__all__ = ["job_runner", "GRACE_S"]

# Seconds a terminated worker gets to exit before it is killed.
GRACE_S = 5.0
_PR_SET_PDEATHSIG = 1


def _die_with_parent(parent: int) -> None:
    """Worker initializer: ask the kernel to send SIGTERM when the parent dies, and catch a parent that died
    before the request took effect."""
    if sys.platform.startswith("linux"):
        try:
            import ctypes

            ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0)
        except (OSError, AttributeError):  # no prctl in this libc: the parent check below still applies
            pass
    if os.getppid() != parent:
        os._exit(1)


class _Stopped(Exception):
    """SIGTERM received while the pool ran (turned into an exception so that the cleanup runs)."""


def _raise_stopped(signum, frame):
    raise _Stopped(f"stopped by signal {signum}")


def _stop(pool) -> None:
    """Cancel queued jobs and end every worker process: terminate, wait up to GRACE_S, then kill."""
    # The executor keeps no public list of its processes.
    processes = list(pool._processes.values()) if getattr(pool, "_processes", None) else []
    pool.shutdown(wait=False, cancel_futures=True)
    for p in processes:
        if p.is_alive():
            p.terminate()
    for p in processes:
        p.join(GRACE_S)
        if p.is_alive():
            p.kill()
            p.join(GRACE_S)


@contextlib.contextmanager
def job_runner(workers: int) -> Iterator[Callable[[Callable, Iterable], Iterator]]:
    """``with job_runner(workers) as run: for result in run(fn, jobs): ...`` computes ``fn(job)`` for each job,
    in order, in ``workers`` spawned processes (in this process when ``workers == 1``).

    Leaving the block by an exception (an error in a job or in the loop, SIGINT's KeyboardInterrupt) ends
    every worker first; SIGTERM, while the block runs, does the same and leaves as ``SystemExit(143)``
    (128 + SIGTERM), the status a shell reports for a process ended by it.
    """
    if workers == 1:
        yield lambda fn, jobs: map(fn, jobs)
        return
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    pool = ProcessPoolExecutor(max_workers=workers, mp_context=mp.get_context("spawn"),
                               initializer=_die_with_parent, initargs=(os.getpid(),))
    try:
        previous = signal.signal(signal.SIGTERM, _raise_stopped)
    except ValueError:  # not the main thread: no handler; errors still end the workers
        previous = None
    try:
        yield lambda fn, jobs: pool.map(fn, jobs)
    except _Stopped:
        _stop(pool)
        raise SystemExit(128 + signal.SIGTERM) from None
    except BaseException:
        _stop(pool)
        raise
    else:
        pool.shutdown()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
