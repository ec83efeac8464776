"""The recorder: a run's samples on disk as they arrive, and in memory for the analysis.

The run engine hands it one sample at a time; the recorder knows nothing of the machine.
It owns the run file's name (``<date-time>_<specimen>_<method>.csv``, never overwriting one),
its ``#`` header (what the engine says describes the run), one line per sample with the step
and cycle each sample belongs to as columns, the flush of every line (a crash of the process
loses nothing) and the fsync on its own thread (a power cut loses at most FSYNC_INTERVAL_S;
the disk never delays a sample), and the arrays that become the run's RunData. That RunData is
made of the lines the file holds (header, labels, trailer), read as load_run reads them: the
run analysed straight after acquisition is the run read back from its file.

A full disk or a folder that became unwritable raises RecordingFailed (one line) from
``record``: the engine then stops the machine. Every sample already written stays in the file,
which is cut back to its last whole line and closed with an ``aborted`` trailer when the disk
takes one (a file without a trailer reads back as aborted too).
"""

from __future__ import annotations

import datetime as _dt
import logging
import math
import os
import re
import tempfile
import threading
from pathlib import Path
from typing import Any, Callable, TextIO

import numpy as np

from foamlab import FoamlabError
from foamlab.rundata import RunData, Specimen
from foamlab.runformat import NO_TRAILER_REASON, header_value, runfile_fields
from foamlab.storage.runfile import RunWriter, now_iso, trailer_lines

log = logging.getLogger(__name__)

#: The run file's columns: the three every reader needs, then the sample's request round trip,
#: the method step (0-based index in the plan) and the cycle (1-based) it was taken in.
COLUMNS = ("time_s", "displacement_mm", "force_N", "rtt_ms", "step", "cycle")
#: fsync period of the background syncer (wall s): what a power cut may cost.
FSYNC_INTERVAL_S = 0.5


class RecordingFailed(FoamlabError):
    """The run file cannot be created or written (full disk, unwritable folder)."""


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc) or type(exc).__name__


def safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "-", text).strip("-") or "run"


class FileSyncer:
    """fsync a file every `interval_s` from a background thread (a power cut loses at most that).

    fsync works on the file (inode), whatever descriptor wrote it, so this thread opens its
    own read-only descriptor and the writer never waits for the disk.
    """

    def __init__(self, path: Path, interval_s: float = FSYNC_INTERVAL_S):
        self._fd = os.open(path, os.O_RDONLY)
        self._interval = interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._loop, name="foamlab-run-fsync", daemon=True)
        self._thread.start()

    def _loop(self) -> None:
        while not self._stop.wait(self._interval):
            try:
                os.fsync(self._fd)
            except OSError as exc:
                log.warning("fsync of the run file failed: %s", exc)

    def close(self) -> None:
        self._stop.set()
        self._thread.join(5.0)
        try:
            os.close(self._fd)
        except OSError:
            pass


class Recorder:
    """Records one run into `out_dir` (see the module docstring).

    check_folder() before any motion; open(header) once the run's first sample is due;
    record() per sample; finish() at the end (never raises); run_data() for the analysis.
    `opener` opens the file (``open``'s signature): tests inject a failing one.
    """

    def __init__(self, out_dir: str | Path, run_name: str | None = None, *,
                 opener: Callable[..., TextIO] = open) -> None:
        self.out_dir = Path(out_dir)
        self.run_name = run_name
        self.opener = opener
        self.path: Path | None = None
        self.started_at = ""
        self.failure = ""                   # why the file stopped taking samples ("" while it does)
        self.written = 0                    # samples that reached the file
        self._writer: RunWriter | None = None
        self._lines: list[str] = []         # the header and trailer lines, as the file has them
        self._syncer: FileSyncer | None = None
        self._time: list[float] = []
        self._disp: list[float] = []
        self._force: list[float] = []
        self._rtt: list[float] = []
        self._step: list[int] = []
        self._cycle: list[int] = []

    # -- before the run ------------------------------------------------------------------
    def check_folder(self) -> None:
        """Raise RecordingFailed (one line) unless a run file can be created in out_dir."""
        try:
            self.out_dir.mkdir(parents=True, exist_ok=True)
            # a real file, not os.access: root, ACLs and read-only mounts answer differently
            with tempfile.NamedTemporaryFile(dir=self.out_dir, prefix=".foamlab-probe-"):
                pass
        except OSError as exc:
            raise RecordingFailed(f"cannot write run files in {self.out_dir}: {_why(exc)}") from None

    def file_name(self, specimen_label: str, method: str) -> Path:
        stamp = _dt.datetime.now().strftime("%Y%m%d-%H%M%S")
        name = self.run_name or f"{stamp}_{safe_name(specimen_label or 'specimen')}_{method}"
        path = self.out_dir / f"{name}.csv"
        n = 2
        while path.exists():                # a run never overwrites another
            path = self.out_dir / f"{name}-{n}.csv"
            n += 1
        return path

    def open(self, header: dict[str, Any]) -> Path:
        """Create the run file with `header` (RunWriter's keys; specimen and method name it)."""
        specimen = header.get("specimen")
        label = specimen.label if isinstance(specimen, Specimen) else ""
        path = self.file_name(label, str(header.get("method", "run")))
        self.started_at = header.setdefault("started_at", now_iso())
        try:
            # flushed per line by the writer; fsync on the syncer's thread instead (never inline)
            self._writer = RunWriter(path, header, columns=COLUMNS, fsync_interval_s=math.inf,
                                     opener=self.opener)
        except OSError as exc:           # the header did not fit on the disk
            self._remove_empty(path)
            raise RecordingFailed(f"cannot write the run file {path}: {_why(exc)}") from None
        except FoamlabError as exc:
            raise RecordingFailed(str(exc)) from None
        self.path = path
        self._lines = list(self._writer.header)
        self._syncer = FileSyncer(path)
        return path

    # -- during the run ------------------------------------------------------------------
    def record(self, time_s: float, displacement_mm: float, force_N: float, rtt_ms: float,
               step: int, cycle: int) -> None:
        """Keep one sample (in memory first: nothing acquired is lost), then write it."""
        self._time.append(time_s)
        self._disp.append(displacement_mm)
        self._force.append(force_N)
        self._rtt.append(rtt_ms)
        self._step.append(step)
        self._cycle.append(cycle)
        if self.failure:
            raise RecordingFailed(self.failure)
        try:
            self._writer.write_sample(time_s, displacement_mm, force_N, rtt_ms, step, cycle)
        except OSError as exc:
            self.failure = (f"cannot write the run file {self.path}: {_why(exc)}; "
                            f"the {self.written} samples before are kept")
            self._salvage()
            raise RecordingFailed(self.failure) from None
        self.written += 1

    def __len__(self) -> int:
        return len(self._time)

    @property
    def last(self) -> tuple[float, float, float] | None:
        """(time_s, displacement_mm, force_N) of the latest sample."""
        return (self._time[-1], self._disp[-1], self._force[-1]) if self._time else None

    @property
    def rtt_ms(self) -> list[float]:
        return self._rtt

    @property
    def labels(self) -> tuple[np.ndarray, np.ndarray]:
        """Per sample: the plan's step index and the cycle."""
        return np.asarray(self._step, int), np.asarray(self._cycle, int)

    # -- after the run -------------------------------------------------------------------
    def finish(self, status: str, reason: str, safety: str = "", facts: dict[str, Any] | None = None) -> None:
        """Write the status trailer (with `facts`: runfile.trailer_lines) and close. Never raises
        (the run's end must go on)."""
        if self._syncer is not None:
            self._syncer.close()
            self._syncer = None
        if self._writer is None or self._writer.closed:
            return
        try:
            self._writer.finish(status, reason, safety, facts)
            self._lines += self._writer.trailer
        except (OSError, FoamlabError) as exc:
            log.error("could not close the run file %s: %s", self.path, exc)
            self._salvage(status, reason, facts)

    def run_data(self) -> RunData | None:
        """The run as its file holds it (None when no file was opened: the run ended before it
        began): the samples with their labels, and the header and trailer lines read as
        load_run reads them."""
        if self.path is None:
            return None
        header = dict(item for item in map(header_value, self._lines) if item)
        fields = runfile_fields(header)
        if "status" not in header:          # no trailer reached the disk: the file reads so
            fields.update(status="aborted", abort_reason=NO_TRAILER_REASON)
        fields["metadata"].update({"format": "foamlab run file", "extra_columns": list(COLUMNS[3:])})
        return RunData(np.asarray(self._time), np.asarray(self._disp), np.asarray(self._force),
                       step=np.asarray(self._step, int), cycle=np.asarray(self._cycle, int),
                       source=str(self.path), **fields)

    def _salvage(self, status: str = "aborted", reason: str = "", facts: dict[str, Any] | None = None) -> None:
        """After a failed write: close, cut the file back to its last whole line, add the trailer
        if the disk takes it. Best effort, never raises: the samples written are what matters."""
        writer, self._writer = self._writer, None
        if writer is None:
            return
        writer.abandon()                    # its last flush may append part of a line: cut below
        try:
            fd = os.open(self.path, os.O_RDWR)
        except OSError as exc:
            log.error("run file %s: cannot reopen it to cut a partial line: %s", self.path, exc)
            return
        try:
            size = os.fstat(fd).st_size
            tail = os.pread(fd, min(size, 1 << 16), max(0, size - (1 << 16)))
            cut = size - len(tail) + tail.rfind(b"\n") + 1
            if cut < size:
                os.ftruncate(fd, cut)
            lines = trailer_lines(status, reason or self.failure, facts=facts)
            os.pwrite(fd, ("\n".join(lines) + "\n").encode("utf-8"), cut)
            os.fsync(fd)
            self._lines += lines
        except OSError as exc:              # a full disk may refuse even the trailer: reads as aborted
            log.error("run file %s: trailer not written: %s", self.path, exc)
        finally:
            os.close(fd)

    @staticmethod
    def _remove_empty(path: Path) -> None:
        try:
            if path.exists() and path.stat().st_size == 0:
                path.unlink()
        except OSError:
            pass
