"""Keep a fit with its run: the ``<run stem>.fit.json`` sidecar, indexed in the catalog, and read
it back (the report and the window show a stored fit instead of fitting the run again).

The sidecar holds the ``foamlab fit --json`` object, the model's parameters under "model", so
``ModelParameters.load(sidecar)`` (and ``foamlab sim --specimen``) use the fitted specimen
directly, and the whole FitReport under "report" (FitReport.load).
"""

from __future__ import annotations

import logging
from pathlib import Path

from foamlab import FoamlabError
from foamlab.identification.result import FitReport
from foamlab.rundata import RunData
from foamlab.storage.catalog import Stored, sidecar_path, store_sidecar

log = logging.getLogger(__name__)


def store_fit(result: FitReport, run_path: str | Path, out_dir: str | Path | None = None) -> Stored:
    """Keep the fit: beside a foamlab run file (indexed in the catalog of its folder, or the
    default one under the data dir), or in ``out_dir`` when given; nothing is written beside
    an imported export the user did not ask for (storage.catalog.sidecar_target)."""
    return store_sidecar(run_path, "fit", out_dir, result.save,
                         lambda catalog, run, side: catalog.add_fit(run, side, rmse=result.rmse))


def stored_fit(run_path: str | Path, run: RunData) -> tuple[FitReport, Path] | None:
    """The fit stored beside a run file when it is the fit of this run as it is now: not older
    than the file, a report this foamlab reads, of as many samples as the run. None otherwise (the
    caller fits; a sidecar it cannot read is said in the log, not raised: fitting again is the
    remedy)."""
    run_path = Path(run_path)
    side = sidecar_path(run_path, "fit")
    try:
        if not side.is_file() or side.stat().st_mtime < run_path.stat().st_mtime:
            return None
        report = FitReport.load(side)
    except (OSError, FoamlabError) as exc:
        log.info("stored fit of %s not used: %s", run_path, exc)
        return None
    if report.run_samples != len(run):
        log.info("stored fit of %s not used: made on %d samples, the run has %d", run_path,
                 report.run_samples, len(run))
        return None
    return report, side
