"""Python's cyclic garbage is collected on the GUI thread only once the window's background
queues exist (foamlab.gui.background.collect_garbage_on_the_gui_thread): a collection in a queue's
thread destroyed Qt objects there and deadlocked the window (ci18)."""

from __future__ import annotations

import gc
import threading

import pytest

pytestmark = pytest.mark.gui


def test_a_background_queue_turns_automatic_collection_over_to_the_gui_thread(qtbot):
    from foamlab.gui import background

    queue = background.BackgroundQueue("gc-test")
    try:
        assert not gc.isenabled() and background._COLLECTOR.timer.isActive()
        collected_in: list[str] = []

        class Marker:
            def __del__(self):
                collected_in.append(threading.current_thread().name)

        def cycles() -> bool:
            for _ in range(2 * gc.get_threshold()[0]):   # enough to pass the first generation's threshold
                a = []
                a.append(a)
            return False

        def make_garbage():
            cycles()
            m = Marker()
            m.cycle = m                 # freed only by the cyclic collector
            return None

        results = []
        queue.submit(make_garbage, results.append, lambda msg: results.append(msg))
        qtbot.waitUntil(lambda: bool(results), timeout=10_000)
        # the GUI thread's timer (1 s) collects the young generation, the older ones every tenth time
        qtbot.waitUntil(lambda: cycles() or bool(collected_in), timeout=30_000)
        assert collected_in == [threading.main_thread().name]
    finally:
        queue.shutdown(wait=True)
