"""What every window test does at its end, whatever the test did: answer an open question,
end any run (e-stop), close the machine link and the simulator, stop the window's threads."""

from __future__ import annotations

from PySide6 import QtCore

from simulator.process import START_TIMEOUT_S

#: How long a window test waits for the next thing the window or the simulated machine does: a
#: guard against a hang, never a promptness check (the schedule tests and benchmarks/ time things).
#: Phase 1 runs in the idle class beside phase 2 on two shared cores; there a step that takes
#: 50 ms alone can wait many seconds (stop 48: the built-in machine's start took over 20 s).
WAIT_MS = 60_000
#: Connecting waits past the built-in machine's own start timeout, so a start that fails is
#: reported by the window (its message in the assertion), not cut short by the test.
CONNECT_WAIT_MS = int(START_TIMEOUT_S * 1000) + WAIT_MS


def connect_window(qtbot, w) -> None:
    """Click Connect and wait until the window is connected; fail with the window's own words."""
    qtbot.mouseClick(w.connect_button, QtCore.Qt.MouseButton.LeftButton)
    qtbot.waitUntil(lambda: w.connected or "Not connected" in w.connection_label.text(),
                    timeout=CONNECT_WAIT_MS)
    assert w.connected, w.connection_label.text()


def shut_window(w) -> None:
    close_dialog = getattr(w, "close_dialog", None)   # a window built before dialogs (none open)
    if close_dialog is not None:
        close_dialog()
    if w.engine is not None:
        w.engine.emergency_stop()
        w.engine.wait(10.0)
        w.engine = None
    w.link.shutdown()
    w.analysis.shutdown(wait=True)
    live = getattr(getattr(w, "display", None), "live", None)   # a window built before live prediction
    if live is not None:
        live.shutdown()
    w.estop_queue.shutdown(wait=True)
    series = getattr(w, "series_view", None)           # a window built before the Series tab
    if series is not None:
        series.queue.shutdown(wait=True)
