"""Modbus profile: a load-cell indicator and a crosshead drive (RTU or TCP, pymodbus client).

The registers come from the profile's register map (configs/machines/_modbus_map.toml),
described once as `Register`/`Block` objects; the word order of 32-bit values is the
profile's `word_order`. Both devices share one `ModbusLink` (one socket or one serial
line, two unit ids); every request runs under the link's lock, so the run engine and
the GUI may share a machine. pymodbus errors never escape: they become DeviceTimeout,
DeviceProtocolError or DeviceConnectionLost with a one-line message naming the
register and the unit id.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import threading
from dataclasses import dataclass
from typing import Callable, Sequence

import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.client.mixin import ModbusClientMixin
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

try:  # POSIX only; elsewhere socket:// RTU falls back to pymodbus' byte-wise polling
    import fcntl
    import termios
except ImportError:  # pragma: no cover
    fcntl = termios = None

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
)

# pymodbus logs every timeout at ERROR; we raise DeviceError instead, so keep its log
# records away from logging's last-resort stderr handler (an application may still
# attach its own handler to "pymodbus").
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Word orders of 32-bit values a profile may set (`word_order`): vendors differ.
WORD_ORDERS = ("big", "little")

_DATATYPE = ModbusClientMixin.DATATYPE
#: Register types a register map may use, and how pymodbus converts each.
_DATATYPES = {
    "uint16": _DATATYPE.UINT16,
    "int16": _DATATYPE.INT16,
    "uint32": _DATATYPE.UINT32,
    "int32": _DATATYPE.INT32,
    "float32": _DATATYPE.FLOAT32,
}

#: Standard Modbus exception codes (Modbus Application Protocol v1.1b3, section 7).
MODBUS_EXCEPTIONS = {
    0x01: "illegal function",
    0x02: "illegal data address",
    0x03: "illegal data value",
    0x04: "server device failure",
    0x05: "acknowledge",
    0x06: "server device busy",
    0x08: "memory parity error",
    0x0A: "gateway path unavailable",
    0x0B: "gateway target device failed to respond",
}


# --------------------------------------------------------------------------- register map

@dataclass(frozen=True)
class Register:
    """One value in holding registers: 16-bit, or 32-bit over two registers."""

    name: str
    address: int
    type: str
    unit: str = ""

    @property
    def count(self) -> int:
        return 2 if self.type.endswith("32") else 1

    def decode(self, words: Sequence[int], word_order: str) -> int | float:
        return ModbusClientMixin.convert_from_registers(list(words), _DATATYPES[self.type], word_order=word_order)

    def encode(self, value: int | float, word_order: str) -> list[int]:
        if self.type != "float32":
            value = int(value)
            bits = 16 if self.count == 1 else 32
            low, high = (-(1 << bits - 1), (1 << bits - 1) - 1) if self.type.startswith("int") else (0, (1 << bits) - 1)
            if not low <= value <= high:
                raise ValueError(f"{value} does not fit register {self.name} ({self.type})")
        return ModbusClientMixin.convert_to_registers(value, _DATATYPES[self.type], word_order=word_order)

    def label(self) -> str:
        return f"{self.name} (0x{self.address:04X})"


@dataclass(frozen=True)
class Block:
    """Consecutive registers read in one request (e.g. the indicator's 0x3500 block)."""

    name: str
    address: int
    count: int
    layout: tuple[Register, ...]

    def decode(self, words: Sequence[int], word_order: str) -> dict[str, int | float]:
        values, offset = {}, 0
        for register in self.layout:
            values[register.name] = register.decode(words[offset:offset + register.count], word_order)
            offset += register.count
        return values

    def label(self) -> str:
        return f"{self.name} (0x{self.address:04X}, {self.count} registers)"


@dataclass(frozen=True)
class RegisterMap:
    """One device's section of the register map: registers, blocks and named constants
    (status bits, command / trigger codes, fault codes)."""

    device: str
    registers: dict[str, Register]
    blocks: dict[str, Block]
    constants: dict[str, dict[str, int]]

    @classmethod
    def from_toml(cls, wire: dict, device: str) -> "RegisterMap":
        section = wire.get(device)
        if not isinstance(section, dict):
            raise ValueError(f"no [{device}] section")
        registers, raw_blocks, constants = {}, {}, {}
        for name, entry in section.items():
            where = f"[{device}] {name}"
            if not isinstance(entry, dict):
                raise ValueError(f"{where}: expected a table")
            address = entry.get("address")
            if "layout" in entry:
                raw_blocks[name] = entry
            elif address is not None:
                if not isinstance(address, int) or not 0 <= address <= 0xFFFF:
                    raise ValueError(f"{where}: address must be 0..0xFFFF, got {address!r}")
                if entry.get("type") not in _DATATYPES:
                    raise ValueError(f"{where}: type must be one of {', '.join(_DATATYPES)}, got {entry.get('type')!r}")
                registers[name] = Register(name, address, entry["type"], entry.get("unit", ""))
            else:
                if not all(isinstance(v, int) and not isinstance(v, bool) for v in entry.values()):
                    raise ValueError(f"{where}: constants must be integers")
                constants[name] = dict(entry)
        blocks = {}
        for name, entry in raw_blocks.items():
            where = f"[{device}] {name}"
            try:
                layout = tuple(registers[r] for r in entry["layout"])
            except KeyError as exc:
                raise ValueError(f"{where}: layout names unknown register {exc.args[0]!r}") from None
            count = entry.get("count")
            if count != sum(r.count for r in layout):
                raise ValueError(f"{where}: count {count!r} does not match its layout ({sum(r.count for r in layout)} registers)")
            blocks[name] = Block(name, entry["address"], count, layout)
        return cls(device, registers, blocks, constants)

    def require(self, registers: Sequence[str] = (), blocks: Sequence[str] = (), constants: dict[str, Sequence[str]] | None = None) -> "RegisterMap":
        """Check that the names a driver uses exist; raise ValueError naming the first missing one."""
        for name in registers:
            if name not in self.registers:
                raise ValueError(f"[{self.device}] lacks register {name!r}")
        for name in blocks:
            if name not in self.blocks:
                raise ValueError(f"[{self.device}] lacks block {name!r}")
        for table, names in (constants or {}).items():
            for name in names:
                if name not in self.constants.get(table, {}):
                    raise ValueError(f"[{self.device}.{table}] lacks {name!r}")
        return self

    def bits(self, table: str, word: int) -> dict[str, bool]:
        return {name: bool(word >> bit & 1) for name, bit in self.constants[table].items()}


# --------------------------------------------------------------------------- the link

class _SerialClient(ModbusSerialClient):
    """ModbusSerialClient that knows how many bytes a socket:// port really holds.

    pyserial's socket:// `in_waiting` is 1 when anything is readable, and pymodbus polls
    `in_waiting` every millisecond until it stops growing - so it would read an RTU reply
    one byte per poll (slow, and timeouts mid-frame under load: measured in
    docs/protocols.md#rtu-waiting-for-a-reply-without-polling). FIONREAD gives the real
    count; other ports (ttys, ptys) keep pyserial's answer.
    """

    def _in_waiting(self) -> int:
        sock = getattr(self.socket, "_socket", None)
        if sock is None or fcntl is None:
            return super()._in_waiting()
        count = struct.unpack("i", fcntl.ioctl(sock.fileno(), termios.FIONREAD, b"\0\0\0\0"))[0]
        if count == 0 and select.select([sock], [], [], 0)[0]:
            return 1   # readable yet empty: the peer closed; pyserial's read will report it
        return count

    def _readable_fd(self):
        port = self.socket
        sock = getattr(port, "_socket", None)
        return sock.fileno() if sock is not None else getattr(port, "fd", None)

    def recv(self, size: int | None) -> bytes:
        """Wake when the reply's bytes arrive instead of polling the port every millisecond.

        pymodbus waits for a reply by sleeping 1 ms, checking `in_waiting`, until the count
        stops growing: milliseconds per request whatever the line's speed (measured:
        docs/protocols.md#rtu-waiting-for-a-reply-without-polling). Here select() wakes on
        the first byte and returns what has come; pymodbus' framer keeps a partial frame and
        asks again for the rest (each wait bounded by the timeout, an empty return meaning
        "no reply").
        """
        fd = self._readable_fd() if size is None and self.socket else None
        if fd is None:
            return super().recv(size)
        try:
            if not select.select([fd], [], [], self.comm_params.timeout_connect)[0]:
                return b""
            return self.socket.read(max(1, self._in_waiting()))
        except (BlockingIOError, InterruptedError):
            raise
        except (OSError, ValueError):
            self.close()
            raise ConnectionException(str(self)) from None


def _is_other_transaction(got: bytes, sent: bytes) -> bool:
    """A whole, well-formed MBAP frame from the request's unit whose transaction id is another."""
    if len(got) < 8 or len(sent) < 8:
        return False
    _, protocol, length, unit = struct.unpack(">HHHB", got[:7])
    return protocol == 0 and length == len(got) - 6 and unit == sent[6] and got[:2] != sent[:2]


class ModbusLink:
    """One Modbus connection (TCP socket or RTU serial line) shared by several unit ids."""

    def __init__(self, connection: dict, word_order: str):
        if word_order not in WORD_ORDERS:
            raise ValueError(f"word_order must be one of {WORD_ORDERS}")
        self.word_order = word_order
        self.timeout_s = float(connection["timeout_s"])
        self.retries = int(connection["retries"])
        self.lock = threading.RLock()
        self._received = b""
        self._sent = b""
        if connection["transport"] == "tcp":
            self.where = f"Modbus TCP {connection['host']}:{connection['port']}"
            self._client: ModbusTcpClient | ModbusSerialClient = ModbusTcpClient(
                connection["host"], port=int(connection["port"]), timeout=self.timeout_s,
                retries=self.retries, trace_packet=self._trace_packet)
        else:
            self.where = f"Modbus RTU {connection['port_url']}"
            # pymodbus opens the port with serial.serial_for_url, so any pyserial URL works.
            self._client = _SerialClient(
                connection["port_url"], framer=FramerType.RTU, baudrate=int(connection["baudrate"]),
                parity=connection.get("parity", "N"), stopbits=int(connection.get("stopbits", 1)),
                bytesize=8, timeout=self.timeout_s, retries=self.retries, trace_packet=self._trace_packet)

    def _trace_packet(self, sending: bool, data: bytes) -> bytes:
        # pymodbus hands us the receive buffer before framing; remembering it lets us tell
        # "nothing came back" (timeout) from "bytes came back but no valid frame" (bad CRC).
        if not sending and data:
            self._received = bytes(data)
        elif sending:
            self._sent = bytes(data)
        return data

    def _invalid_reply(self, what: str) -> str:
        """Why bytes came back but no reply to this request: a late answer to an earlier one
        (Modbus TCP: a well-formed frame whose transaction id is not the request's) or a frame
        that does not check (a bad RTU CRC, a TCP header that does not add up, garbage)."""
        got, sent = self._received, self._sent
        if isinstance(self._client, ModbusTcpClient):
            if _is_other_transaction(got, sent):
                return (f"{self.where}: stale reply to {what}: transaction {int.from_bytes(got[:2], 'big')} "
                        f"answers an earlier request, not {int.from_bytes(sent[:2], 'big')} "
                        f"(a reply that came after its timeout)")
            return f"{self.where}: invalid reply (bad framing) to {what}: {got[:32].hex(' ')}"
        return f"{self.where}: invalid reply (bad CRC or framing) to {what}: {got[:32].hex(' ')}"

    def connect(self) -> None:
        with self.lock:
            if not self._client.connect():
                raise DeviceConnectionLost(f"{self.where}: cannot connect{self._why_not_connected()}")

    def _why_not_connected(self) -> str:
        """pymodbus only logs why connect() failed; try once more ourselves for the reason
        (refused, no such device, permission denied - the user can act on those)."""
        params = self._client.comm_params
        try:
            if isinstance(self._client, ModbusTcpClient):
                socket.create_connection((params.host, params.port), timeout=params.timeout_connect).close()
            else:
                serial.serial_for_url(params.host, baudrate=params.baudrate).close()
        except Exception as exc:  # any reason is better than none; this is the failure path
            return f": {getattr(exc, 'strerror', None) or exc}"
        return ""

    def close(self) -> None:
        with self.lock:
            try:
                self._client.close()
            except Exception:  # close() must never raise; the port may already be gone
                pass

    @property
    def connected(self) -> bool:
        return bool(self._client.connected)

    def _drain_stale_tcp_input(self) -> None:
        """Drop bytes of a late reply to an earlier (timed-out) request before a new one.

        pymodbus' serial client does this itself; the TCP client does not.
        """
        sock = getattr(self._client, "socket", None)
        if not isinstance(self._client, ModbusTcpClient) or sock is None:
            return
        try:
            while select.select([sock], [], [], 0)[0]:
                sock.setblocking(False)
                if not sock.recv(4096):
                    self._client.close()   # peer closed: the request will reconnect
                    return
        except (BlockingIOError, InterruptedError):
            return
        except (OSError, ValueError):
            self._client.close()

    def _execute(self, action: str, unit: int, call: Callable[[], object]):
        with self.lock:
            self._drain_stale_tcp_input()
            self._received = b""
            what = f"{action} of unit {unit}"
            try:
                response = call()
            except ConnectionException:
                self._client.close()
                raise DeviceConnectionLost(f"{self.where}: connection lost during {what}") from None
            except ModbusIOException:
                if self._received:
                    raise DeviceProtocolError(self._invalid_reply(what)) from None
                attempts = self.retries + 1
                raise DeviceTimeout(
                    f"{self.where}: no reply to {what} ({attempts} attempt{'s' * (attempts > 1)} "
                    f"of {self.timeout_s * 1000:.0f} ms)") from None
            except ModbusException as exc:
                raise DeviceProtocolError(f"{self.where}: {what} failed: {exc}") from None
            except OSError as exc:   # serial.SerialException is an OSError
                self._client.close()
                raise DeviceConnectionLost(f"{self.where}: {exc.strerror or exc} during {what}") from None
            if response.isError():
                code = getattr(response, "exception_code", None)
                meaning = MODBUS_EXCEPTIONS.get(code, "unknown exception")
                raise DeviceRefused(
                    f"{self.where}: unit {unit} refused {action}: Modbus exception "
                    f"0x{code or 0:02X} ({meaning})")
            return response

    def _read_words(self, unit: int, address: int, count: int, label: str) -> list[int]:
        response = self._execute(
            f"read of {label}", unit,
            lambda: self._client.read_holding_registers(address, count=count, device_id=unit))
        words = list(response.registers)
        if len(words) != count:
            raise DeviceProtocolError(
                f"{self.where}: unit {unit} returned {len(words)} registers for {label}, expected {count}")
        return words

    def read(self, unit: int, register: Register) -> int | float:
        return register.decode(self._read_words(unit, register.address, register.count, register.label()),
                               self.word_order)

    def read_block(self, unit: int, block: Block) -> dict[str, int | float]:
        return block.decode(self._read_words(unit, block.address, block.count, block.label()), self.word_order)

    def write_together(self, unit: int, values: Sequence[tuple[Register, int | float]]) -> None:
        """Write several registers; one request (atomic on the device) when they are contiguous."""
        ordered = sorted(values, key=lambda rv: rv[0].address)
        contiguous = all(a.address + a.count == b.address for (a, _), (b, _) in zip(ordered, ordered[1:]))
        if not contiguous:
            for register, value in values:
                self.write(unit, register, value)
            return
        words = [w for register, value in ordered for w in register.encode(value, self.word_order)]
        first = ordered[0][0]
        action = "write of " + ", ".join(f"{r.label()} = {v}" for r, v in ordered)
        self._execute(action, unit, lambda: self._client.write_registers(first.address, words, device_id=unit))

    def write(self, unit: int, register: Register, value: int | float) -> None:
        words = register.encode(value, self.word_order)
        action = f"write of {register.label()} = {value}"
        if len(words) == 1:
            self._execute(action, unit, lambda: self._client.write_register(register.address, words[0], device_id=unit))
        else:
            self._execute(action, unit, lambda: self._client.write_registers(register.address, words, device_id=unit))


# --------------------------------------------------------------------------- devices

class ModbusLoadCell(LoadCell):
    """Load-cell indicator modelled on the Flintec DAD 141.1: one block read per sample."""

    REGISTERS = ("net_force", "status", "command")
    BLOCKS = ("block",)
    CONSTANTS = {"status_bits": ("under_range", "over_range", "no_motion", "tare_set"),
                 "commands": ("zero", "tare")}

    @classmethod
    def checked_map(cls, registers: RegisterMap) -> RegisterMap:
        registers.require(cls.REGISTERS, cls.BLOCKS, cls.CONSTANTS)
        layout = {r.name for r in registers.blocks["block"].layout}
        if not {"net_force", "status"} <= layout:
            raise ValueError(f"[{registers.device}] block must contain net_force and status")
        return registers

    def __init__(self, link: ModbusLink, registers: RegisterMap, settings: dict):
        self.link = link
        self.map = self.checked_map(registers)
        self.unit = int(settings["unit_id"])
        self.capacity_N = float(settings["capacity_N"])
        self.force_sign = int(settings.get("force_sign", 1))

    def read(self) -> ForceReading:
        values = self.link.read_block(self.unit, self.map.blocks["block"])
        bits = self.map.bits("status_bits", int(values["status"]))
        status = LoadCellStatus(under_range=bits["under_range"], over_range=bits["over_range"],
                                stable=bits["no_motion"], tare_set=bits["tare_set"])
        return ForceReading(self.force_sign * float(values["net_force"]), status)

    def command(self, name: str) -> None:
        """Write a command code (zero, tare, reset_peak, clear_tare) to the command register."""
        self.link.write(self.unit, self.map.registers["command"], self.map.constants["commands"][name])

    def zero(self) -> None:
        self.command("zero")

    def tare(self) -> None:
        self.command("tare")


class ModbusCrosshead(Crosshead):
    """Closed-loop stepper drive modelled on a Leadshine CS2RS (PR motion: target, speed, trigger).

    Positions are int32 micrometres (positive down), speeds int32 in 0.01 mm/min.
    """

    REGISTERS = ("target_position", "target_speed", "acceleration", "actual_position", "status",
                 "trigger", "upper_limit", "lower_limit", "watchdog_ms", "fault_code")
    CONSTANTS = {"status_bits": ("fault", "moving", "in_position", "upper_limit", "lower_limit", "emergency_stop"),
                 "triggers": ("move_absolute", "jog_down", "jog_up", "set_zero", "stop", "emergency", "reset_fault")}
    BLOCKS = ()
    UM_PER_MM = 1000
    SPEED_UNITS_PER_MM_MIN = 100

    @classmethod
    def checked_map(cls, registers: RegisterMap) -> RegisterMap:
        return registers.require(cls.REGISTERS, cls.BLOCKS, cls.CONSTANTS)

    def __init__(self, link: ModbusLink, registers: RegisterMap, settings: dict):
        self.link = link
        self.map = self.checked_map(registers)
        self.unit = int(settings["unit_id"])
        self.max_speed_mm_min = float(settings["max_speed_mm_min"])
        self.acceleration_mm_s2 = settings.get("acceleration_mm_s2")
        self.watchdog_ms = settings.get("watchdog_ms")

    # one-line helpers over the map
    def _write(self, name: str, value: int | float) -> None:
        self.link.write(self.unit, self.map.registers[name], value)

    def _read(self, name: str) -> int | float:
        return self.link.read(self.unit, self.map.registers[name])

    def _trigger(self, name: str) -> None:
        self._write("trigger", self.map.constants["triggers"][name])

    def _speed_units(self, speed_mm_min: float) -> int:
        if not 0 < speed_mm_min <= self.max_speed_mm_min:
            raise ValueError(f"speed {speed_mm_min} mm/min outside (0, {self.max_speed_mm_min}] mm/min")
        return max(1, round(speed_mm_min * self.SPEED_UNITS_PER_MM_MIN))

    def configure(self) -> None:
        """Write the profile's acceleration and watchdog to the drive (on connect)."""
        if self.acceleration_mm_s2 is not None:
            self._write("acceleration", round(float(self.acceleration_mm_s2) * self.UM_PER_MM))
        if self.watchdog_ms is not None:
            self._write("watchdog_ms", int(self.watchdog_ms))

    def read_position(self) -> float:
        return self._read("actual_position") / self.UM_PER_MM

    def status(self) -> CrossheadStatus:
        bits = self.map.bits("status_bits", int(self._read("status")))
        return CrossheadStatus(moving=bits["moving"], in_position=bits["in_position"],
                               upper_limit=bits["upper_limit"], lower_limit=bits["lower_limit"],
                               fault=bits["fault"], emergency_stopped=bits["emergency_stop"])

    def fault_reason(self) -> str:
        """The drive's fault code as a name from the map (`none`, `stall`, `watchdog`, ...)."""
        code = int(self._read("fault_code"))
        names = {v: k for k, v in self.map.constants.get("fault_codes", {}).items()}
        return names.get(code, f"code {code}")

    def move_to(self, target_mm: float, speed_mm_min: float) -> None:
        speed = self._speed_units(speed_mm_min)
        with self.link.lock:   # the three writes belong together
            self._write("target_position", round(target_mm * self.UM_PER_MM))
            self._write("target_speed", speed)
            self._trigger("move_absolute")

    def jog(self, direction: int, speed_mm_min: float) -> None:
        if direction not in (1, -1):
            raise ValueError("jog direction must be +1 (down) or -1 (up)")
        speed = self._speed_units(speed_mm_min)
        with self.link.lock:
            self._write("target_speed", speed)
            self._trigger("jog_down" if direction > 0 else "jog_up")

    def stop(self) -> None:
        self._trigger("stop")

    def emergency_stop(self) -> None:
        self._trigger("emergency")

    def reset_fault(self) -> None:
        self._trigger("reset_fault")

    def set_zero(self) -> None:
        self._trigger("set_zero")

    def set_travel_limits(self, upper_mm: float, lower_mm: float) -> None:
        if not upper_mm < lower_mm:
            raise ValueError(f"upper limit {upper_mm} mm must be above (smaller than) lower limit {lower_mm} mm")
        # Together: a drive that checks upper < lower on each write could refuse either half alone.
        self.link.write_together(self.unit, [
            (self.map.registers["upper_limit"], round(upper_mm * self.UM_PER_MM)),
            (self.map.registers["lower_limit"], round(lower_mm * self.UM_PER_MM))])


class ModbusMachine(Machine):
    """Load cell and crosshead on one Modbus link (two unit ids), from a loaded profile."""

    def __init__(self, profile: dict):
        self.profile = profile
        self.link = ModbusLink(profile["connection"], profile["word_order"])
        self.load_cell = ModbusLoadCell(self.link, RegisterMap.from_toml(profile["wire"], "load_cell"),
                                        profile["load_cell"])
        self.crosshead = ModbusCrosshead(self.link, RegisterMap.from_toml(profile["wire"], "crosshead"),
                                         profile["crosshead"])
        self._configured = False

    def connect(self) -> None:
        with self.link.lock:
            if self._configured and self.link.connected:
                return
            try:
                self.link.connect()
                self.crosshead.configure()
                limits = self.profile["limits"]
                self.crosshead.set_travel_limits(limits["travel_upper_mm"], limits["travel_lower_mm"])
            except DeviceError:
                self.link.close()
                raise
            self._configured = True

    def close(self) -> None:
        self.link.close()
        self._configured = False
