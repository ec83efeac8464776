"""What a test report holds, gathered once: the run and its file's SHA-256, the method, the
pipeline's Analysis (method results, fit, diagnosis) and the schedule statistics.

The analysis comes from the caller (the window's Analysis), else from the pipeline's stages
(foamlab.pipeline: the run is fitted once and diagnosed with that fit). A diagnosis stored
beside a foamlab run file (<run>.diagnosis.json) is used instead of diagnosing again when it
is current: not older than the fit stored beside the run (<run>.fit.json), which the pipeline's
fit stage reads instead of fitting again; the stored FitReport holds the fitted force at every
sample, so the fit's figures are the stored fit's. A run without a current stored fit is fitted
once (the report says so).
"""

from __future__ import annotations

import hashlib
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

from foamlab import FoamlabError, __version__, pipeline
from foamlab.methods import Method, load_method, method_of_run
from foamlab.rundata import RunData
from foamlab.runformat import SCHEDULE_KEY, is_run_file_path
from foamlab.storage.catalog import sidecar_path


@dataclass(frozen=True)
class ScheduleSummary:
    samples: int
    sampling_hz: float | None          # the method's (header), else the median of the time steps
    duration_s: float
    expected_samples: int | None       # the method's plan for this specimen (None: method unknown)
    missed: int | None
    missed_source: str                 # "recorded in the run file" | "estimated from the time stamps" | ""
    speedup: float | None = None

    @property
    def missed_percent(self) -> float | None:
        if self.missed is None or not (self.samples + self.missed):
            return None
        return 100.0 * self.missed / (self.samples + self.missed)


@dataclass(frozen=True)
class StoredDiagnosis:
    """A diagnosis read from its sidecar (the `foamlab diagnose --json` object)."""

    path: Path
    data: dict

    @property
    def verdict(self) -> str:
        return str(self.data.get("verdict", ""))


@dataclass
class ReportContent:
    path: Path
    run: RunData
    sha256: str
    analysis: pipeline.Analysis
    method: Method | None = None
    stored_diagnosis: StoredDiagnosis | None = None
    schedule: ScheduleSummary | None = None
    notes: list[str] = field(default_factory=list)
    software: str = f"foamlab {__version__}"

    @property
    def diagnosis_dict(self) -> dict | None:
        """The diagnosis as `foamlab diagnose --json` has it (made now or stored)."""
        if self.analysis.diagnosis is not None:
            return self.analysis.diagnosis.to_dict()
        return self.stored_diagnosis.data if self.stored_diagnosis else None


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    try:
        with open(path, "rb") as fh:
            for block in iter(lambda: fh.read(1 << 20), b""):
                h.update(block)
    except OSError as exc:
        raise FoamlabError(f"{path}: cannot read ({exc.strerror or exc})") from None
    return h.hexdigest()


def schedule_summary(run: RunData, method: Method | None) -> ScheduleSummary:
    n = len(run)
    t = run.time_s
    hz = _number(run.metadata.get("sampling_hz")) or (run.sampling_hz if n > 1 else None)
    duration = float(t[-1] - t[0]) if n > 1 else 0.0
    expected = None
    if method is not None and run.specimen.height_mm:
        expected = method.expected_samples(run.specimen.height_mm)
    missed, source = None, ""
    recorded = run.metadata.get(SCHEDULE_KEY)       # the engine's count, in a foamlab run file's trailer
    value = _number(recorded.get("missed")) if isinstance(recorded, dict) else None
    if value is not None:
        missed, source = int(value), "recorded in the run file"
    elif hz and n > 1:
        # deadlines between the first and the last sample, less the samples: a sample stamped a
        # little off its deadline moves no count (a gap test would), a skipped deadline does
        deadlines = int(round(duration * hz)) + 1
        missed, source = max(0, deadlines - n), "estimated from the time stamps"
    return ScheduleSummary(n, hz, duration, expected, missed, source, _number(run.metadata.get("speedup")))


def _number(v) -> float | None:
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def _quiet(stage: str, fraction: float) -> None:
    pass


def _read_json(path: Path) -> dict | None:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return data if isinstance(data, dict) else None


def current_diagnosis(path: Path, fit_side: Path | None) -> StoredDiagnosis | None:
    """The stored diagnosis of this fit: beside a current fit sidecar, not older than it."""
    side = sidecar_path(path, "diagnosis")
    if fit_side is None or not side.is_file() or side.stat().st_mtime < fit_side.stat().st_mtime:
        return None
    data = _read_json(side)
    if data is None or not isinstance(data.get("verdict"), str) or not isinstance(data.get("findings"), list):
        return None
    if data.get("run") and Path(str(data["run"])).name != path.name:
        return None
    return StoredDiagnosis(side, data)


def gather(path: str | Path, analysis: pipeline.Analysis | None = None, *, method: Method | str | None = None,
           fit: bool = True, diagnose: bool = True, store: bool = True,
           progress: pipeline.Progress | None = None) -> ReportContent:
    """Everything the report shows. `analysis` (the window's) is used as it is and completed;
    `store`: sidecars made now are written beside a foamlab run file and catalogued (as the
    pipeline does after `foamlab run`); other files are never written beside. `progress` is
    the pipeline's (stage, fraction)."""
    from foamlab.importers import load_run  # noqa: PLC0415

    progress = progress or _quiet
    path = Path(path)
    sha = sha256_of(path)
    if analysis is None:
        analysis = pipeline.Analysis(load_run(path), path)
        if sha256_of(path) != sha:      # the SHA-256 must be that of the data the report shows
            raise FoamlabError(f"{path}: the file changed while it was read (a run still being recorded?)")
    elif analysis.path is None:
        analysis.path = path
    run = analysis.run
    if isinstance(method, (str, Path)):
        method = load_method(method)
    if method is None and run.method:
        try:
            method = method_of_run(run)
        except FoamlabError as exc:
            analysis.method_error = analysis.method_error or str(exc)
    if analysis.method_results is None and method is not None:
        analysis.method_error = ""
        pipeline.method_stage(analysis, method)
    content = ReportContent(path, run, sha, analysis, method)
    if fit and run.status != "aborted":
        _fit_and_diagnose(content, diagnose, store, progress)
    elif run.status == "aborted" and fit:
        content.notes.append("not fitted: the run was aborted (its protocol is incomplete)")
    content.schedule = schedule_summary(run, method)
    return content


def _fit_and_diagnose(c: ReportContent, diagnose: bool, store: bool, progress: pipeline.Progress) -> None:
    a = c.analysis
    ours = is_run_file_path(c.path)
    had_fit = a.fit is not None
    pipeline.fit_stage(a, progress)
    if a.fit is not None and not had_fit and a.fit_path is None:
        c.notes.append("fitted now: no current fit was stored beside the run")
    if ours and a.fit is not None:
        fit_side = a.fit_path if a.fit_path is not None and a.fit_path.is_file() else None
        if diagnose and a.diagnosis is None:
            c.stored_diagnosis = current_diagnosis(c.path, fit_side)
            if c.stored_diagnosis is not None:
                a.diagnosis_path = c.stored_diagnosis.path
    if diagnose and c.stored_diagnosis is None:
        pipeline.diagnose_stage(a, progress)
    pipeline.forecast_stage(a, progress)
    if store and ours:
        before = (a.fit_path, a.diagnosis_path)
        pipeline.files_stage(a)
        if (a.fit_path, a.diagnosis_path) != before:      # new sidecars: index them as the pipeline does
            pipeline.catalog_stage(a)
