"""Frames per second of the GUI's live plots with 20 000 points (offscreen).

A frame = append the samples that arrived since the last frame, push the changed
curves (LivePlots.refresh) and paint the view synchronously. Compared with the
naive way (re-plot every point each frame). Prints a table of medians over
repeats and keeps it in docs/benchmarks.md (its own section, replaced on rerun).

    .venv/bin/python benchmarks/bench_plot.py [--points 20000] [--repeats 5] [--no-write]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np  # noqa: E402
from PySide6 import QtCore, QtWidgets  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from _table import publish  # noqa: E402  (benchmarks/ is on sys.path when run as a script)
from foamlab.gui.plots import LivePlots  # noqa: E402

SECTION = "GUI live plots"


def synthetic_run(n_points: int, cycles: int = 3, rate_hz: float = 16.0):
    """A triangular three-cycle history with a stiffening, hysteretic force: display
    data only (the benchmark measures drawing, not physics)."""
    t = np.arange(n_points) / rate_hz
    period = t[-1] / cycles
    phase = (t % period) / period
    x = 58.0 * np.where(phase < 0.5, 2 * phase, 2 - 2 * phase)
    loading = phase < 0.5
    s = x / 58.0
    f = 300 * s**5 + 40 * s + np.where(loading, 25 * np.sin(np.pi * s), -10 * np.sin(np.pi * s))
    f += np.random.default_rng(0).normal(0, 0.3, n_points)
    return t, x, f


class PaintCounter(QtCore.QObject):
    """Counts paint events of the plot view, to check a frame is exactly one paint."""

    def __init__(self) -> None:
        super().__init__()
        self.paints = 0

    def eventFilter(self, obj, event) -> bool:
        if event.type() == QtCore.QEvent.Type.Paint:
            self.paints += 1
        return False


def paint(plots: LivePlots, app: QtWidgets.QApplication) -> None:
    # The event loop runs the scene's pending updates and paints the view once, as
    # in the window (a repaint() before it would paint a stale scene, then again).
    app.processEvents()


def frames_incremental(app, plots, data, prefill: int, chunk: int, frames: int) -> list[float]:
    t, x, f = data
    plots.clear(expected_samples=len(t))
    plots.add_samples(t[:prefill], x[:prefill], f[:prefill])
    plots.refresh()
    paint(plots, app)
    times = []
    i = prefill
    for _ in range(frames):
        start = time.perf_counter()
        j = min(i + chunk, len(t))
        plots.add_samples(t[i:j], x[i:j], f[i:j])
        plots.refresh()
        paint(plots, app)
        times.append(time.perf_counter() - start)
        i = j
    return times


def frames_naive(app, plots, data, prefill: int, chunk: int, frames: int) -> list[float]:
    """What the live plots avoid: clear both plots and plot every sample again each frame."""
    t, x, f = data
    times = []
    n = prefill
    for _ in range(frames):
        start = time.perf_counter()
        n = min(n + chunk, len(t))
        plots.fd_plot.clear()
        plots.fd_plot.plot(x[:n], f[:n], pen="b")
        plots.ft_curve.setData(t[:n], f[:n])
        paint(plots, app)
        times.append(time.perf_counter() - start)
    return times


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", type=int, default=20000)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--frames", type=int, default=60, help="frames timed per repeat")
    parser.add_argument("--chunk", type=int, default=27,
                        help="samples per frame (16 Hz x speedup 50 / 30 fps ~ 27)")
    parser.add_argument("--size", default="1280x560", help="plot area in pixels, WxH")
    parser.add_argument("--no-write", action="store_true", help="don't update docs/benchmarks.md")
    args = parser.parse_args()

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    width, height = (int(v) for v in args.size.split("x"))
    total = args.points + args.chunk * args.frames
    data = synthetic_run(total)
    prefill = args.points

    rows = []
    for label, fn in (("live plots (incremental setData)", frames_incremental),
                      ("naive re-plot every frame", frames_naive)):
        medians = []
        for _ in range(args.repeats):
            plots = LivePlots()
            plots.resize(width, height)
            plots.show()
            app.processEvents()
            if fn is frames_naive:
                plots.clear()
            counter = PaintCounter()
            plots.view.viewport().installEventFilter(counter)
            times = fn(app, plots, data, prefill, args.chunk, args.frames)
            paints_per_frame = counter.paints / args.frames
            if not 0.9 <= paints_per_frame <= 1.1:
                print(f"warning: {paints_per_frame:.2f} paints per frame in '{label}'", file=sys.stderr)
            medians.append(statistics.median(times))
            plots.close()
            plots.deleteLater()
            app.processEvents()
        med = statistics.median(medians)
        rows.append((label, args.points, med * 1e3, 1.0 / med, min(medians) * 1e3, max(medians) * 1e3))

    live_fps = rows[0][3]
    verdict = "meets" if live_fps >= 30 else "MISSES"
    lines = [
        f"`benchmarks/bench_plot.py`: offscreen Qt, plot area {args.size}, {args.chunk} new samples per frame, "
        f"{args.frames} frames x {args.repeats} repeats, load average {os.getloadavg()[0]:.1f} on "
        f"{os.cpu_count()} cores at the end. A frame = append the new samples + setData of the "
        f"changed curves + one paint of both plots (verified: one paint event per frame).",
        "",
        "| variant | points | frame ms (median) | frames/s | best repeat ms | worst repeat ms |",
        "|---|---:|---:|---:|---:|---:|",
    ]
    lines += [f"| {r[0]} | {r[1]} | {r[2]:.2f} | {r[3]:.0f} | {r[4]:.2f} | {r[5]:.2f} |" for r in rows]
    lines += ["", f"Target >= 30 frames/s with {args.points} points: {verdict} ({live_fps:.0f} frames/s)."]
    if args.no_write:
        print("\n".join(lines))
    else:
        publish(SECTION, lines)
    return 0


if __name__ == "__main__":
    sys.exit(main())
