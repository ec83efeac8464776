"""Virtual time for the simulated machine.

The simulator's physics, its watchdog and its fault schedule all run on one
virtual clock that may run faster than the wall clock (``--speedup``), so the
paper's ~15 min three-cycle protocol takes about a second in CI while every
duration (speeds, accelerations, watchdog timeouts, fault times) stays
consistent in virtual seconds.

- VirtualClock: ``now() = speedup * (monotonic() - t0)``.
- ManualClock: advanced explicitly (deterministic unit tests, batch studies); it is also a run's
  clock (foamlab.acquisition.clock.RunClock): a run's waits advance it, so the run engine drives
  the in-process machine (simulator.inprocess) in virtual time.

Both convert virtual durations to real ones (``to_real``), so a server can wait
on the wall clock for a virtual deadline.
"""

from __future__ import annotations

import threading
import time


class VirtualClock:
    """Virtual seconds since construction, running ``speedup`` times faster than real time."""

    def __init__(self, speedup: float = 1.0) -> None:
        if not (speedup > 0 and speedup < float("inf")):
            raise ValueError(f"speedup must be a positive number, got {speedup!r}")
        self._speedup = float(speedup)
        self._t0 = time.monotonic()

    @property
    def speedup(self) -> float:
        return self._speedup

    def now(self) -> float:
        return self._speedup * (time.monotonic() - self._t0)

    def to_real(self, virtual_s: float) -> float:
        """Wall-clock seconds that ``virtual_s`` virtual seconds take."""
        return virtual_s / self._speedup

    def to_virtual(self, real_s: float) -> float:
        return real_s * self._speedup


class ManualClock:
    """A clock that only moves when told to (``advance``/``set``): reproducible runs."""

    speedup = float("inf")  # virtual time does not depend on the wall clock at all

    def __init__(self, start: float = 0.0) -> None:
        self._t = float(start)
        self._lock = threading.Lock()

    def now(self) -> float:
        with self._lock:
            return self._t

    def advance(self, dt: float) -> float:
        if dt < 0:
            raise ValueError("a clock cannot go back in time")
        with self._lock:
            self._t += dt
            return self._t

    def set(self, t: float) -> None:
        with self._lock:
            if t < self._t:
                raise ValueError("a clock cannot go back in time")
            self._t = float(t)

    def wait(self, event: threading.Event, timeout: float) -> bool:
        """A run's wait (foamlab.acquisition.clock.RunClock): virtual time moves on by `timeout`
        unless `event` is already set - a run in virtual time never sleeps."""
        if event.is_set():
            return True
        self.advance(max(float(timeout), 0.0))
        return event.is_set()

    def sleep(self, seconds: float) -> None:
        self.advance(max(float(seconds), 0.0))

    def to_real(self, virtual_s: float) -> float:
        return 0.0

    def to_virtual(self, real_s: float) -> float:
        return 0.0
