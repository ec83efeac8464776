"""Keep a fit with its run: the ``<run stem>.fit.json`` sidecar, indexed in the catalog.

The sidecar holds the ``foamlab fit --json`` object plus the model's parameters
under "model", so ``ModelParameters.load(sidecar)`` (and ``foamlab sim
--specimen``) use the fitted specimen directly.
"""

from __future__ import annotations

from pathlib import Path

from foamlab.identification.result import FitResult
from foamlab.storage.catalog import Stored, store_sidecar


def store_fit(result: FitResult, run_path: str | Path, out_dir: str | Path | None = None) -> Stored:
    """Keep the fit: beside a foamlab run file (indexed in the catalog of its folder, or the
    default one under the data dir), or in ``out_dir`` when given; nothing is written beside
    an imported export the user did not ask for (storage.catalog.sidecar_target)."""
    return store_sidecar(run_path, "fit", out_dir, result.save,
                         lambda catalog, run, side: catalog.add_fit(run, side, rmse=result.rmse))
