"""The simulated machine's two Modbus devices, served by pymodbus 3.16 server classes.

One server carries both devices of a Modbus profile (configs/machines/_modbus_map.toml):
the load-cell indicator (Flintec DAD 141.1-style) and the crosshead drive
(Leadshine CS2RS-style), each at its profile's unit id. Transports:

- ``tcp``        Modbus TCP (MBAP framing) on a TCP port;
- ``rtu-socket`` RTU frames over a TCP socket (what pyserial calls ``socket://host:port``);
- ``rtu-pty``    RTU frames over a pseudo-terminal: clients open a device path.

The datastore is live: pymodbus' SimDevice ``action`` hook runs before every
access; reads of measured registers are computed from the SimulatedMachine at
that moment (float32/int32 packed in the profile's word order), writes of
command/trigger/target/limit registers act on it. Addresses outside the map
answer exception 0x02 (SimData ranges make pymodbus do that), writes to measured
registers 0x02 too (read-only), bad values 0x03.

Wire faults come from ``machine.faults`` (simulator.faults.FaultPlan), asked once
per request: drop (connection closed; a pty is hung up and replaced behind the same
path), timeout (request lost: no reply, not done), exception (0x04 slave device
failure, not done), crc (done; RTU reply with a flipped bit so its CRC fails, TCP
reply with a non-zero MBAP protocol id), garbage (done; the reply replaced by
random bytes). Requests to a unit id that is not on the line get no reply on RTU
and exception 0x0B (gateway target failed to respond) on TCP.
"""

from __future__ import annotations

import asyncio
import logging
import random
import socket
import struct
from dataclasses import dataclass, field
from typing import Any, Callable

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import DataType, SimData, SimDevice

from simulator.pty_link import PtyPort, PtyTransport

log = logging.getLogger(__name__)

#: Transports this module serves.
TRANSPORTS = ("tcp", "rtu-socket", "rtu-pty")
#: Wire faults a Modbus server injects, in the order they are asked for on each request.
MODBUS_WIRE_FAULTS = ("drop", "timeout", "exception", "crc", "garbage")

_STRUCT = {"uint16": "H", "int16": "h", "uint32": "I", "int32": "i", "float32": "f"}


# --------------------------------------------------------------------------- register map

@dataclass(frozen=True)
class Register:
    name: str
    address: int
    type: str

    @property
    def width(self) -> int:
        return struct.calcsize(_STRUCT[self.type]) // 2

    @property
    def span(self) -> range:
        return range(self.address, self.address + self.width)


@dataclass(frozen=True)
class Block:
    """A read-only run of registers that repeats named values (one read per sample)."""

    address: int
    layout: tuple[str, ...]
    count: int


@dataclass(frozen=True)
class DeviceMap:
    """One device section of the register map TOML ([load_cell] or [crosshead])."""

    registers: dict[str, Register]
    block: Block | None = None
    status_bits: dict[str, int] = field(default_factory=dict)
    codes: dict[str, int] = field(default_factory=dict)  # [x.commands] / [x.triggers]

    @classmethod
    def from_wire(cls, wire: dict, device: str) -> "DeviceMap":
        section = wire[device]
        registers, block = {}, None
        for name, entry in section.items():
            if not isinstance(entry, dict) or "address" not in entry:
                continue
            if "layout" in entry:
                block = Block(int(entry["address"]), tuple(entry["layout"]), int(entry["count"]))
            else:
                registers[name] = Register(name, int(entry["address"]), str(entry["type"]))
        if block is not None:
            width = sum(registers[n].width for n in block.layout)
            if width != block.count:
                raise ValueError(f"[{device}] block: layout is {width} registers, count says {block.count}")
        return cls(
            registers=registers,
            block=block,
            status_bits=dict(section.get("status_bits", {})),
            codes=dict(section.get("commands", section.get("triggers", {}))),
        )


def encode(value: float, kind: str, word_order: str) -> list[int]:
    """Registers for one value; 32-bit values in the profile's word order (bytes are big-endian)."""
    fmt = _STRUCT[kind]
    if fmt != "f":
        lo, hi = {"H": (0, 0xFFFF), "h": (-0x8000, 0x7FFF), "I": (0, 0xFFFFFFFF), "i": (-0x80000000, 0x7FFFFFFF)}[fmt]
        value = min(max(int(round(value)), lo), hi)
    raw = struct.pack(f">{fmt}", value)
    words = [int.from_bytes(raw[i:i + 2], "big") for i in range(0, len(raw), 2)]
    return words[::-1] if word_order == "little" else words


def decode(words: list[int], kind: str, word_order: str) -> float | int:
    words = words[::-1] if word_order == "little" else list(words)
    return struct.unpack(f">{_STRUCT[kind]}", b"".join(w.to_bytes(2, "big") for w in words))[0]


def _bits(flags: dict[str, bool], positions: dict[str, int]) -> int:
    return sum(1 << bit for name, bit in positions.items() if flags.get(name))


class _BadValue(Exception):
    """A write the device refuses: answered with exception 0x03 (illegal data value)."""


# --------------------------------------------------------------------------- devices

class _LiveDevice:
    """A SimDevice whose measured registers are computed at each read and whose writes act.

    Subclasses provide ``live_values()`` (name -> value, read from the machine) for the
    read-only registers and ``on_write(name, value)`` for the writable ones.
    """

    READ_ONLY: frozenset[str] = frozenset()

    def __init__(self, machine: Any, dmap: DeviceMap, word_order: str):
        self.machine = machine
        self.map = dmap
        self.word_order = word_order

    def sim_device(self, unit_id: int) -> SimDevice:
        data = []
        for reg in self.map.registers.values():
            if reg.name in self.READ_ONLY:
                data.append(SimData(reg.address, count=reg.width, datatype=DataType.REGISTERS, readonly=True))
            else:
                data.append(SimData(reg.address, datatype=DataType.REGISTERS,
                                    values=encode(self.initial_value(reg.name), reg.type, self.word_order)))
        if self.map.block:
            data.append(SimData(self.map.block.address, count=self.map.block.count,
                                datatype=DataType.REGISTERS, readonly=True))
        return SimDevice(unit_id, simdata=data, action=self._action)

    def initial_value(self, name: str) -> float:
        return 0

    def live_values(self, names: set[str]) -> dict[str, float]:
        raise NotImplementedError

    def on_write(self, name: str, value: float, stored: Callable[[str], float]) -> None:
        raise NotImplementedError

    async def _action(self, function_code: int, start_address: int, address: int, count: int,
                      registers: list[int], set_values: list[int] | None) -> ExcCodes | None:
        requested = range(address, address + count)
        if set_values is None:
            self._fill_live(requested, start_address, registers)
            return None
        # A write: store the new words first so a 32-bit value written in two halves
        # (two function-6 writes) is acted on with both halves present.
        offset = address - start_address
        previous = registers[offset:offset + len(set_values)]
        registers[offset:offset + len(set_values)] = set_values

        def stored(name: str) -> float:
            reg = self.map.registers[name]
            first = reg.address - start_address
            return decode(registers[first:first + reg.width], reg.type, self.word_order)

        try:
            for reg in self.map.registers.values():
                if reg.name not in self.READ_ONLY and set(reg.span) & set(requested):
                    self.on_write(reg.name, stored(reg.name), stored)
        except (_BadValue, ValueError) as exc:  # ValueError: the machine refused the value
            registers[offset:offset + len(set_values)] = previous
            log.info("refused write at 0x%04X: %s", address, exc)
            return ExcCodes.ILLEGAL_VALUE
        return None

    def _fill_live(self, requested: range, start_address: int, registers: list[int]) -> None:
        wanted = {r for r in self.READ_ONLY if set(self.map.registers[r].span) & set(requested)}
        block = self.map.block
        in_block = block is not None and address_overlaps(block.address, block.count, requested)
        if in_block:
            wanted |= set(block.layout)
        if not wanted:
            return
        values = self.live_values(wanted)
        for name in wanted & self.READ_ONLY:
            reg = self.map.registers[name]
            first = reg.address - start_address
            registers[first:first + reg.width] = encode(values[name], reg.type, self.word_order)
        if in_block:
            words: list[int] = []
            for name in block.layout:
                words += encode(values[name], self.map.registers[name].type, self.word_order)
            first = block.address - start_address
            registers[first:first + block.count] = words


def address_overlaps(first: int, count: int, requested: range) -> bool:
    return first < requested.stop and requested.start < first + count


class LoadCellDevice(_LiveDevice):
    """Flintec DAD 141.1-style indicator: float32 gross/net/peak, status bits, command register."""

    READ_ONLY = frozenset({"gross_force", "net_force", "peak_force", "capacity", "status"})

    def __init__(self, machine: Any, dmap: DeviceMap, word_order: str, capacity_N: float):
        super().__init__(machine, dmap, word_order)
        self.capacity_N = capacity_N
        self._commands = {
            "zero": machine.zero_load_cell, "tare": machine.tare,
            "reset_peak": machine.reset_peak, "clear_tare": machine.clear_tare,
        }

    def live_values(self, names: set[str]) -> dict[str, float]:
        values: dict[str, float] = {"capacity": self.capacity_N}
        if names - {"capacity"}:
            r = self.machine.read_load_cell()
            values.update(gross_force=r.gross_N, net_force=r.net_N, peak_force=r.peak_N,
                          status=_bits(dict(under_range=r.under_range, over_range=r.over_range,
                                            no_motion=r.no_motion, tare_set=r.tare_set),
                                       self.map.status_bits))
        return values

    def on_write(self, name: str, value: float, stored: Callable[[str], float]) -> None:
        if name != "command":
            return
        for command, code in self.map.codes.items():
            if code == value and command in self._commands:
                self._commands[command]()
                return
        raise _BadValue(f"unknown load-cell command {value}")


class CrossheadDevice(_LiveDevice):
    """Leadshine CS2RS-style drive: int32 targets in um and 0.01 mm/min, trigger register."""

    READ_ONLY = frozenset({"actual_position", "actual_speed", "status", "fault_code"})

    def __init__(self, machine: Any, dmap: DeviceMap, word_order: str, *,
                 max_speed_mm_min: float, acceleration_mm_s2: float,
                 travel_upper_mm: float, travel_lower_mm: float, watchdog_ms: int = 0):
        super().__init__(machine, dmap, word_order)
        self.max_speed_mm_min = max_speed_mm_min
        self._initial = {
            "acceleration": acceleration_mm_s2 * 1000.0,
            "upper_limit": travel_upper_mm * 1000.0,
            "lower_limit": travel_lower_mm * 1000.0,
            "watchdog_ms": watchdog_ms,
        }

    def initial_value(self, name: str) -> float:
        return self._initial.get(name, 0)

    def live_values(self, names: set[str]) -> dict[str, float]:
        values: dict[str, float] = {}
        if names & {"status", "fault_code"}:
            s = self.machine.crosshead_status()
            values["status"] = _bits(dict(
                fault=s.fault, enabled=s.enabled, moving=s.moving, in_position=s.in_position,
                upper_limit=s.upper_limit, lower_limit=s.lower_limit, emergency_stop=s.emergency_stop,
            ), self.map.status_bits)
            values["fault_code"] = s.fault_code
        if "actual_position" in names:
            values["actual_position"] = self.machine.position_mm() * 1000.0
        if "actual_speed" in names:
            values["actual_speed"] = self.machine.speed_mm_min() * 100.0
        return values

    def _speed(self, stored: Callable[[str], float]) -> float:
        speed = stored("target_speed") / 100.0
        if not 0 < speed <= self.max_speed_mm_min:
            raise _BadValue(f"target speed {speed} mm/min outside (0, {self.max_speed_mm_min}]")
        return speed

    def on_write(self, name: str, value: float, stored: Callable[[str], float]) -> None:
        m = self.machine
        if name == "acceleration":
            if value <= 0:
                raise _BadValue("acceleration must be > 0")
            m.set_acceleration(value / 1000.0)
        elif name in ("upper_limit", "lower_limit"):
            upper, lower = stored("upper_limit") / 1000.0, stored("lower_limit") / 1000.0
            if not upper < lower:
                raise _BadValue(f"upper limit {upper} mm must be above (smaller than) lower limit {lower} mm")
            m.set_travel_limits(upper, lower)
        elif name == "watchdog_ms":
            m.set_watchdog_ms(int(value))
        elif name == "trigger":
            trigger = {code: t for t, code in self.map.codes.items()}.get(int(value))
            if trigger == "move_absolute":
                m.move_to(stored("target_position") / 1000.0, self._speed(stored))
            elif trigger == "jog_down":
                m.jog(+1, self._speed(stored))
            elif trigger == "jog_up":
                m.jog(-1, self._speed(stored))
            elif trigger == "set_zero":
                m.set_zero()
            elif trigger == "stop":
                m.stop()
            elif trigger == "emergency":
                m.emergency_stop()
            elif trigger == "reset_fault":
                m.reset_fault()
            else:
                raise _BadValue(f"unknown trigger 0x{int(value):04X}")
        # target_position / target_speed are parameters: stored, used by the next trigger.


# --------------------------------------------------------------------------- faults on the wire

def corrupt_frame(packet: bytes, framer: FramerType, rng: random.Random) -> bytes:
    """A reply a careful client must reject: RTU - one flipped bit (CRC no longer matches);
    TCP - a non-zero MBAP protocol id (the standard requires 0)."""
    data = bytearray(packet)
    if framer == FramerType.SOCKET:
        data[2:4] = b"\xff\xff"
    else:
        i = rng.randrange(1, max(2, len(data) - 2))
        data[i] ^= 1 << rng.randrange(8)
    return bytes(data)


def garbage_bytes(rng: random.Random, n: int = 12) -> bytes:
    return bytes(rng.randrange(256) for _ in range(n))


class _SimRequestHandler(ServerRequestHandler):
    """pymodbus' request handler plus the simulator's wire faults and watchdog kicks."""

    def __init__(self, owner, *args):
        super().__init__(owner, *args)
        self._mangle_next: str | None = None

    async def handle_request(self):
        pdu = self.last_pdu
        if pdu is None:
            return
        sim: ModbusSimServer = self.server.sim
        if pdu.dev_id not in sim.unit_ids:
            if sim.framer == FramerType.SOCKET:  # a gateway answers for units it cannot reach
                self._reply_exception(pdu, ExcCodes.GATEWAY_NO_RESPONSE)
            return  # on a serial line, nobody answers for a unit that is not there
        fault = sim.next_wire_fault()
        if fault == "drop":
            sim.drop_link(self)
            return
        if fault == "timeout":  # the request is lost: no reply, nothing done
            return
        sim.machine.host_activity()
        if fault == "exception":  # the device heard it and could not do it
            self._reply_exception(pdu, ExcCodes.DEVICE_FAILURE)
            return
        self._mangle_next = fault  # crc / garbage: done, but the reply is hit on the way back
        await super().handle_request()

    def _reply_exception(self, pdu, code: ExcCodes) -> None:
        self.server_send(ExceptionResponse(pdu.function_code, code, device_id=pdu.dev_id,
                                           transaction=pdu.transaction_id), self.last_addr)

    def pdu_send(self, pdu, addr=None) -> None:
        packet = self.framer.buildFrame(pdu)
        mangle, self._mangle_next = self._mangle_next, None
        if mangle == "crc":
            packet = corrupt_frame(packet, self.server.sim.framer, self.server.sim.rng)
        elif mangle == "garbage":
            packet = garbage_bytes(self.server.sim.rng, len(packet))
        self.send(packet, addr)


class _TcpServer(ModbusTcpServer):
    def callback_new_connection(self):
        return _SimRequestHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


class _PtyRtuServer(ModbusSerialServer):
    """ModbusSerialServer whose "serial port" is the master side of our pty."""

    def __init__(self, context, pty: PtyPort, **kwargs):
        super().__init__(context, framer=FramerType.RTU, port=pty.path, baudrate=pty.baudrate, **kwargs)
        self.pty = pty
        self.call_create = self._open_link  # instead of opening a device path with pyserial

    async def _open_link(self):
        protocol = self.handle_new_connection()
        return PtyTransport(self.loop, self.pty, protocol), protocol

    def callback_new_connection(self):
        return _SimRequestHandler(self, self.trace_packet, self.trace_pdu, self.trace_connect)


# --------------------------------------------------------------------------- the server

def _bind_error(host: str, port: int) -> str:
    """Why a TCP listen failed, in the OS's words (pymodbus only logs it)."""
    probe = socket.socket(socket.AF_INET6 if ":" in host else socket.AF_INET)
    try:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        probe.bind((host, port))
    except OSError as exc:
        return exc.strerror or str(exc)
    finally:
        probe.close()
    return "the address could not be bound"


class ModbusSimServer:
    """Both Modbus devices of a profile on one transport, backed by one SimulatedMachine.

    Create and use it inside a running asyncio loop (launch.start_simulator does that in
    a background thread): ``await start()``, ``await stop()``.
    """

    def __init__(self, machine: Any, profile: dict, transport: str, *,
                 host: str = "127.0.0.1", port: int = 0, seed: int = 0):
        if transport not in TRANSPORTS:
            raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
        self.machine = machine
        self.profile = profile
        self.transport = transport
        self.host, self.port = host, port
        self.framer = FramerType.SOCKET if transport == "tcp" else FramerType.RTU
        self.rng = random.Random(seed)
        self.drops = 0
        wire, word_order = profile["wire"], profile["word_order"]
        lc, ch = profile["load_cell"], profile["crosshead"]
        # The registers start as the machine was built (its settings come from the profile).
        st = machine.settings
        self.load_cell = LoadCellDevice(machine, DeviceMap.from_wire(wire, "load_cell"), word_order,
                                        capacity_N=st.capacity_N)
        self.crosshead = CrossheadDevice(
            machine, DeviceMap.from_wire(wire, "crosshead"), word_order,
            max_speed_mm_min=st.max_speed_mm_min, acceleration_mm_s2=st.acceleration_mm_s2,
            travel_upper_mm=st.travel_upper_mm, travel_lower_mm=st.travel_lower_mm,
            watchdog_ms=st.watchdog_ms,
        )
        self.unit_ids = (int(lc["unit_id"]), int(ch["unit_id"]))
        self.pty: PtyPort | None = None
        self._server: _TcpServer | _PtyRtuServer | None = None
        self._tasks: set[asyncio.Task] = set()

    def devices(self) -> list[SimDevice]:
        return [self.load_cell.sim_device(self.unit_ids[0]), self.crosshead.sim_device(self.unit_ids[1])]

    async def start(self) -> None:
        if self.transport == "rtu-pty":
            self.pty = PtyPort(int(self.profile["connection"].get("baudrate", 115200)))
            self._server = _PtyRtuServer(self.devices(), self.pty)
        else:
            self._server = _TcpServer(self.devices(), framer=self.framer, address=(self.host, self.port))
        self._server.sim = self
        try:
            await self._server.serve_forever(background=True)
        except RuntimeError:  # pymodbus logs the OSError and raises "Could not start listen"
            await self.stop()
            raise OSError(f"cannot listen on {self.host}:{self.port}: {_bind_error(self.host, self.port)}") from None
        if self.transport != "rtu-pty":
            self.port = self._server.transport.sockets[0].getsockname()[1]

    @property
    def client_url(self) -> str:
        """What a client opens: host:port for TCP, a pyserial URL or a device path for RTU."""
        if self.transport == "tcp":
            return f"{self.host}:{self.port}"
        if self.transport == "rtu-socket":
            return f"socket://{self.host}:{self.port}"
        return self.pty.path

    def next_wire_fault(self) -> str | None:
        faults = getattr(self.machine, "faults", None)
        if not faults:
            return None
        for name in MODBUS_WIRE_FAULTS:
            if faults.should_fire(name):
                return name
        return None

    def drop_link(self, handler: ServerRequestHandler) -> None:
        """Close the connection the request came on; a pty is hung up and replaced."""
        self.drops += 1
        handler.close()
        if self.transport == "rtu-pty":
            task = asyncio.get_running_loop().create_task(self._reopen_pty())
            self._tasks.add(task)
            task.add_done_callback(self._tasks.discard)

    async def _reopen_pty(self) -> None:
        await asyncio.sleep(0)  # let the hang-up reach the client first
        if self._server is None or self.pty is None:
            return
        self.pty.reopen()
        await self._server.listen()

    async def stop(self) -> None:
        """Close the listener and every connection; idempotent."""
        for task in list(self._tasks):
            task.cancel()
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()
        if self.pty is not None:
            self.pty.close()
