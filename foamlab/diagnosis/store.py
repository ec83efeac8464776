"""Keep a diagnosis with its run: the ``<run stem>.diagnosis.json`` sidecar, indexed in the catalog
(the same rules as identification's fit sidecar: foamlab run files only, the folder's catalog
or the default one under the data dir)."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from foamlab import FoamlabError
from foamlab.storage.catalog import Catalog, catalog_for_run, sidecar_path
from foamlab.storage.runfile import is_run_file, now_iso


@dataclass
class Stored:
    path: Path | None
    catalog: Path | None
    note: str = ""


def store_diagnosis(result: dict, run_path: str | Path) -> Stored:
    """Write the sidecar beside a foamlab run file and index it; other files are left alone."""
    run_path = Path(run_path)
    try:
        with open(run_path, encoding="utf-8-sig", errors="replace") as fh:
            ours = is_run_file(fh.readline())
    except OSError:
        ours = False
    if not ours:
        return Stored(None, None, "not a foamlab run file: diagnosis not stored")
    side = sidecar_path(run_path, "diagnosis")
    try:
        side.write_text(json.dumps({**result, "created": now_iso(), "run": str(run_path)}, indent=1),
                        encoding="utf-8")
    except OSError as exc:
        raise FoamlabError(f"{side}: cannot write the diagnosis ({exc.strerror or exc})") from None
    catalog_path = catalog_for_run(run_path)
    if catalog_path is None:
        return Stored(side, None, "no catalog for this folder ('foamlab catalog' indexes it later)")
    with Catalog(catalog_path) as catalog:
        catalog.add_diagnosis(run_path, side, verdict=result["verdict"])
    return Stored(side, catalog_path)
