"""Keep a diagnosis with its run: the ``<run stem>.diagnosis.json`` sidecar, indexed in the catalog
(the same rules as identification's fit sidecar: foamlab run files only, the folder's catalog
or the default one under the data dir)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from foamlab import FoamlabError
from foamlab.storage.catalog import Catalog, catalog_for_run, sidecar_target
from foamlab.storage.runfile import now_iso


@dataclass
class Stored:
    path: Path | None
    catalog: Path | None
    note: str = ""


def store_diagnosis(result: dict, run_path: str | Path, out_dir: str | Path | None = None) -> Stored:
    """Keep the diagnosis as the fit is kept (identification.store.store_fit): beside a
    foamlab run file, or in ``out_dir`` when given, never beside an export unasked."""
    run_path = Path(run_path)
    target = sidecar_target(run_path, "diagnosis", out_dir)
    if target.path is None:
        return Stored(None, None, target.note)
    try:
        target.path.write_text(json.dumps({**result, "created": now_iso(), "run": str(run_path)}, indent=1),
                               encoding="utf-8")
    except OSError as exc:
        raise FoamlabError(f"{target.path}: cannot write the diagnosis ({exc.strerror or exc})") from None
    if not target.ours:
        return Stored(target.path, None, "not a foamlab run file: not catalogued")
    catalog_path = catalog_for_run(run_path)
    if catalog_path is None:
        return Stored(target.path, None, "no catalog for this folder ('foamlab catalog' indexes it later)")
    with Catalog(catalog_path) as catalog:
        catalog.add_diagnosis(run_path, target.path, verdict=result["verdict"])
    return Stored(target.path, catalog_path)
