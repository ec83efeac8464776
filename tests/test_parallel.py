"""analysis.parallel: the search's fits on forked workers give what they give serially, and the
objects the search compares by identity come back as themselves.

The checks that need a fork run in a fresh interpreter: a test before them in the same pytest
worker may leave a thread behind (the live predictor's executor ends its manager thread after
close() returns), and beside any other thread fork_map is serial by design."""

from __future__ import annotations

import os
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.analysis import parallel

HERE = Path(__file__).parent


class Box:
    def __init__(self, value):
        self.value = value


def _fresh(check: str, timeout: float = 120.0) -> None:
    """Run test_parallel.<check>() in a new interpreter (no thread but its main one)."""
    code = (f"import sys; sys.path[:0] = [{str(HERE)!r}, {str(HERE.parent)!r}]; "
            f"import test_parallel; test_parallel.{check}()")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=timeout)
    assert done.returncode == 0, done.stderr[-3000:]


def _check_shared_objects() -> None:
    assert parallel.can_fork()
    shared = Box(np.arange(5.0))
    out = parallel.fork_map(lambda k: (shared, Box(shared.value * k), os.getpid()), [1, 2, 3, 4], [shared],
                            workers=2)
    assert [o[1].value[1] for o in out] == [1.0, 2.0, 3.0, 4.0]
    assert all(o[0] is shared for o in out)              # the parent's own object, not a copy
    assert all(o[1] is not shared for o in out)
    assert {o[2] for o in out} - {os.getpid()}           # they ran in other processes
    assert parallel.fork_map(lambda _: None, [0, 1], [shared], workers=2) == [None, None]  # None: no shared object
    seen = []
    parallel.fork_map(lambda k: k * k, range(5), workers=2, done=lambda i, r: seen.append((i, r, os.getpid())))
    assert sorted(seen) == [(i, i * i, os.getpid()) for i in range(5)]     # progress: here, once per item


def _check_errors() -> None:
    def boom(k):
        if k == 2:
            raise FoamlabError("fit 2 failed")
        return k

    with pytest.raises(FoamlabError, match="fit 2 failed"):
        parallel.fork_map(boom, range(4), workers=2)
    with pytest.raises(FoamlabError, match="worker process died"):         # not a hang
        parallel.fork_map(lambda k: os._exit(3) if k == 1 else k, range(3), workers=2)


def _check_nested() -> None:
    outer = parallel.fork_map(lambda k: (os.getpid(), parallel.fork_map(lambda j: os.getpid(), range(2), workers=2)),
                              range(2), workers=2)
    assert all(pid != os.getpid() and pids == [pid, pid] for pid, pids in outer)   # a worker's own fits run there


def _check_ahead() -> None:
    shared = Box(np.arange(3.0))
    got, new, pid = parallel.Ahead(lambda: (shared, Box(shared.value * 2), os.getpid()), [shared]).result()
    assert got is shared and new.value[2] == 4.0 and pid != os.getpid()      # computed there, shared as itself

    def boom():
        raise FoamlabError("the fit ahead failed")

    with pytest.raises(FoamlabError, match="the fit ahead failed"):
        parallel.Ahead(boom).result()
    with pytest.raises(FoamlabError, match="worker process died"):           # not a hang
        parallel.Ahead(lambda: os._exit(3)).result()
    blocked = parallel.Ahead(lambda: threading.Event().wait())                # never returns by itself
    blocked.cancel()
    assert not blocked._process.is_alive() and blocked._process.exitcode is not None
    blocked.cancel()                                                           # again: nothing
    parallel.idle_cores = lambda: 0                   # every core busy: work that may be thrown away waits
    assert parallel.fork_ahead(lambda: 1) is None
    parallel.idle_cores = lambda: 1
    assert parallel.fork_ahead(lambda: 1).result() == 1


def _check_fit_ahead() -> None:
    """Identification's whole fit with the turns placed the other way, fitted ahead on another
    core, is the fit it makes here (independent A, clean seed 2000: a run whose first fit misfits
    at its turns, so the other placement is needed)."""
    import independent_effects as ie

    import foamlab.identification.fit as fit

    run = ie.independent_run("A", 2000, None, form="causal", hz=16.0)
    parallel.idle_cores = lambda: 1                   # as on an idle machine, whatever else runs now
    used = []
    original = parallel.Ahead.result
    parallel.Ahead.result = lambda self: used.append(1) or original(self)
    ahead = fit.fit_run(run).to_dict()
    fit.fork_ahead = lambda fn, shared=(): None
    here = fit.fit_run(run).to_dict()
    assert used                                       # the fit ahead was the one kept or compared
    strip = lambda d: {k: v for k, v in d.items() if k != "elapsed_s"}
    assert strip(ahead) == strip(here)


def test_results_come_back_in_order_with_shared_objects_as_themselves():
    _fresh("_check_shared_objects")


def test_an_error_in_a_worker_is_raised_here_and_a_dead_worker_is_said():
    _fresh("_check_errors")


def test_a_workers_own_fits_run_where_it_is():
    _fresh("_check_nested")


def test_work_ahead_comes_back_as_computed_errors_are_said_and_cancel_ends_it():
    _fresh("_check_ahead")


def test_the_fit_with_its_turns_the_other_way_fitted_ahead_is_the_fit_made_here():
    _fresh("_check_fit_ahead", timeout=240.0)


def test_serial_beside_another_thread():
    stop = threading.Event()
    other = threading.Thread(target=stop.wait)
    other.start()
    try:
        assert not parallel.can_fork()                   # a fork would copy the other thread's locks
        assert parallel.fork_map(lambda k: os.getpid(), range(3), workers=2) == [os.getpid()] * 3
        assert parallel.fork_ahead(lambda: 1) is None     # the caller computes it when needed
    finally:
        stop.set()
        other.join()


def _check_diagnosis() -> None:
    """Every figure of the diagnosis, not only its verdict: the search's fits on forked workers
    are the same computations (independent regime A, 1 N friction, seed 1000: a case whose search
    runs every parallel stage, the refits from a new base included)."""
    import independent_effects as ie

    import foamlab.diagnosis.core as core
    from foamlab.diagnosis import diagnose
    from foamlab.diagnosis.settings import DiagnosisSettings

    assert parallel.can_fork()
    run = ie.independent_run("A", 1000, {"direction_friction": 1.0}, form="causal", hz=16.0)
    widths = []
    original = core.fork_map

    def counted(fn, items, *args, **kw):
        widths.append(len(items))
        return original(fn, items, *args, **kw)

    core.fork_map = counted
    one, two = (diagnose([run], settings=DiagnosisSettings(workers=w)).to_dict() for w in (1, 2))
    assert one["verdict"] == "direction_friction"
    assert max(widths) >= 2                              # there was something to share out
    assert one == two


def test_a_diagnosis_on_two_workers_is_the_same_as_on_one():
    _fresh("_check_diagnosis", timeout=240.0)


def test_the_terminal_progress_bar_starts_no_thread(monkeypatch):
    """rich redraws from a thread of its own unless told not to; with that thread running every
    `foamlab diagnose` on a terminal would fit on one core (fork_map is serial beside a thread)."""
    import io

    from foamlab.commands.progress import terminal_progress

    class Tty(io.StringIO):
        def isatty(self):
            return True

    monkeypatch.setattr(sys, "stderr", Tty())
    before = threading.active_count()
    with terminal_progress("diagnose") as report:
        report("testing", 0.5)
        assert threading.active_count() == before
    assert "diagnose: testing" in sys.stderr.getvalue()
