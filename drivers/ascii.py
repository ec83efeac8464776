"""Mark-10 ESM303 test stand + Series 5 / 7 force gauge on one serial line.

Every byte comes from the device file (configs/devices/mark10-esm303.toml, read by
drivers.mark10_device): stand commands are bare letters or fixed-width strings (`e0200.3`,
`g-007.52`) with no terminator; gauge (GCL2) commands go through the stand: `/`, the
command and CR, its CR LF reply, then `\\`. Replies are lines `<number> <unit>` (`n`: the
force line, then the travel line) or status letter codes (`p`: `S L DL`); where the
manuals are silent the device file says what is assumed, and the parser is tolerant
where it can be: a number without a unit is taken, an empty line is skipped, a line
that is a well-formed reply to another command (a late one) is skipped, and a unit
other than the profile's is a one-line DeviceProtocolError naming both.

Errors: `*10`/`*11`/`*12`/`*22` (the gauge's codes) -> DeviceErrorReply, a DeviceRefused:
never retried, the run stops at once. Silence -> DeviceTimeout, garbage or a partial line
-> DeviceProtocolError, both after `retries` repeats (every query here is safe to repeat);
a vanished port -> DeviceConnectionLost.

What the devices lack is absent here too: no e-stop command (emergency_stop sends `s`),
no fault latch or reset (reset_fault sends nothing), no status bits, no go-to-position
(move_to sets the limit in the direction of travel, enters limit mode and moves).
"""

from __future__ import annotations

import logging
import math
import re
import time

from .base import (
    Crosshead,
    CrossheadStatus,
    DeviceError,
    DeviceProtocolError,
    DeviceRefused,
    DeviceTimeout,
    ForceReading,
    LoadCell,
    LoadCellStatus,
    Machine,
    MachineSample,
    handshake,
)
from .mark10_device import CommandSet, GaugeUnit, StandUnit, reply_fields
from .serial_line import SerialLine

__all__ = ["AsciiMachine", "CommandSet", "DeviceErrorReply", "Mark10Crosshead", "Mark10Link", "Series5Gauge",
           "profile_units"]

log = logging.getLogger(__name__)

_NUMBER = re.compile(r"([-+]?(?:\d+\.?\d*|\.\d+))(?:\s*([A-Za-z][A-Za-z/]*))?")
#: Lines of another command's reply (a late one) skipped while reading one reply.
MAX_SKIPPED = 2
#: The quantity each unit field measures.
QUANTITY = {"force_unit": "force", "travel_unit": "travel", "speed_unit": "speed"}
NO_FAULT_COMMAND = "the ESM303 documents no fault latch and no reset command (S1 §6.2): nothing sent"


class DeviceErrorReply(DeviceRefused):
    """The gauge answered `*NN`: it understood and refused (code and the vendor's meaning)."""

    def __init__(self, message: str, code: str, meaning: str):
        super().__init__(message)
        self.code = code
        self.meaning = meaning


class _Retry(Exception):
    """One attempt failed in a way a repeat may cure (silence, garbage); carries the error."""

    def __init__(self, error: DeviceError):
        super().__init__(str(error))
        self.error = error


class Mark10Link:
    """The ESM303's protocol on a SerialLine: stand commands, stand queries, gauge via `/ ... \\`."""

    def __init__(self, line: SerialLine, commands: CommandSet, stand_unit: StandUnit, gauge_unit: GaugeUnit):
        self.line = line
        self.commands = commands
        self.stand_unit = stand_unit
        self.gauge_unit = gauge_unit
        self.expected_unit = {"force_unit": gauge_unit.reply, "travel_unit": stand_unit.reply,
                              "speed_unit": stand_unit.speed_unit}
        units = {"force": [u.reply for u in commands.gauge_units.values()],
                 "travel": [u.reply for u in commands.stand_units.values()],
                 "speed": [u.speed_unit for u in commands.stand_units.values()]}
        self.quantity_of = {unit: quantity for quantity, names in units.items() for unit in names}

    def connect(self) -> None:
        self.line.connect()

    def close(self) -> None:
        self.line.close()

    # -- sending
    def send(self, name: str, **values) -> str:
        """A stand command that answers nothing (the manual documents no acknowledgement)."""
        return self.send_text(self.commands.stand[name].text(**values))

    def send_text(self, text: str) -> str:
        # under the lock: never while a pass-through is open (an `s` there would reach the gauge)
        with self.line.lock:
            self.line.write(text.encode("ascii") + self.commands.stand_terminator)
        return text

    def ask(self, name: str) -> dict:
        """A stand query: its reply lines parsed into {field: value}."""
        command = self.commands.stand[name]
        return self._exchange(command.send, command.reply, gauge=False)

    def gauge_ask(self, name: str) -> dict:
        command = self.commands.gauge[name]
        return self._exchange(command.send, command.reply, gauge=True)

    def gauge_set(self, text: str) -> None:
        """A gauge setter (`Z`, `N`, `FULL`): silent unless refused, so listen a short while for `*NN`."""
        with self.line.lock:
            self.line.flush_input()
            self._open_gauge(text)
            try:
                raw = self.line.read_line(self.commands.setter_window_s)
            finally:
                self._close_gauge()
            line = raw.decode("ascii", "replace").strip()
            if line in self.commands.errors:
                raise self._refused(text, line)
            if line:
                log.info("%s: gauge setter %r answered %r (not documented; ignored)", self.line.where, text, raw)

    def capture(self, text: str, lines: int, *, gauge: bool) -> list[bytes]:
        """Raw reply lines to `text`, unparsed (commissioning: compare them with the device file)."""
        with self.line.lock:
            self.line.flush_input()
            if gauge:
                self._open_gauge(text)
            else:
                self.line.write(text.encode("ascii") + self.commands.stand_terminator)
            try:
                return [self.line.read_line() for _ in range(lines)]
            finally:
                if gauge:
                    self._close_gauge()

    def _open_gauge(self, text: str) -> None:
        self.line.write(self.commands.passthrough_open)
        if self.commands.passthrough_pause_s > 0:
            time.sleep(self.commands.passthrough_pause_s)   # C1 waits before the gauge command
        self.line.write(text.encode("ascii") + self.commands.gauge_terminator)

    def _close_gauge(self) -> None:
        if self.line.connected:
            self.line.write(self.commands.passthrough_close)

    # -- receiving
    def _exchange(self, text: str, templates: tuple[str, ...], *, gauge: bool) -> dict:
        with self.line.lock:
            error: DeviceError | None = None
            for _ in range(self.line.retries + 1):
                self.line.flush_input()   # a late reply must not be taken for this one's
                try:
                    if gauge:
                        self._open_gauge(text)
                    else:
                        self.line.write(text.encode("ascii") + self.commands.stand_terminator)
                    return self._read_reply(text, templates, self.line.read_line)
                except _Retry as retry:
                    error = retry.error
                finally:
                    if gauge:
                        self._close_gauge()
            assert error is not None
            raise error

    def parse_captured(self, text: str, templates: tuple[str, ...], raws: list[bytes]) -> dict:
        """Parse lines capture() fetched, as a query would (commissioning)."""
        lines = iter(raws)
        try:
            return self._read_reply(text, templates, lambda: next(lines, b""))
        except _Retry as retry:
            raise retry.error from None

    def _read_reply(self, text: str, templates: tuple[str, ...], read_line) -> dict:
        values: dict = {}
        skipped = 0
        for template in templates:
            while True:
                line = self._decode(text, read_line())
                if line.strip() in self.commands.errors:
                    raise self._refused(text, line.strip())
                parsed = self._parse(text, template, line)
                if parsed is not None:
                    values.update(parsed)
                    break
                skipped += 1
                if skipped > MAX_SKIPPED:
                    raise _Retry(DeviceProtocolError(f"{self.line.where}: unexpected reply to {text!r}: {line!r}"))
        return values

    def _decode(self, text: str, raw: bytes) -> str:
        where = self.line.where
        if not raw:
            return self._fail(DeviceTimeout(f"{where}: no reply to {text!r} "
                                            f"({self.line.retries + 1} x {self.line.timeout_s * 1000:.0f} ms)"))
        if not raw.endswith(self.line.line_end):
            return self._fail(DeviceProtocolError(f"{where}: incomplete reply to {text!r}: {raw!r}"))
        try:
            return raw.decode("ascii").rstrip("\r\n")
        except UnicodeDecodeError:
            return self._fail(DeviceProtocolError(f"{where}: garbage reply to {text!r}: {raw!r}"))

    @staticmethod
    def _fail(error: DeviceError):
        raise _Retry(error)

    def _parse(self, text: str, template: str, line: str) -> dict | None:
        """{field: value} for one reply line; None for a line to skip (empty, or another command's reply)."""
        content = line.strip()
        if not content:
            return None   # an acknowledge the manual does not describe would be an empty line
        fields = reply_fields(template)
        kind = fields[0]
        tokens = content.split()
        is_status = all(t in self.commands.status_codes for t in tokens)
        if kind == "status":
            return {kind: frozenset(tokens)} if is_status else self._other(text, content)
        if kind in ("text", "settings"):
            return {kind: content}
        match = _NUMBER.fullmatch(content)
        if match is None:
            return None if is_status else self._other(text, content)
        value, unit = float(match[1]), match[2]
        unit_field = fields[1] if len(fields) > 1 else None
        if unit is None or unit_field is None:
            return {kind: value}
        expected = self.expected_unit[unit_field]
        if unit == expected:
            return {kind: value, unit_field: unit}
        quantity = self.quantity_of.get(unit)
        if quantity == QUANTITY[unit_field]:
            device = "gauge" if quantity == "force" else "stand"
            # repeating will not help: the device is set to another unit than the profile's
            raise DeviceProtocolError(f"{self.line.where}: {device} answers {text!r} in {unit}, "
                                      f"the profile expects {expected}")
        return None if quantity is not None else self._other(text, content)

    def _other(self, text: str, content: str) -> None:
        """A line that fits no reply form: a number with some unit is a late reply (skip), else garbage."""
        match = _NUMBER.fullmatch(content)
        if match is not None and match[2] in self.quantity_of:
            return None
        raise _Retry(DeviceProtocolError(f"{self.line.where}: unexpected reply to {text!r}: {content!r}"))

    def _refused(self, text: str, code: str) -> DeviceErrorReply:
        meaning = self.commands.errors[code]
        return DeviceErrorReply(f"{self.line.where}: device refused {text!r}: {code} {meaning}", code, meaning)


class Series5Gauge(LoadCell):
    """The gauge behind the stand: `?C` reads, `Z` zeroes (and tares: the gauge has one zero)."""

    def __init__(self, link: Mark10Link, settings: dict):
        self.link = link
        self.capacity_N = float(settings["capacity_N"])
        self.force_sign = int(settings.get("force_sign", 1))

    def newtons(self, value: float) -> float:
        return self.force_sign * value * self.link.gauge_unit.to_newton

    def status_for(self, force_N: float) -> LoadCellStatus:
        # The gauge reports no status with a reading; over/under range follows from capacity.
        return LoadCellStatus(over_range=force_N >= self.capacity_N, under_range=force_N <= -self.capacity_N)

    def read(self) -> ForceReading:
        force = self.newtons(self.link.gauge_ask("read_current")["force"])
        return ForceReading(force, self.status_for(force))

    def zero(self) -> None:
        self.link.gauge_set(self.link.commands.gauge["zero"].send)

    def tare(self) -> None:
        self.zero()   # one zero on the gauge (`Z`: zero the display and clear the peaks, S6)


class Mark10Crosshead(Crosshead):
    """The ESM303 stand. Positions in mm positive down: stand travel x `travel_sign` (a profile setting)."""

    def __init__(self, link: Mark10Link, settings: dict, limits: dict, travel_sign: int):
        self.link = link
        self.unit = link.stand_unit
        self.position_resolution_mm = self.unit.reading_resolution_mm
        self.travel_sign = travel_sign
        self.max_speed_mm_min = float(settings["max_speed_mm_min"])
        self.safety_upper_mm = float(limits["travel_upper_mm"])
        self.safety_lower_mm = float(limits["travel_lower_mm"])
        self._stand_upper_mm: float | None = None   # what `h` last set (mm, positive down)
        self._stand_lower_mm: float | None = None   # what `g` last set
        self._move_direction = 0                    # +1 down / -1 up for the last move_to, 0 otherwise

    def to_mm(self, stand_value: float) -> float:
        return self.travel_sign * stand_value * self.unit.to_mm

    def to_stand(self, mm: float) -> float:
        return self.travel_sign * mm / self.unit.to_mm

    def _set_speed(self, speed_mm_min: float) -> None:
        """`eXXXX.X` (mm) / `eXX.XX` (inch); a speed that rounds to zero is refused, not sent."""
        text = "0"
        if 0 < speed_mm_min <= self.max_speed_mm_min:
            text = self.unit.speed.format(speed_mm_min / self.unit.to_mm)
        if float(text) <= 0:
            raise ValueError(f"speed {speed_mm_min} mm/min outside (0, {self.max_speed_mm_min}] mm/min "
                             f"at the stand's resolution ({self.unit.speed.resolution:g} {self.unit.speed_unit})")
        self.link.send("set_speed", speed=text)

    def _set_limit(self, direction: int, mm: float) -> None:
        """`g` (lower: stops a move down) or `h` (upper), in the stand's fixed width."""
        try:
            text = self.unit.limit.format(self.to_stand(mm))
        except ValueError as exc:
            raise ValueError(f"travel limit {mm} mm: {exc}") from None
        self.link.send("set_lower_limit" if direction > 0 else "set_upper_limit", limit=text)
        if direction > 0:
            self._stand_lower_mm = self.to_mm(float(text))
        else:
            self._stand_upper_mm = self.to_mm(float(text))

    def _start(self, direction: int, limit_mm: float, speed_mm_min: float) -> None:
        """Limit mode as the vendor documents it: speed, the limit ahead, `l`, then `d` / `u`."""
        self._set_speed(speed_mm_min)
        self._set_limit(direction, limit_mm)
        self.link.send("limit_mode")
        self.link.send("move_down" if direction > 0 else "move_up")

    def read_position(self) -> float:
        return self.to_mm(self.link.ask("read_travel")["travel"])

    def read_speed(self) -> float:
        """The stand's programmed speed (`a`), mm/min."""
        return self.link.ask("read_speed")["speed"] * self.unit.to_mm

    def read_travel_limits(self) -> tuple[float, float]:
        """(upper, lower) as the stand holds them (`v`, `w`), mm positive down."""
        return (self.to_mm(self.link.ask("read_upper_limit")["limit"]),
                self.to_mm(self.link.ask("read_lower_limit")["limit"]))

    def _at(self, held: float | None, safety: float) -> bool:
        return held is None or abs(held - safety) <= self.unit.limit.resolution * self.unit.to_mm / 2

    def status(self) -> CrossheadStatus:
        codes = self.link.ask("status")["status"]
        moving = "U" in codes or "D" in codes
        at_upper, at_lower = "UL" in codes, "DL" in codes
        # A limit move_to() set is its target, so a stop there means "arrived"; only a stop at
        # the safety limit (or a limit foamlab did not set) is a travel-limit event.
        arrived = (at_upper and self._move_direction < 0) or (at_lower and self._move_direction > 0)
        return CrossheadStatus(moving=moving, in_position=not moving and arrived,
                               upper_limit=at_upper and self._at(self._stand_upper_mm, self.safety_upper_mm),
                               lower_limit=at_lower and self._at(self._stand_lower_mm, self.safety_lower_mm))

    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        if not self.safety_upper_mm <= target_mm <= self.safety_lower_mm:
            raise ValueError(f"target {target_mm} mm outside the travel limits "
                             f"[{self.safety_upper_mm}, {self.safety_lower_mm}] mm")
        with self.link.line.lock:
            # At the target already, the move ends at once at its limit: status says arrived.
            direction = 1 if target_mm >= self.read_position() else -1
            self._move_direction = direction
            self._start(direction, target_mm, speed_mm_min)

    def jog(self, direction: int, speed_mm_min: float) -> None:
        if direction not in (1, -1):
            raise ValueError("jog direction must be +1 (down) or -1 (up)")
        with self.link.line.lock:
            self._move_direction = 0
            self._start(direction, self.safety_lower_mm if direction > 0 else self.safety_upper_mm, speed_mm_min)

    def stop(self) -> None:
        self.link.send("stop")

    def emergency_stop(self) -> None:
        # The ESM303 has no e-stop command (S1-S4): `s` is its only stop. The stand's own
        # e-stop button and limit switches are the hardware protection.
        self.link.send("stop")

    def reset_fault(self) -> str:
        """Nothing to reset: the stand has no fault latch. Returns (and logs) why."""
        log.info("%s: reset_fault: %s", self.link.line.where, NO_FAULT_COMMAND)
        return NO_FAULT_COMMAND

    def set_zero(self) -> None:
        self.link.send("zero_travel")

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        if not upper_mm < lower_mm:
            raise ValueError(f"upper limit {upper_mm} mm must be above (smaller than) lower limit {lower_mm} mm")
        with self.link.line.lock:
            self.safety_upper_mm, self.safety_lower_mm = float(upper_mm), float(lower_mm)
            self._move_direction = 0
            self._set_limit(-1, self.safety_upper_mm)
            self._set_limit(+1, self.safety_lower_mm)
            self.link.send("limit_mode")


def profile_units(profile: dict, commands: CommandSet) -> tuple[StandUnit, GaugeUnit, int]:
    """The stand's travel unit, the gauge's force unit and the travel sign the profile names
    (ValueError naming the key; drivers.profile checks it when it loads the profile)."""
    crosshead, load_cell = profile["crosshead"], profile["load_cell"]
    travel, force = crosshead.get("travel_unit", "mm"), load_cell.get("force_unit", "N")
    sign = crosshead.get("travel_sign", 1)
    if travel not in commands.stand_units:
        raise ValueError(f"[crosshead] `travel_unit` must be one of {', '.join(commands.stand_units)}, got {travel!r}")
    if force not in commands.gauge_units:
        raise ValueError(f"[load_cell] `force_unit` must be one of {', '.join(commands.gauge_units)}, got {force!r}")
    if sign not in (1, -1) or isinstance(sign, bool):
        raise ValueError(f"[crosshead] `travel_sign` must be 1 or -1, got {sign!r}")
    return commands.stand_units[travel], commands.gauge_units[force], sign


class AsciiMachine(Machine):
    """Stand and gauge on one serial line, from a loaded profile; `n` reads both per sample."""

    def __init__(self, profile: dict):
        self.profile = profile
        self.commands = CommandSet.from_toml(profile["wire"])
        stand_unit, gauge_unit, sign = profile_units(profile, self.commands)
        framing = self.commands.serial
        self.line = SerialLine(profile["connection"], bytesize=framing["data_bits"], parity=framing["parity"],
                               stopbits=framing["stop_bits"], line_end=b"\n")
        self.link = Mark10Link(self.line, self.commands, stand_unit, gauge_unit)
        self.load_cell = Series5Gauge(self.link, profile["load_cell"])
        self.crosshead = Mark10Crosshead(self.link, profile["crosshead"], profile["limits"], sign)
        self._configured = False

    def connect(self) -> None:
        """Open the line; set the stand's unit (`i`), the gauge's (`N`) and units in replies (`FULL`);
        write the safety travel limits and enter limit mode."""
        with self.line.lock:
            if self._configured and self.line.connected:
                return
            self.line.connect()
            try:
                handshake(self._handshake)
            except DeviceError:
                self.line.close()
                raise
            self._configured = True

    def _handshake(self) -> None:
        self.link.send_text(self.link.stand_unit.command)
        self.link.gauge_set(self.link.gauge_unit.command)
        self.link.gauge_set(self.commands.gauge["full"].send)
        self.crosshead.set_travel_limits(self.crosshead.safety_upper_mm, self.crosshead.safety_lower_mm)

    def read_sample(self) -> MachineSample:
        start = time.monotonic()
        values = self.link.ask("read_sample")
        instant = 0.5 * (start + time.monotonic())          # one request holds both values
        force_N = self.load_cell.newtons(values["force"])
        return MachineSample(force_N, self.crosshead.to_mm(values["travel"]),
                             self.load_cell.status_for(force_N), instant)

    def identify(self) -> str:
        """The gauge's product name, model, firmware and serial number (`RN` `RM` `RV` `RS`)."""
        names = ("read_name", "read_model", "read_firmware", "read_serial")
        return " / ".join(self.link.gauge_ask(name)["text"] for name in names)

    def unconfirmed(self):
        """The device file's entries the manuals do not settle (foamlab probe's checklist)."""
        return self.commands.unconfirmed()

    def self_checks(self) -> list[tuple[str, bool, str]]:
        """Replies compared byte for byte with the device file's assumptions (foamlab probe)."""
        from .mark10_checks import self_checks   # commissioning only

        return self_checks(self)

    def close(self) -> None:
        self.line.close()
        self._configured = False
