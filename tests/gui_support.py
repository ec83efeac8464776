"""What every window test does at its end, whatever the test did: answer an open question,
end any run (e-stop), close the machine link and the simulator, stop the window's threads."""

from __future__ import annotations


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
