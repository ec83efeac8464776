"""Regenerate docs/img/gui.png, gui_results.png and gui_expert.png: the window after a
clean simulated run, grabbed offscreen; with --softening, docs/img/gui_prediction.png.

Connects the window to the built-in simulated machine, runs a method (the paper's
protocol by default) on a 100 x 100 x 72.5 mm block (the simulator's clock sped up),
waits for the fit and the diagnosis, and saves a grab of the whole window (with the live
prediction of cycle 3 from cycles 1-2 and its residual strip), of the technician's results
view and of its Expert tab. Nothing is written unless the run was clean: finished, not a
deadline missed, the live prediction never flagged it, the diagnosis says `none`.

--softening S: the simulated specimen softens by S from cycle 3 on; the window is grabbed when
the live prediction says so (docs/img/gui_prediction.png) and the run is stopped.

    .venv/bin/python scripts/screenshot_gui.py [--speedup 5] [--method iso3386-1] [--out-dir docs/img]
    .venv/bin/python scripts/screenshot_gui.py --softening 0.2
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from PySide6 import QtCore, QtWidgets  # noqa: E402

from foamlab.gui.window import MainWindow  # noqa: E402


def wait_for(app: QtWidgets.QApplication, condition, timeout_s: float, what: str) -> None:
    deadline = time.monotonic() + timeout_s
    while not condition():
        if time.monotonic() > deadline:
            raise SystemExit(f"screenshot_gui: timed out after {timeout_s:.0f} s waiting for {what}")
        app.processEvents(QtCore.QEventLoop.ProcessEventsFlag.AllEvents, 50)
        time.sleep(0.01)


def save(widget: QtWidgets.QWidget, path: Path) -> None:
    if not widget.grab().save(str(path)):
        raise SystemExit(f"screenshot_gui: could not write {path}")
    print(f"written {path}")


def grab_departure(app: QtWidgets.QApplication, window: MainWindow, out_dir: Path) -> int:
    """The window a few seconds after the live prediction flagged the softening; the run stopped."""
    live = window.display.live
    wait_for(app, lambda: bool(live.departures) or window.last_result is not None, 1200, "a departure")
    if not live.departures:
        raise SystemExit("screenshot_gui: the run ended and nothing was flagged; not written")
    print(f"flagged: {live.departures[0].message}")
    shown = time.monotonic()
    wait_for(app, lambda: time.monotonic() > shown + 3.0, 10, "a few more samples")
    save(window, out_dir / "gui_prediction.png")
    window.stop_run()
    wait_for(app, lambda: window.last_result is not None, 120, "the stop")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speedup", type=float, default=5.0, help="simulated machine clock rate (default 5)")
    parser.add_argument("--height", type=float, default=72.5, help="specimen height in mm (default 72.5)")
    parser.add_argument("--out-dir", default=str(ROOT / "docs" / "img"),
                        help="folder of gui.png, gui_results.png, gui_expert.png")
    parser.add_argument("--method", default=None, help="test method (default: the paper's protocol)")
    parser.add_argument("--size", default="1400x900", help="window size WxH")
    parser.add_argument("--softening", type=float, default=None, metavar="S",
                        help="the specimen softens by S from cycle 3 on: grab gui_prediction.png when flagged")
    args = parser.parse_args()

    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication([])
    simulator = {"seed": 1}
    if args.softening is not None:
        from foamlab.model.effects import CycleSoftening, EffectChain

        simulator["effects"] = EffectChain([CycleSoftening(args.softening, from_cycle=3)])
    with tempfile.TemporaryDirectory(prefix="foamlab-screenshot-") as data:
        window = MainWindow(speedup=args.speedup, out_dir=data, method=args.method, simulator=simulator,
                            auto_diagnose=args.softening is None)
        width, height = (int(v) for v in args.size.split("x"))
        window.resize(width, height)
        window.show()
        try:
            window.connect_button.click()
            wait_for(app, lambda: window.connected, 30, "the simulated machine")
            window.specimen_form.set_values("PU-foam-01", args.height, 100.0, 100.0)
            if not window.start_run():
                raise SystemExit(f"screenshot_gui: start refused: {window.specimen_form.message.text()}")
            out_dir = Path(args.out_dir)
            out_dir.mkdir(parents=True, exist_ok=True)
            if args.softening is not None:
                return grab_departure(app, window, out_dir)
            wait_for(app, lambda: window.last_result is not None, 1200, "the end of the run")
            result = window.last_result
            print(f"run {result.status} {result.reason}: {result.n_samples} samples, {result.missed} missed")
            if result.status != "finished" or result.missed or window.results.report.flags:
                # The README shows a finished, fitted run; a busy computer can make the sped-up
                # simulated machine abort (watchdog, timeouts) or miss samples: run again, or
                # lower --speedup.
                raise SystemExit(f"screenshot_gui: the run was not clean ({result.reason or 'missed samples'}; "
                                 f"flags: {[f.name for f in window.results.report.flags]}); not written")
            # The pipeline's fit arrives after the run, then its diagnosis: give each its time.
            wait_for(app, lambda: window.shown_analysis is not None, 120, "the fit")
            wait_for(app, lambda: "running" not in window.results.verdict.text(), 300, "the diagnosis")
            wait_for(app, lambda: window.results.forecast.rowCount() > 0, 120, "the forecast score")
            if window.results.report.verdict != "none":
                raise SystemExit(f"screenshot_gui: diagnosed {window.results.report.verdict!r}, not 'none': "
                                 "not the clean run the README shows; not written")
            app.processEvents()
            save(window, out_dir / "gui.png")
            # The results view on its own, given most of the window's height.
            window.results.parentWidget().setSizes([250, height - 250])
            app.processEvents()
            save(window.results, out_dir / "gui_results.png")
            window.results.setCurrentIndex(1)           # the Expert tab
            app.processEvents()
            save(window.results, out_dir / "gui_expert.png")
        finally:
            if window.engine is not None:
                window.engine.emergency_stop()
                window.engine.wait(10)
                window.engine = None
            window.close()
            window.deleteLater()
            app.processEvents()
    return 0


if __name__ == "__main__":
    sys.exit(main())
