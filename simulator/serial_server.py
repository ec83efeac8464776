"""The simulated machine as a Mark-10 ESM303-style stand with a Series 5-style gauge (ASCII).

Served on a pseudo-terminal (simulator.pty_link): a client opens the printed path
as it would open /dev/ttyUSB0. The command set, terminators and error codes are
read from configs/machines/_mark10_commands.toml (the wire contract): commands end
in CR, replies in CR LF, an acknowledged command answers an empty line, errors are

    *10 unknown command (also a malformed line)
    *11 parameter out of range (or not a number)
    *21 limit reached: a move toward a travel limit the crosshead is already at
    *22 overload: the gauge is over range (force reads, moving down)
    *30 emergency stop latched: motion refused until `r` (also for any other latched
        drive fault - stall, watchdog, overtravel - whose remedy is the same `r`)

Wire faults from ``machine.faults``, asked once per command: drop (the pty is hung
up and replaced behind the same path), timeout (no reply, command not done),
exception (`*10`, as if the command was garbled on the way; not done), crc (done,
one reply character corrupted to a non-ASCII byte), garbage (done, the reply
replaced by random bytes then CR LF).
"""

from __future__ import annotations

import asyncio
import logging
import math
import random
from dataclasses import dataclass
from typing import Any

from simulator.pty_link import PtyPort, PtyTransport

log = logging.getLogger(__name__)

#: Wire faults the ASCII server injects, in the order they are asked for on each command.
ASCII_WIRE_FAULTS = ("drop", "timeout", "exception", "crc", "garbage")
#: A line longer than this without a terminator is noise: dropped and answered `*10`.
MAX_LINE = 64
#: Stand speed before the host sets one (mm/min).
DEFAULT_SPEED_MM_MIN = 50.0


@dataclass(frozen=True)
class Command:
    name: str
    prefix: str
    takes_value: bool


class CommandSet:
    """Server-side reading of the command-set TOML: prefixes, terminators, error codes."""

    def __init__(self, wire: dict):
        self.terminator = wire["terminator"].encode("ascii")
        self.reply_terminator = wire["reply_terminator"].encode("ascii")
        self.errors: dict[str, str] = dict(wire["errors"])
        self.commands: list[Command] = []
        for name, template in wire["commands"].items():
            prefix = template.split("{", 1)[0]
            if not prefix:
                raise ValueError(f"command {name!r}: template {template!r} has no command letters")
            self.commands.append(Command(name, prefix, "{" in template))
        # Longest prefix first, so a multi-letter command is never taken for a shorter one.
        self.commands.sort(key=lambda c: -len(c.prefix))

    def parse(self, line: str) -> tuple[Command, str | None] | None:
        """(command, argument text or None) or None when no command matches."""
        for cmd in self.commands:
            if cmd.takes_value and line.startswith(cmd.prefix):
                rest = line[len(cmd.prefix):].strip()
                return cmd, (rest or None)
            if not cmd.takes_value and line == cmd.prefix:
                return cmd, None
        return None


class _Refused(Exception):
    """A command the stand refuses; carries the error name of the command set."""

    def __init__(self, error: str):
        super().__init__(error)
        self.error = error


class Stand:
    """What the ESM303 + gauge do with each command, on the shared SimulatedMachine."""

    def __init__(self, machine: Any, profile: dict):
        self.machine = machine
        st = machine.settings  # the stand starts as the machine was built (from the profile)
        self.max_speed_mm_min = st.max_speed_mm_min
        self.speed_mm_min = min(DEFAULT_SPEED_MM_MIN, self.max_speed_mm_min)
        self.upper_mm = st.travel_upper_mm
        self.lower_mm = st.travel_lower_mm

    def execute(self, name: str, arg: str | None) -> str:
        m = self.machine
        handler = getattr(self, f"_do_{name}", None)
        if handler is None:
            raise _Refused("unknown_command")
        value = None
        if arg is not None:
            try:
                value = float(arg)
            except ValueError:
                raise _Refused("out_of_range") from None
            if not math.isfinite(value):
                raise _Refused("out_of_range")
        return handler(m, value) or ""

    # -- motion
    def _motion_allowed(self, direction: int) -> None:
        s = self.machine.crosshead_status()
        if s.emergency_stop:
            raise _Refused("emergency_stop")
        if (direction > 0 and s.lower_limit) or (direction < 0 and s.upper_limit):
            raise _Refused("limit_reached")
        if direction > 0 and self.machine.read_load_cell().over_range:
            raise _Refused("overload")

    def _jog(self, direction: int) -> None:
        self._motion_allowed(direction)
        if not self.machine.jog(direction, self.speed_mm_min):
            # Refused by the drive: a latched fault (stall, watchdog, overtravel) needs `r`
            # like an e-stop does; otherwise the crosshead is at the limit.
            fault = self.machine.crosshead_status().fault
            raise _Refused("emergency_stop" if fault else "limit_reached")

    def _do_move_down(self, m, _):
        self._jog(+1)

    def _do_move_up(self, m, _):
        self._jog(-1)

    def _do_stop(self, m, _):
        m.stop()

    def _do_emergency_stop(self, m, _):
        m.emergency_stop()

    def _do_reset(self, m, _):
        m.reset_fault()

    def _do_speed(self, m, value):
        if value is None:
            return f"{self.speed_mm_min:.1f}"
        if not 0 < value <= self.max_speed_mm_min:
            raise _Refused("out_of_range")
        self.speed_mm_min = value

    def _do_upper_limit(self, m, value):
        if value is None:
            return f"{self.upper_mm:.3f}"
        if not value < self.lower_mm:
            raise _Refused("out_of_range")
        m.set_travel_limits(value, self.lower_mm)
        self.upper_mm = value

    def _do_lower_limit(self, m, value):
        if value is None:
            return f"{self.lower_mm:.3f}"
        if not value > self.upper_mm:
            raise _Refused("out_of_range")
        m.set_travel_limits(self.upper_mm, value)
        self.lower_mm = value

    def _do_zero_travel(self, m, _):
        m.set_zero()

    # -- reads
    def _force(self) -> float:
        reading = self.machine.read_load_cell()
        if reading.over_range:
            raise _Refused("overload")
        return reading.net_N

    def _do_read_travel(self, m, _):
        return f"{m.position_mm():.3f}"

    def _do_read_both(self, m, _):
        position = m.position_mm()
        return f"{position:.3f},{self._force():.3f}"

    def _do_read_force(self, m, _):
        return f"{self._force():.3f} N"

    def _do_zero_force(self, m, _):
        m.tare()

    def _do_status(self, m, _):
        s = m.crosshead_status()
        overload = m.read_load_cell().over_range
        flags = (("M", s.moving), ("U", s.upper_limit), ("L", s.lower_limit),
                 ("F", s.fault), ("E", s.emergency_stop), ("O", overload))
        return " ".join(f"{letter}{int(bool(on))}" for letter, on in flags)


class _AsciiProtocol(asyncio.Protocol):
    """Line assembly, dispatch and wire faults for one pty connection."""

    def __init__(self, server: "AsciiSimServer"):
        self.server = server
        self.transport: PtyTransport | None = None
        self._buffer = bytearray()

    def connection_made(self, transport) -> None:
        self.transport = transport

    def connection_lost(self, exc) -> None:
        self.transport = None

    def data_received(self, data: bytes) -> None:
        self._buffer += data
        term = self.server.commands.terminator
        while self.transport is not None:
            line, found, rest = bytes(self._buffer).partition(term)
            if not found:
                if len(self._buffer) > MAX_LINE:
                    self._buffer.clear()
                    self._reply(self.server.commands.errors["unknown_command"])
                return
            self._buffer[:] = rest
            self._handle(line.lstrip(b"\n"))  # tolerate CR LF from terminal programs

    def _handle(self, raw: bytes) -> None:
        if not raw:
            return  # a bare CR: nothing asked, nothing answered
        srv = self.server
        fault = srv.next_wire_fault()
        if fault == "drop":
            self.transport = None  # lines still buffered were lost with the line
            self._buffer.clear()
            srv.drop_link()
            return
        if fault == "timeout":
            return
        srv.machine.host_activity()
        if fault == "exception":
            self._reply(srv.commands.errors["unknown_command"])
            return
        try:
            parsed = srv.commands.parse(raw.decode("ascii").strip())
        except UnicodeDecodeError:
            parsed = None
        try:
            if parsed is None:
                raise _Refused("unknown_command")
            reply = srv.stand.execute(parsed[0].name, parsed[1])
        except _Refused as refused:
            reply = srv.commands.errors[refused.error]
        except ValueError as exc:  # the machine refused the value itself
            log.info("command %r refused: %s", raw, exc)
            reply = srv.commands.errors["out_of_range"]
        if fault == "crc":
            self._send(_corrupt(reply, srv.rng) + srv.commands.reply_terminator)
        elif fault == "garbage":  # the command was done; noise replaced its reply
            noise = bytes(b for b in (srv.rng.randrange(256) for _ in range(12)) if b not in b"\r\n")
            self._send(noise + srv.commands.reply_terminator)
        else:
            self._reply(reply)

    def _reply(self, text: str) -> None:
        self._send(text.encode("ascii") + self.server.commands.reply_terminator)

    def _send(self, data: bytes) -> None:
        if self.transport is not None:
            self.transport.write(data)


def _corrupt(reply: str, rng: random.Random) -> bytes:
    """The reply with one character hit by line noise (high bit set: never valid ASCII)."""
    data = bytearray((reply or " ").encode("ascii"))
    i = rng.randrange(len(data))
    data[i] |= 0x80
    return bytes(data)


class AsciiSimServer:
    """The stand + gauge on a pty, backed by one SimulatedMachine. Use inside an asyncio loop."""

    def __init__(self, machine: Any, profile: dict, *, seed: int = 0):
        self.machine = machine
        self.profile = profile
        self.commands = CommandSet(profile["wire"])
        self.stand = Stand(machine, profile)
        self.rng = random.Random(seed)
        self.drops = 0
        self.pty: PtyPort | None = None
        self._transport: PtyTransport | None = None

    async def start(self) -> None:
        self.pty = PtyPort(int(self.profile["connection"].get("baudrate", 115200)))
        self._open()

    def _open(self) -> None:
        loop = asyncio.get_running_loop()
        self._transport = PtyTransport(loop, self.pty, _AsciiProtocol(self))

    @property
    def client_url(self) -> str:
        return self.pty.path

    def next_wire_fault(self) -> str | None:
        faults = getattr(self.machine, "faults", None)
        if not faults:
            return None
        for name in ASCII_WIRE_FAULTS:
            if faults.should_fire(name):
                return name
        return None

    def drop_link(self) -> None:
        """Hang the line up (the client reads EIO) and put a fresh pty behind the same path."""
        self.drops += 1
        if self._transport is not None:
            self._transport.close()
        self.pty.reopen()
        self._open()

    async def stop(self) -> None:
        if self._transport is not None:
            self._transport.close()
            self._transport = None
        if self.pty is not None:
            self.pty.close()
        await asyncio.sleep(0)  # let connection_lost run before the loop goes away
