"""A fake device on a loopback socket that plays a recorded exchange, byte for byte.

In the spirit of PyMeasure's `expected_protocol`: the test lists (request, reply)
pairs; the peer asserts each request's exact bytes and sends the recorded reply.
Drivers reach it as Modbus TCP (host/port) or, through pyserial's `socket://` URL, as
a serial line (Modbus RTU or ASCII) — so the real pymodbus/pyserial clients run
unmodified. Used by tests/test_drivers_*.py.

Reply values: bytes to send (b"" sends nothing: the device stays silent), or CLOSE to
drop the connection. After the last exchange any further byte the client sends is
recorded as unexpected.
"""

from __future__ import annotations

import socket
import threading
import time

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


class RecordedPeer:
    """Listen on 127.0.0.1 (free port), accept one client, play `exchanges`."""

    def __init__(self, exchanges: list[tuple[bytes, object]], *, read_timeout_s: float = 3.0):
        self.exchanges = list(exchanges)
        self.read_timeout_s = read_timeout_s
        self.failures: list[str] = []
        self.played = 0
        self.unexpected = b""
        self._stop = threading.Event()
        self._listener = socket.create_server(("127.0.0.1", 0))
        self._listener.settimeout(0.05)   # poll, so a peer nobody connects to ends promptly
        self.port = self._listener.getsockname()[1]
        self.url = f"socket://127.0.0.1:{self.port}"
        self._thread = threading.Thread(target=self._run, name="recorded-peer", daemon=True)

    def __enter__(self) -> "RecordedPeer":
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join(timeout=5)
        self._listener.close()

    def _read_exactly(self, conn: socket.socket, n: int) -> bytes:
        data = b""
        deadline = time.monotonic() + self.read_timeout_s
        while len(data) < n and time.monotonic() < deadline and not self._stop.is_set():
            conn.settimeout(max(0.001, min(0.05, deadline - time.monotonic())))
            try:
                chunk = conn.recv(n - len(data))
            except socket.timeout:
                continue
            if not chunk:
                break
            data += chunk
        return data

    def _run(self) -> None:
        deadline = time.monotonic() + self.read_timeout_s
        while True:
            try:
                conn, _ = self._listener.accept()
                break
            except socket.timeout:
                if self._stop.is_set() or time.monotonic() > deadline:
                    if self.exchanges:
                        self.failures.append("no client connected")
                    return
        with conn:
            for index, (request, reply) in enumerate(self.exchanges):
                got = self._read_exactly(conn, len(request))
                if got != request:
                    self.failures.append(f"exchange {index}: expected {request.hex(' ')}, got {got.hex(' ')}")
                    return
                self.played += 1
                if reply is CLOSE:
                    return
                if reply:
                    conn.sendall(reply)
            # Anything more is a request nobody recorded.
            conn.settimeout(0.02)
            while not self._stop.is_set():
                try:
                    chunk = conn.recv(256)
                except socket.timeout:
                    continue
                except OSError:
                    break
                if not chunk:
                    break
                self.unexpected += chunk

    def verify(self) -> None:
        """Call after the client closed: every exchange played, nothing else received."""
        self._thread.join(timeout=5)   # the peer ends when the client closes its end
        self._stop.set()
        self._thread.join(timeout=1)
        assert not self._thread.is_alive(), "recorded peer did not finish"
        assert not self.failures, self.failures
        assert self.played == len(self.exchanges), f"only {self.played} of {len(self.exchanges)} exchanges happened"
        assert not self.unexpected, f"unexpected bytes after the recording: {self.unexpected.hex(' ')}"
