"""The batch on Dask distributed: files found, hashed, skipped or submitted, results kept.

One task per run (Client.submit of foamlab.batch.task.analyse_file); results are taken as
they complete and written at once (foamlab.batch.store). When a worker dies, the scheduler
gives its runs to another worker (up to distributed's ``scheduler.allowed-failures`` times);
a run that still has no result becomes a "task" row, retried by the next batch.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import logging
import os
from collections.abc import Callable, Iterable, Iterator
from pathlib import Path

import pandas as pd

from foamlab import FoamlabError, __version__
from foamlab.batch.rows import BatchRow
from foamlab.batch.store import Destination, ResultStore
from foamlab.batch.task import Outcome, analyse_file

#: Files a folder is searched for (a file named on its own is read whatever its name).
DATA_SUFFIXES = (".csv", ".txt", ".tsv")
#: No result for this long (s): the runs still out become "task" rows and the batch ends.
STALL_TIMEOUT_S = 3600.0
CONNECT_TIMEOUT_S = 30.0
#: How long a cluster without workers is waited for (s).
WORKER_TIMEOUT_S = 120.0

#: on_row(row, done, total): called on the client as each run's row is written.
OnRow = Callable[[BatchRow, int, int], None]


def find_runs(paths: Iterable[str | Path], leave_out: Iterable[Path] = ()) -> list[Path]:
    """Every data file under the paths (folders walked, sorted, hidden ones left out; each file
    once), but for the files and folders in `leave_out` (absolute: what the batch writes)."""
    found: dict[Path, None] = {}
    for given in paths:
        p = Path(given).expanduser()
        if p.is_dir():
            for f in sorted(p.rglob("*")):
                if f.is_file() and f.suffix.lower() in DATA_SUFFIXES and not _hidden(f, p):
                    found.setdefault(f.resolve(), None)
        elif p.exists():
            found.setdefault(p.resolve(), None)
        else:
            raise FoamlabError(f"{p}: no such file or folder")
    left_out = set(leave_out)
    return [f for f in found if f not in left_out and not left_out.intersection(f.parents)]


def _hidden(f: Path, root: Path) -> bool:
    return any(part.startswith(".") for part in f.relative_to(root).parts)


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def process(paths: Iterable[str | Path], client=None, *, out: str | Path | None = None,
            catalog: str | Path | None = None, scheduler: str | None = None, workers: int | None = None,
            on_row: OnRow | None = None, stall_timeout: float = STALL_TIMEOUT_S) -> pd.DataFrame:
    """Fit and diagnose every run under `paths`, one Dask task per run; one row per run.

    client: a distributed.Client to use (left open); else one to the scheduler at `scheduler`,
    else a LocalCluster of `workers` processes (default: one per core), closed at the end.
    out: a .csv or .parquet file: results are journalled beside it as they come, earlier results
    of the same content are reused (see foamlab.batch.store). catalog: the SQLite catalog of the
    runs that are not foamlab run files (default: catalog.sqlite beside `out`).
    """
    dest = Destination.choose(out, catalog)
    files = find_runs(paths, leave_out=dest.written())
    store = ResultStore(dest)
    try:
        earlier = store.previous()
        rows: dict[Path, BatchRow] = {}
        todo: list[tuple[Path, str]] = []
        for f in files:
            sha = _sha_or_row(f, rows)
            if sha is None:
                continue
            if sha in earlier:
                rows[f] = _moved(earlier[sha], f)
            else:
                todo.append((f, sha))
        if todo:
            with _client(client, scheduler, workers) as c:
                for outcome in _results(c, todo, stall_timeout):
                    row = store.add(outcome)
                    rows[Path(row.file)] = row
                    if on_row is not None:
                        on_row(row, len(rows), len(files))
    finally:
        store.close()
    return store.finish([rows[f] for f in files])


def _sha_or_row(f: Path, rows: dict[Path, BatchRow]) -> str | None:
    try:
        return sha256_of(f)
    except OSError as exc:
        rows[f] = BatchRow(str(f), "", error=f"{f}: cannot read ({exc.strerror or exc})", error_kind="read")
        return None


def _moved(row: BatchRow, f: Path) -> BatchRow:
    """An earlier result of this content, now found at `f` (the same file, or a copy)."""
    return dataclasses.replace(row, file=str(f), parameters=dict(row.parameters))


@contextlib.contextmanager
def _client(client, scheduler: str | None, workers: int | None) -> Iterator:
    if client is not None:
        yield client
        return
    from distributed import Client, LocalCluster  # noqa: PLC0415 (only a batch needs Dask)

    if scheduler:
        try:
            c = Client(scheduler, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError, ValueError) as exc:
            raise FoamlabError(f"cannot connect to the Dask scheduler at {scheduler} "
                               f"({str(exc).splitlines()[0] if str(exc) else type(exc).__name__})") from None
        with c:
            try:
                c.wait_for_workers(1, timeout=WORKER_TIMEOUT_S)
            except TimeoutError:
                raise FoamlabError(f"the Dask scheduler at {scheduler} has no workers (none came in "
                                   f"{WORKER_TIMEOUT_S:g} s; start some: dask worker {scheduler})") from None
            _check_workers(c, scheduler)
            yield c
        return
    n = workers or os.cpu_count() or 1
    # the worker processes import the foamlab this client runs (also from a checkout, not installed)
    here = str(Path(__file__).resolve().parents[2])
    env = {"PYTHONPATH": os.pathsep.join(p for p in (here, os.environ.get("PYTHONPATH", "")) if p)}
    with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                      silence_logs=logging.ERROR, env=env) as cluster, Client(cluster) as c:
        yield c


def _check_workers(client, scheduler: str) -> None:
    """Every worker imports foamlab, of this client's version (else every task would fail)."""
    try:
        versions = client.run(worker_version)
    except Exception as exc:
        raise FoamlabError(f"the workers of {scheduler} cannot run foamlab ({type(exc).__name__}: "
                           f"{str(exc).splitlines()[0] if str(exc) else ''}); install it on every "
                           "worker (docs/batch.md)") from None
    other = {w: v for w, v in versions.items() if v != __version__}
    if other:
        raise FoamlabError(f"workers run another foamlab than this client ({__version__}): "
                           + ", ".join(f"{w} {v}" for w, v in sorted(other.items())))


def worker_version() -> str:
    return __version__


def _results(client, todo: list[tuple[Path, str]], stall_timeout: float) -> Iterator[Outcome]:
    """Each run's Outcome as its task completes (any order); lost runs as "task" rows."""
    from distributed import wait  # noqa: PLC0415

    futures = {client.submit(analyse_file, str(f), sha, key=f"foamlab-batch-{i}-{sha[:16]}"): (f, sha)
               for i, (f, sha) in enumerate(todo)}
    pending = set(futures)
    while pending:
        try:
            done, pending = wait(pending, timeout=stall_timeout, return_when="FIRST_COMPLETED")
        except TimeoutError:
            done, pending = pending, set()
        for future in done:
            f, sha = futures.pop(future)
            yield _outcome_of(future, f, sha, stall_timeout)
            future.release()


def _outcome_of(future, f: Path, sha: str, stall_timeout: float) -> Outcome:
    if future.status == "finished":
        try:
            return future.result(timeout=stall_timeout)
        except Exception as exc:   # the worker holding it died between completion and transfer
            why = f"result lost ({type(exc).__name__}: {exc})"
    elif future.status == "error":
        exc = future.exception(timeout=stall_timeout)
        why = f"{type(exc).__name__}: {exc}"
    elif future.status == "pending":
        why = f"no result within {stall_timeout:g} s"
    else:
        why = f"task {future.status}"
    line = next((ln for ln in why.splitlines() if ln.strip()), why)
    return Outcome(BatchRow(str(f), sha, error=f"not processed: {line}", error_kind="task"))
