"""Independent fits of one diagnosis on the machine's cores: fork workers, shared objects kept.

A diagnosis's search fits each candidate cause on its own (probes, joint fits, several
starts): pure functions of the runs and the model so far, so they can run side by side.
Workers are forked (Linux), so they start with the runs, their cached columns and the fits
so far already in memory; a result is pickled back with the objects that existed before the
fork (``shared``: the series, the current fits) sent as references and restored as the
parent's own objects - the search compares them by identity (``contact_of``, ``c.before is``).

Each task computes exactly what it would serially (the same functions on the same inputs), so
the results are the same bits; only the wall time changes. Serial where forking is not safe
or not worth it: one task, one worker, inside a worker, a daemonic process (multiprocessing's
and Dask's workers), other Python threads running (the window's background diagnosis: a fork
copies their locks), or not Linux. Written here rather than with a library: joblib and
multiprocessing pickle every argument (the runs' column caches: tens of MB per task) and
return copies, where the search needs its own objects back.
"""

from __future__ import annotations

import io
import multiprocessing
import os
import pickle
import sys
import threading
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from typing import Callable, Iterable, Sequence, TypeVar

from foamlab import FoamlabError

T = TypeVar("T")
R = TypeVar("R")

#: Set in a worker: its own fits run serially (the machine's cores are already in use).
_in_worker = False
_MISSING = object()
#: The task of the pool being forked: (function, items, shared objects by id).
_task: tuple | None = None


def default_workers() -> int:
    """The cores this process may use."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def can_fork() -> bool:
    """Forking workers is safe here: Linux, the only Python thread, not itself a worker."""
    return (sys.platform.startswith("linux") and not _in_worker
            and not multiprocessing.current_process().daemon and threading.active_count() == 1)


def processes(workers: int | None = None) -> int:
    """The processes fork_map would use here for as many items (1: it would run serially)."""
    return (workers or default_workers()) if can_fork() else 1


def serial_map(fn: Callable[[T], R], items: Sequence[T], done: Callable[[int, R], None] | None = None) -> list[R]:
    """fork_map in this process, one item after the other."""
    out = []
    for i, item in enumerate(items):
        out.append(fn(item))
        if done is not None:
            done(i, out[-1])
    return out


def fork_map(fn: Callable[[T], R], items: Sequence[T], shared: Iterable[object] = (), workers: int | None = None,
             done: Callable[[int, R], None] | None = None) -> list[R]:
    """[fn(item) for item in items], on up to ``workers`` forked processes where that is safe.

    shared: objects fn's results may refer to that must come back as these very objects.
    done(i, result): called in this process as each result arrives (progress), in completion order.
    """
    items = list(items)
    n = min(processes(workers), len(items))
    if n <= 1:
        return serial_map(fn, items, done)
    global _task
    by_id = {id(o): o for o in shared}
    _task = (fn, items, by_id)
    results: list = [None] * len(items)
    try:
        with ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork"),
                                 initializer=_mark_worker) as pool:
            futures = {pool.submit(_run, i): i for i in range(len(items))}
            for future in as_completed(futures):
                i = futures[future]
                results[i] = _Unpickler(io.BytesIO(future.result()), by_id).load()
                if done is not None:
                    done(i, results[i])
    except BrokenProcessPool as exc:     # killed (out of memory, a signal): nothing to return
        raise FoamlabError(f"a worker process died ({exc}); run with one worker (--workers 1) "
                           "or free memory") from None
    finally:
        _task = None
    return results


class Ahead:
    """One call computed ahead in a forked process (fork_ahead), while this one goes on: its
    result when asked for, or cancelled (the process ended) when it is not needed."""

    def __init__(self, fn: Callable[[], R], shared: Iterable[object] = ()):
        self.by_id = {id(o): o for o in shared}
        ctx = multiprocessing.get_context("fork")
        self._pipe, send = ctx.Pipe(duplex=False)
        self._process = ctx.Process(target=_ahead, args=(fn, self.by_id, send), daemon=True)
        self._process.start()
        send.close()

    def result(self) -> R:
        """The call's result (waits for it); its error raised here, as the call would have."""
        try:
            data = self._pipe.recv_bytes()
        except EOFError:
            raise FoamlabError("a worker process died; run with one worker (--workers 1) or free memory") from None
        finally:
            self.cancel()
        failed, value = _Unpickler(io.BytesIO(data), self.by_id).load()
        if failed:
            raise value
        return value

    def cancel(self) -> None:
        """End the process (its work unused) and wait for it; again: nothing."""
        if self._process.is_alive():
            self._process.terminate()
        self._process.join()
        self._pipe.close()


def fork_ahead(fn: Callable[[], R], shared: Iterable[object] = ()) -> Ahead | None:
    """fn() started in a forked process beside this one (Ahead), or None where fork_map would run
    serially (one core, another thread, inside a worker) or no core is idle: the caller then
    calls fn when it needs it. shared: as fork_map's. For work that may be needed: a core
    otherwise idle computes it while this process finds out whether it is; on a busy machine
    (tests on every core) work that may be thrown away would only slow the rest."""
    return Ahead(fn, shared) if processes() > 1 and idle_cores() > 0 else None


def idle_cores() -> int:
    """The cores this process may use less the processes running now (this one included; Linux's
    /proc/loadavg); 1 where that cannot be read."""
    try:
        with open("/proc/loadavg", encoding="ascii") as fh:
            running = int(fh.read().split()[3].split("/")[0])
    except (OSError, ValueError, IndexError):
        return 1
    return default_workers() - running


def _ahead(fn, by_id: dict[int, object], send) -> None:
    _mark_worker()
    try:
        out = (False, fn())
    except BaseException as exc:       # said where the result is asked for
        out = (True, exc if isinstance(exc, Exception) else FoamlabError(repr(exc)))
    buf = io.BytesIO()
    try:
        _Pickler(buf, by_id).dump(out)
    except Exception as exc:           # an unpicklable result or error: its words
        buf = io.BytesIO()
        _Pickler(buf, by_id).dump((True, FoamlabError(f"{type(exc).__name__}: {exc}")))
    send.send_bytes(buf.getvalue())
    send.close()


def _mark_worker() -> None:
    global _in_worker
    _in_worker = True


def _run(i: int) -> bytes:
    fn, items, by_id = _task
    buf = io.BytesIO()
    _Pickler(buf, by_id).dump(fn(items[i]))
    return buf.getvalue()


class _Pickler(pickle.Pickler):
    def __init__(self, file, by_id: dict[int, object]):
        super().__init__(file, protocol=pickle.HIGHEST_PROTOCOL)
        self.by_id = by_id

    def persistent_id(self, obj):
        # the fork copied the parent's memory: a shared object has the same id here
        return id(obj) if self.by_id.get(id(obj), _MISSING) is obj else None


class _Unpickler(pickle.Unpickler):
    def __init__(self, file, by_id: dict[int, object]):
        super().__init__(file)
        self.by_id = by_id

    def persistent_load(self, pid):
        return self.by_id[pid]
