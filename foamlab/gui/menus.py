"""The window's menus: what they offer, in the words the technician reads. The window
connects each action to what it does (foamlab.gui.window)."""

from __future__ import annotations

from dataclasses import dataclass

from PySide6 import QtGui, QtWidgets


@dataclass
class Menus:
    open: QtGui.QAction
    export_png: QtGui.QAction
    export_csv: QtGui.QAction
    report: QtGui.QAction
    series_csv: QtGui.QAction        # the Series tab's series as one CSV
    series_report: QtGui.QAction     # ... and as a PDF
    quit: QtGui.QAction
    auto_diagnose: QtGui.QAction
    diagnose: QtGui.QAction
    predict: QtGui.QAction
    probe: QtGui.QAction             # Machine > Probe (foamlab.gui.commissioning)


def build_menus(bar: QtWidgets.QMenuBar, auto_diagnose: bool) -> Menus:
    file = bar.addMenu("&File")
    actions = [file.addAction("&Open measured file…", QtGui.QKeySequence.StandardKey.Open),
               file.addAction("Export plot as &PNG…"),
               file.addAction("Export results as &CSV…"),
               file.addAction("Write test &report (PDF)…"),
               file.addAction("Export &series CSV…"),
               file.addAction("Series report (PD&F)…")]
    file.addSeparator()
    actions.append(file.addAction("&Quit", QtGui.QKeySequence.StandardKey.Quit))
    analysis = bar.addMenu("&Analysis")
    # A diagnosis takes seconds to tens of seconds (it refits extended models); it runs in
    # the background, and can be left for later.
    auto = analysis.addAction("Diagnose &automatically")
    auto.setCheckable(True)
    auto.setChecked(auto_diagnose)
    diagnose = analysis.addAction("&Diagnose the shown run")
    # The rest of a run predicted from its first cycles, while it runs (foamlab.prediction).
    predict = analysis.addAction("&Live prediction")
    predict.setCheckable(True)
    predict.setChecked(True)
    machine = bar.addMenu("&Machine")
    probe = machine.addAction("&Probe the connected machine…")
    return Menus(*actions, auto, diagnose, predict, probe)
