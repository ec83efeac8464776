"""The live prediction in the window: the predicted curve of the cycle in progress beside the
measurement, the residual as a strip under the force–displacement plot with the band the
noise allows, and a line that says when the specimen leaves the prediction.

foamlab.prediction.LivePredictor does the work off the acquisition thread (its fits in a worker
process); PredictionBridge carries what it says into the GUI thread (rare events as queued
signals, the compared samples in a deque drained by the window's frame timer, like
foamlab.gui.bridge's samples); PredictionView draws; LivePrediction ties them to a run.
"""

from __future__ import annotations

import collections
import html
import logging

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from foamlab.gui.background import BackgroundQueue
from foamlab.gui.bridge import drained
from foamlab.gui.plots import CYCLE_COLOURS, LivePlots
from foamlab.gui.status import WARNING_STYLE
from foamlab.gui.units import FORCE_DISPLACEMENT, PlotUnits
from foamlab.prediction import MIN_CYCLES, Forecast
from foamlab.prediction.departure import Compared, Departure, departure_limit, window_samples

log = logging.getLogger(__name__)

BAND_COLOUR = (120, 120, 120, 45)
DEPARTURE_COLOUR = "#B00020"
#: Seconds the window waits after a run for the last forecast scores (they come from the worker).
SCORES_TIMEOUT_S = 60.0


class PredictionBridge(QtCore.QObject):
    """LivePredictor listener (its thread) -> Qt (the GUI thread)."""

    forecast = QtCore.Signal(object)       # foamlab.prediction.Forecast
    departure = QtCore.Signal(object)      # foamlab.prediction.Departure
    score = QtCore.Signal(object)          # foamlab.prediction.CycleScore
    note = QtCore.Signal(str)

    def __init__(self, parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self._compared: collections.deque = collections.deque()

    def on_forecast(self, forecast) -> None:
        self.forecast.emit(forecast)

    def on_departure(self, departure) -> None:
        self.departure.emit(departure)

    def on_score(self, score) -> None:
        self.score.emit(score)

    def on_note(self, text: str) -> None:
        self.note.emit(text)

    def on_compared(self, compared) -> None:
        self._compared.append(compared)

    def drain(self) -> list[Compared]:
        return drained(self._compared)


def _pen(cycle: int, dashed: bool, width: int = 2, alpha: int = 150, solid: bool = False) -> QtGui.QPen:
    """The cycle's colour: the prediction dotted (loading) or dashed (unloading), a residual solid or dashed."""
    colour = QtGui.QColor(CYCLE_COLOURS[(max(cycle, 1) - 1) % len(CYCLE_COLOURS)])
    colour.setAlpha(alpha)
    style = (QtCore.Qt.PenStyle.DashLine if dashed else
             QtCore.Qt.PenStyle.SolidLine if solid else QtCore.Qt.PenStyle.DotLine)
    return pg.mkPen(colour, width=width, style=style)


class _Pool:
    """Graphics items made once per plot and reused (hidden when not needed), never removed: an
    item taken off a plot is left to Python's cycle collector, which may free it on another
    thread (the run engine collects as a run starts), where its Qt destructor deadlocks with the
    GUI thread (seen in tests/test_gui.py before the pools)."""

    def __init__(self, plot: pg.PlotItem, make) -> None:
        self.plot, self.make = plot, make
        self.items: list = []
        self.used = 0

    def take(self):
        if self.used == len(self.items):
            item = self.make()
            for part in (item if isinstance(item, tuple) else (item,)):
                self.plot.addItem(part)
            self.items.append(item)
        item = self.items[self.used]
        self.used += 1
        for part in (item if isinstance(item, tuple) else (item,)):
            part.show()
        return item

    def release(self) -> None:
        for item in self.items:
            for part in (item if isinstance(item, tuple) else (item,)):
                part.hide()
        self.used = 0


def _band(strip: pg.PlotItem):
    edge = pg.mkPen(BAND_COLOUR, width=1)
    upper, lower = pg.PlotCurveItem(pen=edge), pg.PlotCurveItem(pen=edge)
    return upper, lower, pg.FillBetweenItem(upper, lower, brush=pg.mkBrush(*BAND_COLOUR))


def _departure_line():
    return pg.InfiniteLine(angle=90, pen=pg.mkPen(DEPARTURE_COLOUR, width=1, style=QtCore.Qt.PenStyle.DashLine),
                           label="departs", labelOpts={"color": DEPARTURE_COLOUR, "position": 0.85})


class PredictionView:
    """Draws the forecast of the cycle in progress on LivePlots and the residual strip under
    its force–displacement plot."""

    def __init__(self, plots: LivePlots) -> None:
        self.plots = plots
        self.strip: pg.PlotItem = plots.view.addPlot(row=1, col=0)
        self.strip.setXLink(plots.fd_plot)
        self.strip.setMaximumHeight(130)
        self.strip.addLine(y=0, pen=pg.mkPen("#888888", width=1))
        self.units: PlotUnits = FORCE_DISPLACEMENT
        self.forecast: Forecast | None = None
        self.cycle = 0                               # the cycle whose prediction is drawn
        self._fd = _Pool(plots.fd_plot, pg.PlotDataItem)
        self._ft = _Pool(plots.ft_plot, pg.PlotDataItem)
        self._bands = _Pool(self.strip, lambda: _band(self.strip))
        self._lines = _Pool(self.strip, _departure_line)
        self._curves = _Pool(self.strip, pg.PlotDataItem)
        self._residuals: dict[int, list[Compared]] = {}      # by step, this cycle's compared samples
        self._residual_curves: dict[int, pg.PlotDataItem] = {}
        self._departures: list[Departure] = []
        self._legend = False                         # the prediction's legend entry is there
        self._dirty = False
        self._label()

    def _label(self) -> None:
        u = self.units
        self.strip.getAxis("left").enableAutoSIPrefix(u.si_prefix)
        self.strip.setLabel("left", "meas. − pred.", units=u.y_unit)
        self.strip.setLabel("bottom", u.x, units=u.x_unit)
        self.strip.setTitle(f"Residual to the live prediction (from cycle {MIN_CYCLES + 1} on); "
                            "grey: what the noise allows", size="9pt")

    def clear(self) -> None:
        """Nothing drawn (a new run: LivePlots.clear has emptied the legend too)."""
        self._release()
        self._residuals.clear()
        self._departures.clear()
        self._legend = False
        self.forecast, self.cycle = None, 0

    def _release(self) -> None:
        for pool in (self._fd, self._ft, self._bands, self._lines, self._curves):
            pool.release()
        self._residual_curves.clear()

    def set_units(self, units: PlotUnits) -> None:
        self.units = units
        self._label()
        self._redraw()

    # -- what arrives --------------------------------------------------------------------
    def show_forecast(self, forecast: Forecast) -> None:
        self.forecast = forecast
        self._switch(forecast.from_cycles + 1)

    def add(self, batches: list[Compared]) -> None:
        for c in batches:
            cycle = int(c.cycle[0])
            if cycle != self.cycle:
                self._switch(cycle)
            self._residuals.setdefault(int(c.step[0]), []).append(c)
            self._dirty = True

    def mark(self, departure: Departure) -> None:
        self._departures.append(departure)
        self._draw_departure(departure)

    def refresh(self) -> None:
        """The residual curves that got samples since the last frame."""
        if not self._dirty:
            return
        self._dirty = False
        u = self.units
        for step, batches in self._residuals.items():
            x = np.concatenate([b.displacement_mm for b in batches]) * u.x_per_mm
            r = np.concatenate([b.residual_N for b in batches]) * u.y_per_N
            curve = self._residual_curves.get(step)
            if curve is None:
                predicted = self.forecast.step(step) if self.forecast else None
                curve = self._residual_curves[step] = self._curves.take()
                curve.setPen(_pen(self.cycle, predicted is not None and predicted.phase == "unloading", 1, 255,
                                  solid=True))
            curve.setData(x, r)

    # -- drawing -------------------------------------------------------------------------
    def _switch(self, cycle: int) -> None:
        """Draw the prediction of `cycle` (the one in progress), its band, no residual yet."""
        self._release()
        self._residuals = {k: v for k, v in self._residuals.items() if v and int(v[0].cycle[0]) == cycle}
        self.cycle = cycle
        self._draw_prediction()
        for d in self._departures:
            self._draw_departure(d)
        self._dirty = True

    def _redraw(self) -> None:
        """Everything again, in the units now chosen."""
        if self.forecast is not None:
            self._switch(self.cycle)
        self.refresh()

    def _draw_prediction(self) -> None:
        f = self.forecast
        if f is None:
            return
        u = self.units
        window = window_samples(f.sampling_hz)
        for step in f.cycle(self.cycle):
            x, y = step.displacement_mm * u.x_per_mm, step.force_N * u.y_per_N
            pen = _pen(self.cycle, step.phase == "unloading")
            curve = self._fd.take()
            curve.setData(x, y, pen=pen)
            if not self._legend:
                self.plots.legend.addItem(curve, "live prediction")
                self._legend = True
            self._ft.take().setData(step.time_s, y, pen=pen)
            if f.noise_N > 0:
                limit = departure_limit(step.force_N, step.sigma_N, step.spread_N, f.noise_N, window) * u.y_per_N
                upper, lower, _ = self._bands.take()
                upper.setData(x, limit)
                lower.setData(x, -limit)

    def _draw_departure(self, d: Departure) -> None:
        if d.cycle != self.cycle:
            return
        line = self._lines.take()
        line.setPos(d.since_mm * self.units.x_per_mm)
        line.label.setFormat(f"{d.phase} departs")


class LivePrediction(QtCore.QObject):
    """One run's live prediction in the window: start it with the run, draw what it says,
    collect its forecast scores when the run ends (`scores_ready`)."""

    message = QtCore.Signal(str, bool)       # a line for the status bar; True: a warning
    scores_ready = QtCore.Signal(object, int)   # ForecastScores, the run's generation

    def __init__(self, plots: LivePlots, parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self.view = PredictionView(plots)
        self.status = QtWidgets.QLabel("")
        self.status.setObjectName("prediction_status")
        self.status.setWordWrap(True)
        self.predictor = None
        self.bridge: PredictionBridge | None = None
        self.departures: list[Departure] = []
        self.queue = BackgroundQueue("foamlab-prediction-end", self)
        self.generation = 0                     # the display's, for the run being predicted
        self._line, self._line_warns = "", False

    def begin(self, engine, method, generation: int) -> None:
        """Predict `engine`'s run (call before engine.start())."""
        from foamlab.session import start_prediction  # noqa: PLC0415

        self.stop()
        self.view.clear()
        self.departures = []
        self.generation = generation
        self.bridge = bridge = PredictionBridge(self)
        bridge.forecast.connect(self._on_forecast)
        bridge.departure.connect(self._on_departure)
        bridge.note.connect(self._on_note)
        self.predictor = start_prediction(engine, method, bridge)     # the CLI's too (foamlab.session)
        wait = "the first cycle" if MIN_CYCLES == 1 else f"cycles 1–{MIN_CYCLES}"
        if method.n_cycles > MIN_CYCLES:
            text = f"Live prediction: from cycle {MIN_CYCLES + 1} on, once {wait} are measured"
        else:
            text = f"Live prediction: none in a {method.n_cycles}-cycle method (it predicts from cycle {MIN_CYCLES + 1} on)"
        self._say(text, False, status_bar=False)

    def reset(self) -> None:
        """Nothing predicted on display (a file is shown)."""
        self.stop()
        self.view.clear()
        self.departures = []
        self._say("", False, status_bar=False)

    def off(self) -> None:
        self.stop()
        self.view.clear()
        self.departures = []
        self._say("Live prediction: off (Analysis > Live prediction)", False, status_bar=False)

    def refresh(self) -> None:
        if self.bridge is not None:
            self.view.add(self.bridge.drain())
        self.view.refresh()

    def end(self) -> None:
        """The run ended: the last scores come from the worker (GUI: `scores_ready`)."""
        predictor, generation = self.predictor, self.generation
        if predictor is None:
            return
        self.refresh()
        self.queue.submit(lambda: predictor.finish(SCORES_TIMEOUT_S),
                          lambda scores: self.scores_ready.emit(scores, generation))

    def stop(self) -> None:
        if self.predictor is not None:
            self.predictor.close()
        self.predictor = None
        self.bridge = None

    def shutdown(self) -> None:
        self.stop()
        self.queue.shutdown(wait=False)

    def _on_forecast(self, forecast: Forecast) -> None:
        if self.bridge is None or self.sender() is not self.bridge:
            return
        self.view.show_forecast(forecast)
        self._say(f"Live prediction: {forecast.describe()}", False,
                  status_bar=False)

    def _on_note(self, text: str) -> None:
        if self.bridge is not None and self.sender() is self.bridge:
            self._say(f"Live prediction: {text}", True, note=True)

    def _on_departure(self, d: Departure) -> None:
        if self.bridge is None or self.sender() is not self.bridge:
            return
        self.departures.append(d)
        self.view.mark(d)
        self._say(d.message, True)

    def _say(self, text: str, warning: bool, status_bar: bool = True, note: bool = False) -> None:
        """The status line: what the prediction is (or why there is none), then each departure."""
        if not warning or note:
            self._line, self._line_warns = text, note
        lines = [html.escape(self._line)] + [f"⚠ {html.escape(d.message)}" for d in self.departures]
        self.status.setText("<br>".join(line for line in lines if line))
        self.status.setStyleSheet(WARNING_STYLE if self.departures or self._line_warns else "")
        if status_bar:
            self.message.emit(text, warning)
