"""Keep a diagnosis with its run: the ``<run stem>.diagnosis.json`` sidecar, indexed in the catalog
(the same rules as identification's fit sidecar: foamlab run files only, the folder's catalog
or the default one under the data dir)."""

from __future__ import annotations

import json
from pathlib import Path

from foamlab.storage.catalog import Stored, store_sidecar
from foamlab.storage.runfile import now_iso


def store_diagnosis(result: dict, run_path: str | Path, out_dir: str | Path | None = None) -> Stored:
    """Keep the diagnosis as the fit is kept (identification.store.store_fit): beside a
    foamlab run file, or in ``out_dir`` when given, never beside an export unasked."""
    text = json.dumps({**result, "created": now_iso(), "run": str(run_path)}, indent=1)
    return store_sidecar(run_path, "diagnosis", out_dir, lambda side: side.write_text(text, encoding="utf-8"),
                         lambda catalog, run, side: catalog.add_diagnosis(run, side, verdict=result["verdict"]))
