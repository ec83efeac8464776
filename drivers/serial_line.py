"""One serial line (a device path or any pyserial URL): bytes out, lines in, one user at a time.

What it knows: opening and closing the port, writing, reading one line within the
timeout, and turning pyserial's and the OS's errors into drivers.base errors (a vanished
port is DeviceConnectionLost). What a line means is the protocol's business (drivers.ascii).
"""

from __future__ import annotations

import threading

import serial

from .base import DeviceConnectionLost

BYTESIZES = {5: serial.FIVEBITS, 6: serial.SIXBITS, 7: serial.SEVENBITS, 8: serial.EIGHTBITS}


class SerialLine:
    """A serial port under a lock; `read_line` returns b"" on silence, the partial bytes on a timeout."""

    def __init__(self, connection: dict, *, bytesize: int = 8, parity: str = "N", stopbits: int = 1,
                 line_end: bytes = b"\n"):
        self.url = connection["port_url"]
        self.baudrate = int(connection["baudrate"])
        self.timeout_s = float(connection["timeout_s"])
        self.retries = int(connection["retries"])
        self.bytesize = BYTESIZES[int(connection.get("bytesize", bytesize))]
        self.parity = str(connection.get("parity", parity))
        self.stopbits = int(connection.get("stopbits", stopbits))
        self.line_end = line_end
        self.lock = threading.RLock()
        self.where = f"serial {self.url}"
        self._port: serial.SerialBase | None = None

    @property
    def connected(self) -> bool:
        return self._port is not None

    def connect(self) -> None:
        with self.lock:
            if self._port is not None:
                return
            try:
                self._port = serial.serial_for_url(
                    self.url, baudrate=self.baudrate, bytesize=self.bytesize, parity=self.parity,
                    stopbits=self.stopbits, timeout=self.timeout_s, write_timeout=max(self.timeout_s, 0.5))
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

    def _open_port(self) -> serial.SerialBase:
        if self._port is None:
            raise DeviceConnectionLost(f"{self.where}: not connected")
        return self._port

    def _lost(self, exc: Exception) -> DeviceConnectionLost:
        self.close()
        return DeviceConnectionLost(f"{self.where}: {exc}")

    def flush_input(self) -> None:
        """Drop whatever arrived unasked (a late reply must not be taken for the next one's)."""
        port = self._open_port()
        try:
            port.reset_input_buffer()
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None

    def write(self, data: bytes) -> None:
        port = self._open_port()
        try:
            port.write(data)
        except (serial.SerialException, OSError) as exc:   # a write timeout too: the line is stuck
            raise self._lost(exc) from None

    def read_line(self, timeout_s: float | None = None) -> bytes:
        """Bytes up to and including the line end; fewer (maybe b"") when the timeout ends first."""
        port = self._open_port()
        try:
            if timeout_s is not None and timeout_s != port.timeout:
                port.timeout = timeout_s
            try:
                return port.read_until(self.line_end)
            finally:
                if port.timeout != self.timeout_s:
                    port.timeout = self.timeout_s
        except (serial.SerialException, OSError) as exc:
            raise self._lost(exc) from None
