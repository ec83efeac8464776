"""The technician's window, driven end to end (offscreen) against the built-in
simulated machine: real drivers over Modbus TCP on 127.0.0.1, the real run engine."""

from __future__ import annotations

import csv
import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np
import pytest
from PySide6 import QtCore, QtWidgets

from foamlab.diagnosis import CAUSES
from foamlab.diagnosis.form import NAME as FORM_VERDICT
from foamlab.gui.window import MainWindow
from tests.gui_support import WAIT_MS, connect_window, shut_window
from foamlab.importers import load_run

pytestmark = [pytest.mark.gui, pytest.mark.hil, pytest.mark.timeout(300)]   # hang guards (gui_support.WAIT_MS)

# The simulated drive's watchdog runs on the machine clock: 2 s is 250 ms of wall time at x8.
# Faster clocks trip it when the two cores are busy (the simulator answers late), which is the
# simulator's and the engine's business, not the window's.
SPEEDUP = 8.0
# An 8 mm block keeps the three cycles short (80 % = 6.4 mm strokes, ~100 s of machine time).
SPECIMEN = ("gui-test", 8.0, 100.0, 100.0)
RUN_TIMEOUT_MS = 60_000
REAL_BLUEHILL = os.path.join(os.path.dirname(__file__), "data", "real", "Specimen_RawData_6.csv")


@pytest.fixture
def window(qtbot, tmp_path):
    w = MainWindow(speedup=SPEEDUP, out_dir=tmp_path / "runs")
    qtbot.addWidget(w)
    w.show()
    yield w
    shut_window(w)


def connect(qtbot, w: MainWindow):
    assert w.profile_combo.currentText() == "Built-in simulated machine"   # the default, no setup
    connect_window(qtbot, w)
    assert w.connect_button.text() == "Disconnect"
    assert "Connected" in w.connection_label.text()
    # Idle readouts come from polling the machine.
    qtbot.waitUntil(lambda: w.state_label.text() == "idle", timeout=WAIT_MS)
    return w.link.connection


def enter_specimen(qtbot, w: MainWindow, label, height, width, depth):
    form = w.specimen_form
    for edit, value in ((form.label_edit, label), (form.edits["height_mm"], height),
                        (form.edits["width_mm"], width), (form.edits["depth_mm"], depth)):
        edit.clear()
        qtbot.keyClicks(edit, str(value))


def wait_mid_run(qtbot, w: MainWindow, n_samples: int) -> None:
    """Until the plot shows n_samples; fails at once (with the reason) if the run ends first."""
    qtbot.waitUntil(lambda: w.plots.sample_count > n_samples or w.last_result is not None,
                    timeout=RUN_TIMEOUT_MS)
    assert w.last_result is None, f"the run ended early: {w.last_result.reason}"


def click(qtbot, button):
    assert button.isEnabled(), f"{button.text()} is disabled"
    qtbot.mouseClick(button, QtCore.Qt.MouseButton.LeftButton)


# its own waits add up to 360 s (run, analysis, verdict): a loaded machine (one core busy: 2-3x
# the 38 s it takes on an idle one) must not be cut off by a shorter hang guard
@pytest.mark.timeout(420)
def test_full_run_plots_progress_fit_and_exports(qtbot, window, tmp_path):
    w = window
    connect(qtbot, w)
    enter_specimen(qtbot, w, *SPECIMEN)
    click(qtbot, w.start_button)
    assert w.running and not w.start_button.isEnabled() and w.stop_button.isEnabled()
    # The window stays responsive during the run: progress moves while samples stream in.
    wait_mid_run(qtbot, w, 0)
    qtbot.waitUntil(lambda: w.progress.value() > 0 or w.last_result is not None, timeout=RUN_TIMEOUT_MS)
    qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)

    result = w.last_result
    assert result.status == "finished", result.reason
    # Three cycles, each its own loading and unloading curve.
    cycles = {(seg.cycle, seg.phase) for seg in w.plots.segments}
    assert {(c, p) for c in (1, 2, 3) for p in ("loading", "unloading")} <= cycles
    # Every sample the engine recorded is on the plots, and on disk.
    assert result.n_samples > 100
    assert w.plots.sample_count == result.n_samples
    assert w.plots.plotted_points() == result.n_samples
    x, y = w.plots.ft_curve.getData()
    assert len(x) == result.n_samples
    on_disk = load_run(result.path)
    assert len(on_disk) == result.n_samples
    np.testing.assert_allclose(w.plots.buffer.force_N[: result.n_samples], on_disk.force_N, atol=1e-3)
    assert w.progress.value() == w.progress.maximum()
    assert "100%" in w.progress.text()
    # The pipeline's method results and fit follow the run (foamlab.pipeline, analysis thread).
    qtbot.waitUntil(lambda: w.shown_analysis is not None, timeout=RUN_TIMEOUT_MS)
    analysis = w.shown_analysis
    # Method results are shown and exported with the run summary.
    assert w.results.method_results.rowCount() == len(analysis.method_results) > 0
    png = w.export_png(tmp_path / "plot.png")
    assert png.exists() and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    out = w.export_csv(tmp_path / "results.csv")
    rows = list(csv.reader(out.open(encoding="utf-8")))
    assert rows[0][0] == "section"
    sections = {r[0] for r in rows[1:]}
    assert {"run", "method_result"} <= sections
    # The fit table and the fitted curve come with the pipeline's fit (foamlab.identification).
    fitted = analysis.fit is not None
    if fitted:
        assert w.results.parameters.rowCount() > 0
        assert w.results.statistics.rowCount() > 0
        assert w.plots.fit_fd is not None
        x_fit, _ = w.plots.fit_fd.getData()
        # samples stamped off the schedule are left out of the fit (analysis.prepared.on_schedule):
        # with the window drawing at speedup 8 on 2 cores, up to 1.7 % of them (27 of 1 566), on
        # session 6's code as on this one
        assert len(x_fit) == len(analysis.fit.predicted_force_N) >= 0.97 * result.n_samples
        assert analysis.fit.prepared.off_schedule <= 0.03 * result.n_samples
        rows = list(csv.reader(w.export_csv(tmp_path / "results.csv").open(encoding="utf-8")))
        assert {"parameter", "statistic"} <= {r[0] for r in rows[1:]}
        # Then the diagnosis verdict (foamlab.diagnosis), computed off the GUI thread - for a
        # run with gaps too (a busy computer made the sped-up machine miss samples: flagged,
        # and analysed as `foamlab run` does, pipeline.AfterRun).
        # a hang guard, not a speed check: with one core busy the verdict took over 90 s (ci33)
        qtbot.waitUntil(lambda: bool(w.results.report.verdict) or "failed" in w.results.verdict.text(),
                        timeout=240_000)
        assert w.results.verdict.text().startswith("<b>Diagnosis verdict:</b>"), w.results.verdict.text()
        side = result.path.with_name(result.path.stem + ".diagnosis.json")
        assert side.exists()                       # kept with the run, so the browser shows it
        # any verdict the catalogue can give: the simulated run's timing is the computer's
        # (a loaded one lags the channels), so which one is not this test's to say
        assert w.results.report.verdict in (*CAUSES, FORM_VERDICT, "unexplained", "none")

    # The run is in the catalog's browser; opening it from there shows the same curves (and fit).
    w.browser.refresh()
    verdict = w.results.report.verdict if fitted else ""

    def listed() -> bool:
        return any(r["file"] == str(result.path.resolve()) and r["verdict"] == verdict for r in w.browser.rows)

    qtbot.waitUntil(listed, timeout=WAIT_MS)
    table = w.browser.table
    row = next(i for i in range(table.rowCount())
               if table.item(i, 0).data(QtCore.Qt.ItemDataRole.UserRole) == str(result.path.resolve()))
    w.auto_diagnose_action.setChecked(False)      # diagnosed above already; keep the test short
    w.shown_run = None
    w.tabs.setCurrentWidget(w.browser)
    cell = table.visualItemRect(table.item(row, 1)).center()
    qtbot.mouseClick(table.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=cell)
    qtbot.mouseDClick(table.viewport(), QtCore.Qt.MouseButton.LeftButton, pos=cell)
    qtbot.waitUntil(lambda: w.shown_run is not None, timeout=WAIT_MS)
    assert w.plots.sample_count == result.n_samples
    assert {(s.cycle, s.phase) for s in w.plots.segments} >= {(3, "unloading")}
    if fitted:   # the stored diagnosis is shown at once, not recomputed
        assert w.results.report.verdict == verdict and "stored with the run" in w.results.report.diagnosis_note
    if not fitted:
        pytest.skip(f"no fit to show: {analysis.fit_error}")
    qtbot.waitUntil(lambda: w.results.parameters.rowCount() > 0, timeout=WAIT_MS)


def test_emergency_stop_mid_run_stops_crosshead_and_keeps_data(qtbot, tmp_path):
    w = MainWindow(speedup=SPEEDUP, out_dir=tmp_path / "runs")
    qtbot.addWidget(w)
    w.show()
    try:
        conn = connect(qtbot, w)
        enter_specimen(qtbot, w, *SPECIMEN)
        click(qtbot, w.start_button)
        # Mid-run: the plate is compressing the specimen in the first cycle.
        wait_mid_run(qtbot, w, 80)
        shown_before = w.plots.sample_count
        click(qtbot, w.estop_button)
        qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)
        result = w.last_result
        assert result.status == "aborted" and result.end == "estop", (result.status, result.reason)
        state = conn.simulator.crosshead_status()      # the simulated machine's own view
        assert not state["moving"]
        assert state["emergency_stop"]
        # Not parked after an e-stop, and every sample acquired is on disk and on the plot.
        assert "not parked" in result.park
        assert result.path.exists()
        on_disk = load_run(result.path)
        assert len(on_disk) == result.n_samples >= shown_before
        assert w.plots.sample_count == result.n_samples
        assert "Aborted" in w.progress.text()
        # The window is idle again; the e-stop can be reset from it.
        assert w.start_button.isEnabled() and w.reset_button.isEnabled()
        click(qtbot, w.reset_button)
        qtbot.waitUntil(lambda: not conn.simulator.crosshead_status()["emergency_stop"], timeout=WAIT_MS)
    finally:
        if w.engine is not None:
            w.engine.emergency_stop()
            w.engine.wait(10.0)
        w.link.shutdown()


def test_invalid_specimen_is_refused_with_a_visible_message(qtbot, window):
    w = window
    connect(qtbot, w)
    cases = [("", "72.5", "100", "100", "label"),
             ("s1", "abc", "100", "100", "Height"),
             ("s1", "-5", "100", "100", "Height"),
             ("s1", "72.5", "0", "100", "Width"),
             ("s1", "72.5", "100", "", "Depth")]
    for label, height, width, depth, complaint in cases:
        form = w.specimen_form
        form.label_edit.setText(label)
        form.edits["height_mm"].setText(height)
        form.edits["width_mm"].setText(width)
        form.edits["depth_mm"].setText(depth)
        click(qtbot, w.start_button)
        assert w.engine is None, f"started with {label!r} {height!r} {width!r} {depth!r}"
        assert form.message.isVisible()
        assert complaint in form.message.text()
        assert form.message.text().startswith("Cannot start")
    # Corrected: the message goes away and the run starts.
    enter_specimen(qtbot, w, *SPECIMEN)
    assert not w.specimen_form.message.isVisible()
    click(qtbot, w.start_button)
    assert w.engine is not None
    click(qtbot, w.stop_button)
    qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)
    assert w.last_result.status == "aborted"


def test_limits_entered_only_within_profile_bounds(qtbot, window):
    w = window
    connect(qtbot, w)
    profile_limits = w.limits_form.profile_limits
    # Beyond the profile's bounds: shown wrong as typed (not clamped), and Start refuses.
    force = w.limits_form.fields["force_N"]
    force.clear()
    qtbot.keyClicks(force, "4500")
    assert force.text() == "4500" and force.value() is None
    assert "Force limit 4500 N is outside 0.1 to 450 N." in w.limits_form.message.text()
    lower = w.limits_form.fields["travel_lower_mm"]
    lower.setValue(profile_limits.travel_lower_mm + 100)
    assert lower.value() is None and "Travel, lower 170 mm" in w.limits_form.message.text()
    enter_specimen(qtbot, w, *SPECIMEN)
    click(qtbot, w.start_button)
    assert w.engine is None and "Force limit 4500 N" in w.specimen_form.message.text()
    lower.setValue(profile_limits.travel_lower_mm)
    assert not w.limits_form.message.isVisible() or "Force" in w.limits_form.message.text()
    # A tighter force limit than the method's peak force stops the run on the limit.
    force.setValue(2.0)
    assert not w.limits_form.message.isVisible()
    click(qtbot, w.start_button)
    qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)
    assert w.last_result.status == "aborted"
    assert "force" in w.last_result.reason.lower()


def test_jog_moves_the_crosshead_only_while_held(qtbot, window):
    w = window
    conn = connect(qtbot, w)
    sim = conn.simulator

    def position():
        return sim.snapshot()["position_mm"]

    start = position()
    w.jog_speed.setValue(200.0)
    qtbot.mousePress(w.jog_up, QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: sim.crosshead_status()["moving"], timeout=WAIT_MS)
    qtbot.waitUntil(lambda: position() < start - 1.0, timeout=WAIT_MS)
    qtbot.mouseRelease(w.jog_up, QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: not sim.crosshead_status()["moving"], timeout=WAIT_MS)
    # The idle readout follows the machine.
    qtbot.waitUntil(lambda: abs(float(w.position_label.text()) - position()) < 0.05, timeout=WAIT_MS)
    click(qtbot, w.zero_position_button)
    qtbot.waitUntil(lambda: abs(position()) < 1e-6, timeout=WAIT_MS)


def test_closing_mid_run_stops_the_machine_and_keeps_the_data(qtbot, tmp_path, monkeypatch):
    w = MainWindow(speedup=SPEEDUP, out_dir=tmp_path / "runs")
    qtbot.addWidget(w)
    w.show()
    conn = connect(qtbot, w)
    sim = conn.simulator
    enter_specimen(qtbot, w, *SPECIMEN)
    click(qtbot, w.start_button)
    wait_mid_run(qtbot, w, 50)
    at_close = {}
    close_link = conn.machine.close

    def record_then_close():
        at_close.update(sim.crosshead_status())   # the machine as the window lets go of it
        close_link()

    monkeypatch.setattr(conn.machine, "close", record_then_close)
    w.close()
    # Asked first, in a non-modal question (the e-stop stays at hand); the run goes on meanwhile.
    question = w.dialog
    assert question.objectName() == "close_question" and question.isVisible() and w.running
    click(qtbot, question.button(QtWidgets.QMessageBox.StandardButton.Yes))
    qtbot.waitUntil(lambda: not w.isVisible(), timeout=WAIT_MS)
    result = w.last_result
    assert result is not None and result.status == "aborted"
    assert "window closed" in result.reason
    assert len(load_run(result.path)) == result.n_samples > 50
    assert w.link.connection is None
    # The crosshead was at rest (stopped, or parked) before the link and the simulator closed.
    assert at_close and not at_close["moving"], (at_close, result.park)
    assert not sim.running


@pytest.mark.timeout(300)
def test_open_measured_file_shows_curves(qtbot, window):
    w = window
    # Diagnosing the 18 000-sample real file takes ~25 s: left out here (the full-run test diagnoses).
    w.auto_diagnose_action.setChecked(False)
    w.open_file(REAL_BLUEHILL)
    qtbot.waitUntil(lambda: w.shown_run is not None, timeout=WAIT_MS)
    run = w.shown_run
    assert w.plots.sample_count == len(run) > 1000
    loadings = {seg.cycle for seg in w.plots.segments if seg.phase == "loading"}
    assert loadings == {1, 2, 3}
    assert "3 cycles" in w.run_status.text()
    rows = dict(w.results.report.run)
    assert rows["cycles"] == "3"
    # The fit comes from the analysis thread: parameters, statistics and the fitted curve.
    # an event, bounded only against a hang: the fit took over 30 s with one core kept busy (ci21)
    qtbot.waitUntil(lambda: "fitting" not in w.results.summary.text(), timeout=240_000)
    assert w.results.parameters.rowCount() > 0 and w.results.statistics.rowCount() > 0
    x_fit, f_fit = w.plots.fit_fd.getData()   # the fit's samples: those taken on schedule
    assert len(x_fit) == len(w.shown_analysis.fit.predicted_force_N) >= 0.99 * len(run)
    assert np.isfinite(f_fit).all()
    assert "not run" in w.results.verdict.text()


def test_open_bad_file_says_why(qtbot, window, tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,displacement_mm,force_N\n0,abc,1\n", encoding="utf-8")
    window.open_file(bad)
    qtbot.waitUntil(lambda: "cannot open bad.csv" in window.statusBar().currentMessage(), timeout=WAIT_MS)
    assert window.shown_run is None


def test_connection_failure_is_shown_and_disconnect_closes_the_simulator(qtbot, window):
    w = window
    w.profile_combo.setCurrentText("sim-serial")          # /dev/ttyUSB0: no such device here
    click(qtbot, w.connect_button)
    qtbot.waitUntil(lambda: "Not connected" in w.connection_label.text(), timeout=WAIT_MS)
    assert not w.connected and w.connect_button.text() == "Connect" and not w.start_button.isEnabled()
    w.profile_combo.setCurrentText("Built-in simulated machine")
    conn = connect(qtbot, w)
    assert not w.profile_combo.isEnabled()                 # no profile change while connected
    # The machine goes away (cable pulled, power off): the window says so, it does not hang.
    conn.simulator.stop()
    qtbot.waitUntil(lambda: "does not answer" in w.connection_label.text(), timeout=WAIT_MS)
    assert w.state_label.text() == "no answer"
    click(qtbot, w.connect_button)                         # Disconnect
    qtbot.waitUntil(lambda: w.connection_label.text() == "Disconnected", timeout=WAIT_MS)
    assert not conn.simulator.running
    assert w.force_label.text() == "–" and w.profile_combo.isEnabled()


def test_gui_command_without_a_display_says_so_in_one_line():
    import subprocess
    import sys

    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY", "QT_QPA_PLATFORM")}
    proc = subprocess.run([sys.executable, "-m", "foamlab.cli", "gui"], env=env, capture_output=True,
                          text=True, timeout=60)
    assert proc.returncode == 2
    assert proc.stderr.strip().count("\n") == 0 and "no display" in proc.stderr


def test_gui_command_rejects_a_bad_speedup(capsys):
    from foamlab.cli import main

    assert main(["gui", "--speedup", "0"]) == 2
    err = capsys.readouterr().err
    assert "speedup" in err and "Traceback" not in err
