"""The results view. For the technician ("Results"): the method's headline results large,
with units; the verdict in one line of plain words; data-quality flags in colour with
their meaning; the run summary and the other results with readable names. For the
engineer ("Expert"): fitted parameters with units, the Table-5 statistics, the
thermodynamic checks with what a failure means, the fit's warnings and notes, and the
diagnosis findings. The data come from foamlab.gui.report.Report.
"""

from __future__ import annotations

import html
from typing import Any

from PySide6 import QtCore, QtWidgets

from foamlab.gui.report import (
    CONSTRAINT_MEANINGS,
    STEP_NAMES,
    Report,
    ResultRow,
    number,
)

__all__ = ["Report", "ResultsPanel"]

GOOD_STYLE = "color: #1B7F3B;"
FLAG_COLOUR = "#9A5B00"
MUTED = "color: #555;"


def _table(headers: list[str], name: str) -> QtWidgets.QTableWidget:
    table = QtWidgets.QTableWidget(0, len(headers))
    table.setObjectName(name)
    table.setHorizontalHeaderLabels(headers)
    table.setEditTriggers(QtWidgets.QAbstractItemView.EditTrigger.NoEditTriggers)
    table.verticalHeader().setVisible(False)
    table.verticalHeader().setDefaultSectionSize(table.fontMetrics().height() + 6)  # compact rows
    table.horizontalHeader().setStretchLastSection(True)
    table.setAlternatingRowColors(True)
    return table


def _fill(table: QtWidgets.QTableWidget, rows: list[tuple[str, ...]], numeric: set[int] = frozenset()) -> None:
    """Rows of ready-formatted text; `numeric` columns are right-aligned."""
    table.setRowCount(len(rows))
    for r, row in enumerate(rows):
        for c, text in enumerate(row):
            item = QtWidgets.QTableWidgetItem(text)
            if c in numeric:
                item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
            table.setItem(r, c, item)
    table.resizeColumnsToContents()


def _label(name: str, wrap: bool = True) -> QtWidgets.QLabel:
    label = QtWidgets.QLabel("")
    label.setObjectName(name)
    label.setWordWrap(wrap)
    label.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
    return label


def _boxed(title: str, widget: QtWidgets.QWidget) -> QtWidgets.QGroupBox:
    box = QtWidgets.QGroupBox(title)
    QtWidgets.QVBoxLayout(box).addWidget(widget)
    return box


def shown_value(row: ResultRow) -> tuple[str, str]:
    """Value and unit as read: a strain (a ratio) in %, 'n/a' with the reason when missing."""
    if row.value is None:
        return "n/a", row.note
    if row.name == "residual_strain" and not row.unit:
        return number(100 * row.value, 3), "%"
    return number(row.value), row.unit


class ResultsPanel(QtWidgets.QTabWidget):
    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.report = Report()
        self.addTab(self._technician_tab(), "Results")
        self.addTab(self._expert_tab(), "Expert")

    # -- construction -------------------------------------------------------------------
    def _technician_tab(self) -> QtWidgets.QWidget:
        page = QtWidgets.QWidget()
        layout = QtWidgets.QVBoxLayout(page)
        self.headline = _label("headline_results")
        self.headline.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.verdict = _label("diagnosis_verdict")
        self.flags = _label("quality_flags")
        self.flags.setTextFormat(QtCore.Qt.TextFormat.RichText)
        self.summary = _label("run_summary")
        self.summary.setStyleSheet(MUTED)
        self.method_results = _table(["result", "cycle", "value", "unit", "what it is"], "method_results")
        for w in (self.headline, self.verdict, self.flags, self.summary):
            layout.addWidget(w)
        layout.addWidget(self.method_results, 1)
        return page

    def _expert_tab(self) -> QtWidgets.QWidget:
        self.parameters = _table(["parameter", "value", "std. error", "rel. error", "unit"], "fit_parameters")
        self.statistics = _table(["step", "SSE [N²]", "R²", "adj. R²", "RMSE [N]"], "fit_statistics")
        self.constraints = _table(["check", "result", "a failure means"], "fit_constraints")
        # The meaning is a sentence: wrapped in the width there is, not cut off.
        self.constraints.setWordWrap(True)
        self.constraints.horizontalHeader().setSectionResizeMode(2, QtWidgets.QHeaderView.ResizeMode.Stretch)
        self.warnings = QtWidgets.QPlainTextEdit()
        self.warnings.setObjectName("fit_warnings")
        self.warnings.setReadOnly(True)
        self.findings = _table(["effect", "found", "RMSE before [N]", "RMSE after [N]", "held-out before",
                                "held-out after", "ΔBIC"], "diagnosis_findings")
        self.forecast = _table(["cycle", "predicted from", "RMSE [N]", "× noise", "mean [N]"], "forecast_scores")
        left = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        left.addWidget(_boxed("Fitted parameters", self.parameters))
        left.addWidget(_boxed("Fit statistics (Table 5)", self.statistics))
        left.addWidget(_boxed("Forecast: each cycle predicted from the earlier ones", self.forecast))
        right = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        right.addWidget(_boxed("Thermodynamic checks (Eqs. 23-25)", self.constraints))
        right.addWidget(_boxed("Fit warnings and notes", self.warnings))
        right.addWidget(_boxed("Diagnosis findings", self.findings))
        page = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        page.addWidget(left)
        page.addWidget(right)
        return page

    # -- content ------------------------------------------------------------------------
    def clear(self) -> None:
        self.show_report(Report())

    def show_report(self, report: Report) -> None:
        self.report = report
        self._show_headline(report)
        self._show_verdict(report)
        self._show_flags(report)
        parts = [f"<b>{html.escape(k)}</b>: {html.escape(v)}" for k, v in report.run]
        if report.fit_note:
            parts.append(f"<b>fit</b>: {html.escape(report.fit_note)}")
        self.summary.setText(" &nbsp;·&nbsp; ".join(parts) or "No run yet.")
        rows = []
        # The headline results lead the table too; then the per-cycle ones in cycle order.
        for r in sorted(report.results, key=lambda r: r.name not in report.headline):
            value, unit = shown_value(r)
            rows.append((r.label, str(r.cycle or ""), value, unit, r.description))
        _fill(self.method_results, rows, numeric={1, 2})
        self._show_expert(report)

    def _show_headline(self, report: Report) -> None:
        cells = []
        for row in report.headline_rows():
            value, unit = shown_value(row)
            where = f", cycle {row.cycle}" if row.cycle and row.name in _PER_CYCLE else ""
            cells.append(f"<div><span style='font-size:24pt; font-weight:bold'>{html.escape(value)} "
                         f"{html.escape(unit) if row.value is not None else ''}</span>"
                         f"<br><span style='font-size:11pt'><b>{html.escape(row.label)}</b>{where}"
                         f"{' — ' + html.escape(row.description) if row.description else ''}</span>"
                         f"{'<br>' + html.escape(row.note) if row.value is None and row.note else ''}</div>")
        self.headline.setText("".join(cells))
        self.headline.setVisible(bool(cells))

    def _show_verdict(self, report: Report) -> None:
        text = html.escape(report.verdict_text())
        self.verdict.setText(f"<b>Diagnosis verdict:</b> {text}" if report.verdict else text)
        self.verdict.setStyleSheet(GOOD_STYLE if report.verdict == "none" else
                                   (f"color: {FLAG_COLOUR};" if report.verdict else ""))

    def _show_flags(self, report: Report) -> None:
        flags = report.all_flags()
        self.flags.setText("<br>".join(f"<span style='color:{FLAG_COLOUR}'><b>⚠ {html.escape(f.name)}</b>: "
                                       f"{html.escape(f.meaning)}</span>" for f in flags))
        self.flags.setVisible(bool(flags))

    def _show_expert(self, report: Report) -> None:
        params = []
        for p in report.parameters:
            rel = f"{abs(p.stderr / p.value):.1%}" if p.stderr is not None and p.value else "–"
            error = number(p.stderr, 2) if p.stderr is not None else ("fixed" if not p.varied else "not determined")
            params.append((p.name, number(p.value), error, rel, p.unit))
        _fill(self.parameters, params, numeric={1, 2, 3})
        stats = [(STEP_NAMES.get(step, step), _opt(sse), _r2(r2), _r2(adj), _opt(rmse))
                 for step, sse, r2, adj, rmse in report.statistics]
        if report.rmse is not None:
            stats.append(("whole run", "", "", "", number(report.rmse)))
        _fill(self.statistics, stats, numeric={1, 2, 3, 4})
        _fill(self.constraints, [(CONSTRAINT_MEANINGS.get(n, (n, ""))[0], "pass" if ok else "FAIL",
                                  "" if ok else CONSTRAINT_MEANINGS.get(n, (n, ""))[1])
                                 for n, ok in report.constraints])
        self.constraints.resizeRowsToContents()
        lines = [f"• {w}" for w in report.fit_warnings] + [f"note: {n}" for n in report.fit_notes]
        self.warnings.setPlainText("\n".join(lines) or "none")
        _fill(self.forecast, [(str(f.cycle), f"cycles 1–{f.from_cycles}", number(f.rmse, 3), number(f.ratio, 2),
                               number(f.bias, 3)) for f in report.forecast], numeric={0, 2, 3, 4})
        _fill(self.findings, [(f.effect, f.description, _opt(f.rmse_before), _opt(f.rmse_after),
                               _opt(f.heldout_before), _opt(f.heldout_after), _opt(f.delta_bic))
                              for f in report.findings], numeric={2, 3, 4, 5, 6})


_PER_CYCLE = {"loading_energy", "unloading_energy", "hysteresis_loss", "residual_strain"}


def _opt(value: Any) -> str:
    return "" if value is None else number(value)


def _r2(value: Any) -> str:
    """R² near 1 needs its decimals: 0.999987, never '1'."""
    return "" if value is None else f"{float(value):.6f}"
