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
from foamlab.storage.catalog import Catalog, catalog_for_run, sidecar_path
from foamlab.storage.runfile import is_run_file


@dataclass
class Stored:
    path: Path                    # the sidecar written
    catalog: Path | None          # the catalog it was indexed in, if any
    note: str = ""                # why it was not indexed


def store_fit(result: FitResult, run_path: str | Path) -> Stored:
    """Write the sidecar beside ``run_path`` and index it.

    Indexed in the catalog of the folder holding the run (``<folder>/catalog.sqlite``)
    if there is one, else in the default catalog if the run lives under the data dir.
    Only foamlab run files are catalogued (imported vendor files are not runs of ours);
    their sidecar is still written.
    """
    run_path = Path(run_path)
    side = sidecar_path(run_path, "fit")
    try:
        result.save(side)
    except OSError as exc:
        raise FoamlabError(f"{side}: cannot write the fit ({exc.strerror or exc})") from None
    try:
        with open(run_path, encoding="utf-8-sig", errors="replace") as fh:
            ours = is_run_file(fh.readline())
    except OSError:
        ours = False
    if not ours:
        return Stored(side, None, "not a foamlab run file: sidecar written, not catalogued")
    catalog_path = catalog_for_run(run_path)
    if catalog_path is None:
        return Stored(side, None, "no catalog for this folder ('foamlab catalog' indexes it later)")
    with Catalog(catalog_path) as catalog:
        catalog.add_fit(run_path, side, rmse=result.rmse)
    return Stored(side, catalog_path)
