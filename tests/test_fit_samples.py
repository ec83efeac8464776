"""One sample set per figure, named (issue 26, item 4): every RMSE of a fit says which samples
it covers and how many, and samples dropped before the fit are counted in the JSON and in the
first line of the summary.

The run is an independent-generator run (tests/independent_model.py, regime A seed 1) with a
few samples taken off the sampling schedule by hand: each moved by 0.7 of a step, so both
intervals next to it are off the step and it and its two neighbours are unsure.
"""

from __future__ import annotations

import json

import independent_model as im
import numpy as np
import pytest

from foamlab.batch.rows import BatchRow
from foamlab.identification import fit_run
from foamlab.rundata import RunData

MOVED = (1000, 2200, 3400)           # isolated samples inside the cycles


@pytest.fixture(scope="module")
def fitted():
    run = im.generate(im.REGIME_A, 1).to_rundata()
    t = run.time_s.copy()
    step = float(np.median(np.diff(t)))
    t[list(MOVED)] += 0.7 * step
    moved = RunData(t, run.displacement_mm, run.force_N, specimen=run.specimen, source=run.source)
    return moved, fit_run(moved, form="causal")


def test_dropped_samples_are_counted_in_the_json_and_the_first_line(fitted):
    run, result = fitted
    dropped = 3 * len(MOVED)                  # each moved sample and its two neighbours
    d = json.loads(result.to_json())
    assert d["samples"]["recorded"] == len(run.time_s)
    assert d["samples"]["off_schedule_dropped"] == dropped
    assert f"{dropped} of {len(run.time_s)} dropped" in result.brief().splitlines()[0]
    assert f"{dropped} of {len(run.time_s)} dropped" in result.summary().splitlines()[0]


def test_each_rmse_names_its_samples_and_their_count(fitted):
    _, result = fitted
    d = json.loads(result.to_json())
    rmse = d["samples"]["rmse"]
    assert rmse["set"] == "recorded"
    # the count is of the samples the RMSE is computed on: recomputed from the stored residuals
    obs = result.samples.observed
    whole = result.samples.residual_N[obs[0]:obs[0] + rmse["count"]]
    assert np.sqrt(np.mean(whole ** 2)) == pytest.approx(d["rmse"], rel=1e-12)
    assert rmse["count"] == len(result.samples.time_s) - obs[0] - (len(result.samples.time_s) - 1 - obs[-1])
    turns = d["turn_samples"]
    assert turns["rmse_without_samples"] == {"set": "evidence", "count": rmse["count"] - turns["count"]}
    assert d["samples"]["statistics"]["joint"] == {"set": "cycles", "count": result.n_obs}
    assert d["forms"]["rmse_samples"] == "recorded" and d["forms"]["heldout_rmse_samples"] == "held-out"
    assert f"on all {rmse['count']} recorded samples" in result.brief()


def test_a_batch_row_names_the_fit_and_the_diagnosis_sets_apart():
    """The fit's rmse (all recorded) and the diagnosis's rmse_before/after (evidence) are separate
    columns, each with its count, and the counts survive the output file's round trip."""
    row = BatchRow(file="f.csv", sha256="0", rmse=0.2, rmse_samples=4700, dropped=9,
                   rmse_before=0.18, rmse_after=0.15, evidence_samples=4690)
    back = BatchRow.from_record(row.to_record())
    assert (back.rmse_samples, back.dropped, back.evidence_samples) == (4700, 9, 4690)
