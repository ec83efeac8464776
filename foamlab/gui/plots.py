"""Live force–displacement and force–time plots that stay smooth for a whole run.

Samples are appended into preallocated numpy buffers; every (cycle, half-cycle)
segment is one curve whose data is a *view* of those buffers, so a frame only
calls setData on the curves that changed (the growing segment and force–time),
never re-plots the run. The window calls `refresh()` from a ~30 Hz timer.

The buffers keep the run as measured (N, mm); `set_units` shows it as stress–strain
(foamlab.gui.units): curves, fit overlay and exported images then carry the scaled values.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pyqtgraph as pg
from PySide6 import QtCore, QtGui, QtWidgets

from foamlab.gui.units import FORCE_DISPLACEMENT, PlotUnits

LOADING = "loading"
UNLOADING = "unloading"

# Colour-blind friendly palette (Okabe–Ito), one colour per cycle; cycles beyond it wrap.
CYCLE_COLOURS = ["#0072B2", "#D55E00", "#009E73", "#CC79A7", "#E69F00", "#56B4E9", "#000000"]
FIT_COLOUR = "#222222"


def cycle_pen(cycle: int, phase: str) -> QtGui.QPen:
    """Loading: solid, full colour. Unloading: dashed, lighter shade of the same colour.
    One-pixel cosmetic pens on purpose: wider pens take the raster engine's slow path
    (frame time 28 -> 40 ms with 20 000 points, benchmarks/bench_plot.py)."""
    colour = QtGui.QColor(CYCLE_COLOURS[(max(cycle, 1) - 1) % len(CYCLE_COLOURS)])
    if phase == UNLOADING:
        return pg.mkPen(colour.lighter(140), width=1, style=QtCore.Qt.PenStyle.DashLine)
    return pg.mkPen(colour, width=1)


class SampleBuffer:
    """Growable, preallocated column store for (time, displacement, force)."""

    def __init__(self, capacity: int = 16384) -> None:
        self.n = 0
        self.time_s = np.empty(capacity)
        self.displacement_mm = np.empty(capacity)
        self.force_N = np.empty(capacity)

    @property
    def capacity(self) -> int:
        return len(self.time_s)

    def reserve(self, capacity: int) -> None:
        if capacity <= self.capacity:
            return
        for name in ("time_s", "displacement_mm", "force_N"):
            old = getattr(self, name)
            new = np.empty(capacity)
            new[: self.n] = old[: self.n]
            setattr(self, name, new)

    def extend(self, time_s, displacement_mm, force_N) -> None:
        k = len(time_s)
        if self.n + k > self.capacity:
            # Doubling keeps appends amortised O(1); finished curves keep views of the old arrays.
            self.reserve(max(2 * self.capacity, self.n + k))
        s = slice(self.n, self.n + k)
        self.time_s[s] = time_s
        self.displacement_mm[s] = displacement_mm
        self.force_N[s] = force_N
        self.n += k

    def clear(self) -> None:
        self.n = 0


@dataclass
class Segment:
    cycle: int
    phase: str
    start: int            # first buffer index (shared with the previous segment's last point)
    curve: pg.PlotDataItem
    dirty: bool = True


class PhaseTracker:
    """Loading/unloading and cycle number from displacement alone, for sources that
    don't label their samples: a turn is declared once the plate has moved back by
    more than `deadband_mm` from the last extreme (noise can't flip it)."""

    def __init__(self, deadband_mm: float = 0.05) -> None:
        self.deadband_mm = deadband_mm
        self.cycle = 1
        self.phase = LOADING
        self._extreme: float | None = None

    def update(self, displacement_mm: float) -> tuple[int, str]:
        x = float(displacement_mm)
        if self._extreme is None:
            self._extreme = x
        elif self.phase == LOADING:
            if x > self._extreme:
                self._extreme = x
            elif x < self._extreme - self.deadband_mm:
                self.phase, self._extreme = UNLOADING, x
        else:
            if x < self._extreme:
                self._extreme = x
            elif x > self._extreme + self.deadband_mm:
                self.phase, self._extreme = LOADING, x
                self.cycle += 1
        return self.cycle, self.phase


class LivePlots(QtWidgets.QWidget):
    """Force–displacement (left) and force–time (right) in one exportable scene."""

    def __init__(self, parent: QtWidgets.QWidget | None = None) -> None:
        super().__init__(parent)
        pg.setConfigOptions(antialias=False, background="w", foreground="k")
        self.view = pg.GraphicsLayoutWidget()
        layout = QtWidgets.QVBoxLayout(self)
        layout.setContentsMargins(0, 0, 0, 0)
        layout.addWidget(self.view)

        self.fd_plot: pg.PlotItem = self.view.addPlot(row=0, col=0)
        # No grid: pyqtgraph repaints grid lines with the axes on every frame (~17 ms).
        self.legend = self.fd_plot.addLegend(offset=(10, 10))

        self.ft_plot: pg.PlotItem = self.view.addPlot(row=0, col=1)
        self.ft_plot.setLabel("bottom", "Time", units="s")
        # Only force–time is monotonic in x, so clipToView is valid there; downsampling
        # (peak mode keeps the extremes) bounds the cost of a frame whatever the run length.
        self.ft_plot.setClipToView(True)
        self.ft_plot.setDownsampling(auto=True, mode="peak")
        self.ft_curve = self.ft_plot.plot(pen=pg.mkPen("#0072B2", width=1), name="force")

        self.fit_fd: pg.PlotDataItem | None = None
        self.fit_ft: pg.PlotDataItem | None = None
        self._fit_data: tuple | None = None       # the fit as given (s, mm, N): redrawn in other units
        self.units: PlotUnits = FORCE_DISPLACEMENT
        self._label_axes()
        self.buffer = SampleBuffer()
        self.segments: list[Segment] = []
        self._tracker = PhaseTracker()
        self._ft_dirty = False
        self._legend_cycles: set[int] = set()

    # ---- feeding -------------------------------------------------------------------
    def clear(self, expected_samples: int = 0) -> None:
        for seg in self.segments:
            self.fd_plot.removeItem(seg.curve)
        self.segments.clear()
        self.legend.clear()
        self._legend_cycles.clear()
        self.clear_fit()
        self.buffer.clear()
        self.buffer.reserve(int(expected_samples * 1.1) + 1024)
        self._tracker = PhaseTracker()
        self.ft_curve.setData([], [])
        self._ft_dirty = False

    def add_samples(self, time_s, displacement_mm, force_N, cycles=None, phases=None) -> None:
        """Append a batch. `cycles`/`phases` label each sample when the source knows them
        (the run engine does); otherwise they are tracked from the displacement."""
        time_s = np.asarray(time_s, dtype=float)
        if len(time_s) == 0:
            return
        displacement_mm = np.asarray(displacement_mm, dtype=float)
        force_N = np.asarray(force_N, dtype=float)
        if cycles is None or phases is None:
            labels = [self._tracker.update(x) for x in displacement_mm]
        else:
            labels = list(zip(cycles, phases))
        first = self.buffer.n
        self.buffer.extend(time_s, displacement_mm, force_N)
        # Split the batch where the label changes; each run of equal labels extends a segment.
        boundaries = [0] + [i for i in range(1, len(labels)) if labels[i] != labels[i - 1]]
        for b in boundaries:
            cycle, phase = labels[b]
            current = self.segments[-1] if self.segments else None
            if current is None or (current.cycle, current.phase) != (cycle, phase):
                self._start_segment(int(cycle), str(phase), first + b)
            else:
                current.dirty = True
        self._ft_dirty = True

    def _start_segment(self, cycle: int, phase: str, index: int) -> None:
        if self.segments:
            self.segments[-1].dirty = True  # its last points still need drawing
        start = max(index - 1, 0)  # share one point so the curve is continuous
        name = None
        if cycle not in self._legend_cycles and phase == LOADING:
            name = f"cycle {cycle}"
            self._legend_cycles.add(cycle)
        curve = self.fd_plot.plot(pen=cycle_pen(cycle, phase), name=name, skipFiniteCheck=True)
        self.segments.append(Segment(cycle, phase, start, curve))

    # ---- drawing -------------------------------------------------------------------
    def refresh(self) -> int:
        """Push new data to the curves that changed. Returns how many curves were updated."""
        updated = 0
        n = self.buffer.n
        for i, seg in enumerate(self.segments):
            if not seg.dirty:
                continue
            stop = self.segments[i + 1].start + 1 if i + 1 < len(self.segments) else n
            seg.curve.setData(
                _scaled(self.buffer.displacement_mm[seg.start:stop], self.units.x_per_mm),
                _scaled(self.buffer.force_N[seg.start:stop], self.units.y_per_N),
                skipFiniteCheck=True,
            )
            seg.dirty = False
            updated += 1
        if self._ft_dirty:
            self.ft_curve.setData(self.buffer.time_s[:n], _scaled(self.buffer.force_N[:n], self.units.y_per_N),
                                  skipFiniteCheck=True)
            self._ft_dirty = False
            updated += 1
        return updated

    # ---- units ---------------------------------------------------------------------
    def set_units(self, units: PlotUnits) -> None:
        """Show the run, its fit and exported images in `units` (foamlab.gui.units)."""
        if units == self.units:
            return
        self.units = units
        self._label_axes()
        for seg in self.segments:
            seg.dirty = True
        self._ft_dirty = self.buffer.n > 0
        self.refresh()
        if self._fit_data is not None:
            self.show_fit(*self._fit_data)
        self.fd_plot.enableAutoRange()
        self.ft_plot.enableAutoRange()

    def _label_axes(self) -> None:
        u = self.units
        for plot, side, name, unit in ((self.fd_plot, "bottom", u.x, u.x_unit), (self.fd_plot, "left", u.y, u.y_unit),
                                       (self.ft_plot, "left", u.y, u.y_unit)):
            plot.getAxis(side).enableAutoSIPrefix(u.si_prefix)
            plot.setLabel(side, name, units=unit)
        self.fd_plot.setTitle(u.title)
        self.ft_plot.setTitle(f"{u.y} – time")

    @property
    def sample_count(self) -> int:
        return self.buffer.n

    def plotted_points(self) -> int:
        """Distinct samples held by the force–displacement curves (shared joints counted once)."""
        total = 0
        for seg in self.segments:
            x, _ = seg.curve.getData()
            total += 0 if x is None else len(x)
        return total - max(len(self.segments) - 1, 0)

    # ---- whole runs and fits ---------------------------------------------------------
    def show_run(self, time_s, displacement_mm, force_N, cycles=None, phases=None) -> None:
        self.clear(expected_samples=len(time_s))
        self.add_samples(time_s, displacement_mm, force_N, cycles, phases)
        self.refresh()
        self.fd_plot.enableAutoRange()
        self.ft_plot.enableAutoRange()

    def show_fit(self, time_s, displacement_mm, force_N) -> None:
        """Overlay the model's predicted force (dashed, dark) on both plots (given in s, mm, N)."""
        self.clear_fit()
        self._fit_data = (time_s, displacement_mm, force_N)
        x = _scaled(np.asarray(displacement_mm, dtype=float), self.units.x_per_mm)
        y = _scaled(np.asarray(force_N, dtype=float), self.units.y_per_N)
        # Dark, thin, dashed and a little transparent: the measured curves stay readable under it.
        colour = QtGui.QColor(FIT_COLOUR)
        colour.setAlpha(190)
        pen = pg.mkPen(colour, width=1, style=QtCore.Qt.PenStyle.DashLine)
        self.fit_fd = self.fd_plot.plot(x, y, pen=pen, name="fitted model")
        self.fit_ft = self.ft_plot.plot(np.asarray(time_s), y, pen=pen)

    def clear_fit(self) -> None:
        for item, plot in ((self.fit_fd, self.fd_plot), (self.fit_ft, self.ft_plot)):
            if item is not None:
                plot.removeItem(item)
                if plot is self.fd_plot:
                    self.legend.removeItem(item)
        self.fit_fd = self.fit_ft = None
        self._fit_data = None

    def export_png(self, path: str, width: int = 1600) -> None:
        from pyqtgraph.exporters import ImageExporter

        self.refresh()
        exporter = ImageExporter(self.view.scene())
        exporter.parameters()["width"] = width
        exporter.export(str(path))


def _scaled(values: np.ndarray, factor: float) -> np.ndarray:
    """`values` in the plotted unit: the buffer's own view when unscaled (no copy per frame)."""
    return values if factor == 1.0 else values * factor


def labels_from_segmentation(segmentation, n_samples: int) -> tuple[np.ndarray, list[str]]:
    """Per-sample (cycle, phase) of a whole run from foamlab.segmentation's half-cycles.
    Samples outside half-cycles (holds, the lead-in) keep the label before them, so
    each half-cycle stays one curve."""
    cycles = np.zeros(n_samples, dtype=int)
    phases = np.full(n_samples, "", dtype=object)
    for half in segmentation.half_cycles:
        cycles[half.start:half.stop] = half.cycle
        phases[half.start:half.stop] = half.direction
    last_cycle, last_phase = 0, LOADING
    for i in range(n_samples):
        if phases[i]:
            last_cycle, last_phase = cycles[i], phases[i]
        else:
            cycles[i], phases[i] = last_cycle, last_phase
    return cycles, list(phases)
