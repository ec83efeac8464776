"""Serial ASCII profile: a Mark-10 ESM303-style stand with a Series 5-style gauge on one line.

Commands and error codes come from the profile's command set
(configs/machines/_mark10_commands.toml); the reply grammar of each command is the
small `REPLIES` table below (documented in docs/protocols.md). Every exchange is
strict: flush stale input, send one CR-terminated command, read exactly one CR LF
line, match it in full. `*NN` -> DeviceErrorReply (a DeviceProtocolError) naming the
error; any other unexpected or partial line -> DeviceProtocolError; silence ->
DeviceTimeout; a vanished port -> DeviceConnectionLost. Timeouts and garbled lines are
retried `retries` times (every command here is safe to repeat); `*NN` replies are not.

The ESM303 has no "go to position" command: it stops at its travel limits. So
move_to(target) sets the limit in the direction of travel to the target and starts
the move; jog() first puts that limit back at the profile's safety limit.
"""

from __future__ import annotations

import re
import threading
import time
from dataclasses import dataclass

import serial

from .base import (
    Crosshead,
    CrossheadStatus,
    DeviceConnectionLost,
    DeviceError,
    DeviceProtocolError,
    DeviceRefused,
    DeviceTimeout,
    ForceReading,
    LoadCell,
    LoadCellStatus,
    Machine,
    MachineSample,
)

_NUMBER = r"([-+]?\d+(?:\.\d+)?)"

#: Reply grammar per command name; None = acknowledge (an empty line).
REPLIES: dict[str, re.Pattern | None] = {
    "move_down": None,
    "move_up": None,
    "stop": None,
    "speed": None,
    "upper_limit": None,
    "lower_limit": None,
    "zero_travel": None,
    "zero_force": None,
    "emergency_stop": None,
    "reset": None,
    "read_travel": re.compile(_NUMBER),
    "read_both": re.compile(f"{_NUMBER},{_NUMBER}"),
    "read_force": re.compile(f"{_NUMBER} N"),
    "status": re.compile(r"M([01]) U([01]) L([01]) F([01]) E([01]) O([01])"),
}

#: Position tolerance under which move_to() considers the crosshead already there.
AT_TARGET_MM = 0.0005


class DeviceErrorReply(DeviceRefused):
    """The device answered `*NN`: it understood and refused (code, name as in the command set)."""

    def __init__(self, message: str, code: str, name: str):
        super().__init__(message)
        self.code = code
        self.name = name


@dataclass(frozen=True)
class CommandSet:
    terminator: bytes
    reply_terminator: bytes
    commands: dict[str, str]         # name -> template, e.g. "speed" -> "e{speed:.1f}"
    errors: dict[str, str]           # "*10" -> "unknown_command"

    @classmethod
    def from_toml(cls, wire: dict) -> "CommandSet":
        commands = wire.get("commands")
        errors = wire.get("errors")
        if not isinstance(commands, dict) or not isinstance(errors, dict):
            raise ValueError("needs [commands] and [errors] tables")
        missing = [name for name in REPLIES if not isinstance(commands.get(name), str)]
        if missing:
            raise ValueError(f"[commands] lacks {', '.join(missing)}")
        for name, code in errors.items():
            if not isinstance(code, str) or not re.fullmatch(r"\*\d\d", code):
                raise ValueError(f"[errors] {name} must look like \"*10\", got {code!r}")
        terminators = [wire.get("terminator", "\r"), wire.get("reply_terminator", "\r\n")]
        if not all(isinstance(t, str) and t for t in terminators):
            raise ValueError("terminator and reply_terminator must be non-empty strings")
        return cls(terminators[0].encode("ascii"), terminators[1].encode("ascii"),
                   dict(commands), {code: name for name, code in errors.items()})

    def format(self, name: str, **params) -> str:
        return self.commands[name].format(**params)


class SerialLine:
    """One serial line (any pyserial URL or device path), one command at a time under a lock."""

    def __init__(self, connection: dict, commands: CommandSet):
        self.url = connection["port_url"]
        self.baudrate = int(connection["baudrate"])
        self.timeout_s = float(connection["timeout_s"])
        self.retries = int(connection["retries"])
        self.commands = commands
        self.lock = threading.RLock()
        self._port: serial.SerialBase | None = None
        self.where = f"serial {self.url}"

    @property
    def connected(self) -> bool:
        return self._port is not None

    def connect(self) -> None:
        with self.lock:
            if self._port is not None:
                return
            try:
                self._port = serial.serial_for_url(self.url, baudrate=self.baudrate, timeout=self.timeout_s,
                                                   write_timeout=max(self.timeout_s, 0.5))
            except (serial.SerialException, OSError, ValueError) as exc:
                raise DeviceConnectionLost(f"{self.where}: cannot open: {getattr(exc, 'strerror', None) or exc}") from None

    def close(self) -> None:
        with self.lock:
            port, self._port = self._port, None
            if port is not None:
                try:
                    port.close()
                except Exception:  # close() must never raise; the port may already be gone
                    pass

    def _exchange(self, command: bytes) -> bytes:
        """Send one command, return the raw reply line (b"" when nothing came back)."""
        port = self._port
        if port is None:
            raise DeviceConnectionLost(f"{self.where}: not connected")
        try:
            # A late or garbled earlier reply must not be taken for this command's reply.
            port.reset_input_buffer()
            port.write(command + self.commands.terminator)
            return port.read_until(self.commands.reply_terminator)
        except serial.SerialTimeoutException:
            return b""
        except (serial.SerialException, OSError) as exc:
            self.close()
            raise DeviceConnectionLost(f"{self.where}: {exc}") from None

    def _read_line(self) -> str | None:
        """One more reply line within the timeout (None on silence or garbage)."""
        try:
            raw = self._port.read_until(self.commands.reply_terminator)
        except (serial.SerialException, OSError):
            return None
        terminator = self.commands.reply_terminator
        if not raw.endswith(terminator):
            return None
        try:
            return raw[:-len(terminator)].decode("ascii")
        except UnicodeDecodeError:
            return None

    @staticmethod
    def _is_stale(line: str, name: str) -> bool:
        """The line is a well-formed reply to some OTHER command."""
        return any(other != name and (line == "" if g is None else bool(g.fullmatch(line)))
                   for other, g in REPLIES.items())

    def query(self, name: str, **params) -> re.Match | None:
        """Send command `name`, return the parsed reply (a match; None for an acknowledge)."""
        text = self.commands.format(name, **params)
        grammar = REPLIES[name]
        terminator = self.commands.reply_terminator
        with self.lock:
            error: DeviceError | None = None
            for _ in range(self.retries + 1):
                raw = self._exchange(text.encode("ascii"))
                if not raw:
                    error = DeviceTimeout(f"{self.where}: no reply to {text!r} "
                                          f"({self.retries + 1} x {self.timeout_s * 1000:.0f} ms)")
                    continue
                if not raw.endswith(terminator):
                    error = DeviceProtocolError(f"{self.where}: incomplete reply to {text!r}: {raw!r}")
                    continue
                try:
                    line = raw[:-len(terminator)].decode("ascii")
                except UnicodeDecodeError:
                    error = DeviceProtocolError(f"{self.where}: garbage reply to {text!r}: {raw!r}")
                    continue
                if line in self.commands.errors:
                    meaning = self.commands.errors[line]
                    raise DeviceErrorReply(f"{self.where}: device refused {text!r}: {line} "
                                           f"{meaning.replace('_', ' ')}", line, meaning)
                if grammar is None and line == "":
                    return None
                match = grammar.fullmatch(line) if grammar is not None else None
                if match:
                    return match
                if self._is_stale(line, name):
                    # a reply to an earlier command that timed out arrived after the
                    # input flush: this command's own reply is still on its way
                    late = self._read_line()
                    if late is not None:
                        if grammar is None and late == "":
                            return None
                        match = grammar.fullmatch(late) if grammar is not None else None
                        if match:
                            return match
                expected = "an empty acknowledge" if grammar is None else f"/{grammar.pattern}/"
                error = DeviceProtocolError(f"{self.where}: unexpected reply to {text!r}: {line!r} (expected {expected})")
            assert error is not None
            raise error


class AsciiLoadCell(LoadCell):
    """Series 5-style gauge: `?` -> "4.285 N"; `Z` tares (the gauge has one zero)."""

    def __init__(self, line: SerialLine, settings: dict):
        self.line = line
        self.capacity_N = float(settings["capacity_N"])
        self.force_sign = int(settings.get("force_sign", 1))

    def status_for(self, force_N: float) -> LoadCellStatus:
        # The gauge reports no status with a reading; over/under range follows from capacity.
        return LoadCellStatus(over_range=force_N >= self.capacity_N, under_range=force_N <= -self.capacity_N)

    def read(self) -> ForceReading:
        force = self.force_sign * float(self.line.query("read_force").group(1))
        return ForceReading(force, self.status_for(force))

    def zero(self) -> None:
        self.line.query("zero_force")

    def tare(self) -> None:
        self.line.query("zero_force")


class AsciiCrosshead(Crosshead):
    """ESM303-style stand. Keeps the safety limits and the limits presently set on the stand."""

    def __init__(self, line: SerialLine, settings: dict, limits: dict):
        self.line = line
        self.max_speed_mm_min = float(settings["max_speed_mm_min"])
        self.safety_upper_mm = float(limits["travel_upper_mm"])
        self.safety_lower_mm = float(limits["travel_lower_mm"])
        self._stand_upper_mm: float | None = None   # what `g` last set
        self._stand_lower_mm: float | None = None   # what `h` last set
        self._move_direction = 0                    # +1 down / -1 up for the last move_to, 0 otherwise

    def _set_speed(self, speed_mm_min: float) -> None:
        if not 0 < speed_mm_min <= self.max_speed_mm_min or round(speed_mm_min, 1) <= 0:
            raise ValueError(f"speed {speed_mm_min} mm/min outside [0.1, {self.max_speed_mm_min}] mm/min")
        self.line.query("speed", speed=speed_mm_min)

    def _set_upper(self, mm: float) -> None:
        self.line.query("upper_limit", mm=mm)
        self._stand_upper_mm = mm

    def _set_lower(self, mm: float) -> None:
        self.line.query("lower_limit", mm=mm)
        self._stand_lower_mm = mm

    def read_position(self) -> float:
        return float(self.line.query("read_travel").group(1))

    def _flags(self) -> tuple[bool, ...]:
        """`w`: moving, at upper limit, at lower limit, fault, e-stop latched, overload."""
        return tuple(g == "1" for g in self.line.query("status").groups())

    def status(self) -> CrossheadStatus:
        moving, upper, lower, fault, estop, _overload = self._flags()
        # The stand flags U/L at whatever limit is set; a limit move_to() set is a target,
        # so only a flag at the safety limit is a travel-limit event, and a flag in the
        # direction of the last move_to() means "arrived".
        arrived = (upper and self._move_direction < 0) or (lower and self._move_direction > 0)
        return CrossheadStatus(moving=moving, in_position=not moving and arrived,
                               upper_limit=upper and self._stand_upper_mm == self.safety_upper_mm,
                               lower_limit=lower and self._stand_lower_mm == self.safety_lower_mm,
                               fault=fault or estop, emergency_stopped=estop)

    def fault_reason(self) -> str:
        """What the stand's flags say (it reports no fault codes): emergency, fault, overload or none."""
        _moving, _upper, _lower, fault, estop, overload = self._flags()
        return "emergency" if estop else "fault" if fault else "overload" if overload else "none"

    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        if not self.safety_upper_mm <= target_mm <= self.safety_lower_mm:
            raise ValueError(f"target {target_mm} mm outside the travel limits "
                             f"[{self.safety_upper_mm}, {self.safety_lower_mm}] mm")
        with self.line.lock:
            position = self.read_position()
            direction = 1 if target_mm > position else -1
            self._move_direction = direction
            if abs(target_mm - position) < AT_TARGET_MM:
                return
            self._set_speed(speed_mm_min)
            if direction > 0:
                self._set_lower(target_mm)
                self.line.query("move_down")
            else:
                self._set_upper(target_mm)
                self.line.query("move_up")

    def jog(self, direction: int, speed_mm_min: float) -> None:
        if direction not in (1, -1):
            raise ValueError("jog direction must be +1 (down) or -1 (up)")
        with self.line.lock:
            self._move_direction = 0
            self._set_speed(speed_mm_min)
            if direction > 0:
                self._set_lower(self.safety_lower_mm)
                self.line.query("move_down")
            else:
                self._set_upper(self.safety_upper_mm)
                self.line.query("move_up")

    def stop(self) -> None:
        self.line.query("stop")

    def emergency_stop(self) -> None:
        self.line.query("emergency_stop")

    def reset_fault(self) -> None:
        self.line.query("reset")

    def set_zero(self) -> None:
        self.line.query("zero_travel")

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        if not upper_mm < lower_mm:
            raise ValueError(f"upper limit {upper_mm} mm must be above (smaller than) lower limit {lower_mm} mm")
        with self.line.lock:
            self.safety_upper_mm, self.safety_lower_mm = float(upper_mm), float(lower_mm)
            self._move_direction = 0
            self._set_upper(self.safety_upper_mm)
            self._set_lower(self.safety_lower_mm)


class AsciiMachine(Machine):
    """Stand and gauge on one serial line, from a loaded profile; `n` reads both per sample."""

    def __init__(self, profile: dict):
        self.profile = profile
        self.commands = CommandSet.from_toml(profile["wire"])
        self.line = SerialLine(profile["connection"], self.commands)
        self.load_cell = AsciiLoadCell(self.line, profile["load_cell"])
        self.crosshead = AsciiCrosshead(self.line, profile["crosshead"], profile["limits"])
        self._configured = False

    def connect(self) -> None:
        with self.line.lock:
            if self._configured and self.line.connected:
                return
            self.line.connect()
            try:
                self.crosshead.set_travel_limits(self.crosshead.safety_upper_mm, self.crosshead.safety_lower_mm)
            except DeviceError:
                self.line.close()
                raise
            self._configured = True

    def read_sample(self) -> MachineSample:
        start = time.monotonic()
        travel, force = self.line.query("read_both").groups()
        instant = 0.5 * (start + time.monotonic())          # one reply holds both values
        force_N = self.load_cell.force_sign * float(force)
        return MachineSample(force_N, float(travel), self.load_cell.status_for(force_N), instant)

    def close(self) -> None:
        self.line.close()
        self._configured = False
