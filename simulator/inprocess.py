"""The simulated machine in-process: a drivers.base.Machine with no wire and no process.

InProcessMachine serves a SimulatedMachine through the machine interface, as the wire
simulators (modbus_server, serial_server) serve it through a protocol, minus the wire: each
request is one call at one instant of the machine's clock, and feeds the drive's watchdog as a
request on the wire does. The run engine, the window and the tests use it like any driver.

With a ManualClock shared with the run (RunEngine(..., clock=machine.clock)) the run's waits
advance virtual time: minutes of machine time, stops, limits and faults take milliseconds and
never depend on how busy the computer is. With a VirtualClock (speedup) it runs in real time.

The link cannot fail by itself; a test scripts a request's failure (`fail("status",
DeviceTimeout(...), times=2)`), so a lost reading, a failed status poll or a stop that is not
acknowledged are tested without a wire. The wire's own faults (dropped frames, bad checksums)
are the HIL tests' (tests/test_faults.py).
"""

from __future__ import annotations

import collections
import time
from typing import Any, Mapping

from drivers.base import (Crosshead, CrossheadStatus, DeviceError, ForceReading, LoadCell, LoadCellStatus, Machine,
                          MachineSample)
from drivers.profile import load_profile
from simulator.clock import ManualClock
from simulator.machine import FAULT_CODES, LoadCellReading, SimulatedMachine

#: The profile an in-process machine takes its limits, capacity and speeds from by default.
DEFAULT_PROFILE = "sim-modbus-tcp"
#: The requests a test may script to fail (InProcessMachine.fail).
REQUESTS = ("connect", "read", "position", "status", "move", "jog", "stop", "estop", "reset", "zero", "tare",
            "limits")
_FAULT_NAMES = {code: name for name, code in FAULT_CODES.items()}


class _Link:
    """The requests' way to the machine: scripted failures, a count of each request, the watchdog."""

    def __init__(self, sim: SimulatedMachine):
        self.sim = sim
        self.requests: collections.Counter[str] = collections.Counter()
        self._failures: dict[str, collections.deque[DeviceError]] = collections.defaultdict(collections.deque)

    def fail(self, request: str, error: DeviceError, times: int = 1) -> None:
        if request not in REQUESTS:
            raise ValueError(f"unknown request {request!r}; one of {', '.join(REQUESTS)}")
        self._failures[request].extend([error] * times)

    def request(self, name: str) -> None:
        self.requests[name] += 1
        if self._failures[name]:
            raise self._failures[name].popleft()
        self.sim.host_activity()


def _load_cell_status(reading: LoadCellReading) -> LoadCellStatus:
    return LoadCellStatus(under_range=reading.under_range, over_range=reading.over_range,
                          stable=reading.no_motion, tare_set=reading.tare_set)


class InProcessLoadCell(LoadCell):
    def __init__(self, sim: SimulatedMachine, link: _Link):
        self.sim, self._link = sim, link
        self.capacity_N = sim.settings.capacity_N

    def read(self) -> ForceReading:
        self._link.request("read")
        reading = self.sim.read_load_cell()
        return ForceReading(reading.net_N, _load_cell_status(reading))

    def zero(self) -> None:
        self._link.request("zero")
        self.sim.zero_load_cell()

    def tare(self) -> None:
        self._link.request("tare")
        self.sim.tare()


class InProcessCrosshead(Crosshead):
    """A refused motion command is ignored, as a drive ignores it: its status says why (fault, limit)."""

    def __init__(self, sim: SimulatedMachine, link: _Link):
        self.sim, self._link = sim, link

    def read_position(self) -> float:
        self._link.request("position")
        return self.sim.position_mm()

    def status(self) -> CrossheadStatus:
        self._link.request("status")
        s = self.sim.crosshead_status()
        return CrossheadStatus(moving=s.moving, in_position=s.in_position, upper_limit=s.upper_limit,
                               lower_limit=s.lower_limit, fault=s.fault, emergency_stopped=s.emergency_stop)

    def fault_reason(self) -> str:
        """The latched fault in words (the run's reason names it: safety.fault_name)."""
        return _FAULT_NAMES.get(self.sim.crosshead_status().fault_code, "unknown")

    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        self._link.request("move")
        self.sim.move_to(target_mm, speed_mm_min)

    def jog(self, direction: int, speed_mm_min: float) -> None:
        self._link.request("jog")
        self.sim.jog(direction, speed_mm_min)

    def stop(self) -> None:
        self._link.request("stop")
        self.sim.stop()

    def emergency_stop(self) -> None:
        self._link.request("estop")
        self.sim.emergency_stop()

    def reset_fault(self) -> None:
        self._link.request("reset")
        self.sim.reset_fault()

    def set_zero(self) -> None:
        self._link.request("zero")
        self.sim.set_zero()

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        self._link.request("limits")
        self.sim.set_travel_limits(upper_mm, lower_mm)


class InProcessMachine(Machine):
    """A SimulatedMachine behind the machine interface (see the module docstring).

    `sim`: the machine to serve (default: one made from `profile` and `sim_settings`, on a
    ManualClock unless a clock or speedup is given); `profile`: a profile name or dict for the
    machine's limits (default DEFAULT_PROFILE, named "sim-in-process").
    """

    def __init__(self, sim: SimulatedMachine | None = None, profile: str | Mapping[str, Any] | None = None,
                 **sim_settings):
        if profile is None or isinstance(profile, str):
            loaded = load_profile(profile or DEFAULT_PROFILE)
            profile = dict(loaded, name="sim-in-process") if profile is None else loaded
        self.profile = dict(profile)
        if sim is None:
            if "clock" not in sim_settings and "speedup" not in sim_settings:
                sim_settings["clock"] = ManualClock()
            sim = SimulatedMachine(self.profile, **sim_settings)
        self.sim = sim
        self.clock = sim.clock
        self._link = _Link(sim)
        self.load_cell = InProcessLoadCell(sim, self._link)
        self.crosshead = InProcessCrosshead(sim, self._link)
        # the instants a sample describes, on the host's clock: the machine's own when the run
        # shares its ManualClock, else the monotonic clock the run keeps its deadlines by
        self._host_clock = self.clock.now if isinstance(self.clock, ManualClock) else time.monotonic

    @property
    def requests(self) -> collections.Counter[str]:
        """How many of each request the machine has been sent."""
        return self._link.requests

    def fail(self, request: str, error: DeviceError, times: int = 1) -> None:
        """The next `times` requests named `request` (REQUESTS) raise `error` instead of reaching the machine."""
        self._link.fail(request, error, times)

    def connect(self) -> None:
        self._link.request("connect")

    def read_sample(self) -> MachineSample:
        """Force and position at one instant of the machine (one request)."""
        self._link.request("read")
        reading, position = self.sim.read_sample()
        return MachineSample(reading.net_N, position, _load_cell_status(reading), self._host_clock())

    def close(self) -> None:
        """The link has nothing to close; the simulated machine stays the caller's (sim.close())."""
