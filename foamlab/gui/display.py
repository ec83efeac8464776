"""The window's Test tab: live curves, progress, the run's status line and the results view.

It shows a run as it grows, a run that ended, or a run read from a file, and analyses a
shown run with foamlab.pipeline on its own analysis thread (method results and the fit
first, then the diagnosis of that fit). Every new thing shown starts a new generation:
analysis results that arrive for an older one are dropped.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any, Callable

import numpy as np
from PySide6 import QtCore, QtWidgets

from foamlab import pipeline
from foamlab.gui.background import BackgroundQueue
from foamlab.gui.plots import LOADING, LivePlots
from foamlab.gui.prediction import LivePrediction
from foamlab.gui.report import Report
from foamlab.gui.results import ResultsPanel
from foamlab.gui.status import end_message, missed_flag
from foamlab.gui.units import UnitsChoice
from foamlab.runformat import is_run_file_path

log = logging.getLogger(__name__)


def clock(seconds: float) -> str:
    seconds = max(0, int(round(seconds)))
    h, rest = divmod(seconds, 3600)
    m, s = divmod(rest, 60)
    return f"{h}:{m:02d}:{s:02d}" if h else f"{m:02d}:{s:02d}"


def run_rows(result) -> list[tuple[str, str]]:
    """The run summary of a foamlab.acquisition.RunResult."""
    rows = [("status", result.status + (f" ({result.reason})" if result.reason else "")),
            ("file", str(result.path) if result.path else "–"),
            ("samples", f"{result.n_samples} ({result.missed} missed)")]
    if result.park:
        rows.append(("crosshead", result.park))
    if getattr(result, "safety", ""):
        rows.append(("safety", "⚠ " + result.safety))
    timing = result.timing
    if timing is not None and timing.samples:
        rows.append(("schedule", f"lateness p50 {timing.lateness_p50_ms:.2f} ms, p99 {timing.lateness_p99_ms:.2f} ms"))
    return rows


class RunDisplay(QtWidgets.QWidget):
    message = QtCore.Signal(str, bool)       # a line for the status bar; True: an error
    catalog_changed = QtCore.Signal()        # a diagnosis was stored beside its run

    def __init__(self, auto_diagnose: Callable[[], bool], out_dir: Path,
                 parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self._auto_diagnose = auto_diagnose
        self.out_dir = out_dir                 # the catalog the analysed runs are indexed in
        self.analysis = BackgroundQueue("foamlab-analysis", self)
        self.generation = 0
        self.shown_run = None                  # RunData on display (finished run or opened file)
        self.shown_analysis: pipeline.Analysis | None = None   # its pipeline results so far
        self.plots = LivePlots()
        self.units_choice = UnitsChoice()
        self.units_choice.changed.connect(self.plots.set_units)
        self.live = LivePrediction(self.plots, self)
        self.units_choice.changed.connect(self.live.view.set_units)
        self.live.message.connect(self._say)
        self.live.scores_ready.connect(self._show_forecast)
        self._ended: tuple[int, pipeline.Analysis, Report] | None = None   # the last run's, for its scores
        self._run_on_display = False           # live, ended or opened: its specimen sets the axes
        self.progress = QtWidgets.QProgressBar()
        self.progress.setObjectName("run_progress")
        self.progress.setRange(0, 1000)
        self.progress.setFormat("No run")
        self.progress.setTextVisible(True)
        self.run_status = QtWidgets.QLabel("")
        self.run_status.setObjectName("run_status")
        self.run_status.setWordWrap(True)
        self.results = ResultsPanel()
        top = QtWidgets.QWidget()
        top_layout = QtWidgets.QVBoxLayout(top)
        top_layout.setContentsMargins(0, 0, 0, 0)
        axes_row = QtWidgets.QHBoxLayout()
        axes_row.addWidget(QtWidgets.QLabel("Axes:"))
        axes_row.addWidget(self.units_choice)
        axes_row.addStretch(1)
        top_layout.addLayout(axes_row)
        top_layout.addWidget(self.plots, 1)
        top_layout.addWidget(self.progress)
        top_layout.addWidget(self.run_status)
        top_layout.addWidget(self.live.status)
        splitter = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        splitter.addWidget(top)
        splitter.addWidget(self.results)
        splitter.setStretchFactor(0, 1)
        splitter.setStretchFactor(1, 1)
        splitter.setSizes([470, 430])
        QtWidgets.QVBoxLayout(self).addWidget(splitter)

    def _say(self, text: str, error: bool = False) -> None:
        self.message.emit(text, error)

    # -- the axes ------------------------------------------------------------------------
    def preview_specimen(self, specimen) -> None:
        """The specimen entered, before any run is shown: stress–strain can be chosen for the
        first run. Once a run is shown its own specimen decides (it is not what is typed next)."""
        if not self._run_on_display:
            self.units_choice.set_specimen(specimen)

    def _show_specimen(self, specimen) -> None:
        self._run_on_display = True
        self.units_choice.set_specimen(specimen)

    # -- a run as it goes ---------------------------------------------------------------
    def begin_run(self, title: str, n_cycles: int, expected_samples: int, specimen=None) -> None:
        self.generation += 1                   # results of an earlier file/analysis no longer apply
        self.shown_run = None
        self.shown_analysis = None
        self._show_specimen(specimen)
        self.plots.clear(expected_samples=expected_samples)
        self.results.clear()
        self.progress.setValue(0)
        self.progress.setFormat(f"Cycle 0/{n_cycles} — %p% — starting")
        self.run_status.setText(f"{title}: starting…")
        self.run_status.setStyleSheet("")

    def predict(self, engine, method, on: bool) -> None:
        """The live prediction of the run about to start (before engine.start())."""
        if on:
            self.live.begin(engine, method, self.generation)
        else:
            self.live.off()

    def add_samples(self, samples: list, phase_of_step: dict[int, str]) -> None:
        n = len(samples)
        t = np.fromiter((s.time_s for s in samples), float, n)
        d = np.fromiter((s.displacement_mm for s in samples), float, n)
        f = np.fromiter((s.force_N for s in samples), float, n)
        phases = [phase_of_step.get(s.step, LOADING) for s in samples]
        self.plots.add_samples(t, d, f, [s.cycle for s in samples], phases)

    def show_progress(self, progress) -> None:
        self.progress.setValue(int(round(progress.fraction * 1000)))
        cycle = max(progress.cycle, 0)
        self.progress.setFormat(f"Cycle {cycle}/{progress.n_cycles} — %p% — {clock(progress.time_left_s)} left")

    # -- a run that ended ---------------------------------------------------------------
    def show_result(self, result, headline: list[str]) -> tuple[str, str]:
        """A foamlab.acquisition.RunResult: curves, status line; then the pipeline's method
        results and fit, then its diagnosis. Returns the run's last word and its style."""
        self.plots.refresh()
        ok = result.status == "finished"
        if ok:
            self.progress.setValue(1000)
            self.progress.setFormat("Finished — %p%")
        else:
            self.progress.setFormat(f"Aborted — %p% — {result.reason}")
        where = str(result.path) if result.path else "nothing recorded (ended before contact)"
        text, style = end_message(result.status, result.reason, result.n_samples, result.missed, where)
        self.run_status.setText(text)
        self.run_status.setStyleSheet(style)
        plan = pipeline.AfterRun.of(result)
        report = Report()
        report.run = run_rows(result)
        if plan.gaps:
            report.flags.append(missed_flag(result.n_samples, result.missed))
        report.fit_note = "fitting…" if plan.fit else plan.fit_note
        for departure in self.live.departures:
            report.add_departure(departure)
        self.shown_run, self.shown_analysis = result.run, None
        self.results.show_report(report)
        self.live.end()
        if result.run is not None:
            analysis = pipeline.Analysis(result.run, result.path)
            self._ended = (self.generation, analysis, report)
            self._analyse(analysis, report, self.generation, headline, fit=plan.fit)
        return text.split(" Data:")[0], style

    def _show_forecast(self, scores, generation: int) -> None:
        """The live prediction's forecast scores, once the worker has made the last one."""
        if self._ended is None or self._ended[0] != generation or generation != self.generation:
            return
        _, analysis, report = self._ended
        analysis.forecast = scores
        report.set_forecast(scores)
        for departure in self.live.departures:        # found by a forecast that came after the run
            report.add_departure(departure)
        self.results.show_report(report)

    # -- a run from a file --------------------------------------------------------------
    def open(self, path: Path, on_shown: Callable[[Any], None]) -> None:
        """Read `path` on the analysis thread, show it, then fit it; `on_shown(run)` once shown."""
        self.generation += 1
        generation = self.generation
        self._say(f"opening {path}…")
        from foamlab.gui.analysis import load_for_display

        def loaded(value) -> None:
            if generation == self.generation:
                self._show_loaded(value, generation)
                on_shown(value.run)

        self.analysis.submit(lambda: load_for_display(path), loaded,
                             lambda msg: self._say(f"cannot open {path.name}: {msg}", True))

    def _show_loaded(self, loaded, generation: int) -> None:
        run = loaded.run
        self.shown_run, self.shown_analysis = run, None
        self.live.reset()
        self._show_specimen(run.specimen)
        self.plots.show_run(run.time_s, run.displacement_mm, run.force_N, loaded.cycles, loaded.phases)
        self.progress.setValue(0)
        self.progress.setFormat(f"{Path(run.source).name if run.source else 'file'}: {len(run)} samples")
        self.run_status.setText(loaded.describe())
        self.run_status.setStyleSheet("")
        report = Report()
        report.run = loaded.rows()
        if loaded.method_results is not None:
            report.set_method_results(loaded.method_results, loaded.headline)
        report.fit_note = "fitting…"
        if loaded.stored_diagnosis:
            report.set_diagnosis(loaded.stored_diagnosis)
            report.diagnosis_note = "stored with the run"
        self.results.show_report(report)
        self._analyse(loaded.analysis, report, generation, loaded.headline, stored=loaded.stored_diagnosis)

    # -- analysis (foamlab.pipeline) -------------------------------------------------------
    def _analyse(self, analysis: pipeline.Analysis, report: Report, generation: int, headline: list[str],
                 fit: bool = True, stored: dict | None = None) -> None:
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
            if generation != self.generation:
                return
            self.shown_analysis = a
            if a.method_results is not None:
                report.set_method_results(a.method_results, headline)
            if a.fit is not None:
                report.fit_note = ""
                report.set_fit(a.fit)
                self._overlay_fit(a.fit)
            elif fit:
                report.fit_note = a.fit_error
            self.results.show_report(report)
            self.catalog_changed.emit()
            if a.fit is not None:
                self._maybe_diagnose(a, report, generation, stored)

        def failed(message: str) -> None:
            if generation == self.generation:
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
        elif self._auto_diagnose():
            self._start_diagnosis(analysis, report, generation)
        else:
            report.diagnosis_note = "not run (Analysis > Diagnose the shown run)"
            self.results.show_report(report)

    def diagnose_shown(self) -> str:
        """Diagnose the run on display; '' once started, else why not."""
        if self.shown_run is not None and self.shown_analysis is None:
            return "the fit is still being made: the diagnosis extends it, try again when it shows"
        if self.shown_analysis is None or not len(self.shown_analysis.run):
            return "no run to diagnose: finish a run or open a file first"
        self._start_diagnosis(self.shown_analysis, self.results.report, self.generation)
        return ""

    def _start_diagnosis(self, analysis: pipeline.Analysis, report: Report, generation: int) -> None:
        """The pipeline's diagnosis stage (it extends the run's fit), its file and catalog entry."""
        report.diagnosis_note = "running…"
        self.results.show_report(report)
        folder = self.out_dir

        def work() -> pipeline.Analysis:
            pipeline.diagnose_stage(analysis)
            return pipeline.catalog_stage(pipeline.files_stage(analysis), folder)

        def done(a: pipeline.Analysis) -> None:
            if generation != self.generation:
                return
            if a.diagnosis is not None:
                report.set_diagnosis(a.diagnosis)
                report.diagnosis_note = ""
            else:
                report.diagnosis_note = f"failed: {a.diagnosis_error}"
            self.results.show_report(report)
            self.catalog_changed.emit()      # the verdict is in the catalog now

        def failed(message: str) -> None:
            if generation == self.generation:
                report.diagnosis_note = f"failed: {message}"
                self.results.show_report(report)

        self.analysis.submit(work, done, failed)

    # -- export ---------------------------------------------------------------------------
    def report_path(self) -> Path:
        """Where the shown run's PDF report goes by default (foamlab.reporting's rule)."""
        from foamlab.reporting import default_report_path  # noqa: PLC0415

        a = self.shown_analysis
        path = a.path if a is not None else None
        if path is None:
            return self.out_dir / "report.pdf"
        return default_report_path(path, is_run_file_path(path))

    def write_report(self, out: Path) -> None:
        """The shown run's test report (foamlab.reporting) on the analysis thread, with what the
        window found (its fit, its diagnosis when done, the live prediction's scores)."""
        a = self.shown_analysis
        if a is None or a.path is None:
            self._say("the fit is still being made (or the run has no file): write the report when it shows", True)
            return
        from foamlab.reporting import write_report  # noqa: PLC0415

        self._say(f"writing the report {out.name}…")
        self.analysis.submit(lambda: write_report(a.path, out, analysis=a, diagnose=a.diagnosis is not None),
                             lambda written: self._say(f"report written to {written}"),
                             lambda msg: self._say(f"report failed: {msg}", True))


    def export_png(self, path: Path) -> Path | None:
        try:
            self.plots.export_png(str(path))
        except Exception as exc:
            self._say(f"export failed: {exc}", True)
            return None
        self._say(f"plot written to {path}")
        return path

    def export_csv(self, path: Path) -> Path | None:
        try:
            self.results.report.write_csv(str(path))
        except OSError as exc:
            self._say(f"export failed: {exc}", True)
            return None
        self._say(f"results written to {path}")
        return path
