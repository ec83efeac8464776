"""Run-engine listener for the window: worker-thread callbacks -> Qt.

The engine calls on_sample / on_progress / on_state / on_finished from its worker
thread. Progress, state and the end are rare: they are Qt signals, emitted from
the worker and delivered queued into the GUI thread. Samples are frequent (16 Hz
times the speedup, thousands per second in tests): one queued event each would
flood the event loop, so they go into a deque (append/popleft are thread-safe)
that the window's 30 Hz frame timer drains in one batch.
"""

from __future__ import annotations

import collections

from PySide6 import QtCore


class EngineBridge(QtCore.QObject):
    progress = QtCore.Signal(object)      # foamlab.acquisition.Progress
    state = QtCore.Signal(str)
    finished = QtCore.Signal(object)      # foamlab.acquisition.RunResult

    def __init__(self, parent: QtCore.QObject | None = None) -> None:
        super().__init__(parent)
        self._samples: collections.deque = collections.deque()

    # -- engine side (worker thread) -------------------------------------------------------
    def on_sample(self, sample) -> None:
        self._samples.append(sample)

    def on_progress(self, progress) -> None:
        self.progress.emit(progress)

    def on_state(self, state: str) -> None:
        self.state.emit(state)

    def on_finished(self, result) -> None:
        self.finished.emit(result)

    # -- GUI side --------------------------------------------------------------------------
    def drain(self) -> list:
        """Every sample received since the last call, in order."""
        return drained(self._samples)


def drained(queue: collections.deque) -> list:
    """Everything appended to `queue` (by another thread) so far, in order, taken out of it."""
    out = []
    pop = queue.popleft
    try:
        while True:
            out.append(pop())
    except IndexError:
        return out
