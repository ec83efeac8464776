"""What the window shows after a run: run summary, fitted parameters with standard
errors, Table-5 statistics, the method's results and the diagnosis; CSV export.

Fit and diagnosis results are read through their JSON form (the contract of
`foamlab fit --json` / `foamlab diagnose --json` in docs/DESIGN), so the window does
not depend on their classes' internals.
"""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from typing import Any

from PySide6 import QtCore, QtWidgets


def as_dict(obj: Any) -> dict | None:
    """The JSON-shaped dict of a result object (to_dict(), to_json(), or a dict already)."""
    if obj is None:
        return None
    if isinstance(obj, dict):
        return obj
    for name in ("to_dict", "as_dict"):
        fn = getattr(obj, name, None)
        if callable(fn):
            value = fn()
            if isinstance(value, dict):
                return value
    fn = getattr(obj, "to_json", None)
    if callable(fn):
        value = fn()
        return json.loads(value) if isinstance(value, str) else value
    return None


def fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return "–"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, (int, float)):
        v = float(value)
        if math.isnan(v):
            return "n/a"
        return f"{v:.{digits}g}"
    return str(value)


@dataclass
class Report:
    """Everything shown in the results tab, as plain rows (also what the CSV holds)."""

    run: list[tuple[str, str]] = field(default_factory=list)
    parameters: list[tuple[str, Any, Any]] = field(default_factory=list)        # name, value, stderr
    statistics: list[tuple[str, Any, Any, Any, Any]] = field(default_factory=list)  # step, sse, r2, adj_r2, rmse
    constraints: list[tuple[str, bool]] = field(default_factory=list)
    method_results: list[tuple[str, Any, Any, str, str]] = field(default_factory=list)  # name, cycle, value, unit, note
    verdict: str = ""
    findings: list[tuple[str, Any, Any, Any]] = field(default_factory=list)     # effect, rmse before, after, delta BIC
    fit_note: str = ""
    fit_warnings: list[str] = field(default_factory=list)
    diagnosis_note: str = ""

    def set_fit(self, fit: Any) -> None:
        data = as_dict(fit) or {}
        self.parameters = [(name, p.get("value"), p.get("stderr")) if isinstance(p, dict) else (name, p, None)
                           for name, p in (data.get("parameters") or {}).items()]
        stats = data.get("statistics") or {}
        self.statistics = [(step, s.get("sse"), s.get("r2"), s.get("adj_r2"), s.get("rmse"))
                           for step, s in stats.items() if isinstance(s, dict)]
        if "rmse" in data and not any(row[0] in ("run", "whole run", "total") for row in self.statistics):
            self.statistics.append(("whole run", None, None, None, data["rmse"]))
        self.constraints = [(name, bool(ok)) for name, ok in (data.get("constraints") or {}).items()]
        self.fit_warnings = [str(w) for w in (getattr(fit, "warnings", None) or data.get("warnings") or [])]

    def set_method_results(self, results: Any) -> None:
        values = results.to_dict() if hasattr(results, "to_dict") else (results or [])
        self.method_results = [(v["name"], v.get("cycle"), v.get("value"), v.get("unit", ""), v.get("note", ""))
                               for v in values]

    def set_diagnosis(self, diagnosis: Any) -> None:
        data = as_dict(diagnosis) or {}
        self.verdict = str(data.get("verdict", ""))
        self.findings = []
        for finding in data.get("findings") or []:
            gain = finding.get("gain") or {}
            self.findings.append((finding.get("effect", "?"), gain.get("rmse_before"), gain.get("rmse_after"),
                                  gain.get("delta_bic")))

    def csv_rows(self) -> list[list[str]]:
        rows = [["section", "name", "value", "stderr_or_unit", "extra"]]
        rows += [["run", k, v, "", ""] for k, v in self.run]
        rows += [["parameter", n, _num(v), _num(e), ""] for n, v, e in self.parameters]
        for step, sse, r2, adj, rmse in self.statistics:
            for key, value in (("sse", sse), ("r2", r2), ("adj_r2", adj), ("rmse", rmse)):
                if value is not None:
                    rows.append(["statistic", f"{step}.{key}", _num(value), "", ""])
        rows += [["constraint", n, "pass" if ok else "FAIL", "", ""] for n, ok in self.constraints]
        rows += [["fit_warning", "", w, "", ""] for w in self.fit_warnings]
        rows += [["method_result", n + (f" (cycle {c})" if c else ""), _num(v), u, note]
                 for n, c, v, u, note in self.method_results]
        if self.verdict:
            rows.append(["diagnosis", "verdict", self.verdict, "", ""])
        rows += [["finding", e, _num(b), _num(a), _num(d)] for e, b, a, d in self.findings]
        return rows

    def write_csv(self, path: str) -> None:
        with open(path, "w", newline="", encoding="utf-8") as f:
            csv.writer(f).writerows(self.csv_rows())


def _num(value: Any) -> str:
    if value is None:
        return ""
    return repr(float(value)) if isinstance(value, (int, float)) and not isinstance(value, bool) else str(value)


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


def _fill(table: QtWidgets.QTableWidget, rows: list[tuple]) -> None:
    table.setRowCount(len(rows))
    for r, row in enumerate(rows):
        for c, value in enumerate(row):
            item = QtWidgets.QTableWidgetItem(fmt(value) if not isinstance(value, str) else value)
            if not isinstance(value, str):
                item.setTextAlignment(QtCore.Qt.AlignmentFlag.AlignRight | QtCore.Qt.AlignmentFlag.AlignVCenter)
            table.setItem(r, c, item)
    table.resizeColumnsToContents()


class ResultsPanel(QtWidgets.QWidget):
    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        self.report = Report()
        layout = QtWidgets.QVBoxLayout(self)
        self.summary = QtWidgets.QLabel("No run yet.")
        self.summary.setObjectName("run_summary")
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(QtCore.Qt.TextInteractionFlag.TextSelectableByMouse)
        layout.addWidget(self.summary)

        self.verdict = QtWidgets.QLabel("")
        self.verdict.setObjectName("diagnosis_verdict")
        self.verdict.setWordWrap(True)
        layout.addWidget(self.verdict)

        splitter = QtWidgets.QSplitter(QtCore.Qt.Orientation.Vertical)
        top = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        self.parameters = _table(["parameter", "value", "std. error", "rel. error"], "fit_parameters")
        self.statistics = _table(["step", "SSE", "R²", "adj. R²", "RMSE [N]"], "fit_statistics")
        top.addWidget(_boxed("Fitted parameters", self.parameters))
        top.addWidget(_boxed("Fit statistics (Table 5)", self.statistics))
        bottom = QtWidgets.QSplitter(QtCore.Qt.Orientation.Horizontal)
        self.method_results = _table(["result", "cycle", "value", "unit", "note"], "method_results")
        self.findings = _table(["effect", "RMSE before", "RMSE after", "ΔBIC"], "diagnosis_findings")
        bottom.addWidget(_boxed("Method results", self.method_results))
        bottom.addWidget(_boxed("Diagnosis findings", self.findings))
        splitter.addWidget(top)
        splitter.addWidget(bottom)
        splitter.setSizes([3000, 2000])   # proportions: the fit tables get the larger share
        layout.addWidget(splitter, 1)

    def clear(self) -> None:
        self.report = Report()
        self.summary.setText("No run yet.")
        self.verdict.setText("")
        for table in (self.parameters, self.statistics, self.method_results, self.findings):
            table.setRowCount(0)

    def show_report(self, report: Report) -> None:
        self.report = report
        parts = [f"<b>{k}</b>: {v}" for k, v in report.run]
        if report.fit_note:
            parts.append(f"<b>fit</b>: {report.fit_note}")
        text = " &nbsp;·&nbsp; ".join(parts) or "No run yet."
        if report.fit_warnings:
            # Often a dozen long lines: a count here, the list in the tooltip and the CSV.
            text += (f"<br><b>fit warnings</b>: {len(report.fit_warnings)} (hover for the list; "
                     f"exported with the results)")
            self.summary.setToolTip("\n".join(report.fit_warnings))
        else:
            self.summary.setToolTip("")
        self.summary.setText(text)
        params = []
        for name, value, stderr in report.parameters:
            rel = None
            if isinstance(value, (int, float)) and isinstance(stderr, (int, float)) and value:
                rel = f"{abs(stderr / value):.1%}"
            params.append((name, value, stderr, rel or "–"))
        _fill(self.parameters, params)
        stats = list(report.statistics) + [(f"constraint {n}", "pass" if ok else "FAIL", None, None, None)
                                           for n, ok in report.constraints]
        _fill(self.statistics, stats)
        _fill(self.method_results, [(n, c if c else "", v, u, note) for n, c, v, u, note in report.method_results])
        _fill(self.findings, report.findings)
        if report.verdict:
            self.verdict.setText(f"<b>Diagnosis verdict:</b> {report.verdict}")
        else:
            self.verdict.setText(f"<b>Diagnosis:</b> {report.diagnosis_note}" if report.diagnosis_note else "")


def _boxed(title: str, widget: QtWidgets.QWidget) -> QtWidgets.QGroupBox:
    box = QtWidgets.QGroupBox(title)
    QtWidgets.QVBoxLayout(box).addWidget(widget)
    return box
