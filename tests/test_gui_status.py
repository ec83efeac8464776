"""Issue 18, status that is true: messages replaced as the state changes, a run with gaps
reported as such, an opened past run shown in every panel, the travel a method needs
checked before Start in plain words. Offscreen; the built-in simulated machine where a
machine is needed."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import threading

import numpy as np
import pytest
from test_gui import (
    RUN_TIMEOUT_MS,
    SPEEDUP,
    click,
    connect,
    enter_specimen,
    wait_mid_run,
)

from foamlab.acquisition import RunResult
from foamlab.gui.forms import ERROR_STYLE
from foamlab.gui.status import WARNING_STYLE
from foamlab.gui.window import MainWindow
from tests.gui_support import WAIT_MS, shut_window
from foamlab.rundata import RunData, Specimen
from foamlab.storage.runfile import write_run_file

pytestmark = [pytest.mark.gui, pytest.mark.hil, pytest.mark.timeout(300)]   # hang guards (gui_support.WAIT_MS)

# 3 mm: the paper's three cycles are 2.4 mm strokes, ~5 s of wall time at x8.
SHORT_SPECIMEN = ("status-test", 3.0, 100.0, 100.0)


@pytest.fixture
def win(qtbot, tmp_path):
    w = MainWindow(speedup=SPEEDUP, out_dir=tmp_path / "runs", auto_diagnose=False)
    qtbot.addWidget(w)
    w.show()
    yield w
    shut_window(w)


def status(w: MainWindow) -> tuple[str, str]:
    return w.statusBar().currentMessage(), w.statusBar().styleSheet()


def test_status_after_an_estop_and_a_later_run_is_current(qtbot, win):
    w = win
    sim = connect(qtbot, w).simulator
    enter_specimen(qtbot, w, *SHORT_SPECIMEN)
    click(qtbot, w.start_button)
    # "starting…" is replaced as the engine moves on.
    qtbot.waitUntil(lambda: "starting" not in w.run_status.text(), timeout=RUN_TIMEOUT_MS)
    assert w.run_status.text().startswith("Run of paper-3cycle on status-test: ")
    wait_mid_run(qtbot, w, 20)
    click(qtbot, w.estop_button)
    qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)
    text, style = status(w)
    assert "aborted" in text and "emergency stop" in text and style == ERROR_STYLE
    click(qtbot, w.reset_button)
    qtbot.waitUntil(lambda: not sim.crosshead_status()["emergency_stop"], timeout=WAIT_MS)
    qtbot.waitUntil(lambda: status(w) == ("e-stop reset: the crosshead may move again", ""), timeout=WAIT_MS)
    # Back to where the run started (above the specimen), so the next run may tare.
    w.jog_speed.setValue(300.0)
    click(qtbot, w.return_button)
    qtbot.waitUntil(lambda: abs(sim.snapshot()["position_mm"] - w._run_start_mm) < 0.01
                    and not sim.crosshead_status()["moving"], timeout=WAIT_MS)
    qtbot.waitUntil(lambda: w.start_button.isEnabled() and w.last_readout.position_mm < 1.0, timeout=WAIT_MS)
    w.last_result = None
    click(qtbot, w.start_button)
    text, style = status(w)
    assert "started" in text and style == "", (text, style)       # the red e-stop is gone at once
    qtbot.waitUntil(lambda: w.last_result is not None, timeout=RUN_TIMEOUT_MS)
    assert w.last_result.status == "finished", w.last_result.reason
    # The e-stop is history: the line is this run's end (amber, not red, if a busy computer
    # made the simulated machine miss samples: that is reported too, see the next test).
    text, style = status(w)
    assert text.startswith("Run finished") and style != ERROR_STYLE, (text, style)
    assert w.run_status.text().startswith("Run finished") and w.run_status.styleSheet() != ERROR_STYLE


def test_a_reset_is_sent_after_an_estop_clicked_before_it(qtbot, win):
    """ci 63: the run's e-stop waited for the link's lock until after the operator's reset, and
    stopped the drive the reset had just freed."""
    w = win
    conn = connect(qtbot, w)
    release = threading.Event()

    def late_estop() -> None:      # an e-stop still waiting for the link when Reset is clicked
        release.wait(WAIT_MS / 1000)
        conn.machine.crosshead.emergency_stop()

    w.estop_queue.submit(late_estop)
    click(qtbot, w.reset_button)
    release.set()
    qtbot.waitUntil(lambda: status(w) == ("e-stop reset: the crosshead may move again", ""), timeout=WAIT_MS)
    w.estop_queue.submit(lambda: None).result(WAIT_MS / 1000)     # the late e-stop has been sent
    assert not conn.simulator.crosshead_status()["emergency_stop"]


def test_a_run_with_many_missed_samples_is_flagged_not_just_finished(qtbot, win):
    w = win
    w.show_finished(RunResult(path=None, status="finished", reason="", n_samples=730, missed=270))
    assert "27.0% of the samples missed" in w.run_status.text()
    assert w.run_status.styleSheet() == WARNING_STYLE
    assert w.results.flags.isVisible() and "curves have gaps" in w.results.flags.text()
    assert w.results.report.diagnosis_note == ""     # analysed as `foamlab run` does (pipeline.AfterRun)
    # A clean run is plain "finished".
    w.show_finished(RunResult(path=None, status="finished", reason="", n_samples=1000, missed=2))
    assert w.run_status.text().startswith("Run finished: 1000 samples") and w.run_status.styleSheet() == ""
    assert not w.results.flags.isVisible()


def synthetic_run(path, method: str, specimen: Specimen) -> None:
    """Four 35 mm triangular cycles at 100 mm/min, 16 Hz, a stiffening foam-like force."""
    half = np.linspace(0.0, 35.0, 336, endpoint=False)
    x = np.tile(np.concatenate([half, 35.0 - half]), 4)
    t = np.arange(len(x)) / 16.0
    f = 0.02 * x ** 2 + 2.0 * x
    write_run_file(path, RunData(t, x, f, specimen=specimen, method=method, machine="sim-modbus-tcp",
                                 started_at="2026-01-02T03:04:05+00:00"))


def test_opening_a_past_run_updates_every_panel(qtbot, win, tmp_path):
    w = win
    past = tmp_path / "past.csv"
    synthetic_run(past, "iso3386-1", Specimen("past-7", 50.0, 80.0, 90.0))
    enter_specimen(qtbot, w, "current", 20.0, 100.0, 100.0)
    w.method_combo.setCurrentText("paper-3cycle")
    w.open_file(past)
    qtbot.waitUntil(lambda: w.shown_run is not None, timeout=WAIT_MS)
    form = w.specimen_form
    assert form.label_edit.text() == "past-7"
    assert [form.values()[k] for k in ("height_mm", "width_mm", "depth_mm")] == [50.0, 80.0, 90.0]
    assert w.method_combo.currentText() == "iso3386-1" and "ISO 3386-1" in w.method_info.text()
    rows = dict(w.results.report.run)
    assert rows["specimen"] == "past-7" and rows["method"] == "iso3386-1"
    assert "past-7" in w.run_status.text()
    # Its results, headline first: CV40 in kPa, from the past run's own area (80 x 90 mm).
    assert "CV40" in w.results.headline.text() and "kPa" in w.results.headline.text()
    cv40 = w.results.report.headline_rows()[0]
    force_at_40 = 0.02 * 20.0 ** 2 + 2.0 * 20.0
    assert cv40.name == "CV40" and cv40.value == pytest.approx(force_at_40 / (80 * 90) * 1000, rel=0.02)


def test_start_checks_the_travel_the_method_needs_in_plain_words(qtbot, win):
    w = win
    connect(qtbot, w)
    w.limits_form.fields["travel_lower_mm"].setValue(50.0)
    w.specimen_form.label_edit.setText("tall")
    w.specimen_form.edits["height_mm"].setText("72,5")
    assert not w.start_run()
    message = w.specimen_form.message.text()
    assert "72.5 mm specimen, 80% stroke: needs 58 mm of travel; the lower travel limit (50 mm) allows" \
        in message, message
    assert "start refused" in w.statusBar().currentMessage()
