"""A pseudo-terminal standing in for a serial cable, served from asyncio.

The simulator owns the master side of a pty pair; clients (the drivers, mbpoll,
a terminal program) open the slave side by path, exactly as they would open
/dev/ttyUSB0. Clients are given a stable symlink rather than the /dev/pts/N
path, because a "dropped connection" fault hangs the pty up (the client sees
EIO, as when a USB-serial adapter is unplugged) and a fresh pty replaces it:
the symlink then points at the new one, so a client that reopens the same path
reconnects.

Why hand-written: pymodbus' SerialTransport and pyserial open a device *path*;
the master side of a pty has none (reopening /dev/ptmx makes a new pair), so a
small asyncio transport over the master fd is needed.
"""

from __future__ import annotations

import asyncio
import errno
import os
import shutil
import tempfile
import termios
import tty
from pathlib import Path


class PtyPort:
    """A pty pair with a stable path for clients; `reopen()` hangs it up and makes a fresh one."""

    LINK_NAME = "ttySIM0"

    def __init__(self, baudrate: int = 115200):
        self.baudrate = baudrate
        self._dir = Path(tempfile.mkdtemp(prefix="foamlab-sim-"))
        self.path = str(self._dir / self.LINK_NAME)  #: what clients open (a symlink)
        self.master_fd: int | None = None
        self._slave_keeper: int | None = None
        self.device_path = ""  #: the current /dev/pts/N behind `path`
        self.generation = 0  #: how many times the pty was (re)opened
        self._open_pair()

    def _open_pair(self) -> None:
        master, slave = os.openpty()
        # Raw 8N1 on the line discipline: no echo, no CR/LF translation, no line buffering.
        tty.setraw(slave, termios.TCSANOW)
        attrs = termios.tcgetattr(slave)
        speed = getattr(termios, f"B{self.baudrate}", termios.B115200)
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(slave, termios.TCSANOW, attrs)
        os.set_blocking(master, False)
        self.master_fd = master
        # Holding a slave fd open keeps the pty alive between clients: without it the
        # master reports hang-up (EIO) each time the last client closes the port.
        self._slave_keeper = slave
        self.device_path = os.ttyname(slave)
        tmp_link = self._dir / f".{self.LINK_NAME}.new"
        tmp_link.unlink(missing_ok=True)
        os.symlink(self.device_path, tmp_link)
        os.replace(tmp_link, self.path)
        self.generation += 1

    def hang_up(self) -> None:
        """Close both sides we hold: a client's open fd now reads EIO."""
        for name in ("master_fd", "_slave_keeper"):
            fd = getattr(self, name)
            if fd is not None:
                setattr(self, name, None)
                try:
                    os.close(fd)
                except OSError:
                    pass

    def reopen(self) -> None:
        """Hang up and open a fresh pty behind the same client path."""
        self.hang_up()
        self._open_pair()

    def close(self) -> None:
        """Hang up and remove the client path; idempotent."""
        self.hang_up()
        shutil.rmtree(self._dir, ignore_errors=True)


class PtyTransport(asyncio.Transport):
    """Non-blocking asyncio transport over a pty master fd (reads via add_reader, buffered writes)."""

    def __init__(self, loop: asyncio.AbstractEventLoop, port: PtyPort, protocol: asyncio.Protocol):
        super().__init__()
        if port.master_fd is None:
            raise OSError(errno.EBADF, "pty is closed")
        self._loop = loop
        self._port = port
        self._fd = port.master_fd
        self._protocol = protocol
        self._out = bytearray()
        self._closing = False
        loop.add_reader(self._fd, self._read_ready)
        loop.call_soon(protocol.connection_made, self)

    # -- asyncio.Transport API used by pymodbus and our ASCII protocol
    def write(self, data: bytes) -> None:
        if self._closing or not data:
            return
        if not self._out:
            try:
                written = os.write(self._fd, data)
            except BlockingIOError:
                written = 0
            except OSError as exc:
                self._fail(exc)
                return
            data = data[written:]
            if not data:
                return
            self._loop.add_writer(self._fd, self._write_ready)
        self._out += data

    def close(self) -> None:
        """Stop I/O and hang the pty up (the owner decides whether to reopen it)."""
        if self._closing:
            return
        self._closing = True
        self._loop.remove_reader(self._fd)
        self._loop.remove_writer(self._fd)
        self._out.clear()
        if self._port.master_fd == self._fd:
            self._port.hang_up()
        self._loop.call_soon(self._protocol.connection_lost, None)

    def abort(self) -> None:
        self.close()

    def is_closing(self) -> bool:
        return self._closing

    def get_write_buffer_size(self) -> int:
        return len(self._out)

    def get_protocol(self) -> asyncio.BaseProtocol:
        return self._protocol

    def set_protocol(self, protocol: asyncio.BaseProtocol) -> None:
        self._protocol = protocol

    def can_write_eof(self) -> bool:
        return False

    def is_reading(self) -> bool:
        return not self._closing

    def pause_reading(self) -> None:  # flow control is not needed at these rates
        pass

    def resume_reading(self) -> None:
        pass

    # -- internals
    def _read_ready(self) -> None:
        try:
            data = os.read(self._fd, 4096)
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        if data:
            self._protocol.data_received(data)

    def _write_ready(self) -> None:
        try:
            written = os.write(self._fd, bytes(self._out))
        except BlockingIOError:
            return
        except OSError as exc:
            self._fail(exc)
            return
        del self._out[:written]
        if not self._out:
            self._loop.remove_writer(self._fd)

    def _fail(self, exc: OSError) -> None:
        self.close()
