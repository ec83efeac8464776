"""Issue 18, item 3's stress/strain axes: force–displacement converted to stress [kPa] and
strain [%] of the specimen in the live plots, a past run, the fit overlay and the export;
offered only when the specimen's area and height are known. Offscreen, no machine."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np
import pytest
from test_gui_status import synthetic_run

from foamlab.acquisition import Sample
from foamlab.gui.display import RunDisplay
from foamlab.gui.plots import LOADING
from foamlab.gui.window import MainWindow
from foamlab.rundata import RunData, Specimen
from foamlab.storage.runfile import write_run_file
from tests.gui_support import WAIT_MS

pytestmark = [pytest.mark.gui, pytest.mark.timeout(300)]   # hang guards (gui_support.WAIT_MS)

PAPER_BLOCK = Specimen("paper-block", 72.5, 100.0, 100.0)     # 10 000 mm², 72.5 mm high
# 7.25 mm into the 72.5 mm block is 10 % strain; 50 N on 100 x 100 mm is 5 kPa.
SAMPLE_MM, SAMPLE_N, STRAIN_PCT, STRESS_KPA = 7.25, 50.0, 10.0, 5.0


def sample(i: int, d_mm: float, f_N: float) -> Sample:
    return Sample(index=i, time_s=i / 16, displacement_mm=d_mm, force_N=f_N, rtt_ms=1.0, lateness_ms=0.0,
                  position_mm=d_mm, cycle=1, step=0)


def drawn(curve) -> tuple[np.ndarray, np.ndarray]:
    x, y = curve.getData()
    return np.asarray(x), np.asarray(y)


@pytest.fixture
def display(qtbot, tmp_path):
    d = RunDisplay(lambda: False, tmp_path)
    qtbot.addWidget(d)
    d.resize(1000, 800)
    d.show()
    yield d
    d.analysis.shutdown(wait=True)


def test_live_samples_are_shown_as_stress_and_strain_of_the_specimen(qtbot, display, tmp_path):
    d = display
    d.begin_run("Run of paper-3cycle on paper-block", 3, 100, PAPER_BLOCK)
    assert d.units_choice.isEnabled()
    d.add_samples([sample(0, 0.0, 0.0), sample(1, SAMPLE_MM, SAMPLE_N)], {0: LOADING})
    d.plots.refresh()
    x, y = drawn(d.plots.segments[0].curve)
    np.testing.assert_allclose([x[-1], y[-1]], [SAMPLE_MM, SAMPLE_N])       # as measured by default
    d.units_choice.setCurrentIndex(1)
    d.units_choice.activated.emit(1)                                          # the operator's pick
    x, y = drawn(d.plots.segments[0].curve)
    np.testing.assert_allclose([x[-1], y[-1]], [STRAIN_PCT, STRESS_KPA])
    np.testing.assert_allclose(drawn(d.plots.ft_curve)[1], [0.0, STRESS_KPA])  # force–time's force axis
    bottom, left = d.plots.fd_plot.getAxis("bottom"), d.plots.fd_plot.getAxis("left")
    assert (bottom.labelText, bottom.labelUnits, left.labelText, left.labelUnits) == ("Strain", "%", "Stress", "kPa")
    assert d.plots.ft_plot.getAxis("left").labelUnits == "kPa"
    # Samples that arrive later are converted too; the fit overlay as well.
    d.add_samples([sample(2, 2 * SAMPLE_MM, 2 * SAMPLE_N)], {0: LOADING})
    d.plots.refresh()
    x, y = drawn(d.plots.segments[0].curve)
    np.testing.assert_allclose([x[-1], y[-1]], [2 * STRAIN_PCT, 2 * STRESS_KPA])
    d.plots.show_fit([0.0, 1.0], [0.0, SAMPLE_MM], [0.0, SAMPLE_N])
    np.testing.assert_allclose(drawn(d.plots.fit_fd)[0], [0.0, STRAIN_PCT])
    np.testing.assert_allclose(drawn(d.plots.fit_fd)[1], [0.0, STRESS_KPA])
    np.testing.assert_allclose(drawn(d.plots.fit_ft)[1], [0.0, STRESS_KPA])
    # The exported image is the plots as shown: it differs from the force–displacement one.
    stress_png, force_png = tmp_path / "stress.png", tmp_path / "force.png"
    d.plots.export_png(str(stress_png), width=800)
    d.units_choice.setCurrentIndex(0)
    d.units_choice.activated.emit(0)
    np.testing.assert_allclose(drawn(d.plots.fit_fd)[1], [0.0, SAMPLE_N])     # back to N, mm
    assert d.plots.fd_plot.getAxis("left").labelUnits == "N"
    d.plots.export_png(str(force_png), width=800)
    assert stress_png.read_bytes()[:4] == b"\x89PNG" and stress_png.read_bytes() != force_png.read_bytes()


def test_unknown_area_or_height_disables_stress_strain_and_says_why(qtbot, display):
    d = display
    d.begin_run("Run", 3, 100, PAPER_BLOCK)
    d.units_choice.setCurrentIndex(1)
    d.units_choice.activated.emit(1)
    d.begin_run("Run", 3, 100, Specimen("no-size", 72.5, None, 100.0))
    assert not d.units_choice.isEnabled()
    assert d.units_choice.currentIndex() == 0 and d.plots.units.y_unit == "N"
    assert "width is not known" in d.units_choice.toolTip()
    d.begin_run("Run", 3, 100, Specimen("no-height", None, 100.0, 100.0))
    assert not d.units_choice.isEnabled() and "height is not known" in d.units_choice.toolTip()
    # The operator's choice comes back with the next specimen whose size is known.
    d.begin_run("Run", 3, 100, PAPER_BLOCK)
    assert d.units_choice.isEnabled() and d.plots.units.y_unit == "kPa"


@pytest.fixture
def win(qtbot, tmp_path):
    w = MainWindow(out_dir=tmp_path / "runs", auto_diagnose=False)
    qtbot.addWidget(w)
    w.show()
    yield w
    w.close_dialog()
    w.link.shutdown()
    w.analysis.shutdown(wait=True)
    w.estop_queue.shutdown(wait=True)


def test_a_past_run_is_shown_in_stress_and_strain_of_its_own_specimen(qtbot, win, tmp_path):
    w = win
    choice = w.display.units_choice
    # Before any run: the specimen entered decides (the form's default is the paper's block).
    assert choice.isEnabled()
    w.specimen_form.edits["depth_mm"].setText("")
    assert not choice.isEnabled() and "depth is not known" in choice.toolTip()
    w.specimen_form.edits["depth_mm"].setText("100")
    choice.setCurrentIndex(1)
    choice.activated.emit(1)

    past = tmp_path / "past.csv"
    synthetic_run(past, "paper-3cycle", PAPER_BLOCK)
    w.open_file(past)
    qtbot.waitUntil(lambda: w.shown_run is not None, timeout=WAIT_MS)
    run = w.shown_run
    assert choice.isEnabled() and w.plots.units.y_unit == "kPa"
    x = np.concatenate([drawn(s.curve)[0] for s in w.plots.segments])
    y = np.concatenate([drawn(s.curve)[1] for s in w.plots.segments])
    assert x.max() == pytest.approx(run.displacement_mm.max() / 72.5 * 100)      # 35 mm: 48.3 %
    assert y.max() == pytest.approx(run.force_N.max() / 10_000 * 1000)
    # The fit overlay arrives in the same units.
    qtbot.waitUntil(lambda: w.plots.fit_fd is not None, timeout=60_000)
    fit = w.shown_analysis.fit
    np.testing.assert_allclose(drawn(w.plots.fit_fd)[1], np.asarray(fit.predicted_force_N) / 10.0)

    # A run whose area is not recorded: force–displacement only, and why.
    bare = tmp_path / "bare.csv"
    t = np.arange(200) / 16.0
    x_mm = np.concatenate([np.linspace(0, 10, 100), np.linspace(10, 0, 100)])
    write_run_file(bare, RunData(t, x_mm, 3 * x_mm, specimen=Specimen("bare", 50.0)))
    w.open_file(bare)
    qtbot.waitUntil(lambda: w.shown_run is not None and w.shown_run.specimen.label == "bare", timeout=WAIT_MS)
    assert not choice.isEnabled() and w.plots.units.y_unit == "N"
    assert "width and depth are not known" in choice.toolTip()
    x, y = drawn(w.plots.segments[0].curve)
    assert x.max() == pytest.approx(10.0, abs=0.2) and y.max() == pytest.approx(30.0, abs=0.6)
