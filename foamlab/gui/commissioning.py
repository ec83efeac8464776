"""Machine > Probe the connected machine: `foamlab probe` from the window.

On connecting to a machine profile that has not passed a probe on this computer the status line
says so; the probe runs on the machine thread (foamlab.gui.machine_link), asks - non-modally, the
e-stop stays at hand - before its 1 mm move, and shows its report in words. A pass is remembered
(foamlab.storage.probes) as `foamlab probe` remembers it.
"""

from __future__ import annotations

from typing import Callable

from PySide6 import QtCore, QtWidgets

from foamlab import FoamlabError
from foamlab.gui.dialogs import ask


class Commissioning(QtCore.QObject):
    finished = QtCore.Signal(object)          # foamlab.acquisition.commissioning.ProbeReport

    def __init__(self, link, show_dialog: Callable[[QtWidgets.QDialog], None],
                 status: Callable[..., None], parent: QtWidgets.QWidget) -> None:
        super().__init__(parent)
        self.link, self._show_dialog, self._status, self._parent = link, show_dialog, status, parent
        self.last_report = None
        link.connected.connect(self._on_connected)
        self.finished.connect(self._show)

    def _on_connected(self, conn) -> None:
        from foamlab.storage.probes import passed_probe

        if conn.simulator is not None:
            return                      # the built-in machine is the simulator's own profile
        try:
            passed = passed_probe(conn.profile)
        except FoamlabError as exc:
            self._status(str(exc), error=True)
            return
        if passed is None:
            self._status(f"{conn.name} has not passed a probe on this computer: its units, scales and limits are "
                         "unchecked - Machine > Probe the connected machine", error=True)

    def start(self) -> None:
        """Ask whether to move, then probe (the answer No still probes, without moving)."""
        if self.link.connection is None or self.link.run_active:
            self._status("connect first (and not during a run) to probe the machine", error=True)
            return
        box = ask(self._parent, "Probe the machine",
                  "Read every channel and check the profile against the device.\n\nAlso move the crosshead "
                  "1 mm UP and back, watching force and position? Keep clear of the plates.",
                  lambda: self._run(True), name="probe_question")
        box.buttonClicked.connect(lambda button: self._run(False)
                                  if box.standardButton(button) != QtWidgets.QMessageBox.StandardButton.Yes else None)
        self._show_dialog(box)

    def _run(self, move: bool) -> None:
        conn = self.link.connection
        if conn is None:
            return
        self._status("probing the machine…")

        def work():
            from foamlab.acquisition.commissioning import probe
            from foamlab.acquisition.safety import Limits

            return probe(conn.machine, conn.profile, Limits.from_profile(conn.profile),
                         confirm_move=(lambda question: move))

        self.link.submit(work, self.finished.emit, lambda message: self._status(f"probe failed: {message}", error=True))

    def _show(self, report) -> None:
        from foamlab.storage.probes import record_passed

        self.last_report = report
        conn = self.link.connection
        if report.passed and conn is not None and conn.simulator is None:
            try:
                record_passed(conn.profile)
            except FoamlabError as exc:
                self._status(str(exc), error=True)
        self._status(report.text().splitlines()[0], error=not report.passed)
        box = QtWidgets.QMessageBox(QtWidgets.QMessageBox.Icon.Information if report.passed
                                    else QtWidgets.QMessageBox.Icon.Warning, "Probe", report.text(),
                                    QtWidgets.QMessageBox.StandardButton.Ok, self._parent)
        box.setObjectName("probe_report")
        box.setWindowModality(QtCore.Qt.WindowModality.NonModal)
        box.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)
        box.show()
        self._show_dialog(box)
