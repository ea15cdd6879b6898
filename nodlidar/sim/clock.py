"""One clock for every emulated device, so lidar scans and servo motion agree in time.

``SimClock(rate=1.0)`` runs in real time; ``rate=20`` runs twenty times faster than the
wall clock (emulators pace their output against it); ``ManualClock`` only moves when a
test advances it.
"""

from __future__ import annotations

import math
import threading
import time

from ..errors import require

__all__ = ["SimClock", "ManualClock"]


class SimClock:
    """Simulated time [s] = ``rate`` x wall time elapsed since construction (+ ``t0``).

    Thread-safe: emulator threads share one instance.
    """

    def __init__(self, rate: float = 1.0, t0: float = 0.0):
        require(isinstance(rate, (int, float)) and math.isfinite(rate) and rate > 0,
                "clock.rate", rate, "a finite number > 0 (simulated seconds per wall second)")
        self.rate = float(rate)
        self._t0 = float(t0)
        self._wall0 = time.monotonic()

    def now(self) -> float:
        """Current simulated time [s]."""
        return self._t0 + (time.monotonic() - self._wall0) * self.rate

    def sleep_until(self, t_sim: float, stop: threading.Event | None = None) -> bool:
        """Block until simulated time ``t_sim``; return False if ``stop`` was set first."""
        while True:
            dt = (t_sim - self.now()) / self.rate
            if dt <= 0:
                return True
            if stop is not None:
                if stop.wait(min(dt, 0.05)):
                    return False
            else:
                time.sleep(min(dt, 0.05))


class ManualClock(SimClock):
    """A clock that stands still until :meth:`advance` is called (deterministic tests)."""

    def __init__(self, t0: float = 0.0):
        super().__init__(rate=1.0, t0=t0)
        self._t = float(t0)
        self._cond = threading.Condition()

    def now(self) -> float:
        return self._t

    def advance(self, dt: float) -> None:
        with self._cond:
            self._t += float(dt)
            self._cond.notify_all()

    def sleep_until(self, t_sim: float, stop: threading.Event | None = None) -> bool:
        with self._cond:
            while self._t < t_sim:
                if stop is not None and stop.is_set():
                    return False
                self._cond.wait(0.05)
        return True
