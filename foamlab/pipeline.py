"""The analysis of a recorded run: one pipeline for `foamlab run`, the window and batches.

    method results -> fit -> diagnosis with that same fit -> files beside the run -> catalog
    (forecast: each cycle predicted from the earlier ones - the live prediction's scores when
    the run had one, else forecast_stage)

    from foamlab import pipeline
    a = pipeline.analyse(run, path, method=method, folder=out_dir)   # every stage
    a.fit, a.fit_error, a.diagnosis.verdict, a.files

Each stage takes the run's Analysis (the typed record of what was found), fills its part and
returns it, so a caller may run them one by one (the window shows the fit, then diagnoses in
the background). A run is fitted exactly once (fit_stage keeps a fit it already has) and the
diagnosis extends that fit, never a fit of its own. A stage that fails says why in one line
(its *_error field) and the others go on: the run file is already the record.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from foamlab import FoamlabError
from foamlab.acquisition.settings import DEFAULT as ACQUISITION
from foamlab.acquisition.settings import AcquisitionSettings
from foamlab.diagnosis import Diagnosis, diagnose
from foamlab.diagnosis.store import store_diagnosis
from foamlab.identification import FitReport, fit_run
from foamlab.identification.store import store_fit, stored_fit
from foamlab.methods import Method, MethodResults, method_of_run
from foamlab.prediction.forecast import ForecastScores, forecast_scores
from foamlab.rundata import RunData
from foamlab.runformat import is_run_file_path
from foamlab.storage.catalog import CATALOG_NAME, Catalog

log = logging.getLogger(__name__)

#: progress(stage, fraction 0..1): "method results", "fit: <its step>", "diagnosis", "files", "catalog"
Progress = Callable[[str, float], None]


def _quiet(stage: str, fraction: float) -> None:
    pass


@dataclass
class Analysis:
    """What the pipeline found for one run. Errors are one line ("" when the stage went well
    or did not run); a field left None with no error means the stage was not asked for."""

    run: RunData
    path: Path | None = None                   # the foamlab run file (sidecars go beside it)
    method_results: MethodResults | None = None
    method_error: str = ""
    fit: FitReport | None = None
    fit_error: str = ""
    diagnosis: Diagnosis | None = None
    diagnosis_error: str = ""
    fit_path: Path | None = None               # <run>.fit.json, once written
    diagnosis_path: Path | None = None         # <run>.diagnosis.json, once written
    files_error: str = ""
    catalog: Path | None = None                # the catalog the run is indexed in
    catalog_error: str = ""
    forecast: ForecastScores | None = None     # each cycle predicted from the earlier ones
    forecast_error: str = ""

    @property
    def verdict(self) -> str:
        return self.diagnosis.verdict if self.diagnosis is not None else ""

    @property
    def files(self) -> list[Path]:
        """The run file and the sidecars written beside it."""
        return [p for p in (self.path, self.fit_path, self.diagnosis_path) if p is not None]


def schedule_gaps(n_samples: int, missed: int, settings: AcquisitionSettings = ACQUISITION) -> tuple[float, str]:
    """The share of a run's sample deadlines it missed, and the data-quality flag's name ('' when
    the share is within settings.gaps_warn_fraction): one definition for both front ends."""
    total = n_samples + missed
    share = missed / total if total else 0.0
    flag = f"{share:.1%} of the samples missed ({missed} of {total})" if share > settings.gaps_warn_fraction else ""
    return share, flag


@dataclass(frozen=True)
class AfterRun:
    """What the analysis after a run does, decided once for `foamlab run` and the window (which
    analyse result.run when it is there): an aborted or empty run is not fitted (its protocol is
    incomplete); a finished one is fitted and diagnosed, and flagged when it missed more of its
    deadlines than settings.gaps_warn_fraction (its samples are the record: none is filled in,
    the model is evaluated where they were taken)."""

    fit: bool
    missed_share: float
    gaps: str = ""          # the data-quality flag, '' when the run kept its schedule
    fit_note: str = ""      # why the fit is left out

    @classmethod
    def of(cls, result, settings: AcquisitionSettings = ACQUISITION) -> AfterRun:
        """From a foamlab.acquisition.RunResult."""
        share, gaps = schedule_gaps(result.n_samples, result.missed, settings)
        fit = result.status == "finished" and result.n_samples > 0
        return cls(fit, share, gaps, "" if fit else "not fitted (the run did not finish)")


def _attempt(what: str, make: Callable[[], object]) -> tuple[object, str]:
    """(make(), "") - or (None, why in one line). A stage that fails must not cost the others:
    the run is saved already, and a bug in one stage must not hide what the others found."""
    try:
        return make(), ""
    except FoamlabError as exc:
        return None, str(exc)
    except Exception as exc:
        log.debug("%s failed", what, exc_info=True)
        return None, f"{what} failed: {type(exc).__name__}: {exc}"


def method_stage(a: Analysis, method: Method | None = None, progress: Progress = _quiet) -> Analysis:
    """The method's results (the run's own method, by name, when none is given)."""
    progress("method results", 0.0)

    def results() -> MethodResults | None:
        chosen = method or method_of_run(a.run)
        return chosen.compute_results(a.run) if len(a.run) else None

    a.method_results, a.method_error = _attempt("method results", results)
    progress("method results", 1.0)
    return a


def fit_stage(a: Analysis, progress: Progress = _quiet) -> Analysis:
    """Identify the model on the run - once: a fit the Analysis already has is kept, and a fit
    stored beside the run file (identification.store.stored_fit) is read, not made again."""
    if a.fit is not None:
        return a
    stored = stored_fit(a.path, a.run) if a.path is not None else None
    if stored is not None:
        a.fit, a.fit_path = stored
        return a
    a.fit, a.fit_error = _attempt("fit", lambda: fit_run(
        a.run, progress=lambda stage, fraction: progress(f"fit: {stage}", fraction)))
    return a


def diagnose_stage(a: Analysis, progress: Progress = _quiet) -> Analysis:
    """Diagnose the run as an extension of its fit (fit_stage first)."""
    if a.diagnosis is not None:
        return a
    if a.fit is None:
        a.diagnosis_error = f"not diagnosed: no fit ({a.fit_error or 'the fit stage has not run'})"
        return a
    progress("diagnosis", 0.0)
    a.diagnosis, a.diagnosis_error = _attempt("diagnosis", lambda: _diagnose(
        a.run, a.fit, lambda stage, f: progress(f"diagnosis: {stage}", f)))
    progress("diagnosis", 1.0)
    return a


def forecast_stage(a: Analysis, progress: Progress = _quiet) -> Analysis:
    """Each cycle predicted from the earlier ones (foamlab.prediction.forecast_scores: one fit
    per scored cycle); kept when the live prediction already scored the run."""
    if a.forecast is not None:
        return a
    progress("forecast", 0.0)
    a.forecast, a.forecast_error = _attempt("forecast", lambda: forecast_scores(a.run))
    progress("forecast", 1.0)
    return a


def _diagnose(run: RunData, fit: FitReport, progress: Progress = _quiet) -> Diagnosis:
    # The one call into the diagnosis: it extends this fit instead of fitting the run again.
    return diagnose([run], fit=fit, progress=progress)


def files_stage(a: Analysis, progress: Progress = _quiet) -> Analysis:
    """Write the fit and the diagnosis beside the run file (foamlab run files only: a vendor
    export opened for a look is not ours to add to); what is written already is left alone."""
    if a.path is None or not is_run_file_path(a.path):
        return a
    progress("files", 0.0)
    try:
        if a.fit is not None and a.fit_path is None:
            a.fit_path = store_fit(a.fit, a.path).path
        if a.diagnosis is not None and a.diagnosis_path is None:
            a.diagnosis_path = store_diagnosis(a.diagnosis.to_dict(), a.path).path
        a.files_error = ""
    except FoamlabError as exc:
        a.files_error = str(exc)
    progress("files", 1.0)
    return a


def catalog_stage(a: Analysis, folder: str | Path | None = None, progress: Progress = _quiet) -> Analysis:
    """Index the run, its fit and its diagnosis in `folder`'s catalog (default: the run's folder).
    Idempotent: run it after each stage whose result should be listed."""
    if a.path is None or not is_run_file_path(a.path):
        return a
    progress("catalog", 0.0)
    folder = Path(folder) if folder is not None else a.path.parent
    try:
        a.catalog = index_run(folder / CATALOG_NAME, a.path, a.run, a.fit_path,
                              a.fit.rmse if a.fit is not None else None, a.diagnosis_path, a.verdict)
        a.catalog_error = ""
    except Exception as exc:   # the files are the record; `foamlab catalog rebuild` recovers the index
        a.catalog_error = f"not added to the catalog: {exc}"
    progress("catalog", 1.0)
    return a


def index_run(catalog_path: Path, path: Path, run: RunData | None, fit_path: Path | None = None,
              rmse: float | None = None, diagnosis_path: Path | None = None, verdict: str = "") -> Path:
    """The catalog stage's one write: the run, its fit and its diagnosis files in a catalog
    (also what `foamlab batch` calls on its client, which holds the results, not the Analysis)."""
    with Catalog(catalog_path) as catalog:
        catalog.add_run(path, run)
        if fit_path is not None:
            catalog.add_fit(path, fit_path, rmse=rmse)
        if diagnosis_path is not None:
            catalog.add_diagnosis(path, diagnosis_path, verdict=verdict)
        return catalog.path


def analyse(run: RunData, path: str | Path | None = None, *, method: Method | None = None,
            folder: str | Path | None = None, fit: bool = True, diagnose: bool = True,
            progress: Progress = _quiet) -> Analysis:
    """Every stage in order. An aborted run is not fitted (its protocol is incomplete)."""
    a = Analysis(run, Path(path) if path is not None else None)
    method_stage(a, method, progress)
    if fit and run.status != "aborted":
        fit_stage(a, progress)
        if diagnose:
            diagnose_stage(a, progress)
    files_stage(a, progress)
    return catalog_stage(a, folder, progress)
