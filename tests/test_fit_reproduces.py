"""A fit file is the fit (issue 26 item 5): the stored report's parameters, stepped along its
stored path by the model as the simulator steps its specimen, give the fitted force at every
sample within 1e-6 of the peak; and the simulator's specimen built from the sidecar senses it.

Runs from tests/independent_model.py (no foamlab model code), turns between samples, both
residual forms; the real Bluehill file (a clock 10-30 us off its 50 Hz) is checked in
test_identification, where its fit is made, to the same 1e-6.
"""

from __future__ import annotations

import independent_model as im
import numpy as np
import pytest

#: Reproduction required at every sample, as a share of the fitted force's peak.
TOLERANCE = 1e-6

CASES = [(im.REGIME_A, 1, "auto"), (im.REGIME_B, 2, "auto"), (im.REGIME_B, 3, "paper")]


def assert_reproduces(report, tolerance: float = TOLERANCE) -> None:
    fitted = report.predicted_force_N
    gap = np.abs(report.reproduced_force_N() - fitted)
    worst = int(np.argmax(gap))
    assert gap[worst] <= tolerance * np.max(np.abs(fitted)), (
        f"stored fit off its fitted force by {gap[worst]:.3g} N at sample {worst} "
        f"(t = {report.run_time_s[worst]:.4f} s; peak {np.max(np.abs(fitted)):.3g} N)")


def assert_simulator_senses_it(report, sidecar, tolerance: float = TOLERANCE) -> None:
    """The simulator's specimen from the sidecar, its plate driven along the fit's path: the
    contact force it senses is the fitted force wherever the fitted reading is above the run's
    unloaded reading and above 0. (The parameters carry the run's load cell zero in k0, the
    fit's convention: reading = max(model, zero); a simulated plate cannot pull, so where the
    run's load cell read its zero, or a model force between a negative zero and 0, the simulated
    one reads its own zero.)"""
    from foamlab.model import ModelParameters
    from foamlab.model.effects import make_effects
    from simulator.specimen import SimSpecimen, surface_offset_mm

    params = ModelParameters.load(sidecar)
    specimen = SimSpecimen(params, make_effects(None), top_mm=10.0)
    s = report.samples
    surface = surface_offset_mm(params)
    sensed = np.array([specimen.step(float(t), 10.0 + float(x) - surface, 0.0)
                       for t, x in zip(s.path_time_s, s.path_mm)])[s.path_of_sample]
    fitted = report.predicted_force_N
    on = fitted > max(report.contact_zero_N, 0.0)
    gap = np.abs(sensed[on] - fitted[on])
    assert on.mean() > 0.5
    assert gap.max() <= tolerance * np.max(np.abs(fitted)), f"simulator off the fit by {gap.max():.3g} N"


@pytest.mark.parametrize("regime,seed,form", CASES, ids=[f"{r.name}-{s}-{f}" for r, s, f in CASES])
def test_stored_fit_reproduces_its_fitted_force(regime, seed, form, tmp_path):
    from foamlab.identification import fit_run
    from foamlab.identification.result import FitReport

    report = fit_run(im.generate(regime, seed).to_rundata(), form=form)
    assert report.turn_parameters or report.samples.path_mm.size > report.samples.time_s.size, \
        "the case must have turns between samples"
    sidecar = report.save(tmp_path / "run.fit.json")
    loaded = FitReport.load(sidecar)
    assert_reproduces(loaded)
    assert_simulator_senses_it(loaded, sidecar)
    if form == "paper":
        assert loaded.params.residual_form == "paper"


def test_a_report_without_a_path_loads_and_says_so():
    """A report written before the path was stored loads (a missing field that has a default takes
    it) and says what to do instead of reproducing something else."""
    from foamlab import FoamlabError
    from foamlab.identification.record import decode, encode
    from foamlab.identification.result import FitReport, FittedSamples

    written = encode(FittedSamples(*(np.zeros(3),) * 5, np.zeros(3), np.arange(3)))
    for key in ("path_time_s", "path_mm", "path_of_sample"):
        del written[key]
    old = decode(FittedSamples, written)
    assert old.path_time_s.size == 0 and old.observed.tolist() == [0, 1, 2]
    with pytest.raises(FoamlabError, match="fit the run again"):
        FitReport.reproduced_force_N(type("Old", (), {"samples": old})())
