"""A fit ends converged, or its first line and its JSON say it did not (issue 26, item 2).

The run is the README main job's shape from the independent generator (three cycles at
16 Hz, tests/independent_model.py); the converged case of every generated run is in
test_fit_independent.py. A fit forced to stop is one given a budget of one evaluation on
every sample (FitSettings): it cannot converge there, and must say so before anything else.
"""

from __future__ import annotations

import json

import independent_model as im
import pytest

from foamlab.identification import fit_run
from foamlab.identification.settings import FitSettings


@pytest.fixture(scope="module")
def run():
    return im.generate(im.REGIME_A, 1).to_rundata()


def test_a_fit_forced_to_stop_says_so_first(run):
    result = fit_run(run, form="causal", settings=FitSettings(polish_nfev=1, max_nfev=1))
    assert not result.success
    data = json.loads(result.to_json())
    assert data["converged"] is False
    assert data["optimizer"]["meaning"].startswith("NOT CONVERGED")
    assert "maximum number of function evaluations" in data["optimizer"]["message"]
    assert result.brief().splitlines()[0].startswith("NOT CONVERGED")
    assert result.summary().splitlines()[0].startswith("NOT CONVERGED")


def test_a_converged_fit_opens_with_the_fit(run):
    result = fit_run(run, form="causal")
    assert result.success, result.convergence
    assert json.loads(result.to_json())["converged"] is True
    assert result.brief().splitlines()[0].startswith("fit of ")
    assert "optimizer: converged" in result.brief()
