"""The technician's main window. It drives foamlab.acquisition.RunEngine, shows what
the engine reports and analyses each run with foamlab.pipeline (the stages `foamlab run`
uses: the fit shown first, the diagnosis after it in the background); it holds no test
logic of its own.

Threads: the GUI thread only draws. Machine I/O runs on the MachineLink's thread
(idle polling, jog, zero/tare, starting a run), e-stops on a thread of their own
(never queued behind anything), the run on the engine's worker, fits, diagnoses and
file loading on an analysis thread. Results come back as queued Qt signals.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np
from PySide6 import QtCore, QtGui, QtWidgets

from foamlab import FoamlabError, pipeline
from foamlab.gui.background import BackgroundQueue
from foamlab.gui.bridge import EngineBridge
from foamlab.gui.forms import ERROR_STYLE, LimitsForm, SpecimenForm
from foamlab.gui.machine_link import BUILTIN_SIMULATOR, Connection, MachineLink, Readout
from foamlab.gui.plots import LOADING, UNLOADING, LivePlots, labels_from_segmentation
from foamlab.gui.results import Report, ResultsPanel

log = logging.getLogger(__name__)

FRAME_HZ = 30          # plot refresh while samples arrive
POLL_HZ = 5            # idle readouts
DEFAULT_JOG_SPEED = 50.0
#: Closing mid-run: how long to wait for the engine to stop before e-stopping (s).
CLOSE_STOP_TIMEOUT_S = 20.0

STATE_TEXT = {
    "idle": "idle", "connecting": "connecting", "taring": "taring the load cell",
    "contact_search": "searching contact", "running": "running", "stopping": "stopping",
    "parking": "returning to start", "fitting": "fitting the model", "finished": "finished",
    "aborted": "aborted",
}
PHASE_OF_ACTION = {"compress": LOADING, "return": UNLOADING, "dwell": "dwell"}


def _clock(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


def _big_label(text: str, name: str) -> QtWidgets.QLabel:
    label = QtWidgets.QLabel(text)
    label.setObjectName(name)
    font = label.font()
    font.setPointSize(font.pointSize() + 4)
    font.setBold(True)
    label.setFont(font)
    label.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
    label.setMinimumWidth(110)
    return label


class MainWindow(QtWidgets.QMainWindow):
    def __init__(self, speedup: float = 1.0, out_dir: str | Path = "foamlab-data",
                 profile: str | None = None, method: str | None = None, auto_diagnose: bool = True) -> None:
        super().__init__()
        self.setWindowTitle("foamlab — compression test")
        self.speedup = float(speedup)
        self.out_dir = Path(out_dir)
        self.engine = None
        self.bridge: EngineBridge | None = None
        self.last_result = None
        self.shown_run = None                  # RunData on display (finished run or opened file)
        self.shown_analysis: pipeline.Analysis | None = None   # its pipeline results so far
        self._phase_of_step: dict[int, str] = {}
        self._close_requested = False
        self._analysis_generation = 0
        self.progress_fraction = 0.0
        self._auto_diagnose = auto_diagnose
        self._link_trouble = False

        self.link = MachineLink(self)
        self.analysis = BackgroundQueue("foamlab-analysis", self)
        self.estop_queue = BackgroundQueue("foamlab-estop", self)

        self._build_ui()
        self._fill_choices(profile, method)
        self._wire()
        self._update_controls()

    # ================================================================ UI construction
    def _build_ui(self) -> None:
        controls = QtWidgets.QWidget()
        left = QtWidgets.QVBoxLayout(controls)

        machine_box = QtWidgets.QGroupBox("Machine")
        grid = QtWidgets.QGridLayout(machine_box)
        self.profile_combo = QtWidgets.QComboBox()
        self.profile_combo.setObjectName("profile_combo")
        self.connect_button = QtWidgets.QPushButton("Connect")
        self.connect_button.setObjectName("connect_button")
        self.connection_label = QtWidgets.QLabel("Disconnected")
        self.connection_label.setObjectName("connection_label")
        self.connection_label.setWordWrap(True)
        grid.addWidget(self.profile_combo, 0, 0)
        grid.addWidget(self.connect_button, 0, 1)
        grid.addWidget(self.connection_label, 1, 0, 1, 2)
        left.addWidget(machine_box)

        readout_box = QtWidgets.QGroupBox("Readouts")
        form = QtWidgets.QFormLayout(readout_box)
        self.force_label = _big_label("–", "force_readout")
        self.position_label = _big_label("–", "position_readout")
        self.state_label = QtWidgets.QLabel("–")
        self.state_label.setObjectName("state_readout")
        self.state_label.setAlignment(QtCore.Qt.AlignmentFlag.AlignRight)
        form.addRow("Force [N]", self.force_label)
        form.addRow("Position [mm]", self.position_label)
        form.addRow("State", self.state_label)
        left.addWidget(readout_box)

        jog_box = QtWidgets.QGroupBox("Jog and zero (idle only)")
        jog = QtWidgets.QGridLayout(jog_box)
        self.jog_speed = QtWidgets.QDoubleSpinBox()
        self.jog_speed.setObjectName("jog_speed")
        self.jog_speed.setRange(1.0, 500.0)
        self.jog_speed.setValue(DEFAULT_JOG_SPEED)
        self.jog_speed.setSuffix(" mm/min")
        self.jog_up = QtWidgets.QPushButton("▲ Up")
        self.jog_up.setObjectName("jog_up")
        self.jog_down = QtWidgets.QPushButton("▼ Down")
        self.jog_down.setObjectName("jog_down")
        for b in (self.jog_up, self.jog_down):
            b.setToolTip("Hold to move; release to stop")
        self.zero_position_button = QtWidgets.QPushButton("Zero position")
        self.zero_force_button = QtWidgets.QPushButton("Zero force")
        self.tare_button = QtWidgets.QPushButton("Tare")
        self.reset_button = QtWidgets.QPushButton("Reset e-stop")
        self.reset_button.setToolTip("Clear a latched emergency stop or fault of the crosshead")
        jog.addWidget(QtWidgets.QLabel("Speed"), 0, 0)
        jog.addWidget(self.jog_speed, 0, 1, 1, 2)
        jog.addWidget(self.jog_up, 1, 0)
        jog.addWidget(self.jog_down, 1, 1)
        jog.addWidget(self.reset_button, 1, 2)
        jog.addWidget(self.zero_position_button, 2, 0)
        jog.addWidget(self.zero_force_button, 2, 1)
        jog.addWidget(self.tare_button, 2, 2)
        left.addWidget(jog_box)

        self.limits_form = LimitsForm()
        left.addWidget(self.limits_form)

        method_box = QtWidgets.QGroupBox("Method")
        mform = QtWidgets.QVBoxLayout(method_box)
        self.method_combo = QtWidgets.QComboBox()
        self.method_combo.setObjectName("method_combo")
        self.method_info = QtWidgets.QLabel("")
        self.method_info.setWordWrap(True)
        self.method_info.setStyleSheet("color: #555;")
        mform.addWidget(self.method_combo)
        mform.addWidget(self.method_info)
        left.addWidget(method_box)

        self.specimen_form = SpecimenForm()
        left.addWidget(self.specimen_form)

        left.addStretch(1)

        scroll = QtWidgets.QScrollArea()
        scroll.setWidget(controls)
        scroll.setWidgetResizable(True)
        scroll.setHorizontalScrollBarPolicy(QtCore.Qt.ScrollBarPolicy.ScrollBarAlwaysOff)
        scroll.setMinimumWidth(360)

        # Start / Stop / EMERGENCY STOP stay visible below the scrolling controls.
        self.start_button = QtWidgets.QPushButton("Start")
        self.start_button.setObjectName("start_button")
        self.stop_button = QtWidgets.QPushButton("Stop")
        self.stop_button.setObjectName("stop_button")
        for b in (self.start_button, self.stop_button):
            b.setMinimumHeight(32)
        self.estop_button = QtWidgets.QPushButton("EMERGENCY STOP")
        self.estop_button.setObjectName("estop_button")
        self.estop_button.setMinimumHeight(52)
        self.estop_button.setStyleSheet(
            "QPushButton { background: #C62828; color: white; font-weight: bold; font-size: 16px; }"
            "QPushButton:disabled { background: #E8A5A5; }")
        self.estop_button.setShortcut(QtGui.QKeySequence("Esc"))
        self.estop_button.setToolTip("Stops the crosshead at once (Esc). The data acquired are kept.")
        left_panel = QtWidgets.QWidget()
        left_outer = QtWidgets.QVBoxLayout(left_panel)
        left_outer.setContentsMargins(0, 0, 0, 0)
        left_outer.addWidget(scroll, 1)
        run_row = QtWidgets.QHBoxLayout()
        run_row.addWidget(self.start_button)
        run_row.addWidget(self.stop_button)
        left_outer.addLayout(run_row)
        left_outer.addWidget(self.estop_button)

        # Right: live test (plots, progress, results) and the run browser.
        test_tab = QtWidgets.QWidget()
        right = QtWidgets.QVBoxLayout(test_tab)
        self.plots = LivePlots()
        self.progress = QtWidgets.QProgressBar()
        self.progress.setObjectName("run_progress")
        self.progress.setRange(0, 1000)
        self.progress.setValue(0)
        self.progress.setFormat("No run")
        self.progress.setTextVisible(True)
        self.run_status = QtWidgets.QLabel("")
        self.run_status.setObjectName("run_status")
        self.run_status.setWordWrap(True)
        self.results = ResultsPanel()
        splitter = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        top = QtWidgets.QWidget()
        top_layout = QtWidgets.QVBoxLayout(top)
        top_layout.setContentsMargins(0, 0, 0, 0)
        top_layout.addWidget(self.plots, 1)
        top_layout.addWidget(self.progress)
        top_layout.addWidget(self.run_status)
        splitter.addWidget(top)
        splitter.addWidget(self.results)
        splitter.setStretchFactor(0, 1)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([470, 430])
        right.addWidget(splitter)

        from foamlab.gui.browser import RunBrowser

        self.browser = RunBrowser(self.out_dir)
        self.tabs = QtWidgets.QTabWidget()
        self.tabs.addTab(test_tab, "Test")
        self.tabs.addTab(self.browser, "Runs")

        main = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        main.addWidget(left_panel)
        main.addWidget(self.tabs)
        main.setStretchFactor(1, 1)
        self.setCentralWidget(main)

        menu = self.menuBar().addMenu("&File")
        self.open_action = menu.addAction("&Open measured file…", QtGui.QKeySequence.StandardKey.Open)
        self.export_png_action = menu.addAction("Export plot as &PNG…")
        self.export_csv_action = menu.addAction("Export results as &CSV…")
        menu.addSeparator()
        self.quit_action = menu.addAction("&Quit", QtGui.QKeySequence.StandardKey.Quit)
        analysis_menu = self.menuBar().addMenu("&Analysis")
        # A diagnosis takes seconds to tens of seconds (it refits extended models); it runs in
        # the background, and can be left for later.
        self.auto_diagnose_action = analysis_menu.addAction("Diagnose &automatically")
        self.auto_diagnose_action.setCheckable(True)
        self.auto_diagnose_action.setChecked(self._auto_diagnose)
        self.diagnose_action = analysis_menu.addAction("&Diagnose the shown run")

        self.frame_timer = QtCore.QTimer(self)
        self.frame_timer.setInterval(int(1000 / FRAME_HZ))
        self.poll_timer = QtCore.QTimer(self)
        self.poll_timer.setInterval(int(1000 / POLL_HZ))
        self.resize(1400, 900)

    def _fill_choices(self, profile: str | None, method: str | None) -> None:
        self.profile_combo.addItem(BUILTIN_SIMULATOR)
        try:
            from drivers.profile import available_profiles

            self.profile_combo.addItems(available_profiles())
        except Exception as exc:  # a broken configs folder must not stop the window
            self._status(f"machine profiles unavailable: {exc}", error=True)
        if profile:
            index = self.profile_combo.findText(profile)
            if index < 0:
                raise FoamlabError(f"unknown machine profile {profile!r}")
            self.profile_combo.setCurrentIndex(index)
        try:
            from foamlab.methods import DEFAULT_METHOD, available_methods

            self.method_combo.addItems(available_methods())
            chosen = method or DEFAULT_METHOD
            index = self.method_combo.findText(chosen)
            if method and index < 0:
                raise FoamlabError(f"unknown method {method!r}")
            self.method_combo.setCurrentIndex(max(index, 0))
        except ImportError as exc:
            self._status(f"test methods unavailable: {exc}", error=True)
        self._on_method_changed()

    def _wire(self) -> None:
        self.connect_button.clicked.connect(self.toggle_connection)
        self.link.connected.connect(self._on_connected)
        self.link.connect_failed.connect(self._on_connect_failed)
        self.link.disconnected.connect(self._on_disconnected)
        self.link.readout.connect(self._on_readout)
        self.link.poll_failed.connect(self._on_poll_failed)
        self.link.error.connect(lambda msg: self._status(msg, error=True))
        self.poll_timer.timeout.connect(self.link.poll)
        self.frame_timer.timeout.connect(self._on_frame)
        self.method_combo.currentIndexChanged.connect(self._on_method_changed)
        self.jog_up.pressed.connect(lambda: self._jog(-1))
        self.jog_down.pressed.connect(lambda: self._jog(+1))
        self.jog_up.released.connect(self._stop_motion)
        self.jog_down.released.connect(self._stop_motion)
        self.zero_position_button.clicked.connect(
            lambda: self.link.call("zero position", lambda m: m.crosshead.set_zero()))
        self.zero_force_button.clicked.connect(
            lambda: self.link.call("zero force", lambda m: m.load_cell.zero()))
        self.tare_button.clicked.connect(lambda: self.link.call("tare", lambda m: m.load_cell.tare()))
        self.reset_button.clicked.connect(
            lambda: self.link.call("reset e-stop", lambda m: m.crosshead.reset_fault()))
        self.start_button.clicked.connect(self.start_run)
        self.stop_button.clicked.connect(self.stop_run)
        self.estop_button.clicked.connect(self.emergency_stop)
        self.open_action.triggered.connect(lambda: self.open_file())
        self.export_png_action.triggered.connect(lambda: self.export_png())
        self.export_csv_action.triggered.connect(lambda: self.export_csv())
        self.quit_action.triggered.connect(self.close)
        self.diagnose_action.triggered.connect(self.diagnose_shown_run)
        self.browser.open_requested.connect(self.open_file)

    # ================================================================ state
    @property
    def connected(self) -> bool:
        return self.link.connection is not None

    @property
    def running(self) -> bool:
        return self.engine is not None

    def _update_controls(self) -> None:
        connected, running = self.connected, self.running
        connecting = self.connect_button.text() == "Connecting…"
        idle = connected and not running
        self.profile_combo.setEnabled(not connected and not connecting)
        self.connect_button.setEnabled(not running and not connecting)
        self.connect_button.setText("Connecting…" if connecting else ("Disconnect" if connected else "Connect"))
        for w in (self.jog_up, self.jog_down, self.jog_speed, self.zero_position_button,
                  self.zero_force_button, self.tare_button, self.reset_button):
            w.setEnabled(idle)
        self.limits_form.setEnabled(idle and self.limits_form.profile_limits is not None)
        self.method_combo.setEnabled(not running)
        self.specimen_form.setEnabled(not running)
        self.start_button.setEnabled(idle)
        self.stop_button.setEnabled(running)
        self.estop_button.setEnabled(connected)
        self.open_action.setEnabled(not running)
        self.browser.setEnabled(not running)

    def _status(self, text: str, error: bool = False, timeout_ms: int = 0) -> None:
        self.statusBar().setStyleSheet(ERROR_STYLE if error else "")
        self.statusBar().showMessage(text, timeout_ms)
        (log.warning if error else log.info)("%s", text)

    # ================================================================ connection
    def toggle_connection(self) -> None:
        if self.connected:
            self.poll_timer.stop()
            self.link.disconnect_machine()
            self.connection_label.setText("Disconnecting…")
            self._update_controls()
            return
        self.connect_button.setText("Connecting…")
        self.connection_label.setText("Connecting…")
        self.connection_label.setStyleSheet("")
        self._update_controls()
        self.link.connect_machine(self.profile_combo.currentText(), self.speedup)

    def _on_connected(self, conn: Connection) -> None:
        from foamlab.acquisition import Limits

        self.connect_button.setText("Disconnect")
        self._link_trouble = False
        self._show_connected(conn)
        try:
            limits = Limits.from_profile(conn.profile)
            self.limits_form.set_profile_limits(limits)
            self.jog_speed.setMaximum(limits.max_speed_mm_min)
        except FoamlabError as exc:
            self._status(str(exc), error=True)
        self._status(f"connected to {conn.name}", timeout_ms=5000)
        self.poll_timer.start()
        self._update_controls()

    def _show_connected(self, conn: Connection) -> None:
        note = f", clock x{conn.speedup:g}" if conn.speedup != 1 else ""
        self.connection_label.setText(f"● Connected: {conn.name}{note}")
        self.connection_label.setStyleSheet("color: #1B7F3B; font-weight: bold;")

    def _on_connect_failed(self, message: str) -> None:
        self.connect_button.setText("Connect")
        self.connection_label.setText(f"✖ Not connected: {message}")
        self.connection_label.setStyleSheet(ERROR_STYLE)
        self._status(f"connection failed: {message}", error=True)
        self._update_controls()

    def _on_disconnected(self) -> None:
        self.poll_timer.stop()
        self.connect_button.setText("Connect")
        self.connection_label.setText("Disconnected")
        self.connection_label.setStyleSheet("")
        for label in (self.force_label, self.position_label, self.state_label):
            label.setText("–")
        self._update_controls()

    def _on_poll_failed(self, message: str) -> None:
        self._link_trouble = True
        self.connection_label.setText(f"⚠ Connected, but the machine does not answer: {message}")
        self.connection_label.setStyleSheet(ERROR_STYLE)
        self.state_label.setText("no answer")
        self.state_label.setStyleSheet(ERROR_STYLE)

    def _on_readout(self, readout: Readout) -> None:
        if self._link_trouble and self.link.connection is not None:
            self._link_trouble = False
            self._show_connected(self.link.connection)
        self.force_label.setText(f"{readout.force_N:.2f}")
        self.position_label.setText(f"{readout.position_mm:.3f}")
        state = readout.state + (" · OVERLOAD" if readout.overload else "")
        self.state_label.setText(state)
        self.state_label.setStyleSheet(ERROR_STYLE if readout.state not in ("idle", "moving") else "")

    # ================================================================ idle machine commands
    def _jog(self, direction: int) -> None:
        speed = self.jog_speed.value()
        if self.limits_form.profile_limits is not None:   # the speed limit entered applies to jogging too
            speed = min(speed, self.limits_form.values()["max_speed_mm_min"])
        self.link.call("jog", lambda m: m.crosshead.jog(direction, speed))

    def _stop_motion(self) -> None:
        self.link.call("stop", lambda m: m.crosshead.stop())

    # ================================================================ method
    def _on_method_changed(self) -> None:
        name = self.method_combo.currentText()
        if not name:
            return
        try:
            from foamlab.methods import load_method

            method = load_method(name)
            first = method.steps[0].describe() if method.steps else ""
            self.method_info.setText(f"{method.describe()}; first step: {first}")
            self.method_info.setToolTip("\n".join(s.describe() for s in method.steps))
        except (FoamlabError, ImportError) as exc:
            self.method_info.setText(f"<span style='color:#B00020'>{exc}</span>")

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
            from foamlab.acquisition import Limits, RunEngine
            from foamlab.methods import load_method

            method = load_method(self.method_combo.currentText())
            limits = Limits(**self.limits_form.values())
            if not limits.travel_upper_mm < limits.travel_lower_mm:
                raise FoamlabError("the upper travel limit must be above (smaller than) the lower one")
            engine = RunEngine(conn.machine, method, specimen, self.out_dir, limits=limits,
                               speedup=conn.speedup, connect=False, machine_name=conn.profile.get("name"))
        except FoamlabError as exc:
            self.specimen_form.show_error(f"Cannot start: {exc}")
            self._status(f"start refused: {exc}", error=True)
            return False

        self._analysis_generation += 1   # results of an earlier file/analysis no longer apply
        self.bridge = EngineBridge(self)
        self.bridge.progress.connect(self._on_progress)
        self.bridge.state.connect(self._on_engine_state)
        self.bridge.finished.connect(self._on_finished)
        engine.add_listener(self.bridge)
        self.engine = engine
        self.last_result = None
        self.shown_run = None
        self._phase_of_step = {p.index: PHASE_OF_ACTION.get(p.step.action, LOADING) for p in engine.plan}
        self.link.run_active = True
        self.poll_timer.stop()
        self.plots.clear(expected_samples=method.expected_samples(specimen.height_mm))
        self.results.clear()
        self.progress_fraction = 0.0
        self.progress.setValue(0)
        self.progress.setFormat(f"Cycle 0/{method.n_cycles} — %p% — starting")
        self.run_status.setText(f"Run of {method.name} on {specimen.label}: starting…")
        self.run_status.setStyleSheet("")
        self.tabs.setCurrentIndex(0)
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

    def _drain_samples(self) -> None:
        if self.bridge is None:
            return
        samples = self.bridge.drain()
        if not samples:
            return
        n = len(samples)
        t = np.fromiter((s.time_s for s in samples), float, n)
        d = np.fromiter((s.displacement_mm for s in samples), float, n)
        f = np.fromiter((s.force_N for s in samples), float, n)
        cycles = [s.cycle for s in samples]
        phases = [self._phase_of_step.get(s.step, LOADING) for s in samples]
        self.plots.add_samples(t, d, f, cycles, phases)
        last = samples[-1]
        self.force_label.setText(f"{last.force_N:.2f}")
        self.position_label.setText(f"{last.position_mm:.3f}")

    def _on_progress(self, progress) -> None:
        self.progress_fraction = progress.fraction
        self.progress.setValue(int(round(progress.fraction * 1000)))
        cycle = max(progress.cycle, 0)
        self.progress.setFormat(f"Cycle {cycle}/{progress.n_cycles} — %p% — {_clock(progress.time_left_s)} left")

    def _on_engine_state(self, state: str) -> None:
        self.state_label.setText(STATE_TEXT.get(state, state))
        self.state_label.setStyleSheet("")
        if state == "parking" and self._close_requested and self.engine is not None:
            # The operator is closing the window: don't keep them waiting for the park.
            self.engine.request_stop("window closed during the run")

    def _on_finished(self, result) -> None:
        if self.bridge is None or self.sender() is not self.bridge:
            return
        self._drain_samples()
        self.plots.refresh()
        self.last_result = result
        self._end_run_ui()
        ok = result.status == "finished"
        if ok:
            self.progress.setValue(1000)
            self.progress.setFormat("Finished — %p%")
        else:
            self.progress.setFormat(f"Aborted — %p% — {result.reason}")
        where = str(result.path) if result.path else "nothing recorded (ended before contact)"
        self.run_status.setText(f"Run {result.status}{': ' + result.reason if result.reason else ''}. "
                                f"{result.n_samples} samples, {result.missed} missed. Data: {where}")
        self.run_status.setStyleSheet("" if ok else ERROR_STYLE)

        report = Report()
        report.run = self._run_rows(result)
        report.fit_note = "fitting…" if ok else "not fitted (the run did not finish)"
        self.shown_run = result.run
        self.shown_analysis = None
        self.results.show_report(report)
        if result.run is not None:
            self._analyse(pipeline.Analysis(result.run, result.path), report, self._analysis_generation,
                          fit=ok and len(result.run) > 0)
        if self._close_requested:
            self.close()

    def _end_run_ui(self) -> None:
        self.frame_timer.stop()
        self.engine = None
        self.link.run_active = False
        if self.connected:
            self.poll_timer.start()
        self._update_controls()

    @staticmethod
    def _run_rows(result) -> list[tuple[str, str]]:
        rows = [("status", result.status + (f" ({result.reason})" if result.reason else "")),
                ("file", str(result.path) if result.path else "–"),
                ("samples", f"{result.n_samples} ({result.missed} missed)")]
        if result.park:
            rows.append(("crosshead", result.park))
        timing = result.timing
        if timing is not None and timing.samples:
            rows.append(("schedule", f"lateness p50 {timing.lateness_p50_ms:.2f} ms, p99 {timing.lateness_p99_ms:.2f} ms"))
        return rows

    # ================================================================ analysis (foamlab.pipeline)
    def _analyse(self, analysis: pipeline.Analysis, report: Report, generation: int, fit: bool = True,
                 stored: dict | None = None) -> None:
        """Method results and the fit on the analysis thread (files beside the run, catalog), then
        the diagnosis of that same fit: stored, automatic or on request."""
        folder = self.out_dir

        def work() -> pipeline.Analysis:
            if analysis.method_results is None and not analysis.method_error:
                pipeline.method_stage(analysis)
            if fit:
                pipeline.fit_stage(analysis)
            return pipeline.catalog_stage(pipeline.files_stage(analysis), folder)

        def done(a: pipeline.Analysis) -> None:
            if generation != self._analysis_generation:
                return
            self.shown_analysis = a
            if a.method_results is not None:
                report.set_method_results(a.method_results)
            if a.fit is not None:
                report.fit_note = ""
                report.set_fit(a.fit)
                self._overlay_fit(a.fit)
            elif fit:
                report.fit_note = a.fit_error
            self.results.show_report(report)
            self.browser.refresh()
            if a.fit is not None:
                self._maybe_diagnose(a, report, generation, stored)

        def failed(message: str) -> None:
            if generation == self._analysis_generation:
                report.fit_note = f"failed: {message}"
                self.results.show_report(report)

        self.analysis.submit(work, done, failed)

    def _overlay_fit(self, fit) -> None:
        from foamlab.gui.analysis import fit_curve

        curve = fit_curve(fit)
        if curve is not None:
            self.plots.show_fit(*curve)

    def _maybe_diagnose(self, analysis: pipeline.Analysis, report: Report, generation: int,
                        stored: dict | None = None) -> None:
        """Show a stored diagnosis, else diagnose now when automatic diagnosis is on."""
        if stored:
            report.set_diagnosis(stored)
            report.diagnosis_note = "stored with the run"
            self.results.show_report(report)
        elif self.auto_diagnose_action.isChecked():
            self._start_diagnosis(analysis, report, generation)
        else:
            report.diagnosis_note = "not run (Analysis > Diagnose the shown run)"
            self.results.show_report(report)

    def diagnose_shown_run(self) -> None:
        if self.shown_run is not None and self.shown_analysis is None and not self.running:
            self._status("the fit is still being made: the diagnosis extends it, try again when it shows",
                         error=True)
            return
        if self.running or self.shown_analysis is None or not len(self.shown_analysis.run):
            self._status("no run to diagnose: finish a run or open a file first", error=True)
            return
        self._start_diagnosis(self.shown_analysis, self.results.report, self._analysis_generation)

    def _start_diagnosis(self, analysis: pipeline.Analysis, report: Report, generation: int) -> None:
        """The pipeline's diagnosis stage (it extends the run's fit), its file and catalog entry."""
        report.diagnosis_note = "running…"
        self.results.show_report(report)
        folder = self.out_dir

        def work() -> pipeline.Analysis:
            pipeline.diagnose_stage(analysis)
            return pipeline.catalog_stage(pipeline.files_stage(analysis), folder)

        def done(a: pipeline.Analysis) -> None:
            if generation != self._analysis_generation:
                return
            if a.diagnosis is not None:
                report.set_diagnosis(a.diagnosis)
                report.diagnosis_note = ""
            else:
                report.diagnosis_note = f"failed: {a.diagnosis_error}"
            self.results.show_report(report)
            self.browser.refresh()      # the verdict is in the catalog now

        def failed(message: str) -> None:
            if generation == self._analysis_generation:
                report.diagnosis_note = f"failed: {message}"
                self.results.show_report(report)

        self.analysis.submit(work, done, failed)

    # ================================================================ files
    def open_file(self, path: str | Path | None = None) -> None:
        """Show a run from a file (any supported format): curves, then fit, then diagnosis."""
        if self.running:
            self._status("a run is going: open files after it ends", error=True)
            return
        if path is None:
            path, _ = QtWidgets.QFileDialog.getOpenFileName(
                self, "Open measured data", str(self.out_dir),
                "Measured data (*.csv *.txt *.tsv);;All files (*)")
            if not path:
                return
        path = Path(path)
        self._analysis_generation += 1
        generation = self._analysis_generation
        self._status(f"opening {path}…")
        from foamlab.gui.analysis import load_for_display

        self.analysis.submit(lambda: load_for_display(path),
                             lambda loaded: self._show_loaded(loaded, generation),
                             lambda msg: self._status(f"cannot open {path.name}: {msg}", error=True))

    def _show_loaded(self, loaded, generation: int) -> None:
        if generation != self._analysis_generation or self.running:
            return
        run = loaded.run
        self.shown_run = run
        self.last_result = None
        self.tabs.setCurrentIndex(0)
        self.plots.show_run(run.time_s, run.displacement_mm, run.force_N, loaded.cycles, loaded.phases)
        self.progress.setValue(0)
        self.progress.setFormat(f"{Path(run.source).name if run.source else 'file'}: {len(run)} samples")
        self.run_status.setText(loaded.describe())
        self.run_status.setStyleSheet("")
        report = Report()
        report.run = loaded.rows()
        if loaded.method_results is not None:
            report.set_method_results(loaded.method_results)
        report.fit_note = "fitting…"
        if loaded.stored_diagnosis:
            report.set_diagnosis(loaded.stored_diagnosis)
            report.diagnosis_note = "stored with the run"
        self.shown_analysis = None
        self.results.show_report(report)
        self._status(f"opened {run.source}", timeout_ms=5000)
        self._analyse(loaded.analysis, report, generation, stored=loaded.stored_diagnosis)

    def export_png(self, path: str | Path | None = None) -> Path | None:
        if path is None:
            path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Export plot", str(self.out_dir / "plot.png"),
                                                            "PNG image (*.png)")
            if not path:
                return None
        path = Path(path)
        try:
            self.plots.export_png(str(path))
        except Exception as exc:
            self._status(f"export failed: {exc}", error=True)
            return None
        self._status(f"plot written to {path}", timeout_ms=5000)
        return path

    def export_csv(self, path: str | Path | None = None) -> Path | None:
        if not self.results.report.run:
            self._status("nothing to export yet: run a test or open a file", error=True)
            return None
        if path is None:
            path, _ = QtWidgets.QFileDialog.getSaveFileName(self, "Export results",
                                                            str(self.out_dir / "results.csv"), "CSV (*.csv)")
            if not path:
                return None
        path = Path(path)
        try:
            self.results.report.write_csv(str(path))
        except OSError as exc:
            self._status(f"export failed: {exc}", error=True)
            return None
        self._status(f"results written to {path}", timeout_ms=5000)
        return path

    # ================================================================ closing
    def confirm_close_during_run(self) -> bool:
        """Asked when the window is closed mid-run (tests replace it)."""
        answer = QtWidgets.QMessageBox.question(
            self, "A test is running",
            "A test is running. Stop the machine and close?\nThe data acquired so far are kept.",
            QtWidgets.QMessageBox.StandardButton.Yes | QtWidgets.QMessageBox.StandardButton.No,
            QtWidgets.QMessageBox.StandardButton.No)
        return answer == QtWidgets.QMessageBox.StandardButton.Yes

    def closeEvent(self, event: QtGui.QCloseEvent) -> None:
        if self.engine is not None:
            if not self._close_requested:
                if not self.confirm_close_during_run():
                    event.ignore()
                    return
                self._close_requested = True
                self.engine.request_stop("window closed during the run")
                self._status("stopping the machine before closing…")
                self.setEnabled(False)
                self.estop_button.setEnabled(True)
                # If the engine cannot stop in time, e-stop; the window closes when it reports.
                QtCore.QTimer.singleShot(int(CLOSE_STOP_TIMEOUT_S * 1000), self._close_timeout)
            event.ignore()
            return
        self.frame_timer.stop()
        self.poll_timer.stop()
        self.analysis.shutdown(wait=False)
        self.estop_queue.shutdown(wait=False)
        self.browser.queue.shutdown(wait=False)
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
