"""The small machine interface every driver implements and the run engine uses.

Conventions (all drivers convert from device units using their profile):
- force in N, compression positive;
- crosshead position in mm, positive DOWN (into the specimen), 0 at the machine's zero;
- speeds in mm/min (what lab people use).
Errors: every driver raises DeviceError subclasses, never a bare exception from
pyserial/pymodbus; the engine relies on that to stop safely and record a reason.
`drivers` knows nothing of `foamlab`.
"""

from __future__ import annotations

import abc
import time
from collections.abc import Callable
from dataclasses import dataclass, field


class DeviceError(Exception):
    """Base class for anything that went wrong talking to a device."""


class DeviceTimeout(DeviceError):
    """The device did not answer in time (after the configured retries)."""


class DeviceConnectionLost(DeviceError):
    """The link (socket, serial port) is gone."""


class DeviceProtocolError(DeviceError):
    """Garbled reply, bad CRC, Modbus exception reply, `*10`-style error reply."""


class DeviceRefused(DeviceProtocolError):
    """The device understood and answered with its own error (a Modbus exception, a `*22`):
    repeating the request will not help, and the run stops at once."""


#: Sends of a connect's handshake whose reply was lost (DeviceTimeout). Each step reads or writes a
#: setting, the same however often it arrives: one reply lost to a busy computer (CI run 47: the
#: CS2RS's 0x0001 unanswered in 2 x 40 ms) must not refuse the machine.
HANDSHAKE_ATTEMPTS = 3


def handshake(steps: Callable[[], None], attempts: int = HANDSHAKE_ATTEMPTS) -> None:
    """Run a connect's handshake, again from its start after a lost reply (other errors raise at once)."""
    for attempt in range(attempts):
        try:
            steps()
            return
        except DeviceTimeout:
            if attempt == attempts - 1:
                raise


@dataclass(frozen=True)
class LoadCellStatus:
    under_range: bool = False
    over_range: bool = False      # overload: force beyond the cell's capacity
    stable: bool = False          # no-motion flag
    tare_set: bool = False


@dataclass(frozen=True)
class CrossheadStatus:
    moving: bool = False
    in_position: bool = False
    upper_limit: bool = False     # travel limit reached going up (position low)
    lower_limit: bool = False     # travel limit reached going down (position high)
    fault: bool = False           # stall, following error, watchdog, e-stop latched
    emergency_stopped: bool = False


@dataclass(frozen=True)
class ForceReading:
    force_N: float
    status: LoadCellStatus


class LoadCell(abc.ABC):
    capacity_N: float

    @abc.abstractmethod
    def read(self) -> ForceReading:
        """Net force and status, in one request when the device allows it."""

    @abc.abstractmethod
    def zero(self) -> None:
        """Set the gross zero (no load on the cell)."""

    @abc.abstractmethod
    def tare(self) -> None:
        """Tare: net := 0 at the present load."""


class Crosshead(abc.ABC):
    #: The step of read_position() in mm (a reading's last digit, one encoder pulse), from the
    #: device file and profile; 0 when the driver does not know it. The run file records it.
    position_resolution_mm: float = 0.0

    @abc.abstractmethod
    def read_position(self) -> float:
        """Position in mm, positive down."""

    @abc.abstractmethod
    def status(self) -> CrossheadStatus: ...

    @abc.abstractmethod
    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        """Start a move to an absolute position; returns at once (non-blocking)."""

    @abc.abstractmethod
    def jog(self, direction: int, speed_mm_min: float) -> None:
        """Start moving down (+1) or up (-1) until stopped or a limit is hit."""

    @abc.abstractmethod
    def stop(self) -> None:
        """Controlled stop (decelerate)."""

    @abc.abstractmethod
    def emergency_stop(self) -> None:
        """Immediate stop; latches a fault until reset_fault()."""

    @abc.abstractmethod
    def reset_fault(self) -> None: ...

    @abc.abstractmethod
    def set_zero(self) -> None:
        """Make the present position the machine's zero."""

    @abc.abstractmethod
    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        """Soft limits in mm (upper = smallest position, lower = largest position)."""


@dataclass(frozen=True)
class MachineSample:
    """Force and position at one instant (one request where the device allows it)."""

    force_N: float
    position_mm: float
    load_cell_status: LoadCellStatus | None = None   # None: the device reports none with the sample
    #: time.monotonic() of the instant both values describe (None: not known)
    time: float | None = field(default=None, compare=False)


class Machine(abc.ABC):
    """A load cell and a crosshead behind one connection (or two)."""

    load_cell: LoadCell
    crosshead: Crosshead

    @abc.abstractmethod
    def connect(self) -> None:
        """Open the link(s) and configure the devices; calling it again is harmless."""

    def read_sample(self) -> MachineSample:
        """Force and position at one instant; drivers override it when one request gives both.

        Two devices answer two requests, a round trip apart: at 16 Hz on a real machine that
        is ~1 um of travel, but against a simulated machine whose clock runs S times faster
        it is S round trips of machine time, and the model's fractional near-derivative turns
        1 um into ~0.05 N. So the position is read just before and just after the force and
        interpolated to the force reading's instant (its request's midpoint): the two
        position readings bracket the force reading, so whatever delays a request within a
        sample (the host's or the device's scheduling) shifts all three alike. Reusing the
        previous sample's position instead left structured residuals that diagnosis took for
        a cause (measured: docs/protocols.md#reading-a-sample-the-position-brackets-the-force).
        """
        t0 = time.monotonic()
        before = self.crosshead.read_position()
        t1 = time.monotonic()
        reading = self.load_cell.read()
        t2 = time.monotonic()
        after = self.crosshead.read_position()
        t3 = time.monotonic()
        at_before, at_force, at_after = 0.5 * (t0 + t1), 0.5 * (t1 + t2), 0.5 * (t2 + t3)
        position = before + (after - before) * (at_force - at_before) / max(at_after - at_before, 1e-9)
        return MachineSample(reading.force_N, position, reading.status, at_force)

    @abc.abstractmethod
    def close(self) -> None:
        """Close the link(s); never raises."""

    def __enter__(self) -> "Machine":
        self.connect()
        return self

    def __exit__(self, *exc) -> None:
        self.close()
