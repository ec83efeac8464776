"""One Dask task: one run file through foamlab.pipeline, on a worker.

The worker runs the pipeline's stages (method results, fit, diagnosis of that fit, the files
beside a foamlab run file - what `foamlab run` does) and returns an Outcome: the row, and what
the client needs to index the run (the catalog is written by the client alone: one SQLite
writer, and no database on a file system the cluster shares). The pipeline's Analysis itself
stays on the worker: it holds every intermediate array (8-17 MB pickled for a 400-sample run).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

from foamlab import FoamlabError, pipeline
from foamlab.batch.rows import BatchRow
from foamlab.rundata import RunData

RUN_FILE = "foamlab run file"          # foamlab.importers' name of the project's own format


@dataclass
class Outcome:
    row: BatchRow
    run: RunData | None = None         # the samples and header, for the catalog (None: not read)
    ours: bool = False                 # a foamlab run file: sidecars beside it, its folder's catalog
    fit_path: str = ""                 # the sidecars the pipeline wrote beside a foamlab run file
    diagnosis_path: str = ""
    fit_document: str = ""             # the fit sidecar's JSON, for the batch's own folder (other files)
    diagnosis_document: str = ""


def analyse_file(path: str, sha256: str) -> Outcome:
    """Read, fit, diagnose one file; never raises for a bad file (the row says why)."""
    started = time.perf_counter()
    row = BatchRow(file=path, sha256=sha256)
    try:
        row.format, run = _read(path)
    except FoamlabError as exc:
        row.error, row.error_kind = _one_line(str(exc)), "read"
        return _done(Outcome(row), started)
    except Exception as exc:   # an importer bug must cost one row, not the batch
        row.error, row.error_kind = _one_line(f"cannot read: {type(exc).__name__}: {exc}"), "read"
        return _done(Outcome(row), started)
    a = pipeline.Analysis(run, Path(path))
    pipeline.method_stage(a)
    if run.status != "aborted":
        pipeline.diagnose_stage(pipeline.fit_stage(a))
    pipeline.files_stage(a)
    outcome = Outcome(row, run=run, ours=row.format == RUN_FILE)
    _fill(row, a)
    if a.fit_path is not None:
        outcome.fit_path = str(a.fit_path)
    if a.diagnosis_path is not None:
        outcome.diagnosis_path = str(a.diagnosis_path)
    if not outcome.ours:
        if a.fit is not None:
            outcome.fit_document = a.fit.sidecar_text()
        if a.diagnosis is not None:
            outcome.diagnosis_document = json.dumps({**a.diagnosis.to_dict(), "run": path}, indent=1)
    return _done(outcome, started)


def _read(path: str) -> tuple[str, RunData]:
    from foamlab.importers import detect_format, load_run  # noqa: PLC0415 (a worker imports what it uses)
    from foamlab.importers._text import read_text  # noqa: PLC0415

    return detect_format(read_text(path).lines[:400]) or "", load_run(path)


def _fill(row: BatchRow, a: pipeline.Analysis) -> None:
    run = a.run
    row.specimen, row.started_at, row.status = run.specimen.label, run.started_at, run.status
    row.samples = len(run)
    cycle_notes: tuple[str, ...] = ()
    try:
        seg = run.segments()
        row.cycles, cycle_notes = seg.n_cycles, seg.notes
    except Exception:   # the fit says why a run cannot be segmented
        row.cycles = 0
    if run.status == "aborted":
        row.error, row.error_kind = _one_line(f"not fitted: an aborted run ({run.abort_reason})"), "fit"
    elif a.fit is None:
        row.error, row.error_kind = _one_line(a.fit_error), "fit"
    elif a.diagnosis is None:
        row.error, row.error_kind = _one_line(a.diagnosis_error), "diagnosis"
    if a.fit is not None:
        o = a.fit.orders
        row.orders, row.rmse, row.noise = f"{o.N},{o.M},{o.P}", float(a.fit.rmse), float(a.fit.noise_N)
        row.form = a.fit.params.residual_form
        row.rmse_samples, row.dropped = a.fit.rmse_count, a.fit.dropped
        row.parameters = {n: float(v) for n, v in zip(a.fit.names, a.fit.values)}
    if a.diagnosis is not None:
        _fill_diagnosis(row, a)
    row.note = "; ".join(e for e in (*cycle_notes, a.files_error) if e)


def _fill_diagnosis(row: BatchRow, a: pipeline.Analysis) -> None:
    d = a.diagnosis
    row.verdict, row.noise = d.verdict, float(d.noise_sigma)
    if d.findings:
        top = d.findings[0]
        row.effect, row.rmse_before, row.rmse_after = top.name, float(top.before.rmse), float(top.fit.rmse)
        row.evidence_samples = top.fit.n
    elif d.verdict == "unexplained":
        row.effect, row.rmse_before, row.rmse_after = "unexplained", float(d.base.rmse), float(d.final.rmse)
        row.evidence_samples = d.final.n
    if row.rmse_after > 0:
        row.gain = row.rmse_before / row.rmse_after


def _done(outcome: Outcome, started: float) -> Outcome:
    outcome.row.elapsed_s = time.perf_counter() - started
    return outcome


def _one_line(text: str) -> str:
    lines = [ln.strip() for ln in str(text).splitlines() if ln.strip()]
    return lines[0] if lines else ""
