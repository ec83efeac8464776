"""The window's left-hand controls: machine connection, readouts, jog and zero, safety
limits, method, specimen, and Start / Stop / EMERGENCY STOP (always visible below the
scrolling part). Widgets only: the window wires them to the machine and the engine."""

from __future__ import annotations

from PySide6 import QtCore, QtWidgets

from foamlab import FoamlabError
from foamlab.gui.forms import ERROR_STYLE, LimitsForm, NumberField, SpecimenForm
from foamlab.gui.machine_link import BUILTIN_SIMULATOR, Readout

DEFAULT_JOG_SPEED = 50.0


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


class ControlPanel(QtWidgets.QWidget):
    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        controls = QtWidgets.QWidget()
        left = QtWidgets.QVBoxLayout(controls)
        left.addWidget(self._machine_box())
        left.addWidget(self._readout_box())
        left.addWidget(self._jog_box())
        self.limits_form = LimitsForm()
        left.addWidget(self.limits_form)
        left.addWidget(self._method_box())
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
        self.estop_button.setToolTip("Stops the crosshead at once (Esc). The data acquired are kept.")
        left_outer = QtWidgets.QVBoxLayout(self)
        left_outer.setContentsMargins(0, 0, 0, 0)
        left_outer.addWidget(scroll, 1)
        run_row = QtWidgets.QHBoxLayout()
        run_row.addWidget(self.start_button)
        run_row.addWidget(self.stop_button)
        left_outer.addLayout(run_row)
        left_outer.addWidget(self.estop_button)

    def _machine_box(self) -> QtWidgets.QGroupBox:
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
        return machine_box

    def _readout_box(self) -> QtWidgets.QGroupBox:
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
        return readout_box

    def _jog_box(self) -> QtWidgets.QGroupBox:
        jog_box = QtWidgets.QGroupBox("Jog and zero (idle only)")
        jog = QtWidgets.QGridLayout(jog_box)
        self.jog_speed = NumberField("Jog speed", "mm/min", 1.0, 500.0)
        self.jog_speed.setObjectName("jog_speed")
        self.jog_speed.setRange(1.0, 500.0)
        self.jog_speed.setValue(DEFAULT_JOG_SPEED)
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
        self.return_button = QtWidgets.QPushButton("Return to start")
        self.return_button.setObjectName("return_button")
        self.return_button.setToolTip("Move to where the last run started (0 mm before any run) at the jog "
                                      "speed; Stop or Esc halts it")
        self.reset_button.setToolTip("Clear a latched emergency stop or fault of the crosshead")
        jog.addWidget(QtWidgets.QLabel("Speed [mm/min]"), 0, 0)
        jog.addWidget(self.jog_speed, 0, 1, 1, 2)
        jog.addWidget(self.jog_up, 1, 0)
        jog.addWidget(self.jog_down, 1, 1)
        jog.addWidget(self.reset_button, 1, 2)
        jog.addWidget(self.zero_position_button, 2, 0)
        jog.addWidget(self.zero_force_button, 2, 1)
        jog.addWidget(self.tare_button, 2, 2)
        jog.addWidget(self.return_button, 3, 0, 1, 3)
        return jog_box

    def _method_box(self) -> QtWidgets.QGroupBox:
        method_box = QtWidgets.QGroupBox("Method")
        mform = QtWidgets.QVBoxLayout(method_box)
        self.method_combo = QtWidgets.QComboBox()
        self.method_combo.setObjectName("method_combo")
        self.method_info = QtWidgets.QLabel("")
        self.method_info.setWordWrap(True)
        self.method_info.setStyleSheet("color: #555;")
        mform.addWidget(self.method_combo)
        mform.addWidget(self.method_info)
        return method_box

    # -- what the controls show ------------------------------------------------------------
    def fill_choices(self, profile: str | None, method: str | None) -> list[str]:
        """Machine profiles and methods to choose from; returns what could not be listed.
        Raises FoamlabError for a profile or method asked for by name that does not exist."""
        problems = []
        self.profile_combo.addItem(BUILTIN_SIMULATOR)
        try:
            from drivers.profile import available_profiles

            self.profile_combo.addItems(available_profiles())
        except Exception as exc:  # a broken configs folder must not stop the window
            problems.append(f"machine profiles unavailable: {exc}")
        if profile:
            index = self.profile_combo.findText(profile)
            if index < 0:
                raise FoamlabError(f"unknown machine profile {profile!r}")
            self.profile_combo.setCurrentIndex(index)
        try:
            from foamlab.methods import DEFAULT_METHOD, available_methods

            self.method_combo.addItems(available_methods())
            index = self.method_combo.findText(method or DEFAULT_METHOD)
            if method and index < 0:
                raise FoamlabError(f"unknown method {method!r}")
            self.method_combo.setCurrentIndex(max(index, 0))
        except ImportError as exc:
            problems.append(f"test methods unavailable: {exc}")
        self.show_method()
        return problems

    def show_method(self) -> None:
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

    def show_run_inputs(self, run) -> None:
        """The opened run's method and specimen (what it was run with; a RunData)."""
        spec = run.specimen
        self.specimen_form.set_values(spec.label or "", spec.height_mm, spec.width_mm, spec.depth_mm)
        index = self.method_combo.findText(run.method) if run.method else -1
        if index >= 0:
            self.method_combo.setCurrentIndex(index)
        else:
            self.method_info.setText(f"The opened run's method, {run.method!r}, is not installed here" if run.method
                                     else "The opened run records no method (imported data)")

    def set_state(self, connected: bool, running: bool, closing: bool) -> None:
        """Enable what may be used now. The e-stop stays enabled whenever connected."""
        connecting = self.connect_button.text() == "Connecting…"
        idle = connected and not running and not closing
        self.profile_combo.setEnabled(not connected and not connecting)
        self.connect_button.setEnabled(not running and not connecting)
        self.connect_button.setText("Connecting…" if connecting else ("Disconnect" if connected else "Connect"))
        for w in (self.jog_up, self.jog_down, self.jog_speed, self.zero_position_button,
                  self.zero_force_button, self.tare_button, self.reset_button, self.return_button):
            w.setEnabled(idle)
        self.limits_form.setEnabled(idle and self.limits_form.profile_limits is not None)
        self.method_combo.setEnabled(not running)
        self.specimen_form.setEnabled(not running)
        self.start_button.setEnabled(idle)
        # Stops a run, or an idle move (return to start) when no run is going.
        self.stop_button.setEnabled(connected and not closing)
        self.estop_button.setEnabled(connected)      # in every state, closing included

    def show_connecting(self) -> None:
        self.connect_button.setText("Connecting…")
        self.connection_label.setText("Connecting…")
        self.connection_label.setStyleSheet("")

    def show_connected(self, name: str, speedup: float) -> None:
        note = f", clock x{speedup:g}" if speedup != 1 else ""
        self.connect_button.setText("Disconnect")
        self.connection_label.setText(f"● Connected: {name}{note}")
        self.connection_label.setStyleSheet("color: #1B7F3B; font-weight: bold;")

    def show_connect_failed(self, message: str) -> None:
        self.connect_button.setText("Connect")
        self.connection_label.setText(f"✖ Not connected: {message}")
        self.connection_label.setStyleSheet(ERROR_STYLE)

    def show_disconnected(self) -> None:
        self.connect_button.setText("Connect")
        self.connection_label.setText("Disconnected")
        self.connection_label.setStyleSheet("")
        for label in (self.force_label, self.position_label, self.state_label):
            label.setText("–")

    def show_no_answer(self, message: str) -> None:
        self.connection_label.setText(f"⚠ Connected, but the machine does not answer: {message}")
        self.connection_label.setStyleSheet(ERROR_STYLE)
        self.state_label.setText("no answer")
        self.state_label.setStyleSheet(ERROR_STYLE)

    def show_readout(self, readout: Readout) -> None:
        self.force_label.setText(f"{readout.force_N:.2f}")
        self.position_label.setText(f"{readout.position_mm:.3f}")
        self.state_label.setText(readout.state + (" · OVERLOAD" if readout.overload else ""))
        self.state_label.setStyleSheet(ERROR_STYLE if readout.state not in ("idle", "moving") else "")
