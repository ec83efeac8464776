"""The clock a run keeps its deadlines by: the host's monotonic clock, or a virtual one.

A run on a machine at the end of a wire waits in wall time (WALL_CLOCK). A run against the
in-process simulated machine (simulator.inprocess) shares the machine's ManualClock: every wait
moves virtual time on instead of sleeping, so a run of minutes of machine time, its stops and
its faults take milliseconds and never depend on how busy the computer is.
"""

from __future__ import annotations

import threading
import time
from typing import Protocol


class RunClock(Protocol):
    def now(self) -> float:
        """Seconds on a clock that never goes back."""

    def wait(self, event: threading.Event, timeout: float) -> bool:
        """Wait up to `timeout` s for `event`; True when it is set."""

    def sleep(self, seconds: float) -> None: ...


class WallClock:
    """time.monotonic(), Event.wait and time.sleep: a run in real time."""

    def now(self) -> float:
        return time.monotonic()

    def wait(self, event: threading.Event, timeout: float) -> bool:
        return event.wait(timeout)

    def sleep(self, seconds: float) -> None:
        time.sleep(seconds)


WALL_CLOCK = WallClock()
