"""Modbus machine: a load-cell indicator and a crosshead drive on one link (RTU line or TCP gateway).

Each device is the one its device file describes (configs/devices/<id>.toml, read into a
drivers.registers.DeviceMap) and is driven by that device's class: the Flintec DAD 141.1
(drivers.dad141) or the Laumas TLU (drivers.tlu), and the Leadshine CS2RS (drivers.cs2rs).
Both share one ModbusLink (one socket or one serial line, two unit ids; drivers.modbus_link).
"""

from __future__ import annotations

from .base import DeviceError, Machine, handshake
from .cs2rs import Cs2rsCrosshead
from .dad141 import Dad141LoadCell
from .modbus_link import MODBUS_EXCEPTIONS, DeviceOnLink, ModbusLink
from .registers import DeviceMap, profile_device
from .tlu import TluLoadCell

__all__ = ["DRIVERS", "MODBUS_EXCEPTIONS", "DeviceOnLink", "ModbusLink", "ModbusMachine", "device_map"]

#: Device id (a device file's [device] id) -> the class that drives it, per role.
DRIVERS = {"load_cell": {"flintec-dad141": Dad141LoadCell, "laumas-tlu": TluLoadCell},
           "crosshead": {"leadshine-cs2rs": Cs2rsCrosshead}}


def device_map(profile: dict, role: str) -> DeviceMap:
    """The profile's device for `role` ("load_cell" / "crosshead"), checked against its driver."""
    device = profile_device(profile, role)
    driver = DRIVERS[role].get(device.id)
    if driver is None:
        raise ValueError(f"{device.file}: no {role} driver for {device.id} (drivers: {', '.join(DRIVERS[role])})")
    return driver.check_device(device)


class ModbusMachine(Machine):
    """Load cell and crosshead on one Modbus link (two unit ids), from a loaded profile."""

    def __init__(self, profile: dict):
        self.profile = profile
        self.link = ModbusLink(profile["connection"])
        load_cell, crosshead = device_map(profile, "load_cell"), device_map(profile, "crosshead")
        self.load_cell = DRIVERS["load_cell"][load_cell.id](self.link, load_cell, profile["load_cell"])
        self.crosshead = DRIVERS["crosshead"][crosshead.id](self.link, crosshead, profile["crosshead"],
                                                            profile["limits"])
        self._checked = False

    def connect(self) -> None:
        with self.link.lock:
            if self._checked and self.link.connected:
                return
            try:
                self.link.connect()
                handshake(self._handshake)
            except DeviceError:
                self.link.close()
                raise
            self._checked = True

    def _handshake(self) -> None:
        self.crosshead.check_settings()     # the drive's scaling is the profile's, or no run
        limits = self.profile["limits"]
        self.crosshead.set_travel_limits(limits["travel_upper_mm"], limits["travel_lower_mm"])

    def identify(self) -> str:
        """What the devices say they are (the CS2RS documents no identification register)."""
        return f"{self.load_cell.identify()}; {self.crosshead.drive.device.name}: no identification register"

    def self_checks(self) -> list[tuple[str, bool, str]]:
        """foamlab probe's reads that settle the device files' unconfirmed entries (PROVENANCE.md)."""
        return self.load_cell.self_checks() + self.crosshead.self_checks()

    def close(self) -> None:
        self.link.close()
        self._checked = False
