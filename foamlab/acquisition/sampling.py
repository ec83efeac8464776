"""Sampling: one sample per deadline of the schedule - read the machine, hand the sample to the
recorder, check the limits, tell the listeners - and the drive's status read between samples."""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable

from drivers.base import DeviceConnectionLost, DeviceError, DeviceRefused, Machine
from foamlab.acquisition.clock import WALL_CLOCK, RunClock
from foamlab.acquisition.events import END_FAULT, Listeners, RunAborted, Sample
from foamlab.acquisition.safety import CrossheadWatch, Limits
from foamlab.acquisition.schedule import SampleSchedule, ScheduleStats
from foamlab.acquisition.settings import DEFAULT, AcquisitionSettings
from foamlab.methods import PlannedStep
from foamlab.storage.recorder import Recorder

log = logging.getLogger(__name__)


class Sampler:
    """Takes a run's samples on its schedule (see the module docstring).

    `check_flags` raises when the run must end (stop, e-stop); `on_sample(sample)` follows each
    recorded sample (progress). `step` (the plan step under way) labels the samples and
    `contact` (machine position of displacement 0) makes their displacement.
    """

    def __init__(self, machine: Machine, limits: Limits, recorder: Recorder, listeners: Listeners, *,
                 period_s: float, speedup: float, wake: threading.Event, check_flags: Callable[[], None],
                 on_sample: Callable[[Sample], None], clock: RunClock = WALL_CLOCK,
                 settings: AcquisitionSettings = DEFAULT):
        self.machine, self.limits, self.recorder, self.listeners = machine, limits, recorder, listeners
        self.clock, self.settings = clock, settings
        self.period_s, self.speedup, self.wake = period_s, speedup, wake
        self.check_flags, self.on_sample = check_flags, on_sample
        self.watch = CrossheadWatch(machine, clock, settings)
        self.schedule: SampleSchedule | None = None
        self.t0 = 0.0
        self.step: PlannedStep | None = None
        self.contact = 0.0
        self.failed_reads = 0
        self._in_a_row = 0
        self._late: list[float] = []

    def restart(self, interrupted: bool) -> SampleSchedule:
        """A new schedule (and machine clock) from now; `interrupted`: wake at once (a stop is due)."""
        self.wake.clear()
        if interrupted:
            self.wake.set()
        self.schedule = SampleSchedule(self.period_s, clock=self.clock.now, wake=self.wake, wait=self.clock.wait)
        self.t0 = self.schedule.t0
        self.failed_reads = 0
        return self.schedule

    def machine_time(self, wall: float) -> float:
        return (wall - self.t0) * self.speedup

    def waited_for_device(self, seconds: float) -> None:
        if self.schedule is not None:
            self.schedule.waited_for_device(seconds)

    def read_status(self):
        """The drive's status now (raises on its alarms; None when the request failed)."""
        return self.watch.read(self.schedule)

    def stats(self) -> ScheduleStats:
        if self.schedule is None:
            return ScheduleStats.from_arrays(self.period_s, [], [], 0, 0)
        return self.schedule.stats(self._late, self.recorder.rtt_ms, self.failed_reads)

    def take(self, record: bool) -> tuple[float, float] | None:
        """The next scheduled sample: (position, force), or None when woken or the read failed."""
        schedule = self.schedule
        slot = schedule.next()
        self.check_flags()
        if slot is None:
            return None
        _, lateness = slot
        t_request = self.clock.now()
        try:
            reading = self.machine.read_sample()
        except DeviceConnectionLost:
            raise
        except DeviceRefused as exc:     # the device said no: asking again will not change that
            raise RunAborted(END_FAULT, f"device refused a sample: {exc}") from None
        except DeviceError as exc:
            schedule.waited_for_device(self.clock.now() - t_request)
            self.failed_reads += 1
            self._in_a_row += 1
            schedule.miss()
            if self._in_a_row > self.settings.max_failed_reads:
                raise RunAborted(END_FAULT, f"device not answering: {exc}") from None
            log.warning("sample failed (%d in a row): %s", self._in_a_row, exc)
            return None
        t_done = self.clock.now()
        schedule.waited_for_device(t_done - t_request)
        self._in_a_row = 0
        position, force = reading.position_mm, reading.force_N
        # the sample goes to disk first (also the one that crosses a limit), then the limits
        # are checked (an abort stops the crosshead at once), then the listeners hear of it;
        # stamped with the instant the driver says both values describe (Machine.read_sample)
        instant = reading.time or (t_request + t_done) / 2
        sample = self._record(instant, position, force, (t_done - t_request) * 1e3,
                              lateness * 1e3) if record else None
        self.limits.check_sample(position, force, reading.load_cell_status, self.settings)
        if sample is not None:
            if self.listeners:
                self.listeners.emit("on_sample", sample)
            self.on_sample(sample)
        self.watch.maybe_read(schedule)
        return position, force

    def _record(self, wall: float, position: float, force: float, rtt_ms: float, late_ms: float) -> Sample:
        # rounded far below the instruments' resolution: keeps the float noise of the
        # subtraction (0.015000000000000568) and of float32 registers out of the file
        t = round(self.machine_time(wall), 6)
        disp, force, rtt_ms = round(position - self.contact, 6), round(force, 6), round(rtt_ms, 3)
        index, cycle = (self.step.index, self.step.step.cycle) if self.step else (-1, 0)
        n = len(self.recorder)
        self._late.append(late_ms)
        self.recorder.record(t, disp, force, rtt_ms, index, cycle)
        return Sample(n, t, disp, force, rtt_ms, late_ms, position, cycle, index)
