"""The post-run pipeline (foamlab.pipeline): `foamlab run` and the window analyse a run alike,
and fit it exactly once - the diagnosis extends that fit instead of fitting the run again."""

from __future__ import annotations

import os
import sys

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import pytest

from foamlab import cli, pipeline
from foamlab.identification import fit as identification_fit
from foamlab.storage.catalog import Catalog
from tests.gui_support import connect_window, shut_window
from tests.hil_support import short_method
from tests.synthetic import triangle_run

#: At x12 a 16 Hz sample is due every 5.2 ms of wall time: on a loaded CI host (replies up to
#: 22 ms) the window's run kept 394 of ~630 samples, each force read up to 0.26 machine-seconds
#: from its position; the model misfit 1.3x the noise and its diagnosis took 162 s (session 19's
#: CI 49). At x4 (15.6 ms) these pipeline tests get a run like a machine's.
SPEEDUP = 4.0
#: Three short cycles (15 % of the 72.5 mm specimen at 100 mm/min): ~10 s of wall time at x4.
SHORT = dict(strain=0.15, speed=100.0, cycles=3)


@pytest.fixture
def fits(monkeypatch):
    """Every identification of a run, by the run's source, wherever fit_run was imported (the
    pipeline, identification, the diagnosis when it is given no fit). A re-identification of
    effect-corrected data inside a diagnosis is named after its series: not a fit of the run."""
    calls: list[str] = []
    real = identification_fit.fit_run

    def counting(run, *args, **kwargs):
        calls.append(run.source)
        return real(run, *args, **kwargs)

    for module in list(sys.modules.values()):
        if getattr(module, "fit_run", None) is real:
            monkeypatch.setattr(module, "fit_run", counting)
    assert getattr(pipeline, "fit_run") is counting
    return calls


@pytest.fixture
def diagnosed_with(monkeypatch):
    """The fit each diagnosis was given (the pipeline's one call into foamlab.diagnosis)."""
    given = []
    real = pipeline.diagnose

    def spy(runs, fit=None, **kwargs):
        given.append(fit)
        return real(runs, fit=fit, **kwargs)

    monkeypatch.setattr(pipeline, "diagnose", spy)
    return given


@pytest.mark.hil
@pytest.mark.timeout(300)
def test_foamlab_run_fits_the_run_once_and_diagnoses_that_fit(tmp_path, capsys, fits, diagnosed_with):
    out = tmp_path / "data"
    method = short_method(tmp_path, **SHORT)
    code = cli.main(["run", "--method", str(method), "--speedup", str(SPEEDUP), "--out", str(out), "--quiet",
                     "--specimen-label", "once"])
    printed = capsys.readouterr()
    assert code == 0, printed.err
    run_file = next(out.glob("*_once_short.csv"))
    assert fits.count(str(run_file)) == 1, fits
    assert len(diagnosed_with) == 1 and diagnosed_with[0] is not None
    fit_file = run_file.with_name(f"{run_file.stem}.fit.json")
    diagnosis_file = run_file.with_name(f"{run_file.stem}.diagnosis.json")
    assert fit_file.is_file() and diagnosis_file.is_file()
    assert "fit:" in printed.out and f"({diagnosis_file})" in printed.out
    with Catalog.for_folder(out, sync=False) as catalog:
        assert len(catalog.fits(run_file)) == 1 and len(catalog.diagnoses(run_file)) == 1


@pytest.mark.gui
@pytest.mark.hil
@pytest.mark.timeout(600)
def test_the_window_fits_the_run_once_and_diagnoses_that_fit(qtbot, tmp_path, fits, diagnosed_with):
    from foamlab.gui.window import MainWindow

    w = MainWindow(speedup=SPEEDUP, out_dir=tmp_path / "runs", auto_diagnose=False)
    qtbot.addWidget(w)
    try:
        method = short_method(tmp_path, **SHORT)
        w.method_combo.addItem(str(method))
        w.method_combo.setCurrentText(str(method))
        connect_window(qtbot, w)
        form = w.specimen_form
        for edit, value in ((form.label_edit, "gui-once"), (form.edits["height_mm"], "72.5")):
            edit.clear()
            qtbot.keyClicks(edit, value)
        assert w.start_run()
        qtbot.waitUntil(lambda: w.last_result is not None, timeout=60_000)
        result = w.last_result
        assert result.status == "finished", result.reason
        # The fit is shown first...
        qtbot.waitUntil(lambda: w.shown_analysis is not None, timeout=240_000)   # bounded against a hang only
        assert w.shown_analysis.fit is not None, w.shown_analysis.fit_error
        assert w.results.parameters.rowCount() > 0 and "not run" in w.results.verdict.text()
        # ...the diagnosis on request, in the background, of that same fit.
        w.diagnose_shown_run()
        qtbot.waitUntil(lambda: w.results.report.diagnosis_note != "running…", timeout=240_000)   # a hang only
        assert w.shown_analysis.diagnosis is not None, w.shown_analysis.diagnosis_error
        assert "Diagnosis verdict:" in w.results.verdict.text()
        assert fits.count(str(result.path)) == 1, fits
        assert len(diagnosed_with) == 1 and diagnosed_with[0] is w.shown_analysis.fit
        assert result.path.with_name(f"{result.path.stem}.diagnosis.json").is_file()
    finally:
        shut_window(w)


def test_stages_say_why_they_did_nothing_and_never_fit_behind_the_callers_back(tmp_path, fits):
    run, _ = triangle_run(cycles=1, stroke_mm=5.0, speed_mm_min=60.0, rate_hz=16.0)
    run.status, run.abort_reason = "aborted", "stopped by the operator"
    seen = []
    a = pipeline.analyse(run, progress=lambda stage, fraction: seen.append((stage, fraction)))
    assert a.fit is None and a.diagnosis is None and not fits          # an aborted run is not fitted
    assert a.method_error == "no test method recorded with the run"
    assert a.files == [] and a.catalog is None                         # no run file: nothing written
    assert seen == [("method results", 0.0), ("method results", 1.0)]
    pipeline.diagnose_stage(a)                                         # the diagnosis needs the fit
    assert a.diagnosis is None and a.diagnosis_error.startswith("not diagnosed: no fit") and not fits


def test_files_go_only_beside_foamlab_run_files(tmp_path, fits):
    vendor = tmp_path / "export.csv"
    vendor.write_text("time_s,displacement_mm,force_N\n0,0,0\n")
    run, _ = triangle_run(cycles=1, stroke_mm=5.0, speed_mm_min=60.0, rate_hz=16.0)
    a = pipeline.Analysis(run, vendor)
    pipeline.catalog_stage(pipeline.files_stage(a))
    assert a.files == [vendor] and a.catalog is None
    assert sorted(p.name for p in tmp_path.iterdir()) == ["export.csv"]
