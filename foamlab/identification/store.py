"""Keep a fit with its run: the ``<run stem>.fit.json`` sidecar, indexed in the catalog.

The sidecar holds the ``foamlab fit --json`` object plus the model's parameters
under "model", so ``ModelParameters.load(sidecar)`` (and ``foamlab sim
--specimen``) use the fitted specimen directly.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from foamlab import FoamlabError
from foamlab.identification.result import FitResult
from foamlab.storage.catalog import Catalog, catalog_for_run, sidecar_target


@dataclass
class Stored:
    path: Path | None             # the sidecar written (None: nothing written)
    catalog: Path | None          # the catalog it was indexed in, if any
    note: str = ""                # why it was not written or not indexed


def store_fit(result: FitResult, run_path: str | Path, out_dir: str | Path | None = None) -> Stored:
    """Keep the fit: beside a foamlab run file (indexed in the catalog of its folder, or the
    default one under the data dir), or in ``out_dir`` when given; nothing is written beside
    an imported export the user did not ask for (storage.catalog.sidecar_target)."""
    run_path = Path(run_path)
    target = sidecar_target(run_path, "fit", out_dir)
    if target.path is None:
        return Stored(None, None, target.note)
    try:
        result.save(target.path)
    except OSError as exc:
        raise FoamlabError(f"{target.path}: cannot write the fit ({exc.strerror or exc})") from None
    if not target.ours:
        return Stored(target.path, None, "not a foamlab run file: not catalogued")
    catalog_path = catalog_for_run(run_path)
    if catalog_path is None:
        return Stored(target.path, None, "no catalog for this folder ('foamlab catalog' indexes it later)")
    with Catalog(catalog_path) as catalog:
        catalog.add_fit(run_path, target.path, rmse=result.rmse)
    return Stored(target.path, catalog_path)
