"""analysis.parallel: the search's fits on forked workers give what they give serially, and the
objects the search compares by identity come back as themselves."""

from __future__ import annotations

import os
import threading

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.analysis import parallel

# the thread pytest-timeout's default method starts would make every fork_map here serial
pytestmark = pytest.mark.timeout(120, method="signal")


class Box:
    def __init__(self, value):
        self.value = value


def test_results_come_back_in_order_with_shared_objects_as_themselves():
    shared = Box(np.arange(5.0))
    out = parallel.fork_map(lambda k: (shared, Box(shared.value * k), os.getpid()), [1, 2, 3, 4], [shared],
                            workers=2)
    assert [o[1].value[1] for o in out] == [1.0, 2.0, 3.0, 4.0]
    assert all(o[0] is shared for o in out)              # the parent's own object, not a copy
    assert all(o[1] is not shared for o in out)
    assert {o[2] for o in out} - {os.getpid()}           # they ran in other processes
    assert None in [parallel.fork_map(lambda _: None, [0, 1], [shared], workers=2)[0]]   # None is no shared object


def test_progress_is_called_here_once_per_item():
    seen = []
    parallel.fork_map(lambda k: k * k, range(5), workers=2, done=lambda i, r: seen.append((i, r, os.getpid())))
    assert sorted(seen) == [(i, i * i, os.getpid()) for i in range(5)]


def test_an_error_in_a_worker_is_raised_here():
    def boom(k):
        if k == 2:
            raise FoamlabError("fit 2 failed")
        return k

    with pytest.raises(FoamlabError, match="fit 2 failed"):
        parallel.fork_map(boom, range(4), workers=2)


def test_a_worker_that_dies_is_a_clear_error_not_a_hang():
    with pytest.raises(FoamlabError, match="worker process died"):
        parallel.fork_map(lambda k: os._exit(3) if k == 1 else k, range(3), workers=2)


def test_serial_beside_other_threads_and_inside_a_worker():
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not parallel.can_fork()                   # a fork would copy the other thread's locks
        assert parallel.fork_map(lambda k: os.getpid(), range(3), workers=2) == [os.getpid()] * 3
    finally:
        stop.set()
        other.join()
    # a worker's own fits run where it is
    inner = parallel.fork_map(lambda k: (os.getpid(), parallel.fork_map(lambda j: os.getpid(), range(2), workers=2)),
                              range(2), workers=2)
    assert all(pids == [pid, pid] for pid, pids in inner)


def test_a_diagnosis_on_two_workers_is_the_same_as_on_one(monkeypatch):
    """Every figure of the diagnosis, not only its verdict: the search's fits on forked workers
    are the same computations (independent regime A, 1 N friction, seed 1000: a case whose search
    runs every parallel stage, the refits from a new base included)."""
    import independent_effects as ie

    from foamlab.diagnosis import diagnose
    from foamlab.diagnosis.settings import DiagnosisSettings

    assert parallel.can_fork()
    run = ie.independent_run("A", 1000, {"direction_friction": 1.0}, form="causal", hz=16.0)
    fit_calls = []
    original = parallel.fork_map

    def counted(fn, items, *args, **kw):
        fit_calls.append(len(items))
        return original(fn, items, *args, **kw)

    monkeypatch.setattr("foamlab.diagnosis.core.fork_map", counted)
    one, two = (diagnose([run], settings=DiagnosisSettings(workers=w)).to_dict() for w in (1, 2))
    assert one["verdict"] == "direction_friction"
    assert max(fit_calls) >= 2                           # there was something to share out
    for d in (one, two):
        d.pop("seconds", None)
    assert one == two


def test_the_terminal_progress_bar_leaves_the_diagnosis_free_to_fork(monkeypatch):
    """rich redraws from a thread of its own unless told not to; with that thread running every
    `foamlab diagnose` on a terminal would fit on one core."""
    import io
    import sys

    from foamlab.commands.progress import terminal_progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Tty())
    with terminal_progress("diagnose") as report:
        report("testing", 0.5)
        assert parallel.can_fork()
    assert "diagnose: testing" in sys.stderr.getvalue()
