"""A fake device that plays a recorded exchange, byte for byte.

In the spirit of PyMeasure's `expected_protocol`: the test lists (request, reply)
pairs; the peer asserts each request's exact bytes and sends the recorded reply.
The real pymodbus/pyserial clients run unmodified against it, over

- `transport="socket"`: a loopback TCP listener (free port): Modbus TCP via
  host/port, or a serial line via pyserial's `socket://` URL (`peer.url`);
- `transport="pty"`: a pseudo-terminal; the driver opens `peer.url` (/dev/pts/N),
  as it would a USB serial adapter.

Reply values: bytes to send (b"" sends nothing: the device stays silent), or CLOSE to
hang up. `verify()` (after the client closed) checks that every exchange happened and
that the client sent nothing more. Used by tests/test_drivers_*.py.
"""

from __future__ import annotations

import os
import select
import socket
import threading
import time
import tty

CLOSE = object()


def crc16_modbus(data: bytes) -> bytes:
    """Reference CRC-16/MODBUS (poly 0xA001 reflected, init 0xFFFF), low byte first on the wire."""
    crc = 0xFFFF
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0xA001 if crc & 1 else crc >> 1
    return crc.to_bytes(2, "little")


def rtu(*parts: int | bytes) -> bytes:
    """An RTU frame: the given bytes (ints are single bytes) followed by their CRC."""
    body = b"".join(bytes([p]) if isinstance(p, int) else p for p in parts)
    return body + crc16_modbus(body)


def mbap(transaction_id: int, unit: int, pdu: bytes) -> bytes:
    """A Modbus TCP frame: MBAP header (transaction, protocol 0, length, unit) + PDU."""
    return (transaction_id.to_bytes(2, "big") + b"\x00\x00" + (len(pdu) + 1).to_bytes(2, "big")
            + bytes([unit]) + pdu)


class _SocketSide:
    def __init__(self):
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.05)   # poll, so a peer nobody connects to ends promptly
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._conn: socket.socket | None = None

    def accept(self, deadline: float, stop: threading.Event) -> bool:
        while not stop.is_set() and time.monotonic() < deadline:
            try:
                self._conn, _ = self._listener.accept()
                return True
            except socket.timeout:
                continue
        return False

    def read(self, n: int, timeout: float) -> bytes:
        self._conn.settimeout(timeout)
        try:
            return self._conn.recv(n)
        except socket.timeout:
            return None   # nothing yet
        except OSError:
            return b""

    def send(self, data: bytes) -> None:
        self._conn.sendall(data)

    def hang_up(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def leftover(self, wait_s: float) -> bytes:
        """What the client sent after the recording, up to its close (EOF)."""
        data, deadline = b"", time.monotonic() + wait_s
        while self._conn is not None and time.monotonic() < deadline:
            chunk = self.read(256, 0.05)
            if chunk is None:
                continue
            if not chunk:
                break
            data += chunk
        return data

    def close(self) -> None:
        self.hang_up()
        self._listener.close()


class _PtySide:
    def __init__(self):
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)        # raw 8-bit line: no echo, no CR/LF translation
        os.set_blocking(self._master, False)
        self.url = os.ttyname(self._slave)
        self.port = None

    def accept(self, deadline: float, stop: threading.Event) -> bool:
        return True                    # the client opens the slave whenever it likes

    def read(self, n: int, timeout: float) -> bytes | None:
        if self._master is None or not select.select([self._master], [], [], timeout)[0]:
            return None
        try:
            return os.read(self._master, n)
        except BlockingIOError:
            return None
        except OSError:
            return b""

    def send(self, data: bytes) -> None:
        os.write(self._master, data)

    def hang_up(self) -> None:
        # Closing both ends we hold: the client's next read or write fails (EIO).
        for name in ("_master", "_slave"):
            fd = getattr(self, name)
            if fd is not None:
                setattr(self, name, None)
                os.close(fd)

    def leftover(self, wait_s: float) -> bytes:
        # The client has closed: whatever it wrote already sits in the master's buffer.
        data = b""
        while (chunk := self.read(256, 0)):
            data += chunk
        return data

    def close(self) -> None:
        self.hang_up()


class RecordedPeer:
    """Play `exchanges` to one client over a socket or a pty (see the module docstring)."""

    def __init__(self, exchanges: list[tuple[bytes, object]], *, transport: str = "socket",
                 read_timeout_s: float = 3.0):
        self.exchanges = list(exchanges)
        self.read_timeout_s = read_timeout_s
        self.failures: list[str] = []
        self.played = 0
        self._side = _SocketSide() if transport == "socket" else _PtySide()
        self.port = self._side.port
        self.url = self._side.url
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="recorded-peer", daemon=True)

    def __enter__(self) -> "RecordedPeer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._side.close()

    def _read_exactly(self, n: int) -> bytes:
        data = b""
        deadline = time.monotonic() + self.read_timeout_s
        while len(data) < n and time.monotonic() < deadline and not self._stop.is_set():
            chunk = self._side.read(n - len(data), max(0.001, min(0.05, deadline - time.monotonic())))
            if chunk is None:
                continue
            if not chunk:
                break
            data += chunk
        return data

    def _run(self) -> None:
        if not self._side.accept(time.monotonic() + self.read_timeout_s, self._stop):
            if self.exchanges:
                self.failures.append("no client connected")
            return
        for index, (request, reply) in enumerate(self.exchanges):
            got = self._read_exactly(len(request))
            if got != request:
                self.failures.append(f"exchange {index}: expected {request.hex(' ')}, got {got.hex(' ')}")
                return
            self.played += 1
            if reply is CLOSE:
                self._side.hang_up()
                return
            if reply:
                self._side.send(reply)

    def verify(self) -> None:
        """Call after the client closed: every exchange played, nothing else received."""
        self._thread.join(timeout=self.read_timeout_s + 2)
        assert not self._thread.is_alive(), "recorded peer did not finish"
        assert not self.failures, self.failures
        assert self.played == len(self.exchanges), f"only {self.played} of {len(self.exchanges)} exchanges happened"
        unexpected = self._side.leftover(wait_s=2.0)
        assert not unexpected, f"unexpected bytes after the recording: {unexpected.hex(' ')}"
