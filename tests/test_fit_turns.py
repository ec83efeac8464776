"""Turn instants the samples cannot place are fitted, not swapped after the fit (issue 26, item 1).

Regime A seed 12 of the independent generator (tests/independent_model.py: the crosshead
turns between samples; its first peak 0.4 ms before a sample that reads the peak within the
encoder's step): with every turn placed alike the whole run fits at 5 x the noise. The fit
places that turn the other way alone; every figure is one evaluation of the fitted model, and
each turn's placement is counted in the degrees of freedom.
"""

from __future__ import annotations

import json

import independent_model as im
import numpy as np
import pytest

from foamlab.identification import fit_run
from foamlab.identification.fit import resumed
from foamlab.identification.result import FitReport

TOLERANCE = 1.05


@pytest.fixture(scope="module")
def case():
    run = im.generate(im.REGIME_A, 12)
    return run, fit_run(run.to_rundata(), form="causal")


def _turns_without_a_stop(run) -> int:
    """The generator's turning points: a peak per cycle and a return per cycle but the last
    (the run's end is not a turn); none has a stop (no dwell)."""
    return 2 * run.regime.cycles - 1


def test_the_fit_reaches_the_noise_with_every_prediction_from_the_model(case):
    run, result = case
    assert result.rmse / run.sigma <= TOLERANCE, f"{result.rmse / run.sigma:.3f} x the noise"
    core = result.core_fit
    model = np.maximum(core.model.specimen_force(core.nu, core.solution.theta)[0] + result.contact_zero_N,
                       result.contact_zero_N)
    assert np.array_equal(result.predicted_force_N, model)       # nothing swapped in after the fit


def test_the_turn_parameters_are_counted_and_reported(case, tmp_path):
    run, result = case
    d = json.loads(result.to_json())
    k = _turns_without_a_stop(run)
    assert d["turn_placement"]["parameters"] == k == d["dof"]["turn_parameters"]
    free = sum(p.vary and not p.tie for p in result.parameters.values())
    assert d["dof"]["n_params"] >= free + k
    assert len(d["turn_placement"]["placed_other_way_s"]) >= 1
    # the stored fit places its turns as the fit did
    loaded = FitReport.load(result.save(tmp_path / "fit.json"))
    assert loaded.turns_flipped == result.turns_flipped
    again = resumed(loaded, run.to_rundata())
    assert again.prepared.nodes.flipped == result.prepared.nodes.flipped


def test_a_form_at_the_noise_settles_the_choice_and_progress_never_goes_back():
    """A seed 12 (a turn the samples misplace): the causal form, its turn placed the other way,
    leaves only the noise, so the paper form is not fitted (identification.forms.settles); the
    refits' progress stays within the form's share, never restarting at 0, and ends at 1."""
    run = im.generate(im.REGIME_A, 12)
    seen: list[float] = []
    result = fit_run(run.to_rundata(), progress=lambda stage, fraction: seen.append(fraction))
    assert result.rmse / run.sigma <= TOLERANCE
    assert len(result.turns_flipped) >= 1
    assert result.form_choice.settled and not result.alternatives, result.form_choice.reason()
    assert all(b >= a for a, b in zip(seen, seen[1:])), seen
    assert seen[-1] == pytest.approx(1.0)
