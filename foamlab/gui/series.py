"""The window's Series tab: the specimen series of the shown run, as Bluehill and testXpert keep one.

A run's series is the runs of the window's data folder (its run catalog) tested with the same
method and of the same series name (foamlab.reporting.series.series_name: the specimen label
without its run number, "PU45-03" -> "PU45"). Each specimen's method results and the series'
n / mean / sd / CV per result come from foamlab.reporting.series (what `foamlab series` prints
and its CSV holds); they are computed on the tab's own background thread, never in the GUI's.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from PySide6 import QtCore, QtGui, QtWidgets

from foamlab import FoamlabError
from foamlab.gui.background import BackgroundQueue, describe_error
from foamlab.gui.report import number
from foamlab.reporting.series import (
    SpecimenSeries,
    series_from_runs,
    series_name,
    unit_text,
)

#: The statistics rows under the specimens: (title, Statistic attribute, what it is).
STATISTICS = (("n", "n", "specimens with a value"),
              ("mean", "mean", "mean of the specimens' values"),
              ("sd", "sd", "sample standard deviation (n - 1)"),
              ("CV %", "cv_percent", "coefficient of variation: sd / |mean| × 100"))


@dataclass
class Found:
    """The series of one run: its name, its specimens and the files that could not be read."""

    name: str
    series: SpecimenSeries
    left_out: list[str] = field(default_factory=list)    # "file.csv: why", one line each


def series_files(out_dir: Path, path: Path, label: str, method: str) -> list[Path]:
    """The run files of the series of the run in `path` (specimen `label`, tested with `method`),
    oldest first: the runs in `out_dir`'s catalog with that method and series name, and `path`."""
    from foamlab.gui.browser import catalog_rows

    name = series_name(label, path)
    members: dict[Path, Path] = {}
    for row in reversed(catalog_rows(out_dir)):          # the catalog lists the newest first
        p = Path(row["file"])
        if row["method"] == method and series_name(row["specimen"], p) == name and p.is_file():
            members.setdefault(p.resolve(), p)
    members.setdefault(path.resolve(), path)              # an opened file from another folder
    return list(members.values())


def find_series(out_dir: Path, path: Path, label: str, method: str) -> Found:
    """The series of the run in `path` with every specimen's results and the statistics
    (called on a background thread: it reads every file of the series and computes its results)."""
    from foamlab.importers import load_run

    if not method:
        raise FoamlabError(f"{path.name} records no test method: a series is specimens of one method")
    runs, left_out = [], []
    for p in series_files(out_dir, path, label, method):
        try:
            runs.append((p, load_run(p)))
        except Exception as exc:  # noqa: BLE001 (an importer bug costs this file, not the series)
            left_out.append(f"{p.name}: {describe_error(exc)}")
    # the runs' own method (all of this name): a method file that is not built in is found by the
    # file recorded with the runs (foamlab.methods.method_of_run), not by the name
    return Found(series_name(label, path), series_from_runs(runs), left_out)


def column_title(column) -> str:
    """A result's column heading: its readable name and unit, e.g. "Loading energy, cycle 1 [J]"."""
    return f"{column.title} [{unit_text(column.unit)}]"


def safe_file_name(text: str) -> str:
    return re.sub(r"[^\w.\-]+", "_", text).strip("._") or "series"


class SeriesView(QtWidgets.QWidget):
    message = QtCore.Signal(str, bool)       # a line for the status bar; True: an error
    updated = QtCore.Signal()                # a series (or why there is none) is shown

    def __init__(self, out_dir: Path, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.out_dir = Path(out_dir)
        self.queue = BackgroundQueue("foamlab-series", self)
        self.generation = 0
        self.found: Found | None = None
        self.current: Path | None = None          # the shown run's file
        layout = QtWidgets.QVBoxLayout(self)
        bar = QtWidgets.QHBoxLayout()
        self.title = QtWidgets.QLabel("No series yet: finish a run or open one.")
        self.title.setObjectName("series_title")
        self.title.setWordWrap(True)
        self.csv_button = QtWidgets.QPushButton("Export series CSV…")
        self.pdf_button = QtWidgets.QPushButton("Series report (PDF)…")
        bar.addWidget(self.title, 1)
        bar.addWidget(self.csv_button)
        bar.addWidget(self.pdf_button)
        layout.addLayout(bar)
        self.table = QtWidgets.QTableWidget(0, 0)
        self.table.setObjectName("series_table")
        self.table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
        self.table.verticalHeader().setVisible(False)
        self.table.verticalHeader().setDefaultSectionSize(self.table.fontMetrics().height() + 6)  # compact rows
        self.table.setAlternatingRowColors(True)
        layout.addWidget(self.table, 1)
        self.note = QtWidgets.QLabel("")
        self.note.setObjectName("series_note")
        self.note.setWordWrap(True)
        layout.addWidget(self.note)
        self._enable()

    @property
    def series(self) -> SpecimenSeries | None:
        return self.found.series if self.found is not None else None

    def _enable(self) -> None:
        for button in (self.csv_button, self.pdf_button):
            button.setEnabled(self.found is not None)

    # -- finding the series ------------------------------------------------------------------
    def show_series_of(self, path: str | Path, run) -> None:
        """Find and show the series of the run read from `path` (in the background)."""
        self.generation += 1
        generation = self.generation
        path = Path(path)
        self.current = path
        self.found = None
        self._enable()
        label, method, out_dir = run.specimen.label, run.method, self.out_dir
        self.title.setText(f"Reading the series of {label or path.name}…")

        def done(found: Found) -> None:
            if generation == self.generation:
                self.show_found(found)

        def failed(message: str) -> None:
            if generation == self.generation:
                self.show_none(f"No series for {path.name}: {message}")

        self.queue.submit(lambda: find_series(out_dir, path, label, method), done, failed)

    def show_none(self, why: str) -> None:
        self.found = None
        self._enable()
        self.title.setText(why)
        self.table.clear()
        self.table.setRowCount(0)
        self.table.setColumnCount(0)
        self.note.setText("")
        self.updated.emit()

    # -- the table ---------------------------------------------------------------------------
    def show_found(self, found: Found) -> None:
        self.found = found
        self._enable()
        s = found.series
        self.title.setText(f"Series {found.name}: {len(s)} specimen{'s' if len(s) != 1 else ''} tested with "
                           f"{s.method.name} ({s.method.title})")
        heads = ["Specimen", "File"] + [column_title(c) for c in s.columns] + ["Note"]
        self.table.clear()
        self.table.setColumnCount(len(heads))
        self.table.setHorizontalHeaderLabels(heads)
        self.table.setRowCount(len(s.specimens) + len(STATISTICS))
        for r, sp in enumerate(s.specimens):
            error = sp.error.splitlines()[0] if sp.error else ""
            note = f"no results: {error}" if error else ("" if sp.results else "no results")
            self._row(r, sp.label, sp.path.name, [sp.value(c) for c in s.columns], note,
                      bold=self.current is not None and sp.path.resolve() == self.current.resolve())
        for i, (title, attr, meaning) in enumerate(STATISTICS):
            r = len(s.specimens) + i
            self._row(r, title, "", [getattr(st, attr) for st in s.statistics], "", tooltip=meaning)
        self.table.resizeColumnsToContents()
        self.note.setText("Left out (cannot be read): " + "; ".join(found.left_out) if found.left_out else
                          "sd: sample standard deviation (n - 1); CV: sd / |mean|. "
                          "Series: the runs in the data folder with this method and specimen name.")
        self.updated.emit()

    def _row(self, r: int, first: str, file: str, values: list, note: str, bold: bool = False,
             tooltip: str = "") -> None:
        cells = [first, file] + [("–" if v is None else (str(v) if isinstance(v, int) else number(v)))
                                 for v in values] + [note]
        for c, text in enumerate(cells):
            item = QtWidgets.QTableWidgetItem(text)
            if 2 <= c < 2 + len(values):
                item.setData(QtCore.Qt.ItemDataRole.UserRole, values[c - 2])    # the value, unrounded
                item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
            if bold:
                font = QtGui.QFont(item.font())
                font.setBold(True)
                item.setFont(font)
            if tooltip:
                item.setToolTip(tooltip)
            self.table.setItem(r, c, item)

    # -- export ------------------------------------------------------------------------------
    def default_path(self, suffix: str) -> Path:
        """Where an export is offered by default: the data folder, named after the series and method."""
        f = self.found
        name = f"{f.name}_{f.series.method.name}_series" if f is not None else "series"
        return self.out_dir / f"{safe_file_name(name)}{suffix}"

    def export_csv(self, out: Path) -> Path | None:
        """The shown series as CSV (SpecimenSeries.write_csv: one row per specimen, then n/mean/sd/cv)."""
        if self.series is None:
            self.message.emit("no series to export: finish a run or open one first", True)
            return None
        try:
            written = self.series.write_csv(out)
        except FoamlabError as exc:
            self.message.emit(f"series export failed: {exc}", True)
            return None
        self.message.emit(f"series written to {written}", False)
        return written

    def write_report(self, out: Path) -> None:
        """The shown series' PDF (foamlab.reporting.write_series_report) on the tab's thread."""
        series = self.series
        if series is None:
            self.message.emit("no series to report: finish a run or open one first", True)
            return
        from foamlab.reporting import write_series_report

        self.message.emit(f"writing the series report {out.name}…", False)
        self.queue.submit(lambda: write_series_report(series, out),
                          lambda written: self.message.emit(f"series report written to {written}", False),
                          lambda msg: self.message.emit(f"series report failed: {msg}", True))
