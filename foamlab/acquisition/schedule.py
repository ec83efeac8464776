"""The sampling schedule: fixed deadlines on the monotonic clock, misses counted and
attributed, and what the operating system can do for a worker that must keep them
(real-time priority, zero CPU wake-up latency)."""

from __future__ import annotations

import os
import sys
import threading
import time
from dataclasses import dataclass
from typing import Callable

import numpy as np


@dataclass(frozen=True)
class ScheduleStats:
    period_s: float           # wall period of the schedule
    samples: int
    missed: int
    failed_reads: int
    missed_waiting_device: int   # of `missed`: deadlines that passed only because a request was out
    lateness_p50_ms: float
    lateness_p99_ms: float
    lateness_max_ms: float
    rtt_p50_ms: float
    rtt_p99_ms: float
    rtt_max_ms: float
    work_p99_ms: float = float("nan")   # the engine's own work per sample (device waits excluded)
    work_max_ms: float = float("nan")

    @classmethod
    def from_arrays(cls, period_s: float, lateness_ms, rtt_ms, missed: int, failed: int,
                    missed_waiting_device: int = 0, work_ms=()) -> "ScheduleStats":
        def q(a, p):
            return float(np.percentile(a, p)) if len(a) else float("nan")
        lat, rtt, work = (np.asarray(a, float) for a in (lateness_ms, rtt_ms, work_ms))
        return cls(period_s, len(lat), missed, failed, missed_waiting_device, q(lat, 50), q(lat, 99),
                   q(lat, 100), q(rtt, 50), q(rtt, 99), q(rtt, 100), q(work, 99), q(work, 100))

    @property
    def missed_by_engine(self) -> int:
        """Deadlines the engine's own work lost: they would have passed with instant replies."""
        return self.missed - self.missed_waiting_device


class SampleSchedule:
    """Deadlines t0 + k * period on the monotonic clock.

    `next()` blocks until the next deadline (or until `wake` is set) and returns
    (k, lateness_s). A deadline whose whole period has passed before its sample
    could start is skipped and counted in `missed`: sample k is taken in
    [deadline_k, deadline_k+1) or not at all.

    The caller reports the wall time it spent waiting for the device (`waited_for_device`), so
    that each miss is attributed: `missed_waiting_device` counts the deadlines that would not
    have passed had the device answered at once (a stalled reply, a failed read), the rest are
    the caller's own (`missed - missed_waiting_device`): its work between samples (`work_s`,
    device waits excluded) or a stall of the computer while it worked.
    """

    def __init__(self, period_s: float, start: float | None = None,
                 clock: Callable[[], float] = time.monotonic, wake: threading.Event | None = None,
                 wait: Callable[[threading.Event, float], bool] | None = None):
        if not period_s > 0:
            raise ValueError("the sampling period must be > 0")
        self.period = float(period_s)
        self.clock = clock
        self.t0 = clock() if start is None else start
        self.k = 0
        self.missed = 0
        self.missed_waiting_device = 0
        self._device_s = 0.0          # waited for the device since the last next()
        self._returned = None         # when next() last returned a deadline
        self.work_s: list[float] = []  # per sample: wall time between next()s minus device waits
        self._wake = wake or threading.Event()
        # how to wait for a deadline: on `wake` in wall time, or a virtual clock's wait (RunClock)
        self._wait = wait or (lambda event, timeout: event.wait(timeout))

    def deadline(self, k: int) -> float:
        return self.t0 + k * self.period

    def miss(self) -> None:
        """The sample of the deadline just returned by next() failed (the device's doing)."""
        self.missed += 1
        self.missed_waiting_device += 1

    def waited_for_device(self, seconds: float) -> None:
        """The caller spent `seconds` (wall) in a request to the device."""
        self._device_s += max(0.0, seconds)

    def next(self) -> tuple[int, float] | None:
        """Wait for the next deadline; None when woken early (check your stop flags)."""
        deadline = self.deadline(self.k)
        now = self.clock()
        if self._returned is not None:
            self.work_s.append(max(0.0, now - self._returned - self._device_s))
        self._returned = None
        while now < deadline:
            if self._wait(self._wake, deadline - now):
                return None
            now = self.clock()
        behind = int((now - deadline) // self.period)
        if behind > 0:
            without_device = max(0, int((now - self._device_s - deadline) // self.period))
            self.missed += behind
            self.missed_waiting_device += behind - without_device
            self.k += behind
            deadline = self.deadline(self.k)
        self._device_s = 0.0
        self._returned = now
        k = self.k
        self.k += 1
        return k, now - deadline

    def slack(self) -> float:
        """Wall seconds until the next deadline."""
        return self.deadline(self.k) - self.clock()

    def stats(self, lateness_ms, rtt_ms, failed_reads: int) -> ScheduleStats:
        return ScheduleStats.from_arrays(self.period, lateness_ms, rtt_ms, self.missed, failed_reads,
                                         self.missed_waiting_device, np.multiply(self.work_s, 1e3))


#: Real-time priority asked for the worker thread (Linux SCHED_FIFO, low priority: above
#: normal processes, below the kernel's own real-time threads).
REALTIME_PRIORITY = 10


def in_background() -> bool:
    """The process was started in the idle scheduling class (`chrt --idle 0`, as scripts/test.sh
    runs the tests that keep no schedule): it asked to use only what other work leaves, so it
    takes no real-time priority (which would escape the class)."""
    getter = getattr(os, "sched_getscheduler", None)
    idle = getattr(os, "SCHED_IDLE", None)
    try:
        return getter is not None and idle is not None and getter(0) == idle
    except OSError:
        return False


def raise_thread_priority(priority: int = REALTIME_PRIORITY) -> str:
    """Give the calling thread SCHED_FIFO priority when the OS allows it; say what we got.

    On a busy computer an ordinary thread may wake several ms after its deadline;
    a SCHED_FIFO thread wakes within ~0.1 ms. It needs CAP_SYS_NICE or an rtprio
    limit (/etc/security/limits.conf); without it the run proceeds at normal priority
    (and the schedule statistics show the difference). The thread sleeps between
    samples and blocks on I/O, so it cannot starve the machine.
    """
    setter = getattr(os, "sched_setscheduler", None)   # absent outside Linux
    if setter is None:
        return "normal (no SCHED_FIFO on this OS)"
    if in_background():
        return "idle class (started in the background: no real-time priority taken)"
    try:
        setter(0, os.SCHED_FIFO, os.sched_param(priority))   # pid 0: the calling thread (Linux)
    except (OSError, ValueError) as exc:
        return f"normal (SCHED_FIFO refused: {exc.strerror if isinstance(exc, OSError) else exc})"
    return f"SCHED_FIFO {priority}"


class CpuWakeupLatency:
    """Hold a Linux PM QoS request for zero CPU wake-up latency while a run samples.

    An idle CPU sleeps in a state it takes time to leave (a virtual machine's halted CPU
    waits for its hypervisor: replies came up to ~20 ms late; docs/acquisition.md). With the
    request held (/dev/cpu_dma_latency, as cyclictest does) idle CPUs poll instead. It costs
    power during a run only; it needs root (or a udev rule for the file) and is skipped without.
    """

    PATH = "/dev/cpu_dma_latency"

    def __init__(self) -> None:
        self._fd: int | None = None

    def hold(self) -> str:
        try:
            fd = os.open(self.PATH, os.O_WRONLY)
        except OSError as exc:
            return f"CPU idle states as configured ({exc.strerror})"
        try:
            os.write(fd, (0).to_bytes(4, sys.byteorder))
        except OSError as exc:
            os.close(fd)
            return f"CPU idle states as configured ({exc.strerror})"
        self._fd = fd
        return "CPU wake-up latency 0 us"

    def release(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
