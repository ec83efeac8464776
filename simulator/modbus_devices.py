"""The simulated machine as the two Modbus devices of its profile: a Flintec DAD 141.1 (or a Laumas
TLU) and a Leadshine CS2RS.

Each answers the registers of its device file (configs/devices/<id>.toml, read by
drivers.registers, as the driver reads it) and nothing else: pymodbus' SimData covers
exactly those addresses, so any other address answers exception 0x02, and so does a
write to a read-only register. The datastore is live (SimDevice's `action` hook runs
before every access): read-only registers are computed from the SimulatedMachine at that
moment, writes are stored first and then acted on (a 32-bit value written in two halves
acts with both halves present). A value the device refuses answers 0x03 (the CS2RS's
"wrong data", S3 §4.4.1) and leaves the stored value as it was.

Where a manual leaves behaviour open, the simulator's choice is said where it is made.
"""

from __future__ import annotations

import logging
import math
from typing import Any, Callable

from pymodbus.constants import ExcCodes
from pymodbus.simulator import DataType, SimData, SimDevice

from drivers.registers import UNIT_N, DeviceMap
from simulator.machine import FAULT_EMERGENCY, FAULT_NONE, FAULT_STALL

log = logging.getLogger(__name__)


class Refused(Exception):
    """A write the device does not take: answered with exception 0x03."""


class LiveDevice:
    """A SimDevice serving one device file; subclasses compute `live()` values and act `on_write()`."""

    def __init__(self, machine: Any, device: DeviceMap):
        self.machine = machine
        self.device = device
        self.functions = device.functions
        self._stored: dict[str, int | float] = {}

    def sim_device(self, unit_id: int) -> SimDevice:
        spans = [(r.address, r.count, r) for r in self.device.registers.values()]
        spans += [(b.address, b.count, None) for b in self.device.blocks.values() if b.is_copy]
        data = []
        for address, count, register in sorted(spans, key=lambda s: s[0]):
            if register is None or register.access == "r":
                data.append(SimData(address, count=count, datatype=DataType.REGISTERS, readonly=True))
            else:
                words = register.encode(self.initial(register.name), self.device.word_order)
                data.append(SimData(address, datatype=DataType.REGISTERS, values=words))
        return SimDevice(unit_id, simdata=data, action=self._action)

    def initial(self, name: str) -> int | float:
        return 0

    def live(self, names: set[str]) -> dict[str, int | float]:
        raise NotImplementedError

    def on_write(self, name: str, value: int, stored: Callable[[str], int | float]) -> None:
        raise NotImplementedError

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | None) -> ExcCodes | None:
        requested = range(address, address + count)
        order = self.device.word_order
        if set_values is None:
            self._fill(requested, start_address, registers)
            return None
        offset = address - start_address
        previous = registers[offset:offset + len(set_values)]
        registers[offset:offset + len(set_values)] = set_values

        def stored(name: str) -> int | float:
            reg = self.device.registers[name]
            first = reg.address - start_address
            return reg.decode(registers[first:first + reg.count], order)

        try:
            for reg in sorted(self.device.registers.values(), key=lambda r: r.address):
                if reg.access != "r" and _overlaps(reg.address, reg.count, requested):
                    self.on_write(reg.name, int(stored(reg.name)), stored)
        except (Refused, ValueError) as exc:   # ValueError: the machine refused the value
            registers[offset:offset + len(set_values)] = previous
            log.info("%s refused a write at 0x%04X: %s", self.device.name, address, exc)
            return ExcCodes.ILLEGAL_VALUE
        return None

    def _fill(self, requested: range, start_address: int, registers: list[int]) -> None:
        """Put the machine's present values into the read-only registers (and copies) asked for."""
        order = self.device.word_order
        regs = [r for r in self.device.registers.values() if r.access == "r" and _overlaps(r.address, r.count, requested)]
        copies = [b for b in self.device.blocks.values() if b.is_copy and _overlaps(b.address, b.count, requested)]
        wanted = {r.name for r in regs} | {r.name for b in copies for r in b.layout}
        if not wanted:
            return
        values = self.live(wanted)
        for reg in regs:
            first = reg.address - start_address
            registers[first:first + reg.count] = reg.encode(values[reg.name], order)
        for block in copies:
            first = block.address - start_address
            registers[first:first + block.count] = block.encode(values, order)


def _overlaps(first: int, count: int, requested: range) -> bool:
    return first < requested.stop and requested.start < first + count


class Dad141Device(LiveDevice):
    """The Flintec DAD 141.1: floats in the calibration unit, Int32 copies, qualifier, bit commands."""

    def __init__(self, machine: Any, device: DeviceMap, settings: dict):
        super().__init__(machine, device)
        self.per_N = 1.0 / (UNIT_N[settings.get("unit", "N")] * int(settings.get("force_sign", 1)))
        # Int32 copies: display increments, i.e. the value without its decimal point
        # (unconfirmed, S1 is silent): the simulated cell's resolution sets the decimals.
        self.decimals = max(0, round(-math.log10(machine.settings.resolution_N * self.per_N)))
        self.capacity_N = machine.settings.capacity_N
        self._commands = {
            "reset_zero": machine.reset_load_cell_zero, "set_zero": self._set_zero,
            "reset_tare": machine.clear_tare, "set_tare": self._set_tare, "reset_max": machine.reset_peak,
        }

    def live(self, names: set[str]) -> dict[str, int | float]:
        r = self.machine.read_load_cell()
        flags = {"under_range": r.under_range, "over_range": r.over_range, "no_motion": r.no_motion,
                 "tare_set": r.tare_set}
        values: dict[str, int | float] = {"gross": r.gross_N * self.per_N, "net": r.net_N * self.per_N,
                                          "peak": r.peak_N * self.per_N}
        for name in ("gross", "net", "peak"):
            values[f"{name}_int"] = round(values[name] * 10 ** self.decimals)
        values["qualifier"] = sum(1 << bit for name, bit in self.device.bits["qualifier"].items() if flags.get(name))
        # identity: S2 p.30's "D:1410"; firmware 1.06 as S1 p.4 lays it out (minor byte first)
        values.update(device_id=1410, firmware=0x0601)
        return values

    def _stable(self) -> bool:
        return self.machine.read_load_cell().no_motion

    def _set_zero(self) -> None:
        # SZ fails unless stable and within 2 % of CM of the calibration zero (S3 §10.5); S1
        # does not say how Modbus answers then: the write is echoed and nothing happens.
        gross_now = self.machine.read_load_cell().gross_N
        if self._stable() and abs(gross_now) <= 0.02 * self.capacity_N:
            self.machine.zero_load_cell()

    def _set_tare(self) -> None:
        if self._stable():   # ST is disabled when not stable (S3 §10.5); echoed, as for SZ
            self.machine.tare()

    def on_write(self, name: str, value: int, stored: Callable[[str], int | float]) -> None:
        # One documented value per write: S1 never says that bits may be combined.
        names = {v: k for k, v in self.device.values["bit_commands"].items()}
        command = names.get(value)
        if command not in self._commands:
            raise Refused(f"bit command 0x{value:04X} is not one documented value")
        self._commands[command]()


class Cs2rsDevice(LiveDevice):
    """The Leadshine CS2RS in PR mode: pulses and rpm through the profile's screw, PR0, 0x6002, 0x1801.

    Simulated: PR0 position moves (absolute 0x0001, relative 0x0041), set zero, quick stop,
    alarm reset and save. Not simulated, answered 0x03: other paths (0x11-0x1F: only PR0 is
    modelled), homing 0x20 (the simulated machine has no home switch), velocity mode, and
    the RS-485 jog 0x4001/0x4002 (its 50 ms re-send timing). A bad-CRC request is dropped by
    pymodbus, where the real drive answers exception 0x08 (S3 §4.4.1).
    """

    def __init__(self, machine: Any, device: DeviceMap, settings: dict):
        super().__init__(machine, device)
        self.lead_mm, self.gear_ratio = float(settings["lead_mm"]), float(settings["gear_ratio"])
        self.commissioned_ppr = int(settings["pulses_per_rev"])   # the drive as the machine was set up
        self.max_rpm = machine.settings.max_speed_mm_min * self.gear_ratio / self.lead_mm

    def initial(self, name: str) -> int:
        return self.commissioned_ppr if name == "pulses_per_rev" else 0

    def _mm_per_pulse(self, stored: Callable[[str], int | float] | None = None) -> float:
        ppr = stored("pulses_per_rev") if stored else self._ppr
        return self.lead_mm / (self.gear_ratio * ppr)

    @property
    def _ppr(self) -> int:
        return int(self._stored.get("pulses_per_rev", self.commissioned_ppr))

    def live(self, names: set[str]) -> dict[str, int | float]:
        m = self.machine
        s = m.crosshead_status()
        # 0x40 is a stop, not an alarm (nothing documents one): the e-stop record is no fault here.
        fault = s.fault_code not in (FAULT_NONE, FAULT_EMERGENCY)
        flags = {"fault": fault, "enabled": not fault, "running": s.moving, "command_done": not s.moving,
                 "path_done": s.in_position, "homing_done": False}
        pulses = round(m.position_mm() / self._mm_per_pulse())
        alarm = self.device.value("alarm", "position_following") if s.fault_code == FAULT_STALL else 0
        return {"status": sum(1 << bit for name, bit in self.device.bits["status"].items() if flags[name]),
                "alarm": alarm, "motor_position": pulses, "command_position": pulses}

    def on_write(self, name: str, value: int, stored: Callable[[str], int | float]) -> None:
        if name == "pulses_per_rev":
            low, high = self.device.registers[name].range
            if not low <= value <= high:
                raise Refused(f"pulses per revolution {value} outside {low}..{high}")
            self._stored[name] = value
        elif name in ("trigger", "pr0_trigger"):
            self._trigger(value, stored)
        elif name == "control_word":
            self._control(value)
        # the PR0 registers are parameters: stored, used by the next trigger

    def _trigger(self, value: int, stored: Callable[[str], int | float]) -> None:
        codes = self.device.values["trigger"]
        m = self.machine
        if value == codes["start_path0"]:
            self._start_pr0(stored)
        elif value == codes["set_zero"]:
            m.set_zero()
        elif value == codes["quick_stop"]:
            # Pr8.23's deceleration is not documented for the CS2RS: the quick stop is immediate.
            # The machine records it as its e-stop (tests read that); the drive latches nothing,
            # and a latched alarm (a stall) stays what it is.
            if m.crosshead_status().fault_code in (FAULT_NONE, FAULT_EMERGENCY):
                m.emergency_stop()
            else:
                m.stop()
        else:
            raise Refused(f"trigger 0x{value:04X} is not simulated (only PR0, set zero and quick stop)")

    def _start_pr0(self, stored: Callable[[str], int | float]) -> None:
        modes = self.device.values["pr0_mode"]
        mode = int(stored("pr0_mode"))
        if mode not in (modes["absolute"], modes["relative"]):
            raise Refused(f"PR0 mode 0x{mode:04X} is not simulated (position moves only)")
        rpm, ramp = int(stored("pr0_speed")), int(stored("pr0_accel"))
        if rpm > self.max_rpm:
            raise Refused(f"{rpm} rpm beyond the machine's {self.max_rpm:g} rpm")
        if rpm == 0:
            return   # a path at 0 rpm goes nowhere (the manual's own example has velocity 0)
        if ramp == 0:
            raise Refused("acceleration 0 ms/1000 rpm")
        m = self.machine
        if m.crosshead_status().fault_code == FAULT_EMERGENCY:
            m.reset_fault()    # a quick stop is not latched: the next path runs
        mm_per_rev = self.lead_mm / self.gear_ratio
        m.set_acceleration(1000.0 * mm_per_rev / 60.0 / (ramp / 1000.0))
        target = int(stored("pr0_position")) * self._mm_per_pulse(stored)
        if mode == modes["relative"]:
            target += m.position_mm()
        m.move_to(target, rpm * mm_per_rev)   # refused (returns False) while an alarm is latched

    def _control(self, value: int) -> None:
        codes = self.device.values["control_word"]
        if value == codes["reset_alarm"]:
            self.machine.reset_fault()
        elif value != codes["save"]:     # saving parameters changes nothing the simulation models
            raise Refused(f"control word 0x{value:04X} is not simulated")


class TluDevice(LiveDevice):
    """The Laumas TLU: 32-bit weights without their decimal point, the status word, the command register.

    Functions 03 and 16 only (others answer 0x01, simulator.modbus_server); a request with a bad CRC
    gets no reply (pymodbus drops it), as L1 p.30 says. The weights are sent as L3 p.3 has them:
    the magnitude, with the sign in the status bits. The command register takes the documented
    save (99, nothing to model) and answers any other value 0x03: the TLU's zero and tare values
    are not documented, so no value is simulated as doing one. Firmware, instrument type, year,
    serial number, program type and 40014 have no documented encoding: they read 0.
    """

    def __init__(self, machine: Any, device: DeviceMap, settings: dict):
        super().__init__(machine, device)
        self.counts_per_N = 10 ** int(settings["decimals"]) / (UNIT_N[settings.get("unit", "N")]
                                                              * int(settings.get("force_sign", 1)))
        self.capacity_N = machine.settings.capacity_N

    def live(self, names: set[str]) -> dict[str, int | float]:
        r = self.machine.read_load_cell()
        counts = {name: round(value * self.counts_per_N)
                  for name, value in (("gross", r.gross_N), ("net", r.net_N), ("peak", r.peak_N))}
        flags = {"over_9_divisions": r.over_range, "over_110_percent": r.gross_N > 1.1 * self.capacity_N,
                 "gross_overflow": abs(counts["gross"]) > 999999, "net_overflow": abs(counts["net"]) > 999999,
                 "net_mode": r.tare_set, "stable": r.no_motion,
                 "centre_of_zero": abs(r.gross_N * self.counts_per_N) <= 0.25}     # within 1/4 division
        flags.update({f"{name}_negative": value < 0 for name, value in counts.items()})
        values: dict[str, int | float] = {name: abs(value) for name, value in counts.items()}
        values["status"] = sum(1 << bit for name, bit in self.device.bits["status"].items() if flags.get(name))
        values.update({name: 0 for name in names - values.keys()})
        return values

    def on_write(self, name: str, value: int, stored: Callable[[str], int | float]) -> None:
        if name == "command" and value != self.device.value("command", "save_eeprom"):
            raise Refused(f"command {value} is not one the TLU's manual documents")
        # setpoint 1 is a parameter: stored (the simulated TLU has no outputs to switch)


#: Device id -> its simulation.
SIMULATIONS = {"flintec-dad141": Dad141Device, "laumas-tlu": TluDevice, "leadshine-cs2rs": Cs2rsDevice}


def simulate(machine: Any, device: DeviceMap, settings: dict) -> LiveDevice:
    try:
        return SIMULATIONS[device.id](machine, device, settings)
    except KeyError:
        raise ValueError(f"no simulation of {device.id} (simulated: {', '.join(SIMULATIONS)})") from None


__all__ = ["Cs2rsDevice", "Dad141Device", "LiveDevice", "Refused", "TluDevice", "simulate"]
