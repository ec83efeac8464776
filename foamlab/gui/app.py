"""Start the window: QApplication, MainWindow, event loop."""

from __future__ import annotations

import logging
import math
import os
import sys
from pathlib import Path

from foamlab import FoamlabError


def run_gui(speedup: float = 1.0, out_dir: str | Path = "foamlab-data", profile: str | None = None,
            method: str | None = None, open_path: str | None = None, simulator: dict | None = None) -> int:
    """`simulator`: the built-in simulated machine's options (effects, seed; simulator.launch)."""
    if not (math.isfinite(speedup) and speedup > 0):
        raise FoamlabError(f"--speedup must be a positive number, got {speedup}")
    if (sys.platform.startswith("linux") and not os.environ.get("QT_QPA_PLATFORM")
            and not os.environ.get("DISPLAY") and not os.environ.get("WAYLAND_DISPLAY")):
        # Qt would abort the process with a long plugin message; say it in one line instead.
        raise FoamlabError("no display to open the window on (DISPLAY/WAYLAND_DISPLAY unset); run it on "
                           "a desktop, or use 'foamlab run' for a headless test")
    try:
        from PySide6 import QtCore, QtWidgets
    except ImportError as exc:
        raise FoamlabError(f"the window needs PySide6 ({exc}); install foamlab's dependencies") from None
    from foamlab.gui.window import MainWindow

    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    app = QtWidgets.QApplication.instance() or QtWidgets.QApplication(sys.argv[:1])
    app.setApplicationName("foamlab")
    window = MainWindow(speedup=speedup, out_dir=out_dir, profile=profile, method=method, simulator=simulator)
    # Deleted while the event loop still runs: Qt objects left to interpreter shutdown can crash it.
    window.setAttribute(QtCore.Qt.WidgetAttribute.WA_DeleteOnClose)
    window.show()
    if open_path:
        window.open_file(open_path)
    return int(app.exec())
