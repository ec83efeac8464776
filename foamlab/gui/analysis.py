"""Analysis the window asks for, run on its analysis thread: load a file for display,
fit it, diagnose it. Thin calls into foamlab's importers, identification and
diagnosis; nothing is computed here that those modules own.
"""

from __future__ import annotations

import importlib
import importlib.util
import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from foamlab import FoamlabError
from foamlab.rundata import RunData

log = logging.getLogger(__name__)


def _module(name: str, what: str):
    try:
        if importlib.util.find_spec(name) is None:
            raise ModuleNotFoundError(name)
    except ModuleNotFoundError:
        raise FoamlabError(f"{what} is not available in this installation") from None
    return importlib.import_module(name)


@dataclass
class Loaded:
    run: RunData
    cycles: Any          # per-sample cycle numbers (None: let the plot track them)
    phases: Any          # per-sample loading/unloading
    n_cycles: int
    method_results: Any = None
    segmentation_note: str = ""
    stored_diagnosis: dict | None = None   # <run>.diagnosis.json beside the file, when there is one
    headline: list[str] = field(default_factory=list)   # the method's headline results (report.py)

    def describe(self) -> str:
        run = self.run
        spec = run.specimen
        size = ""
        if spec.height_mm:
            size = f", {spec.height_mm:g} mm high"
            if spec.area_mm2:
                size += f", {spec.width_mm:g} x {spec.depth_mm:g} mm"
        what = f"{Path(run.source).name if run.source else 'run'}: {len(run)} samples, {self.n_cycles} cycles"
        return what + (f" — {spec.label}" if spec.label else "") + size + (
            f" ({self.segmentation_note})" if self.segmentation_note else "")

    def rows(self) -> list[tuple[str, str]]:
        run = self.run
        rows = [("file", run.source or "–"), ("status", run.status + (f" ({run.abort_reason})" if run.abort_reason else "")),
                ("samples", f"{len(run)} at {run.sampling_hz:.3g} Hz"), ("cycles", str(self.n_cycles))]
        if run.method:
            rows.append(("method", run.method))
        if run.machine:
            rows.append(("machine", run.machine))
        if run.specimen.label:
            rows.append(("specimen", run.specimen.label))
        if run.started_at:
            rows.append(("started", run.started_at))
        return rows


def load_for_display(path: str | Path) -> Loaded:
    importers = _module("foamlab.importers", "reading measured files")
    run = importers.load_run(path)
    if not run.source:
        run.source = str(path)
    cycles = phases = None
    n_cycles, note = 0, ""
    try:
        from foamlab.gui.plots import labels_from_segmentation

        segmentation = run.segments()
        cycles, phases = labels_from_segmentation(segmentation, len(run))
        n_cycles = segmentation.n_cycles
    except FoamlabError as exc:
        note = f"no cycles found: {exc}"
    method_results, headline = None, []
    if run.method:
        try:
            from foamlab.gui.report import headline_names
            from foamlab.methods import load_method

            method = load_method(run.method)
            method_results, headline = method.compute_results(run), headline_names(method)
        except FoamlabError as exc:
            log.info("method results of %s not computed: %s", path, exc)
    return Loaded(run, cycles, phases, n_cycles, method_results, note, stored_diagnosis(path), headline)


def stored_diagnosis(path: str | Path) -> dict | None:
    """The diagnosis kept beside a run file (catalog sidecar), if any and readable."""
    try:
        from foamlab.storage.catalog import sidecar_path

        side = sidecar_path(path, "diagnosis")
        if side.is_file():
            data = json.loads(side.read_text(encoding="utf-8"))
            return data if isinstance(data, dict) and "verdict" in data else None
    except (ImportError, OSError, ValueError) as exc:
        log.info("no stored diagnosis for %s: %s", path, exc)
    return None


def fit_for_display(loaded: Loaded) -> Any:
    identification = _module("foamlab.identification", "model fitting")
    return identification.fit_run(loaded.run)


def diagnose_run(run: RunData) -> Any:
    """Diagnose one run and keep the result beside its file (and in the catalog), as
    `foamlab diagnose` does, so the run browser shows the verdict next time."""
    diagnosis = _module("foamlab.diagnosis", "diagnosis")
    result = diagnosis.diagnose([run])
    if run.source:
        try:
            from foamlab.diagnosis.store import store_diagnosis

            stored = store_diagnosis(result.to_dict(), run.source)
            log.info("diagnosis of %s: %s", run.source, stored.path or stored.note)
        except (ImportError, FoamlabError, OSError) as exc:
            log.warning("diagnosis of %s not stored: %s", run.source, exc)
    return result


def predicted_force(fit: Any, run: RunData) -> np.ndarray | None:
    """The fitted model's force at the run's samples (what the plot overlays); `fit` is a
    foamlab.identification FitResult of this run."""
    value = np.asarray(fit.predicted_force_N, dtype=float)
    return value if value.shape == run.force_N.shape else None
