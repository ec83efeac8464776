"""The FitReport (foamlab.identification.result): one frozen record of a fit, saved and loaded
exactly, and read - not made again - by `foamlab report` and the window on a fitted run.

The run comes from the independent generator (tests/independent_model.py: the paper's model
written again without foamlab's model code), written as a foamlab run file and fitted once."""

from __future__ import annotations

import dataclasses
import json
import sys

import independent_model as im
import numpy as np
import pytest

from foamlab import pipeline
from foamlab.gui.analysis import fit_curve, load_for_display
from foamlab.identification import fit as identification_fit
from foamlab.identification import fit_run
from foamlab.identification.fit import resumed
from foamlab.identification.result import FitReport
from foamlab.identification.store import store_fit
from foamlab.importers import load_run
from foamlab.model import ModelParameters
from foamlab.reporting import write_report
from foamlab.reporting.content import gather
from foamlab.storage.runfile import write_run_file


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    """A three-cycle 16 Hz run of regime B as a foamlab run file, its fit stored beside it."""
    folder = tmp_path_factory.mktemp("fit_report")
    run_file = write_run_file(folder / "independent_B_3.csv", im.generate(im.REGIME_B, 3).to_rundata())
    report = fit_run(load_run(run_file))
    side = store_fit(report, run_file).path
    assert side is not None and side.is_file()
    return run_file, side, report


@pytest.fixture
def no_fitting(monkeypatch):
    """Every entry into identification raises (fit_run wherever it was imported, fit_prepared);
    the forecast (each cycle fitted from the earlier ones: not the fit of the run) is left out."""
    real = identification_fit.fit_run

    def refuse(*args, **kwargs):
        raise AssertionError("the run was fitted again although its fit is stored")

    for module in list(sys.modules.values()):
        if getattr(module, "fit_run", None) is real:
            monkeypatch.setattr(module, "fit_run", refuse)
    monkeypatch.setattr(identification_fit, "fit_prepared", refuse)
    monkeypatch.setattr(pipeline, "forecast_scores", lambda run: None)


def test_a_saved_report_loads_equal_field_by_field(fitted, tmp_path):
    _, side, report = fitted
    loaded = FitReport.load(side)
    assert loaded == report and loaded.work is None and report.work is not None
    # exact, not close: every fitted force and every correlation to the last bit
    assert loaded.predicted_force_N.tobytes() == report.predicted_force_N.tobytes()
    assert np.array_equal(loaded.correlation, report.correlation, equal_nan=True)
    assert loaded.params.damping_alpha.tobytes() == report.params.damping_alpha.tobytes()
    # the comparison can fail: one sample's prediction or one parameter's bound changed is another report
    moved = report.predicted_force_N.copy()
    moved[7] = np.nextafter(moved[7], np.inf)
    assert loaded != dataclasses.replace(report, samples=dataclasses.replace(report.samples, predicted_force_N=moved))
    first = report.parameters.entries[0]
    other = dataclasses.replace(report.parameters, entries=(dataclasses.replace(first, lower=-1.0),)
                                + report.parameters.entries[1:])
    assert loaded != dataclasses.replace(report, parameters=other)
    with pytest.raises(dataclasses.FrozenInstanceError):
        report.rmse = 0.0


def test_the_sidecar_keeps_the_json_keys_and_loads_as_a_simulator_specimen(fitted):
    _, side, report = fitted
    data = json.loads(side.read_text(encoding="utf-8"))
    assert data["rmse"] == report.rmse and data["parameters"]["k0"]["value"] == report.value("k0")
    assert data["orders"]["C"] == report.orders.C and data["report"]["format"] == "foamlab fit report"
    specimen = ModelParameters.load(side)
    assert specimen.to_vector().tobytes() == report.params.to_vector().tobytes()


def test_report_and_window_show_the_stored_fit_without_fitting(fitted, no_fitting, tmp_path):
    run_file, side, report = fitted
    content = gather(run_file, diagnose=False, store=False)
    assert content.analysis.fit == report and content.analysis.fit_path == side
    assert not any("fitted now" in note for note in content.notes)
    pdf = write_report(run_file, tmp_path / "report.pdf", diagnose=False, store=False)
    assert pdf.is_file() and pdf.stat().st_size > 10_000
    # the window: the file opened (gui.analysis), then the pipeline's fit stage on its analysis
    loaded = load_for_display(run_file)
    pipeline.fit_stage(loaded.analysis)
    assert loaded.analysis.fit == report
    t, x, force = fit_curve(loaded.analysis.fit)
    assert force.tobytes() == report.predicted_force_N.tobytes()


def test_a_stale_or_foreign_sidecar_is_fitted_again_and_said(fitted, tmp_path):
    run_file, side, report = fitted
    copy = write_run_file(tmp_path / "copy.csv", load_run(run_file))
    (tmp_path / "copy.fit.json").write_text(json.dumps({"rmse": 1.0}), encoding="utf-8")   # no report in it
    calls = []
    real = pipeline.fit_run
    pipeline_fit = lambda run, **kw: calls.append(run.source) or real(run, **kw)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(pipeline, "fit_run", pipeline_fit)
        mp.setattr(pipeline, "forecast_scores", lambda run: None)
        content = gather(copy, diagnose=False, store=False)
    assert calls == [str(copy)] and any("fitted now" in note for note in content.notes)
    assert content.analysis.fit.rmse == pytest.approx(report.rmse, rel=1e-9)


def test_a_stored_fit_resumed_for_diagnosis_is_not_searched_again(fitted, no_fitting):
    run_file, side, report = fitted
    again = resumed(FitReport.load(side), load_run(run_file))
    assert again == report and again.core_fit is not None
    assert again.prepared.nodes.between_samples == report.prepared.nodes.between_samples
    # the core's model at the stored alpha and beta, its linear parameters solved: the fit's RMSE
    assert again.core_fit.rmse == pytest.approx(report.core_fit.rmse, rel=1e-3)


def test_a_selected_structure_round_trips_with_every_candidate(tmp_path):
    """One cycle: the structure the data determine is selected (identification.structure), so the
    report carries the candidates tried, their orders and the largest structure's own report."""
    report = fit_run(im.generate(im.REGIME_B, 5, cycles=1).to_rundata())
    assert report.structure.candidates and report.largest is not None
    loaded = FitReport.load(report.save(tmp_path / "one.fit.json"))
    assert loaded == report and loaded.structure.candidates == report.structure.candidates
    assert loaded.structure.chosen == report.orders and loaded.largest is None


def test_a_stored_fit_is_diagnosed_without_identifying_the_run_again(fitted, monkeypatch):
    """The report's diagnosis stage of a run whose fit is stored but not its diagnosis: the base
    is the stored fit's (resumed), the run is not identified again."""
    import foamlab.diagnosis.run as diagnosis_run
    from foamlab.diagnosis import diagnose

    run_file, side, report = fitted

    def refuse(*args, **kwargs):
        raise AssertionError("the run was identified again although its fit is stored")

    monkeypatch.setattr(diagnosis_run, "fit_run", refuse)
    d = diagnose([load_run(run_file)], fit=FitReport.load(side))
    assert d.verdict
    assert d.base.rmse <= 1.01 * report.core_fit.rmse      # the stored fit's model, not a worse one


def test_a_run_with_samples_off_its_schedule_reads_its_stored_fit(tmp_path):
    """The fit leaves out samples taken off the sampling schedule (analysis.prepared.on_schedule):
    its stored report has fewer fitted samples than the run, and is still the run's fit."""
    from foamlab.identification.store import stored_fit

    run = im.generate(im.REGIME_B, 5, cycles=1).to_rundata()
    t = run.time_s.copy()
    t[len(t) // 2] += 0.7 * (t[1] - t[0])            # one sample stamped late: off the schedule
    run_file = write_run_file(tmp_path / "late.csv", dataclasses.replace(run, time_s=t))
    report = fit_run(load_run(run_file))
    store_fit(report, run_file)
    assert len(report.samples.time_s) < len(load_run(run_file)) == report.run_samples
    found = stored_fit(run_file, load_run(run_file))
    assert found is not None and found[0] == report
