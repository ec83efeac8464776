"""The window's Series tab (issue 14): the specimen series of the run opened, its statistics the
ones `foamlab series` computes (foamlab.reporting.series), exported as one CSV through the
window's non-modal file chooser. Offscreen; no machine is connected."""

from __future__ import annotations

import csv
import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest
from PySide6 import QtCore, QtWidgets

from foamlab import methods
from foamlab.acquisition import RunResult
from foamlab.gui.report import number
from foamlab.gui.series import Found, SeriesView, column_title
from foamlab.gui.window import MainWindow
from foamlab.importers import load_run
from foamlab.reporting import series_from_runs, specimen_series
from foamlab.rundata import RunData, Specimen
from foamlab.storage.runfile import write_run_file
from tests.gui_support import WAIT_MS, shut_window
from tests.synthetic import triangle_run

pytestmark = [pytest.mark.gui, pytest.mark.timeout(300)]   # hang guards (gui_support.WAIT_MS)

METHOD = "paper-3cycle"          # three cycles to 80 %: 8 mm strokes on a 10 mm block
SERIES_TIMEOUT_MS = 60_000
USER = QtCore.Qt.ItemDataRole.UserRole


def write_specimen(folder, label: str, scale: float, method: str = METHOD, minute: int = 0):
    """One run file: the same triangle run with its force scaled (every energy scales by `scale`)."""
    base, _ = triangle_run(cycles=3, stroke_mm=8.0, speed_mm_min=120.0, rate_hz=16.0, seed=3)
    run = RunData(base.time_s, base.displacement_mm, base.force_N * scale,
                  specimen=Specimen(label, 10.0, 50.0, 50.0), method=method,
                  started_at=f"2026-11-25T10:{minute:02d}:00+00:00")
    return write_run_file(folder / f"{label}.csv", run)


@pytest.fixture
def window(qtbot, tmp_path):
    w = MainWindow(out_dir=tmp_path / "runs")
    w.auto_diagnose_action.setChecked(False)      # the fit of the opened run is enough here
    qtbot.addWidget(w)
    w.show()
    yield w
    shut_window(w)


def texts(table: QtWidgets.QTableWidget, column: int) -> list[str]:
    return [table.item(r, column).text() for r in range(table.rowCount())]


def test_series_tab_shows_the_series_of_the_opened_run_and_exports_it(qtbot, window, tmp_path):
    w = window
    runs = tmp_path / "runs"
    runs.mkdir(exist_ok=True)                     # the window made it for its catalog
    paths = [write_specimen(runs, f"PU45-0{i}", k, minute=i) for i, k in enumerate((1.0, 1.1, 1.3), 1)]
    write_specimen(runs, "PU60-01", 2.0, minute=4)                       # another series
    write_specimen(runs, "PU45-04", 1.5, method="iso3386-1", minute=5)   # another method
    # Opened from the Runs tab, as a technician does.
    w.browser.refresh()
    qtbot.waitUntil(lambda: len(w.browser.rows) == 5, timeout=SERIES_TIMEOUT_MS)
    row = texts(w.browser.table, 1).index("PU45-02")
    w.browser.table.selectRow(row)
    qtbot.mouseClick(w.browser.open_button, QtCore.Qt.MouseButton.LeftButton)
    view = w.series_view
    qtbot.waitUntil(lambda: view.series is not None, timeout=SERIES_TIMEOUT_MS)

    expected = specimen_series(paths)
    shown = view.series
    assert [s.label for s in shown.specimens] == ["PU45-01", "PU45-02", "PU45-03"]
    assert view.title.text().startswith(f"Series PU45: 3 specimens tested with {METHOD}")
    table = view.table
    assert texts(table, 0) == ["PU45-01", "PU45-02", "PU45-03", "n", "mean", "sd", "CV %"]
    assert [table.item(r, 0).font().bold() for r in range(3)] == [False, True, False]   # the run opened
    heads = [table.horizontalHeaderItem(c).text() for c in range(table.columnCount())]
    assert heads[2:-1] == [column_title(c) for c in expected.columns]
    assert "Loading energy, cycle 1 [J]" in heads and "Residual strain, cycle 3 [mm/mm]" in heads
    assert all(note == "" for note in texts(table, len(heads) - 1)[:3])
    for j, st in enumerate(expected.statistics):
        c = 2 + j
        for r, value in ((3, st.n), (4, st.mean), (5, st.sd), (6, st.cv_percent)):
            assert table.item(r, c).data(USER) == pytest.approx(value, rel=1e-12), (st.column.title, r)
        assert table.item(3, c).text() == "3"
        assert table.item(4, c).text() == number(st.mean)
    # Scales 1, 1.1, 1.3: every energy's CV is 13.478 % (worked out by hand in tests/test_report.py).
    energy = heads.index("Loading energy, cycle 1 [J]")
    assert table.item(6, energy).data(USER) == pytest.approx(13.478, abs=1e-3)
    assert table.item(6, energy).text() == "13.48"

    # File > Export series CSV…: Qt's own, non-modal chooser (the e-stop stays at hand).
    before = set(tmp_path.rglob("*.csv"))
    w.series_csv_action.trigger()
    dialog = w.dialog
    assert isinstance(dialog, QtWidgets.QFileDialog) and dialog.isVisible()
    assert not dialog.isModal() and QtWidgets.QApplication.activeModalWidget() is None
    assert set(tmp_path.rglob("*.csv")) == before             # nothing written before a file is chosen
    out = tmp_path / "chosen" / "PU45.csv"
    out.parent.mkdir()
    dialog.selectFile(str(out))
    dialog.accept()
    qtbot.waitUntil(out.exists, timeout=WAIT_MS)
    lines = out.read_text(encoding="utf-8").splitlines()
    assert lines[0].startswith(f"# foamlab specimen series: method {METHOD}")
    assert list(csv.reader(lines[1:])) == expected.rows()
    assert f"series written to {out}" in w.statusBar().currentMessage()
    assert set(tmp_path.rglob("*.csv")) == before | {out}
    # The Series report (PDF)…, given its file, is written on the tab's thread.
    pdf = tmp_path / "chosen" / "PU45.pdf"
    w.write_series_report(pdf)
    qtbot.waitUntil(lambda: "series report written" in w.statusBar().currentMessage(), timeout=SERIES_TIMEOUT_MS)
    assert pdf.read_bytes().startswith(b"%PDF")

    # Another run opened (File > Open): its own series, of one specimen (no sd, no CV).
    w.open_file(runs / "PU60-01.csv")
    qtbot.waitUntil(lambda: view.found is not None and view.found.name == "PU60", timeout=SERIES_TIMEOUT_MS)
    assert texts(view.table, 0) == ["PU60-01", "n", "mean", "sd", "CV %"]
    assert view.table.item(1, energy).text() == "1" and view.table.item(3, energy).text() == "–"

    # A run of the series ends (what the run engine hands the window): the tab shows it with the others.
    done = write_specimen(runs, "PU45-05", 1.2, minute=6)
    w.show_finished(RunResult(done, "finished", "", 433, 0, run=load_run(done)))
    qtbot.waitUntil(lambda: view.found is not None and view.found.name == "PU45", timeout=SERIES_TIMEOUT_MS)
    assert texts(view.table, 0)[:5] == ["PU45-01", "PU45-02", "PU45-03", "PU45-05", "n"]
    assert view.table.item(3, 0).font().bold()
    assert view.table.item(4, energy).text() == "4"


def test_a_specimen_without_results_shows_its_one_line_error(qtbot, tmp_path, monkeypatch):
    good, _ = triangle_run(cycles=3, stroke_mm=8.0, speed_mm_min=120.0, rate_hz=16.0, seed=3)
    good.specimen, good.method = Specimen("F-01", 10.0, 50.0, 50.0), METHOD
    bad = RunData([0.0, 0.1, 0.2], [0.0, 0.5, 1.0], [0.0, 1.0, 2.0],
                  specimen=Specimen("F-02", 10.0, 50.0, 50.0), method=METHOD)
    # The method's results never fail on data (a value that cannot be computed says why): a bug
    # in them is what leaves a specimen without results, as the pipeline reports it.
    real = methods.compute_results

    def buggy(method, run):
        if run is bad:
            raise ValueError("index 7 is out of bounds\nfor axis 0 with size 3")
        return real(method, run)

    monkeypatch.setattr(methods, "compute_results", buggy)
    series = series_from_runs([(tmp_path / "f1.csv", good), (tmp_path / "f2.csv", bad)], METHOD)
    assert "\n" in series.specimens[1].error and not series.specimens[0].error
    view = SeriesView(tmp_path)
    qtbot.addWidget(view)
    view.show_found(Found("F", series, left_out=["f3.csv: no data rows after the header"]))
    note = view.table.item(1, view.table.columnCount() - 1).text()
    assert note == "no results: method results failed: ValueError: index 7 is out of bounds"
    assert "Traceback" not in note and "\n" not in note
    assert view.table.item(1, 2).text() == "–"
    assert texts(view.table, 0)[2:] == ["n", "mean", "sd", "CV %"]
    assert view.table.item(2, 2).text() == "1"                                 # n: F-01's value only
    assert "f3.csv: no data rows" in view.note.text()
    view.queue.shutdown(wait=True)
