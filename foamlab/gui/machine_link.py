"""The window's link to the testing machine, kept off the GUI thread.

Every call that talks to the machine (connect, idle polling, jog, zero/tare, starting
or e-stopping a run) goes through one worker thread, so calls are serialised (a
Modbus or serial client is not thread-safe) and a slow or dead link never freezes
the window. Results come back to the GUI thread as Qt signals (queued: the relay
lives in the GUI thread and is emitted from the worker).

While a run is going the run engine owns the machine; the link then polls nothing
and the window shows the engine's samples.
"""

from __future__ import annotations

import concurrent.futures
import logging
from dataclasses import dataclass
from typing import Any, Callable

from PySide6 import QtCore

from foamlab.gui.background import BackgroundQueue
from foamlab.session import BUILTIN_TRANSPORT, MachineChoice, MachineSession

log = logging.getLogger(__name__)

#: The built-in simulated machine's entry in the profile chooser.
BUILTIN_SIMULATOR = "Built-in simulated machine"


@dataclass(frozen=True)
class Readout:
    force_N: float
    position_mm: float
    state: str            # idle | moving | e-stopped | fault | limit
    overload: bool = False


class MachineLink(QtCore.QObject):
    connected = QtCore.Signal(object)         # MachineSession (the CLI's assembly too)
    connect_failed = QtCore.Signal(str)
    disconnected = QtCore.Signal()
    readout = QtCore.Signal(object)           # Readout
    poll_failed = QtCore.Signal(str)          # the machine did not answer an idle readout
    error = QtCore.Signal(str)                # one line for the status area

    def __init__(self, parent: QtCore.QObject | None = None, simulator: dict | None = None) -> None:
        super().__init__(parent)
        self.simulator_options = dict(simulator or {})   # the built-in machine's effects, seed
        self.queue = BackgroundQueue("foamlab-machine", self)
        self.connection: MachineSession | None = None
        self._poll_in_flight = False
        self.run_active = False               # set by the window while the engine owns the machine

    def submit(self, fn: Callable[[], Any], on_done: Callable[[Any], None] | None = None,
               on_error: Callable[[str], None] | None = None) -> concurrent.futures.Future:
        """Run `fn` on the machine thread; errors without an `on_error` go to the `error` signal."""
        return self.queue.submit(fn, on_done, on_error or self.error.emit)

    # -- connection ------------------------------------------------------------------
    def connect_machine(self, profile_name: str, speedup: float) -> None:
        def work() -> MachineSession:
            return MachineSession.open(self.choice(profile_name, speedup))

        def work_unless_closed() -> MachineSession:
            conn = work()
            if self.queue.closed:   # the window closed while connecting: let nothing run on
                conn.close()
                raise RuntimeError("the window was closed while connecting")
            return conn

        def done(conn: MachineSession) -> None:
            self.connection = conn
            self.connected.emit(conn)

        self.submit(work_unless_closed, done, self.connect_failed.emit)

    def disconnect_machine(self) -> concurrent.futures.Future | None:
        conn, self.connection = self.connection, None
        if conn is None:
            return None

        def work() -> None:
            conn.close()

        return self.submit(work, lambda _: self.disconnected.emit(),
                           lambda msg: (self.error.emit(msg), self.disconnected.emit()))

    def choice(self, profile_name: str, speedup: float) -> MachineChoice:
        """The chooser's entry as a machine choice (the built-in machine with its options)."""
        if profile_name == BUILTIN_SIMULATOR:
            return MachineChoice(speedup=speedup, transport=BUILTIN_TRANSPORT, simulator=self.simulator_options)
        return MachineChoice(profile=profile_name, speedup=speedup)

    # -- idle operations ---------------------------------------------------------------
    def poll(self) -> None:
        """One readout, unless one is still on its way or a run owns the machine."""
        conn = self.connection
        if conn is None or self.run_active or self._poll_in_flight:
            return
        self._poll_in_flight = True

        def work() -> Readout:
            sample = conn.machine.read_sample()
            status = conn.machine.crosshead.status()
            if status.emergency_stopped:
                state = "e-stopped"
            elif status.fault:
                state = "fault"
            elif status.upper_limit or status.lower_limit:
                state = "at travel limit"
            elif status.moving:
                state = "moving"
            else:
                state = "idle"
            overload = bool(sample.load_cell_status and sample.load_cell_status.over_range)
            return Readout(sample.force_N, sample.position_mm, state, overload)

        def done(readout: Readout) -> None:
            self._poll_in_flight = False
            if self.connection is conn and not self.run_active:
                self.readout.emit(readout)

        def failed(message: str) -> None:
            self._poll_in_flight = False
            if self.connection is conn:
                self.poll_failed.emit(message)

        self.submit(work, done, failed)

    def call(self, description: str, action: Callable[[Any], Any]) -> None:
        """An idle machine command (jog, stop, zero, tare...): `action(machine)` on the machine thread."""
        conn = self.connection
        if conn is None:
            self.error.emit(f"{description}: not connected")
            return
        self.submit(lambda: action(conn.machine), None,
                    lambda msg: self.error.emit(f"{description} failed: {msg}"))

    # -- shutdown ------------------------------------------------------------------------
    def shutdown(self, timeout_s: float = 10.0) -> None:
        """Close the link and the simulator, then stop the machine thread (blocks up to timeout_s)."""
        conn, self.connection = self.connection, None
        future = self.queue.submit(conn.close) if conn is not None else None
        self.queue.closed = True          # no more calls, no more callbacks into the window
        if future is not None:
            try:
                future.result(timeout_s)
            except Exception as exc:
                log.warning("closing the machine link: %s", exc)
        self.queue.shutdown(wait=False)
