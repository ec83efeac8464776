"""The simulated machine's two Modbus devices on one transport, served by pymodbus 3.16 server classes.

One server carries both devices of a Modbus profile, each at its profile's unit id and
each as its device file documents it (simulator.modbus_devices: a Flintec DAD 141.1 and
a Leadshine CS2RS). Transports:

- ``tcp``        Modbus TCP (MBAP framing) on a TCP port: a gateway in front of the RS-485
                 line (the CS2RS speaks RTU only);
- ``rtu-socket`` RTU frames over a TCP socket (what pyserial calls ``socket://host:port``);
- ``rtu-pty``    RTU frames over a pseudo-terminal: clients open a device path.

A function code the device does not list (its device file's [device.functions]) answers
exception 0x01 before anything else; an address it does not document answers 0x02.

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
from typing import Any

from pymodbus.constants import ExcCodes
from pymodbus.framer import FramerType
from pymodbus.pdu import ExceptionResponse
from pymodbus.server import ModbusSerialServer, ModbusTcpServer
from pymodbus.server.requesthandler import ServerRequestHandler
from pymodbus.simulator import SimDevice

from drivers.registers import profile_device
from simulator.modbus_devices import LiveDevice, simulate
from simulator.pty_link import PtyPort, PtyTransport

log = logging.getLogger(__name__)

#: Transports this module serves.
TRANSPORTS = ("tcp", "rtu-socket", "rtu-pty")
#: Wire faults a Modbus server injects, in the order they are asked for on each request.
MODBUS_WIRE_FAULTS = ("drop", "timeout", "exception", "crc", "garbage")


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
    """pymodbus' request handler plus each device's function codes and the simulator's wire faults."""

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
        if pdu.function_code not in sim.devices[pdu.dev_id].functions:
            self._reply_exception(pdu, ExcCodes.ILLEGAL_FUNCTION)
            return
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
        # unit id -> the device answering there, as its device file documents it
        self.devices: dict[int, LiveDevice] = {
            int(profile[role]["unit_id"]): simulate(machine, profile_device(profile, role), profile[role])
            for role in ("load_cell", "crosshead")}
        self.unit_ids = tuple(self.devices)
        self.load_cell, self.crosshead = self.devices.values()
        self.pty: PtyPort | None = None
        self._server: _TcpServer | _PtyRtuServer | None = None
        self._tasks: set[asyncio.Task] = set()

    def sim_devices(self) -> list[SimDevice]:
        return [device.sim_device(unit) for unit, device in self.devices.items()]

    async def start(self) -> None:
        if self.transport == "rtu-pty":
            self.pty = PtyPort(int(self.profile["connection"].get("baudrate", 115200)))
            self._server = _PtyRtuServer(self.sim_devices(), self.pty)
        else:
            self._server = _TcpServer(self.sim_devices(), framer=self.framer, address=(self.host, self.port))
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
