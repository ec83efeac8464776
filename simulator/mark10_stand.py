"""What the simulated ESM303 stand and Series 5 gauge do with each command (device semantics).

Commands, argument formats, reply templates, units and error codes come from the device
file (configs/devices/mark10-esm303.toml, read by drivers.mark10_device), the driver's
one source too. Where the manuals are silent the device file's assumptions hold (no
terminator, no acknowledgement, `n` as force line then travel line, `p` as space-separated
codes). What the device file cannot say is the simulator's choice, said here:

- the stand ignores a byte that starts no command, and a command whose fixed-width
  argument does not fit its format (the manual documents no stand error reply);
- a move toward a limit the crosshead is at is ignored (it stays stopped: `p` says S, DL/UL);
- the stand keeps no fault: a jam (fault plan `stall`) stops the crosshead, and the next
  `d` / `u` moves again; there is no e-stop command (the machine's e-stop is never used);
- the stand's ends (manual mode) are the profile's travel limits; it powers up in manual
  mode, in the profile's units, at 50 mm/min;
- the gauge answers `*10` to anything its device file does not list, `*11` to `?A` (it has
  no Average mode), `*22` to AOFF above 30 and `*12` to AOFF without a number.
"""

from __future__ import annotations

import logging
import re
from typing import Any

from drivers.mark10_device import Command, CommandSet, StandUnit

log = logging.getLogger(__name__)

#: Stand speed before the host sets one (mm/min).
DEFAULT_SPEED_MM_MIN = 50.0
#: Identity lines (`RN` `RM` `RV` `RS`): a simulated gauge says so.
IDENTITY = {"read_name": "foamlab simulated Series 5", "read_model": "M5-100 (simulated)",
            "read_firmware": "1.00", "read_serial": "SIM00001"}


class Refused(Exception):
    """The gauge refuses a command with one of its `*NN` codes."""

    def __init__(self, code: str):
        super().__init__(code)
        self.code = code


class Esm303:
    """The stand: limit / manual mode, programmed limits, units, speed, on the shared SimulatedMachine."""

    def __init__(self, machine: Any, commands: CommandSet, profile: dict, gauge: "Series5"):
        self.machine = machine
        self.commands = commands
        self.gauge = gauge
        crosshead = profile.get("crosshead", {})
        self.sign = int(crosshead.get("travel_sign", 1))
        self.unit: StandUnit = commands.stand_units[crosshead.get("travel_unit", "mm")]
        st = machine.settings
        self.ends = (st.travel_upper_mm, st.travel_lower_mm)
        self.upper_mm, self.lower_mm = self.ends      # programmed limits (mm positive down)
        self.speed_mm_min = min(DEFAULT_SPEED_MM_MIN, st.max_speed_mm_min)
        self.mode = "M"
        self.direction = 0                            # of the last d / u
        self.by_letter: dict[str, Command | StandUnit] = {c.prefix: c for c in commands.stand.values()}
        self.by_letter.update({u.command: u for u in commands.stand_units.values()})

    # -- the byte stream
    def argument_width(self, command: Command | StandUnit, following: bytes) -> int | None:
        """Bytes after the letter (fixed width, one more for a minus); None: the next byte is needed first."""
        if isinstance(command, StandUnit):
            return 0
        if "{speed}" in command.send:
            return self._width(self.unit.speed)
        if "{limit}" in command.send:
            if not following:
                return None
            return self._width(self.unit.limit) + (following == b"-")
        return 0

    @staticmethod
    def _width(fmt) -> int:
        return fmt.integer_digits + 1 + fmt.decimals

    def execute(self, entry: Command | StandUnit, argument: str) -> list[str]:
        """Reply lines (none for the silent commands)."""
        if isinstance(entry, StandUnit):
            self.unit = entry
            return []
        if argument:
            fmt = self.unit.speed if "{speed}" in entry.send else self.unit.limit
            if not re.fullmatch(fmt.pattern(signed=fmt is self.unit.limit), argument):
                log.info("stand ignores %r: argument not in the %s format", entry.prefix + argument, self.unit.name)
                return []
        return getattr(self, f"_do_{entry.name}")(argument) or []

    # -- conversions
    def _mm(self, stand_value: float) -> float:
        return self.sign * stand_value * self.unit.to_mm

    def _stand(self, mm: float) -> float:
        return self.sign * mm / self.unit.to_mm

    def _reading(self, mm: float, decimals: int | None = None) -> str:
        return f"{self._stand(mm):.{self.unit.reading_decimals if decimals is None else decimals}f}"

    def _lines(self, name: str, **values) -> list[str]:
        units = {"travel_unit": self.unit.reply, "speed_unit": self.unit.speed_unit}
        return [t.format(**units, **values) for t in self.commands.stand[name].reply]

    def _apply_limits(self) -> None:
        limits = (self.upper_mm, self.lower_mm) if self.mode == "L" else self.ends
        try:
            self.machine.set_travel_limits(*limits)
        except ValueError as exc:   # upper not above lower: the stand keeps its previous limits
            log.info("stand ignores the limits %s: %s", limits, exc)

    # -- motion
    def _move(self, direction: int) -> None:
        if self.machine.crosshead_status().fault:
            self.machine.reset_fault()   # the stand keeps no fault: a jam only stopped it
        self.direction = direction
        self.machine.jog(direction, self.speed_mm_min)   # False at the limit: it stays stopped

    def _do_move_down(self, _):
        self._move(+1)

    def _do_move_up(self, _):
        self._move(-1)

    def _do_stop(self, _):
        self.machine.stop()

    def _do_zero_travel(self, _):
        self.machine.set_zero()

    def _do_limit_mode(self, _):
        self.mode = "L"
        self._apply_limits()

    def _do_manual_mode(self, _):
        self.mode = "M"
        self._apply_limits()

    def _do_set_speed(self, argument):
        speed = float(argument) * self.unit.to_mm
        if speed > 0:
            self.speed_mm_min = min(speed, self.machine.settings.max_speed_mm_min)

    def _do_set_lower_limit(self, argument):
        self.lower_mm = self._mm(float(argument))
        self._apply_limits()

    def _do_set_upper_limit(self, argument):
        self.upper_mm = self._mm(float(argument))
        self._apply_limits()

    # -- requests
    def _do_read_travel(self, _):
        return self._lines("read_travel", travel=self._reading(self.machine.position_mm()))

    def _do_read_sample(self, _):
        travel = self._reading(self.machine.position_mm())
        force, unit = self.gauge.reading()
        return self._lines("read_sample", travel=travel, force=force, force_unit=unit)

    def _do_status(self, _):
        s = self.machine.crosshead_status()
        velocity = self.machine.speed_mm_min()
        down = velocity > 0 or (velocity == 0 and self.direction > 0)   # v = 0 at a move's first instant
        codes = ["D" if down else "U"] if s.moving else ["S"]
        codes.append(self.mode)
        if not s.moving:   # at a limit once stopped there (C3's `S L DL`); leaving it, just moving
            codes += ["UL"] * s.upper_limit + ["DL"] * s.lower_limit
        return self._lines("status", status=" ".join(codes))

    def _do_read_speed(self, _):
        speed = self.speed_mm_min / self.unit.to_mm
        return self._lines("read_speed", speed=f"{speed:.{self.unit.speed.decimals}f}")

    def _do_read_upper_limit(self, _):
        return self._lines("read_upper_limit", limit=self._reading(self.upper_mm, self.unit.limit.decimals))

    def _do_read_lower_limit(self, _):
        return self._lines("read_lower_limit", limit=self._reading(self.lower_mm, self.unit.limit.decimals))


class Series5:
    """The gauge (GCL2): readings in its unit, one zero, the settings its device file lists."""

    def __init__(self, machine: Any, commands: CommandSet):
        self.machine = machine
        self.commands = commands
        self.unit = commands.gauge_units["N"]
        self.full = True            # readings with units
        self.auto_off_min = 5
        self.by_text = {c.send: c for c in commands.gauge.values() if "{" not in c.send}

    def reading(self) -> tuple[str, str]:
        """(number, unit) of the present net force; compression positive (S9)."""
        value = self.machine.read_load_cell().net_N / self.unit.to_newton
        return f"{value:.{self.commands.force_decimals}f}", self.unit.reply

    def _force_lines(self, name: str) -> list[str]:
        force, unit = self.reading()
        if not self.full:
            return [force]
        return [t.format(force=force, force_unit=unit) for t in self.commands.gauge[name].reply]

    def execute(self, line: str) -> list[str]:
        """Reply lines to one GCL2 command (without its CR); Refused for the `*NN` codes."""
        unit = next((u for u in self.commands.gauge_units.values() if u.command == line), None)
        if unit is not None:
            self.unit = unit
            return []
        if line.startswith("AOFF") and "auto_off" in self.commands.gauge:
            return self._auto_off(line[4:])
        command = self.by_text.get(line)
        if command is None:
            raise Refused("*10")
        name = command.name
        if name in ("read_current", "read_displayed"):
            return self._force_lines(name)   # the simulated gauge displays the current reading
        if name == "read_average":
            raise Refused("*11")             # no Average mode here: not applicable
        if name == "zero":
            self.machine.zero_load_cell()    # zero the display and clear the peaks
            return []
        if name in ("full", "data_numeric"):
            self.full = name == "full"
            return []
        if name in IDENTITY:
            return [IDENTITY[name]]
        if name == "list":
            return [self._settings()]
        raise Refused("*10")

    def _auto_off(self, argument: str) -> list[str]:
        if not argument.isdigit():
            raise Refused("*12")
        if int(argument) > 30:
            raise Refused("*22")
        self.auto_off_min = int(argument)
        return []

    def _settings(self) -> str:
        """The LIST line in the form of S5 p.19's example, with this gauge's unit and data format."""
        data = self.commands.gauge["full"].send if self.full else self.commands.gauge["data_numeric"].send
        return f"V1.00;{self.unit.reply.upper()};CUR;FLTC8;FLTP1;AOUT00;AOFF{self.auto_off_min};{data};MIT;POL;B0"
