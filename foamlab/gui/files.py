"""The window's file actions: open a run, export the plot, results and series, write reports.

A mixin of foamlab.gui.window.MainWindow, kept apart so the window class holds the machine
and the run; each action asks for a path with a non-modal dialog when none is given and
checks first that there is something to write (a one-line status otherwise).
"""

from __future__ import annotations

from pathlib import Path

from foamlab.gui.dialogs import choose_file


class FileActions:
    """Needs from the window: running, shown_run, out_dir, display, results, series_view,
    controls, tabs, last_result, _status and _show_dialog."""

    def open_file(self, path: str | Path | None = None) -> None:
        """Show a run from a file (any supported format): curves, then fit, then diagnosis."""
        if self.running:
            self._status("a run is going: open files after it ends", error=True)
            return
        if path is None:
            self._show_dialog(choose_file(self, "Open measured data", self.out_dir,
                                          "Measured data (*.csv *.txt *.tsv);;All files (*)", self.open_file))
            return
        self.display.open(Path(path), lambda run, path=Path(path): self._on_opened(run, path))

    def _on_opened(self, run, path: Path) -> None:
        self.last_result = None
        self.tabs.setCurrentIndex(0)
        self.controls.show_run_inputs(run)
        self.series_view.show_series_of(path, run)
        self._status(f"opened {run.source}")

    def export_png(self, path: str | Path | None = None) -> Path | None:
        if path is None:
            self._show_dialog(choose_file(self, "Export plot", self.out_dir / "plot.png", "PNG image (*.png)",
                                          self.export_png, save=True))
            return None
        return self.display.export_png(Path(path))

    def write_report(self, path: str | Path | None = None) -> None:
        """The shown run's test report as a PDF (foamlab.reporting), written in the background."""
        if self.running or self.shown_run is None:
            self._status("no run to report: finish a run or open a file first", error=True)
            return
        if path is None:
            self._show_dialog(choose_file(self, "Write test report", self.display.report_path(),
                                          "PDF (*.pdf)", self.write_report, save=True))
            return
        self.display.write_report(Path(path))

    def export_csv(self, path: str | Path | None = None) -> Path | None:
        if not self.results.report.run:
            self._status("nothing to export yet: run a test or open a file", error=True)
            return None
        if path is None:
            self._show_dialog(choose_file(self, "Export results", self.out_dir / "results.csv", "CSV (*.csv)",
                                          self.export_csv, save=True))
            return None
        return self.display.export_csv(Path(path))

    def export_series_csv(self, path: str | Path | None = None) -> Path | None:
        """The Series tab's series as one CSV (foamlab.reporting.series), where the operator chooses."""
        if self.series_view.series is None:
            self._status("no series to export: finish a run or open one first", error=True)
            return None
        if path is None:
            self._show_dialog(choose_file(self, "Export series", self.series_view.default_path(".csv"),
                                          "CSV (*.csv)", self.export_series_csv, save=True))
            return None
        return self.series_view.export_csv(Path(path))

    def write_series_report(self, path: str | Path | None = None) -> None:
        """The Series tab's series as a PDF (foamlab.reporting.write_series_report), in the background."""
        if self.running or self.series_view.series is None:
            self._status("a run is going: write the series report after it ends" if self.running else
                         "no series to report: finish a run or open one first", error=True)
            return
        if path is None:
            self._show_dialog(choose_file(self, "Write series report", self.series_view.default_path(".pdf"),
                                          "PDF (*.pdf)", self.write_series_report, save=True))
            return
        self.series_view.write_report(Path(path))
