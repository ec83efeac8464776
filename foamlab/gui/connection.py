"""The window's side of the machine connection: Connect / Disconnect, the profile's limits
put into the forms, the idle readouts (polled while no run goes) and a link that stops
answering. The link itself (its thread, the simulator) is foamlab.gui.machine_link's."""

from __future__ import annotations

from collections.abc import Callable

from PySide6 import QtCore

from foamlab import FoamlabError
from foamlab.gui.controls import ControlPanel
from foamlab.gui.machine_link import MachineLink, Readout
from foamlab.session import MachineSession

POLL_HZ = 5            # idle readouts


class ConnectionView:
    """`status(text, error=False, timeout_ms=0)`: the window's status line; `changed()`: the
    window's controls follow the connection (connected or not)."""

    def __init__(self, link: MachineLink, controls: ControlPanel, status: Callable[..., None],
                 changed: Callable[[], None], parent: QtCore.QObject) -> None:
        self.link, self.controls, self._status, self._changed = link, controls, status, changed
        self.last_readout: Readout | None = None   # the machine's state as last polled
        self._trouble = False                      # the last poll got no answer
        self.poll_timer = QtCore.QTimer(parent)
        self.poll_timer.setInterval(int(1000 / POLL_HZ))
        self.poll_timer.timeout.connect(link.poll)
        link.connected.connect(self._on_connected)
        link.connect_failed.connect(self._on_connect_failed)
        link.disconnected.connect(self._on_disconnected)
        link.readout.connect(self._on_readout)
        link.poll_failed.connect(self._on_poll_failed)
        link.error.connect(lambda msg: self._status(msg, error=True))

    def toggle(self, speedup: float) -> None:
        """Connect to the profile chosen, or disconnect."""
        if self.link.connection is not None:
            self.poll_timer.stop()
            self.link.disconnect_machine()
            self.controls.connection_label.setText("Disconnecting…")
        else:
            self.controls.show_connecting()
            self.link.connect_machine(self.controls.profile_combo.currentText(), speedup)
        self._changed()

    def _on_connected(self, conn: MachineSession) -> None:
        from foamlab.acquisition import Limits

        self._trouble = False
        self.controls.show_connected(conn.name, conn.speedup)
        try:
            limits = Limits.from_profile(conn.profile)
            self.controls.limits_form.set_profile_limits(limits)
            self.controls.jog_speed.setRange(1.0, limits.max_speed_mm_min)
        except FoamlabError as exc:
            self._status(str(exc), error=True)
        self._status(f"connected to {conn.name}", timeout_ms=5000)
        self.poll_timer.start()
        self._changed()

    def _on_connect_failed(self, message: str) -> None:
        self.controls.show_connect_failed(message)
        self._status(f"connection failed: {message}", error=True)
        self._changed()

    def _on_disconnected(self) -> None:
        self.poll_timer.stop()
        self.controls.show_disconnected()
        self.last_readout = None
        self._changed()

    def _on_poll_failed(self, message: str) -> None:
        self._trouble = True
        self.controls.show_no_answer(message)

    def _on_readout(self, readout: Readout) -> None:
        conn = self.link.connection
        if self._trouble and conn is not None:
            self._trouble = False
            self.controls.show_connected(conn.name, conn.speedup)
        self.last_readout = readout
        self.controls.show_readout(readout)
