"""The simulated machine as a Mark-10 ESM303 stand with a Series 5 gauge on it, on a pty.

A client opens the printed path as it would open /dev/ttyUSB0. The bytes are the device
file's (configs/devices/mark10-esm303.toml, as the driver reads it); what each command
does is simulator.mark10_stand's. The stand reads a byte stream without terminators: a
letter is a command, `e` / `g` / `h` take the fixed-width argument of the present unit
(`e0200.3`, `g-007.52`), CR and LF between commands are ignored, anything else is
ignored too (the stand documents no error reply). `/` opens the gauge: GCL2 lines end in
CR (LF ignored) and are answered with CR LF, `*10` for an unknown command; `\\` returns
to the stand.

Wire faults from ``machine.faults``, asked once per command (stand or gauge; not for `/`,
`\\` or ignored bytes): drop (the pty is hung up and replaced behind the same path),
timeout (no reply, command not done), exception (as if the command was garbled on the
way: the gauge answers `*10`, the stand ignores it), crc (done, one reply character
corrupted to a non-ASCII byte), garbage (done, the reply replaced by random bytes then
CR LF). A silent command shows crc and garbage as nothing.
"""

from __future__ import annotations

import asyncio
import logging
import random
from typing import Any

from drivers.mark10_device import CommandSet
from simulator.mark10_stand import Esm303, Refused, Series5
from simulator.pty_link import PtyPort, PtyTransport

log = logging.getLogger(__name__)

#: Wire faults the server injects, in the order they are asked for on each command.
ASCII_WIRE_FAULTS = ("drop", "timeout", "exception", "crc", "garbage")
#: A gauge line longer than this without a CR is noise: dropped and answered `*10`.
MAX_LINE = 64


class _Mark10Protocol(asyncio.Protocol):
    """The byte stream of one pty connection: stand commands, the gauge pass-through, wire faults."""

    def __init__(self, server: "AsciiSimServer"):
        self.server = server
        self.transport: PtyTransport | None = None
        self._buffer = bytearray()
        self._in_gauge = False

    def connection_made(self, transport) -> None:
        self.transport = transport

    def connection_lost(self, exc) -> None:
        self.transport = None

    def data_received(self, data: bytes) -> None:
        self._buffer += data
        while self.transport is not None and self._buffer:
            if not (self._gauge_step() if self._in_gauge else self._stand_step()):
                return   # the rest of a command is still on its way

    def _stand_step(self) -> bool:
        srv, first = self.server, bytes(self._buffer[:1])
        entry = srv.stand.by_letter.get(first.decode("latin-1"))
        if entry is None:
            if first == srv.commands.passthrough_open:
                self._in_gauge = True
            elif first not in b"\r\n":   # a terminator a host may send is ignored quietly
                log.info("stand ignores byte %r", first)
            del self._buffer[:1]
            return True
        width = srv.stand.argument_width(entry, bytes(self._buffer[1:2]))
        if width is None or len(self._buffer) < 1 + width:
            return False
        text = bytes(self._buffer[:1 + width]).decode("latin-1")
        del self._buffer[:1 + width]
        self._command(lambda: srv.stand.execute(entry, text[1:]), gauge=False)
        return True

    def _gauge_step(self) -> bool:
        srv = self.server
        close, end = srv.commands.passthrough_close, srv.commands.gauge_terminator
        cut = min((i for i in (self._buffer.find(close), self._buffer.find(end)) if i >= 0), default=-1)
        if cut < 0:
            if len(self._buffer) > MAX_LINE:
                self._buffer.clear()
                self._send([srv.illegal], gauge=True)
            return False
        line = bytes(self._buffer[:cut]).replace(b"\n", b"")
        closing = self._buffer[cut:cut + 1] == close
        del self._buffer[:cut + 1]
        if closing:
            self._in_gauge = False   # a gauge line not ended by CR is dropped with the channel
        elif line:
            self._command(lambda: srv.gauge_line(line), gauge=True)
        return True

    def _command(self, execute, *, gauge: bool) -> None:
        srv = self.server
        fault = srv.next_wire_fault()
        if fault == "drop":
            self.transport = None   # bytes still buffered were lost with the line
            self._buffer.clear()
            srv.drop_link()
            return
        if fault == "timeout":
            return
        srv.machine.host_activity()
        if fault == "exception":
            if gauge:
                self._send([srv.illegal], gauge=True)
            return
        lines = execute()
        if not lines:
            return
        if fault == "crc":
            lines = [_corrupt(lines[0], srv.rng), *lines[1:]]
        elif fault == "garbage":   # the command was done; noise replaced its reply
            lines = [bytes(b for b in (srv.rng.randrange(256) for _ in range(12)) if b not in b"\r\n")]
        self._send(lines, gauge=gauge)

    def _send(self, lines, *, gauge: bool) -> None:
        commands = self.server.commands
        end = commands.gauge_reply_terminator if gauge else commands.stand_reply_terminator
        data = b"".join((line if isinstance(line, bytes) else line.encode("ascii")) + end for line in lines)
        if self.transport is not None:
            self.transport.write(data)


def _corrupt(reply: str, rng: random.Random) -> bytes:
    """The reply with one character hit by line noise (high bit set: never valid ASCII)."""
    data = bytearray((reply or " ").encode("ascii"))
    i = rng.randrange(len(data))
    data[i] |= 0x80
    return bytes(data)


class AsciiSimServer:
    """The ESM303 + Series 5 on a pty, backed by one SimulatedMachine. Use inside an asyncio loop."""

    def __init__(self, machine: Any, profile: dict, *, seed: int = 0):
        self.machine = machine
        self.profile = profile
        self.commands = CommandSet.from_toml(profile["wire"])
        self.gauge = Series5(machine, self.commands)
        self.stand = Esm303(machine, self.commands, profile, self.gauge)
        self.illegal = next(code for code, meaning in self.commands.errors.items() if meaning == "illegal command")
        self.rng = random.Random(seed)
        self.drops = 0
        self.pty: PtyPort | None = None
        self._transport: PtyTransport | None = None

    async def start(self) -> None:
        self.pty = PtyPort(int(self.profile["connection"].get("baudrate", 115200)))
        self._open()

    def _open(self) -> None:
        loop = asyncio.get_running_loop()
        self._transport = PtyTransport(loop, self.pty, _Mark10Protocol(self))

    @property
    def client_url(self) -> str:
        return self.pty.path

    def gauge_line(self, line: bytes) -> list[str]:
        """Reply lines of the gauge to one GCL2 command line."""
        try:
            return self.gauge.execute(line.decode("ascii").strip())
        except UnicodeDecodeError:
            return [self.illegal]
        except Refused as refused:
            return [refused.code]

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
