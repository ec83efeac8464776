"""What the window shows of a file it opens, prepared on its analysis thread: the run,
its cycles for the plot, its pipeline Analysis (method results first; the window then runs
the fit and diagnosis stages of foamlab.pipeline) and a diagnosis stored beside it.
Nothing is computed here that foamlab's importers or pipeline own.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from foamlab import FoamlabError, pipeline
from foamlab.gui.plots import labels_from_segmentation
from foamlab.gui.report import headline_names
from foamlab.identification import FitReport
from foamlab.importers import load_run
from foamlab.methods import method_of_run
from foamlab.rundata import RunData
from foamlab.storage.catalog import sidecar_path

log = logging.getLogger(__name__)


@dataclass
class Loaded:
    run: RunData
    cycles: Any          # per-sample cycle numbers (None: let the plot track them)
    phases: Any          # per-sample loading/unloading
    n_cycles: int
    analysis: pipeline.Analysis
    segmentation_note: str = ""
    stored_diagnosis: dict | None = None   # <run>.diagnosis.json beside the file, when there is one
    headline: list[str] = field(default_factory=list)   # the method's headline results (report.py)

    @property
    def method_results(self):
        return self.analysis.method_results

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
    run = load_run(path)
    if not run.source:
        run.source = str(path)
    cycles = phases = None
    n_cycles, note = 0, ""
    try:
        segmentation = run.segments()
        cycles, phases = labels_from_segmentation(segmentation, len(run))
        n_cycles = segmentation.n_cycles
        note = "; ".join(segmentation.notes)
    except FoamlabError as exc:
        note = f"no cycles found: {exc}"
    analysis = pipeline.Analysis(run, Path(path))
    headline: list[str] = []
    if run.method:
        try:
            method = method_of_run(run)
            headline = headline_names(method)
            pipeline.method_stage(analysis, method)
        except FoamlabError as exc:
            analysis.method_error = str(exc)
        if analysis.method_error:
            log.info("method results of %s not computed: %s", path, analysis.method_error)
    return Loaded(run, cycles, phases, n_cycles, analysis, note, stored_diagnosis(path), headline)


def stored_diagnosis(path: str | Path) -> dict | None:
    """The diagnosis kept beside a run file (catalog sidecar), if any and readable."""
    try:
        side = sidecar_path(path, "diagnosis")
        if side.is_file():
            data = json.loads(side.read_text(encoding="utf-8"))
            return data if isinstance(data, dict) and "verdict" in data else None
    except (OSError, ValueError) as exc:
        log.info("no stored diagnosis for %s: %s", path, exc)
    return None


def fit_curve(fit: FitReport) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The fitted force at the samples the fit used (time, displacement, force): what the plot
    overlays. Samples taken off the sampling schedule are not among them."""
    if fit.run_time_s is None or fit.run_displacement_mm is None:
        return None
    return fit.run_time_s, fit.run_displacement_mm, np.asarray(fit.predicted_force_N, dtype=float)
