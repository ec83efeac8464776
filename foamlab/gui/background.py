"""A one-thread queue of calls whose results come back into the Qt GUI thread.

Used for everything that may block or take long (machine I/O, fits, diagnoses):
calls on one queue run one after another, in order, off the GUI thread; their
callbacks run in the GUI thread, delivered by a queued Qt signal.
"""

from __future__ import annotations

import concurrent.futures
import logging
from typing import Any, Callable

from PySide6 import QtCore

log = logging.getLogger(__name__)


_COLLECTOR = None


def collect_garbage_on_the_gui_thread() -> None:
    """Python's cyclic garbage collected on the GUI thread only, once per process and for its
    whole life (pyqtgraph's GarbageCollector: automatic collection off, a GUI-thread timer
    collects by the same thresholds). A collection started in one of these queues' threads
    destroys Qt objects there: the destructor holds Qt's connection lock and waits for the
    interpreter lock, which the GUI thread holds while it waits for that Qt lock (ci18: a window
    deadlocked while building its Series tab; the collector was the window's then, made after
    its first queues and stopped when the previous window closed)."""
    global _COLLECTOR
    if _COLLECTOR is None:
        from pyqtgraph.util.garbage_collector import GarbageCollector

        _COLLECTOR = GarbageCollector(interval=1.0)


def collect_pending_garbage() -> None:
    """Where the GUI-thread collector took automatic collection over, collect what its thresholds
    call for now, on the calling thread (a cheap count check when there is nothing to do): for a
    process that goes on without its event loop (the tests after a window test)."""
    if _COLLECTOR is not None:
        _COLLECTOR.check()


def describe_error(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    return text.splitlines()[0]


def _expected(exc: BaseException) -> bool:
    """User-actionable errors are logged without a traceback."""
    from foamlab import FoamlabError

    kinds: list[type] = [FoamlabError, OSError, ValueError]
    try:
        from drivers.base import DeviceError

        kinds.append(DeviceError)
    except ImportError:
        pass
    return isinstance(exc, tuple(kinds))


class BackgroundQueue(QtCore.QObject):
    _done = QtCore.Signal(object, object)      # callback, result
    _failed = QtCore.Signal(object, str)       # callback, message

    def __init__(self, name: str, parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)  # created in the GUI thread, so the slots run there
        collect_garbage_on_the_gui_thread()      # before this queue's thread exists
        self._executor = concurrent.futures.ThreadPoolExecutor(max_workers=1, thread_name_prefix=name)
        self._done.connect(self._deliver)
        self._failed.connect(self._deliver)
        self.closed = False

    def submit(self, fn: Callable[[], Any], on_done: Callable[[Any], None] | None = None,
               on_error: Callable[[str], None] | None = None) -> concurrent.futures.Future:
        """Run `fn()` on this queue's thread; then `on_done(result)` or `on_error(message)` in the GUI.
        After shutdown() nothing runs: the returned future is already cancelled."""
        if self.closed:
            future: concurrent.futures.Future = concurrent.futures.Future()
            future.cancel()
            return future

        def job():
            try:
                result = fn()
            except Exception as exc:  # shown to the user by on_error, never raised into Qt
                log.warning("background call failed: %s", exc, exc_info=not _expected(exc))
                if not self.closed:
                    self._failed.emit(on_error, describe_error(exc))
                raise
            if not self.closed:
                self._done.emit(on_done, result)
            return result

        return self._executor.submit(job)

    def _deliver(self, callback, value) -> None:
        if callback is not None and not self.closed:
            callback(value)

    def shutdown(self, wait: bool = False) -> None:
        self.closed = True
        self._executor.shutdown(wait=wait, cancel_futures=True)
