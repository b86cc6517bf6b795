"""The clocks of the real-time runtime ([R-10]): the wall clock it runs on, and a simulated one.

:func:`softrtc.arm.runtime.run_realtime_episode` reads and waits on time only
through a clock object with these methods:

* ``now() -> float``: seconds on the clock;
* ``sleep_until(t)``: the control thread waits for the start of a tick;
* ``sleep(seconds)``: the worker plays a slower model ([R-8]);
* ``task_started()`` / ``task_done()``: the control thread hands the worker a
  request / the worker has posted its answer (result or error);
* ``join(thread, timeout_s) -> bool``: wait for the stopped worker ([R-7]).

:class:`WallClock` is ``time.perf_counter`` and real sleeps. With
:class:`SimulatedClock` time moves only when the control thread waits, and
only once the worker is idle or waiting in ``sleep``: a policy call takes no
simulated time, so a request is back exactly its added latency after it was
made, and an episode's timeline is the same on every run and machine:

>>> c = SimulatedClock()
>>> c.sleep_until(0.25); c.now()
0.25
>>> c.advance(0.5); c.now()
0.75
"""

from __future__ import annotations

import heapq
import math
import threading
import time

__all__ = ["WallClock", "SimulatedClock"]


class WallClock:
    """The wall clock: ``time.perf_counter`` and ``time.sleep``; the hand-over calls do nothing ([R-10])."""

    def now(self) -> float:
        return time.perf_counter()

    def sleep_until(self, t: float) -> None:
        while True:
            rest = t - time.perf_counter()
            if rest <= 0:
                return
            time.sleep(rest)

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)

    def task_started(self) -> None:
        pass

    def task_done(self) -> None:
        pass

    def join(self, thread: threading.Thread, timeout_s: float) -> bool:
        thread.join(timeout=timeout_s)
        return not thread.is_alive()


def _seconds(name: str, value) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value) and value >= 0
    if not ok:
        raise ValueError(f"{name} must be a finite number of seconds >= 0, got {value!r}")
    return float(value)


class SimulatedClock:
    """Simulated time for the runtime ([R-10]); one clock serves one episode at a time.

    Time starts at ``start`` and moves only in :meth:`sleep_until` (and
    :meth:`advance`, which stands for work of the control thread that takes
    time), and only once every task handed to the worker is either done or
    waiting in :meth:`sleep` for a later time. A worker waiting for a time
    that is reached is woken with the clock standing at that time, and the
    clock moves on once it is done or waits again. ``settle_timeout_s`` bounds
    the real time a policy call may take before the clock reports the worker
    as stuck (a ``RuntimeError`` in the control thread).
    """

    def __init__(self, start: float = 0.0, settle_timeout_s: float = 60.0):
        self._now = _seconds("start", start)
        self._settle = _seconds("settle_timeout_s", settle_timeout_s)
        self._cv = threading.Condition()
        self._busy = 0          # tasks handed over and not yet done
        self._deadlines: list = []  # heap of the times the sleeping tasks wait for

    def now(self) -> float:
        with self._cv:
            return self._now

    def task_started(self) -> None:
        with self._cv:
            self._busy += 1

    def task_done(self) -> None:
        with self._cv:
            self._busy -= 1
            self._cv.notify_all()

    def sleep(self, seconds: float) -> None:
        seconds = _seconds("seconds", seconds)
        with self._cv:
            deadline = self._now + seconds
            heapq.heappush(self._deadlines, deadline)
            self._cv.notify_all()
            while self._now < deadline:
                self._cv.wait()
            self._deadlines.remove(deadline)
            heapq.heapify(self._deadlines)
            self._cv.notify_all()

    def _settled(self) -> bool:
        # Every busy task waits for a time not yet reached.
        return self._busy == sum(d > self._now for d in self._deadlines)

    def _wait_settled(self) -> None:
        if not self._cv.wait_for(self._settled, timeout=self._settle):
            raise RuntimeError(f"SimulatedClock: the worker neither finished nor waited within "
                               f"{self._settle} s of real time")

    def sleep_until(self, t: float) -> None:
        if not isinstance(t, (int, float)) or isinstance(t, bool) or not math.isfinite(t):
            raise ValueError(f"t must be a finite number of seconds, got {t!r}")
        with self._cv:
            while True:
                self._wait_settled()
                ahead = [d for d in self._deadlines if d > self._now]
                if ahead and min(ahead) <= t:
                    self._now = min(ahead)  # wake that task at its own time
                    self._cv.notify_all()
                    continue
                self._now = max(self._now, float(t))
                return

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` pass in the control thread (e.g. a slow environment step)."""
        self.sleep_until(self.now() + _seconds("seconds", seconds))

    def join(self, thread: threading.Thread, timeout_s: float) -> bool:
        """Whether the stopped worker ends within ``timeout_s`` of simulated time.

        Either way no thread is left waiting on this clock: a worker that
        would end later is let run to its end before this returns False.
        """
        timeout_s = _seconds("timeout_s", timeout_s)
        end = self.now() + timeout_s
        self.sleep_until(end)
        with self._cv:
            joined = self._busy == 0
            later = max(self._deadlines, default=end)
        if not joined:
            self.sleep_until(later)
        thread.join(timeout=self._settle)
        return joined and not thread.is_alive()
