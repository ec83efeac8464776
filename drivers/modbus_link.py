"""One Modbus link (a TCP socket, or an RTU serial line) shared by several devices' unit ids.

Every request runs under the link's lock, so the run engine and the GUI may share a
machine. It moves 16-bit words: what they mean is the device's (drivers.registers).
pymodbus errors never escape: they become DeviceTimeout, DeviceProtocolError,
DeviceRefused (a Modbus exception reply) or DeviceConnectionLost, with a one-line
message naming the register and the unit id.
"""

from __future__ import annotations

import logging
import select
import socket
import struct
import threading
import time
from typing import Callable, Sequence

import serial
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException, ModbusException, ModbusIOException
from pymodbus.framer import FramerType

try:  # POSIX only; elsewhere socket:// RTU falls back to pymodbus' byte-wise polling
    import fcntl
    import termios
except ImportError:  # pragma: no cover
    fcntl = termios = None

from .base import DeviceConnectionLost, DeviceProtocolError, DeviceRefused, DeviceTimeout
from .registers import DeviceMap

# pymodbus logs every timeout at ERROR; we raise DeviceError instead, so keep its log
# records away from logging's last-resort stderr handler (an application may still
# attach its own handler to "pymodbus").
logging.getLogger("pymodbus").addHandler(logging.NullHandler())

#: Standard Modbus exception codes (Modbus Application Protocol v1.1b3, section 7); a device
#: file's [exceptions] says what its device means by them.
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


#: How long an unanswered repeatable write (a stop, a reset, a zero: the same effect however
#: often it arrives) is sent again. Such commands are not on the sample clock, and a reply later
#: than the sample-period timeout (a loaded host, a busy drive) must not report a stop or a
#: reset the drive carried out as failed: on a loaded CI host a reset was answered after 80 ms.
REPEAT_FOR_S = 1.0


class ModbusLink:
    """One Modbus connection (TCP socket or RTU serial line) shared by several unit ids."""

    def __init__(self, connection: dict):
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

    def _execute(self, action: str, unit: int, call: Callable[[], object], meanings: dict[int, str] | None):
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
                code = getattr(response, "exception_code", None) or 0
                meaning = (meanings or {}).get(code) or MODBUS_EXCEPTIONS.get(code, "unknown exception")
                raise DeviceRefused(
                    f"{self.where}: unit {unit} refused {action}: Modbus exception 0x{code:02X} ({meaning})")
            return response

    def read_words(self, unit: int, address: int, count: int, label: str,
                   meanings: dict[int, str] | None = None) -> list[int]:
        """Function 3: `count` registers from `address`; `label` names them in errors."""
        response = self._execute(
            f"read of {label}", unit,
            lambda: self._client.read_holding_registers(address, count=count, device_id=unit), meanings)
        words = list(response.registers)
        if len(words) != count:
            raise DeviceProtocolError(
                f"{self.where}: unit {unit} returned {len(words)} registers for {label}, expected {count}")
        return words

    def write_words(self, unit: int, address: int, words: Sequence[int], label: str,
                    meanings: dict[int, str] | None = None, single: bool = True, repeatable: bool = False) -> None:
        """Function 6 for one register, function 16 for several (one request: atomic on the device);
        `single=False`: function 16 always (a device without function 6, such as the Laumas TLU).
        `repeatable`: the write has the same effect however often it arrives, so while it goes
        unanswered it is sent again for up to REPEAT_FOR_S (each send with the link's retries)."""
        words = list(words)
        action = f"write of {label}"
        if len(words) == 1 and single:
            def call():
                return self._client.write_register(address, words[0], device_id=unit)
        else:
            def call():
                return self._client.write_registers(address, words, device_id=unit)
        deadline = time.monotonic() + REPEAT_FOR_S
        sends = 0
        while True:
            sends += 1
            try:
                self._execute(action, unit, call, meanings)
                return
            except DeviceTimeout as timeout:
                if not repeatable or time.monotonic() >= deadline:
                    if sends > 1:
                        raise DeviceTimeout(f"{timeout}, sent {sends} times in {REPEAT_FOR_S:g} s") from None
                    raise


class DeviceOnLink:
    """One device, as its device file describes it, at one unit id of a link: by register name."""

    def __init__(self, link: ModbusLink, device: DeviceMap, unit: int):
        self.link, self.device, self.unit = link, device, unit
        self._meanings = device.exceptions
        self._single = 6 in device.functions

    def read(self, name: str) -> int | float:
        register = self.device.registers[name]
        words = self.link.read_words(self.unit, register.address, register.count, register.label(), self._meanings)
        return register.decode(words, self.device.word_order)

    def read_block(self, name: str) -> dict[str, int | float]:
        block = self.device.blocks[name]
        words = self.link.read_words(self.unit, block.address, block.count, block.label(), self._meanings)
        return block.decode(words, self.device.word_order)

    def write(self, name: str, value: int) -> None:
        register = self.device.registers[name]
        self.link.write_words(self.unit, register.address, register.encode(value, self.device.word_order),
                              f"{register.label()} = {value}", self._meanings, self._single)

    def write_block(self, name: str, values: dict[str, int | float]) -> None:
        block = self.device.blocks[name]
        shown = ", ".join(f"{k} = {v}" for k, v in values.items())
        self.link.write_words(self.unit, block.address, block.encode(values, self.device.word_order),
                              f"{block.label()}: {shown}", self._meanings, self._single)

    def command(self, register: str, name: str, repeatable: bool = False) -> None:
        """Write one of the register's documented values (the device file's [values.<register>]);
        `repeatable`: see ModbusLink.write_words."""
        value = self.device.value(register, name)
        reg = self.device.registers[register]
        self.link.write_words(self.unit, reg.address, reg.encode(value, self.device.word_order),
                              f"{reg.label()} = 0x{value:04X} ({name})", self._meanings, self._single, repeatable)
