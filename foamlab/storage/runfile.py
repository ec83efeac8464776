"""The run file: one CSV per run, written while the run is acquired.

Layout (pandas ``read_csv(path, comment='#')`` and any spreadsheet open it)::

    # foamlab run file v1
    # method: paper-3cycle
    # specimen_label: PU-45 A
    # specimen_height_mm: 72.5
    # ...                               (one ``# key: value`` line per header item;
    # meta.operator: "Anna"              free metadata as ``meta.<key>: <JSON>``)
    time_s,displacement_mm,force_N,rtt_ms
    0.0,0.0,0.012,1.31
    ...                                 (one line per sample, flushed as it arrives)
    # finished_at: 2025-01-01T10:12:00+01:00
    # status: finished                  (or aborted, with # abort_reason: ...)
    # meta.schedule: {"missed": 0, ...}  (what the engine knew at the end: runformat's keys)

A run the engine recorded also has the columns ``step,cycle`` (each sample's labels, read
back as RunData.step / .cycle) and in its header the method itself (methods.METHOD_KEY)
and the machine profile's name.

Durability: every line is flushed to the OS when written, so a crash of the
process loses at most the sample in flight; os.fsync runs at most every
``fsync_interval_s`` (and at close) so a power cut loses at most that much.
A file without a ``# status:`` trailer is a run that never finished (crash, or
still being written); it reads back as ``aborted`` with the samples it has.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import os
import threading
import time
from pathlib import Path
from typing import Any, Callable, TextIO

from foamlab import FoamlabError, __version__
from foamlab.importers import plain_csv
from foamlab.importers._text import read_text
from foamlab.rundata import RunData, Specimen
from foamlab.runformat import (
    BASE_COLUMNS,
    LABEL_COLUMNS,
    MAGIC,
    META_PREFIX,
    SPECIMEN_FIELDS,
    is_run_file,
)

DEFAULT_COLUMNS = BASE_COLUMNS + ("rtt_ms",)
#: Written in this order at the top of the file, when present.
HEADER_ORDER = ("method", "specimen_label", "specimen_height_mm", "specimen_width_mm",
                "specimen_depth_mm", "machine", "software", "started_at", "sampling_hz")


def now_iso() -> str:
    return _dt.datetime.now().astimezone().isoformat(timespec="seconds")


def _one_line(value: Any) -> str:
    return " ".join(str(value).splitlines()).strip()


def header_lines(header: dict[str, Any]) -> list[str]:
    """``# key: value`` lines for a header dict (see RunWriter for the keys)."""
    items: dict[str, Any] = {}
    header = dict(header)
    specimen = header.pop("specimen", None)
    if isinstance(specimen, Specimen):
        header.setdefault("specimen_label", specimen.label)
        header.setdefault("specimen_height_mm", specimen.height_mm)
        header.setdefault("specimen_width_mm", specimen.width_mm)
        header.setdefault("specimen_depth_mm", specimen.depth_mm)
    elif isinstance(specimen, dict):
        for key, field in SPECIMEN_FIELDS.items():
            header.setdefault(key, specimen.get(field))
    header.setdefault("software", f"foamlab {__version__}")
    header.setdefault("started_at", now_iso())
    metadata = dict(header.pop("metadata", None) or {})
    for key in HEADER_ORDER:
        if header.get(key) not in (None, ""):
            items[key] = header.pop(key)
        else:
            header.pop(key, None)
    for key in ("finished_at", "status", "abort_reason", "columns"):
        header.pop(key, None)
    for key, value in header.items():  # anything else the caller described the run with
        if value is not None:
            metadata.setdefault(key, value)
    lines = [MAGIC]
    for key, value in items.items():
        lines.append(f"# {key}: {_one_line(value)}")
    return lines + _meta_lines(metadata)


def _meta_lines(metadata: dict[str, Any]) -> list[str]:
    return [f"# {META_PREFIX}{_one_line(key).replace(':', '_')}: "
            f"{json.dumps(_json_safe(value), ensure_ascii=False)}" for key, value in metadata.items()]


def trailer_lines(status: str, reason: str = "", safety: str = "", finished_at: str = "",
                  facts: dict[str, Any] | None = None) -> list[str]:
    """The ``#`` lines closing a run file: finished_at, status, abort_reason, safety, then
    `facts` known only at the end (the schedule's statistics, how the run ended) as metadata."""
    lines = [f"# finished_at: {finished_at or now_iso()}", f"# status: {status}"]
    if reason or status == "aborted":
        lines.append(f"# abort_reason: {_one_line(reason) or 'not given'}")
    if safety:
        lines.append(f"# safety: {_one_line(safety)}")
    return lines + _meta_lines(facts or {})


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return str(value)
    if isinstance(value, (str, int, float, bool)) or value is None:
        return value
    if isinstance(value, dict):
        return {str(k): _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    if hasattr(value, "item"):          # numpy scalars
        return _json_safe(value.item())
    return str(value)


def _format(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, int):          # labels (step, cycle) stay integers in the file
        return str(value)
    v = float(value)
    return repr(v) if math.isfinite(v) else "nan"


class RunWriter:
    """Writes a run file sample by sample; see the module docstring.

    ``header`` keys: method, specimen (a Specimen or a dict) or specimen_label /
    _height_mm / _width_mm / _depth_mm, machine, software (default: this
    foamlab), started_at (default: now), sampling_hz, metadata (dict); any other
    key is kept as free metadata. ``columns`` are the CSV columns: the three base
    columns first, extra ones (default ``rtt_ms``) after.

    The file must not exist yet: a run never overwrites another. ``opener`` opens it
    (``open``'s signature; tests pass one whose writes fail, as a full disk's do).
    """

    def __init__(self, path: str | Path, header: dict[str, Any],
                 columns: tuple[str, ...] | list[str] | None = None,
                 fsync_interval_s: float = 0.5, opener: Callable[..., TextIO] = open) -> None:
        columns = tuple(columns or header.get("columns") or DEFAULT_COLUMNS)
        if columns[:3] != BASE_COLUMNS:
            raise ValueError(f"run file columns must start with {','.join(BASE_COLUMNS)}")
        self.path = Path(path)
        self.columns = columns
        self.fsync_interval_s = fsync_interval_s
        self.n_samples = 0
        self.closed = False
        self._lock = threading.Lock()
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = opener(self.path, "x", encoding="utf-8", newline="\n")
        except FileExistsError:
            raise FoamlabError(f"{self.path}: already exists; a run file is never overwritten") from None
        except OSError as exc:
            raise FoamlabError(f"{self.path}: cannot create the run file ({exc.strerror or exc})") from None
        self.header = header_lines(header)      # as written: the recorder's RunData is made of them
        self.trailer: list[str] = []
        self._file.write("\n".join(self.header + [",".join(columns)]) + "\n")
        self._sync()

    def write_sample(self, time_s: float, displacement_mm: float, force_N: float,
                     *extra: float | None) -> None:
        """Append one sample (extra values in the order of the extra columns)."""
        if len(extra) > len(self.columns) - 3:
            raise ValueError(f"{len(extra)} extra values for columns {self.columns[3:]}")
        values = (time_s, displacement_mm, force_N) + extra
        values += (None,) * (len(self.columns) - len(values))
        line = ",".join(_format(v) for v in values) + "\n"
        with self._lock:
            if self.closed:
                raise FoamlabError(f"{self.path}: run file already closed")
            self._file.write(line)
            self._file.flush()      # in the OS now: survives a crash of this process
            self.n_samples += 1
            if time.monotonic() - self._last_sync >= self.fsync_interval_s:
                os.fsync(self._file.fileno())
                self._last_sync = time.monotonic()

    def finish(self, status: str = "finished", reason: str = "", safety: str = "",
               facts: dict[str, Any] | None = None) -> None:
        """Write the trailer (trailer_lines) and close. Idempotent.

        `safety`: what went wrong bringing the machine to rest (a stop not acknowledged, a
        crosshead not confirmed at rest, failed status polls), kept with the run it concerns.
        `facts`: what is known only at the end (runformat's SCHEDULE_KEY and END_KEY)."""
        if status not in ("finished", "aborted"):
            raise ValueError(f"status must be 'finished' or 'aborted', not {status!r}")
        with self._lock:
            if self.closed:
                return
            self.trailer = trailer_lines(status, reason, safety, facts=facts)
            self._file.write("\n".join(self.trailer) + "\n")
            self._sync()
            self._file.close()
            self.closed = True

    close = finish

    def abandon(self) -> None:
        """Close without a trailer after a failed write (full disk); the file is left as it is."""
        with self._lock:
            if self.closed:
                return
            self.closed = True
            try:
                self._file.close()          # may retry the failed flush and fail again
            except OSError:
                pass

    def _sync(self) -> None:
        self._file.flush()
        os.fsync(self._file.fileno())
        self._last_sync = time.monotonic()

    def __enter__(self) -> "RunWriter":
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.finish("finished")
        else:
            self.finish("aborted", f"{exc_type.__name__}: {exc}" if exc else exc_type.__name__)


def write_run_file(path: str | Path, run: RunData, extra: dict[str, Any] | None = None) -> Path:
    """Write a whole RunData as a run file (simulated runs, conversions)."""
    header: dict[str, Any] = {
        "method": run.method, "specimen": run.specimen, "machine": run.machine,
        "started_at": run.started_at or now_iso(), "metadata": dict(run.metadata),
    }
    if len(run) > 1:
        header["sampling_hz"] = round(run.sampling_hz, 6)
    header.update(extra or {})
    columns = BASE_COLUMNS + (LABEL_COLUMNS if run.has_labels else ())
    writer = RunWriter(path, header, columns=columns, fsync_interval_s=math.inf)
    arrays = [run.time_s.tolist(), run.displacement_mm.tolist(), run.force_N.tolist()]
    if run.has_labels:
        arrays += [run.step.tolist(), run.cycle.tolist()]
    writer._file.writelines(",".join(_format(v) for v in row) + "\n" for row in zip(*arrays))
    writer.n_samples = len(run)
    status = run.status if run.status in ("finished", "aborted") else "finished"
    writer.finish(status, run.abort_reason)
    return writer.path


def read_run_file(path: str | Path) -> RunData:
    """A run file back as RunData (extra columns are listed in metadata['extra_columns'])."""
    text_file = read_text(path)
    lines = text_file.lines
    if not lines or not is_run_file(lines[0]):
        raise FoamlabError(f"{path}: not a foamlab run file (first line is not '{MAGIC}')")
    return plain_csv.parse(text_file, run_file=True)
