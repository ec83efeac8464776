"""The technician's main window. It drives foamlab.acquisition.RunEngine, shows what
the engine reports and analyses each run with foamlab.pipeline (the stages `foamlab run`
uses: the fit shown first, the diagnosis after it in the background; foamlab.gui.display);
it holds no test logic of its own.

Threads: the GUI thread only draws. Machine I/O runs on the MachineLink's thread
(idle polling, jog, zero/tare, starting a run), e-stops on a thread of their own
(never queued behind anything), the run on the engine's worker, fits, diagnoses and
file loading on the Test tab's analysis thread (foamlab.gui.display); the idle machine's
commands (jog, return to start, zero, tare) are foamlab.gui.idle's. Results come
back as queued Qt signals. No dialog of the window is modal: the e-stop (button and
Esc) is at hand in every state (foamlab.gui.dialogs).
"""

from __future__ import annotations

import gc
import logging
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from foamlab import FoamlabError
from foamlab.acquisition.safety import check_run_fits, remember_contact
from foamlab.gui.background import BackgroundQueue
from foamlab.gui.bridge import EngineBridge
from foamlab.gui.commissioning import Commissioning
from foamlab.gui.connection import ConnectionView
from foamlab.gui.controls import ControlPanel
from foamlab.gui.dialogs import DialogSlot, EscapeStops, ask
from foamlab.gui.display import RunDisplay
from foamlab.gui.files import FileActions
from foamlab.gui.forms import ERROR_STYLE
from foamlab.gui.idle import IdleCommands
from foamlab.gui.machine_link import MachineLink, Readout
from foamlab.gui.menus import build_menus
from foamlab.gui.plots import LOADING, UNLOADING
from foamlab.gui.report import headline_names
from foamlab.gui.series import SeriesView
from foamlab.rundata import Specimen

log = logging.getLogger(__name__)

FRAME_HZ = 30          # plot refresh while samples arrive
#: Closing mid-run: how long to wait for the engine to stop before e-stopping (s).
CLOSE_STOP_TIMEOUT_S = 20.0

STATE_TEXT = {
    "idle": "idle", "connecting": "connecting", "taring": "taring the load cell",
    "contact_search": "searching contact", "running": "running", "stopping": "stopping",
    "parking": "returning to start", "fitting": "fitting the model", "finished": "finished",
    "aborted": "aborted",
}
PHASE_OF_ACTION = {"compress": LOADING, "return": UNLOADING, "dwell": "dwell"}


class MainWindow(FileActions, QtWidgets.QMainWindow):
    def __init__(self, speedup: float = 1.0, out_dir: str | Path = "foamlab-data",
                 profile: str | None = None, method: str | None = None, auto_diagnose: bool = True,
                 simulator: dict | None = None) -> None:
        """`simulator`: options of the built-in simulated machine (effects, seed: simulator.launch)."""
        super().__init__()
        self.setWindowTitle("foamlab — compression test")
        self.speedup = float(speedup)
        self.out_dir = Path(out_dir)
        self.engine = None
        self.bridge: EngineBridge | None = None
        self.last_result = None
        self._phase_of_step: dict[int, str] = {}
        self._close_requested = False
        self._run_start_mm = 0.0                   # where "Return to start" goes: the last run's start
        self._run_title = ""
        self._run_method = None                    # the Method of the run going or last run
        self.dialogs = DialogSlot()                # the open question or file chooser

        self.link = MachineLink(self, simulator)
        self.estop_queue = BackgroundQueue("foamlab-estop", self)

        self._build_ui(auto_diagnose)
        self.connection = ConnectionView(self.link, self.controls, self._status, self._update_controls, self)
        self.poll_timer = self.connection.poll_timer
        self.idle = IdleCommands(self.link, self.controls, self._status, lambda: self._run_start_mm,
                                 self.estop_queue)
        self._fill_choices(profile, method)
        self._wire()
        self._update_controls()
        # Esc is the e-stop whatever has the focus, dialogs included (see foamlab.gui.dialogs).
        self.escape_stops = EscapeStops(self.emergency_stop, self)

    # ================================================================ UI construction
    def _build_ui(self, auto_diagnose: bool) -> None:
        c = self.controls = ControlPanel()
        # The window (and its tests) use the controls by these names.
        self.profile_combo, self.connect_button, self.connection_label = (
            c.profile_combo, c.connect_button, c.connection_label)
        self.force_label, self.position_label, self.state_label = c.force_label, c.position_label, c.state_label
        self.jog_speed, self.jog_up, self.jog_down = c.jog_speed, c.jog_up, c.jog_down
        self.zero_position_button, self.zero_force_button, self.tare_button = (
            c.zero_position_button, c.zero_force_button, c.tare_button)
        self.reset_button, self.return_button = c.reset_button, c.return_button
        self.limits_form, self.method_combo, self.method_info, self.specimen_form = (
            c.limits_form, c.method_combo, c.method_info, c.specimen_form)
        self.start_button, self.stop_button, self.estop_button = c.start_button, c.stop_button, c.estop_button

        m = self.menus = build_menus(self.menuBar(), auto_diagnose)
        self.open_action, self.export_png_action, self.export_csv_action, self.report_action = (
            m.open, m.export_png, m.export_csv, m.report)
        self.series_csv_action, self.series_report_action, self.quit_action = m.series_csv, m.series_report, m.quit
        self.auto_diagnose_action, self.diagnose_action, self.predict_action = m.auto_diagnose, m.diagnose, m.predict

        # Right: the live test (plots, progress, results), the run browser, the shown run's series.
        d = self.display = RunDisplay(self.auto_diagnose_action.isChecked, self.out_dir)
        self.plots, self.progress, self.run_status, self.results, self.analysis = (
            d.plots, d.progress, d.run_status, d.results, d.analysis)
        from foamlab.gui.browser import RunBrowser

        self.browser = RunBrowser(self.out_dir)
        self.series_view = SeriesView(self.out_dir)
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.addTab(d, "Test")
        self.tabs.addTab(self.browser, "Runs")
        self.tabs.addTab(self.series_view, "Series")
        main = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        main.addWidget(c)
        main.addWidget(self.tabs)
        main.setStretchFactor(1, 1)
        self.setCentralWidget(main)

        # Garbage is collected in the GUI thread only, on a timer, once per process: from the first
        # background queue on (foamlab.gui.background.collect_garbage_on_the_gui_thread).
        self.frame_timer = QtCore.QTimer(self)
        self.frame_timer.setInterval(int(1000 / FRAME_HZ))
        self.resize(1400, 900)

    def _fill_choices(self, profile: str | None, method: str | None) -> None:
        for problem in self.controls.fill_choices(profile, method):
            self._status(problem, error=True)

    def _wire(self) -> None:
        self.connect_button.clicked.connect(self.toggle_connection)
        self.frame_timer.timeout.connect(self._on_frame)
        self.method_combo.currentIndexChanged.connect(self.controls.show_method)
        self.jog_up.pressed.connect(lambda: self.idle.jog(-1))
        self.jog_down.pressed.connect(lambda: self.idle.jog(+1))
        self.jog_up.released.connect(self.idle.stop_motion)
        self.jog_down.released.connect(self.idle.stop_motion)
        self.zero_position_button.clicked.connect(self.idle.zero_position)
        self.zero_force_button.clicked.connect(lambda: self.idle.tare("zero force"))
        self.tare_button.clicked.connect(lambda: self.idle.tare("tare"))
        self.return_button.clicked.connect(self.idle.return_to_start)
        self.reset_button.clicked.connect(self.idle.reset_estop)
        self.start_button.clicked.connect(self.start_run)
        self.stop_button.clicked.connect(self.stop_run)
        self.estop_button.clicked.connect(self.emergency_stop)
        self.open_action.triggered.connect(lambda: self.open_file())
        self.export_png_action.triggered.connect(lambda: self.export_png())
        self.export_csv_action.triggered.connect(lambda: self.export_csv())
        self.report_action.triggered.connect(lambda: self.write_report())
        self.series_csv_action.triggered.connect(lambda: self.export_series_csv())
        self.series_report_action.triggered.connect(lambda: self.write_series_report())
        self.series_view.csv_button.clicked.connect(self.series_csv_action.trigger)
        self.series_view.pdf_button.clicked.connect(self.series_report_action.trigger)
        self.series_view.message.connect(lambda text, error: self._status(text, error=error))
        self.quit_action.triggered.connect(self.close)
        self.commissioning = Commissioning(self.link, self._show_dialog, self._status, self)
        self.menus.probe.triggered.connect(self.commissioning.start)
        self.diagnose_action.triggered.connect(self.diagnose_shown_run)
        self.browser.open_requested.connect(self.open_file)
        self.display.message.connect(lambda text, error: self._status(text, error=error))
        self.display.catalog_changed.connect(self.browser.refresh)
        self.specimen_form.changed.connect(self._preview_specimen)
        self._preview_specimen()

    # ================================================================ state
    @property
    def connected(self) -> bool:
        return self.link.connection is not None

    @property
    def running(self) -> bool:
        return self.engine is not None

    @property
    def shown_run(self):
        """The RunData on display (a run that ended, or an opened file), None if none."""
        return self.display.shown_run

    @shown_run.setter
    def shown_run(self, run) -> None:
        self.display.shown_run = run

    @property
    def shown_analysis(self):
        """The shown run's foamlab.pipeline Analysis once its fit is done, else None."""
        return self.display.shown_analysis

    def _update_controls(self) -> None:
        self.controls.set_state(self.connected, self.running, self._close_requested)
        self.open_action.setEnabled(not self.running)
        self.report_action.setEnabled(not self.running)
        self.series_report_action.setEnabled(not self.running)
        self.browser.setEnabled(not self.running)

    def _status(self, text: str, error: bool = False, timeout_ms: int = 0) -> None:
        self.statusBar().setStyleSheet(ERROR_STYLE if error else "")
        self.statusBar().showMessage(text, timeout_ms)
        (log.warning if error else log.info)("%s", text)

    def _preview_specimen(self) -> None:
        """Before any run is shown, the plots' axes follow the specimen entered (wrong entries: unknown)."""
        self.display.preview_specimen(Specimen(**self.specimen_form.values()))

    # ================================================================ connection
    def toggle_connection(self) -> None:
        self.connection.toggle(self.speedup)

    @property
    def last_readout(self) -> Readout | None:
        """The machine's state as last polled (None when not connected)."""
        return self.connection.last_readout

    # ================================================================ run
    def start_run(self) -> bool:
        """Start the method on the connected machine. Returns False (and says why) when refused."""
        if self.running:
            return False
        conn = self.link.connection
        if conn is None:
            self.specimen_form.show_error("Cannot start: connect to a machine first.")
            return False
        specimen = self.specimen_form.specimen()
        if specimen is None:
            self._status("start refused: the specimen entry is not valid", error=True)
            return False
        try:
            from foamlab.acquisition import Limits
            from foamlab.methods import load_method

            method = load_method(self.method_combo.currentText())
            limits = Limits(**self.limits_form.values())
            if not limits.travel_upper_mm < limits.travel_lower_mm:
                raise FoamlabError("the upper travel limit must be above (smaller than) the lower one")
            position = self.last_readout.position_mm if self.last_readout is not None else None
            check_run_fits(method, specimen, limits, position)
            engine = conn.engine(method, specimen, self.out_dir, limits=limits)
        except FoamlabError as exc:
            self.specimen_form.show_error(f"Cannot start: {exc}")
            self._status(f"start refused: {exc}", error=True)
            return False

        self.bridge = EngineBridge(self)
        self.bridge.progress.connect(self._on_progress)
        self.bridge.state.connect(self._on_engine_state)
        self.bridge.finished.connect(self._on_finished)
        engine.add_listener(self.bridge)
        self.engine = engine
        self.last_result = None
        self._phase_of_step = {p.index: PHASE_OF_ACTION.get(p.step.action, LOADING) for p in engine.plan}
        self.link.run_active = True
        self.poll_timer.stop()
        self._run_title = f"Run of {method.name} on {specimen.label}"
        self._run_method = method
        if position is not None:
            self._run_start_mm = position
        self.display.begin_run(self._run_title, method.n_cycles, method.expected_samples(specimen.height_mm),
                               specimen)
        self.display.predict(engine, method, self.predict_action.isChecked())
        self._status(f"{self._run_title} started")      # replaces any earlier e-stop or refusal
        self.tabs.setCurrentIndex(0)
        # The engine collects garbage in its own thread as it starts (acquisition.engine): Qt
        # objects the reset plots left in reference cycles (pyqtgraph's menus) must go here, in
        # the GUI thread - destroyed from the engine's collection they deadlocked the window.
        gc.collect()
        # Queued behind any idle poll still on its way, so the engine gets the machine to itself.
        self.link.submit(engine.start, None, self._on_start_failed)
        self.frame_timer.start()
        self._update_controls()
        return True

    def _on_start_failed(self, message: str) -> None:
        self._status(f"the run could not start: {message}", error=True)
        self._end_run_ui()

    def stop_run(self) -> None:
        if self.engine is not None:
            self.engine.request_stop("stopped by the operator")
            self._status("stop requested: the crosshead stops, the data are kept")
        else:
            self.idle.stop_motion()

    def emergency_stop(self) -> None:
        """Immediate stop: through the engine during a run, else straight to the crosshead."""
        engine, conn = self.engine, self.link.connection
        if engine is not None:
            self.estop_queue.submit(engine.emergency_stop, None,
                                    lambda msg: self._status(f"EMERGENCY STOP failed: {msg}", error=True))
        elif conn is not None:
            self.estop_queue.submit(conn.machine.crosshead.emergency_stop, None,
                                    lambda msg: self._status(f"EMERGENCY STOP failed: {msg}", error=True))
        else:
            return
        self._status("EMERGENCY STOP", error=True)

    # -- engine events (GUI thread) -------------------------------------------------------
    def _on_frame(self) -> None:
        self._drain_samples()
        self.plots.refresh()
        self.display.live.refresh()

    def _drain_samples(self) -> None:
        samples = self.bridge.drain() if self.bridge is not None else []
        if samples:
            self.display.add_samples(samples, self._phase_of_step)
            self.force_label.setText(f"{samples[-1].force_N:.2f}")
            self.position_label.setText(f"{samples[-1].position_mm:.3f}")

    def _on_progress(self, progress) -> None:
        self.display.show_progress(progress)

    def _on_engine_state(self, state: str) -> None:
        self.state_label.setText(STATE_TEXT.get(state, state))
        self.state_label.setStyleSheet("")
        if self.running:
            self.run_status.setText(f"{self._run_title}: {STATE_TEXT.get(state, state)}")
        if state == "parking" and self._close_requested and self.engine is not None:
            # The operator is closing the window: don't keep them waiting for the park.
            self.engine.request_stop("window closed during the run")

    def _on_finished(self, result) -> None:
        if self.bridge is None or self.sender() is not self.bridge:
            return
        self.show_finished(result)

    def show_finished(self, result) -> None:
        """Everything the window says about a run that ended (a foamlab.acquisition.RunResult)."""
        self._drain_samples()
        self.last_result = result
        if self.dialog is not None and self.dialog.objectName() == "close_question":
            self.close_dialog()         # "A test is running" is no longer true
        if result.contact_position_mm is not None and self.link.connection is not None:
            remember_contact(self.link.connection.machine, result.contact_position_mm)
        self._end_run_ui()
        headline = headline_names(self._run_method) if self._run_method is not None else []
        text, style = self.display.show_result(result, headline)
        self.statusBar().setStyleSheet(style)       # replaces the e-stop's or any earlier message
        self.statusBar().showMessage(text)
        self.browser.refresh()
        if result.path is not None and result.run is not None:
            self.series_view.show_series_of(result.path, result.run)
        if self._close_requested:
            self.close()

    def _end_run_ui(self) -> None:
        self.frame_timer.stop()
        self.engine = None
        self.link.run_active = False
        if self.connected:
            self.poll_timer.start()
        self._update_controls()

    def diagnose_shown_run(self) -> None:
        problem = ("no run to diagnose: finish a run or open a file first" if self.running
                   else self.display.diagnose_shown())
        if problem:
            self._status(problem, error=True)

    # ================================================================ dialogs, closing
    @property
    def dialog(self) -> QtWidgets.QDialog | None:
        """The question or file chooser open now (non-modal), if any."""
        return self.dialogs.dialog

    def _show_dialog(self, dialog: QtWidgets.QDialog) -> None:
        self.dialogs.show(dialog)

    def close_dialog(self) -> None:
        self.dialogs.close()

    def _confirm_close(self) -> None:
        """Closing mid-run asks first, without a modal dialog: the e-stop stays at hand."""
        self._show_dialog(ask(self, "A test is running",
                              "A test is running. Stop the machine and close?\nThe data acquired so far are kept.",
                              self._close_after_stop, name="close_question"))

    def _close_after_stop(self) -> None:
        if self.engine is None:          # the run ended while the question was open
            self.close()
            return
        self._close_requested = True
        self.engine.request_stop("window closed during the run")
        self._status("stopping the machine before closing…")
        self._update_controls()
        # If the engine cannot stop in time, e-stop; the window closes when it reports.
        QtCore.QTimer.singleShot(int(CLOSE_STOP_TIMEOUT_S * 1000), self._close_timeout)

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        if self.engine is not None:
            if not self._close_requested:
                self._confirm_close()
            event.ignore()
            return
        self.close_dialog()
        self.escape_stops.remove()
        self.frame_timer.stop()
        self.poll_timer.stop()
        self.analysis.shutdown(wait=False)
        self.display.live.shutdown()
        self.estop_queue.shutdown(wait=False)
        self.browser.queue.shutdown(wait=False)
        self.series_view.queue.shutdown(wait=False)
        self.link.shutdown()
        event.accept()

    def _close_timeout(self) -> None:
        engine = self.engine
        if engine is None:
            return
        log.error("the run did not stop within %.0f s of closing: emergency stop", CLOSE_STOP_TIMEOUT_S)
        try:
            engine.emergency_stop()
        except Exception as exc:
            log.error("emergency stop failed: %s", exc)
        if engine.wait(5.0) is None:
            log.error("the run engine did not end; closing anyway (its thread is a daemon)")
        self.engine = None
        self.close()
