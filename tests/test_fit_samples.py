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


def test_gaps_without_samples_are_said_and_those_ending_at_a_turn_apart():
    """A stretch of missed deadlines: the fit draws the displacement across it as a straight line;
    where the gap ends at a turning point the crosshead may have arrived early and waited unseen
    (ci45: 3 s gaps of a loaded host at x20, a fit at 74 x the noise) - said apart."""
    from foamlab.analysis.prepared import GAP_WARN_STEPS, prepare

    run = im.generate(im.REGIME_A, 1).to_rundata()
    x = run.displacement_mm
    peak = int(np.argmax(x[:len(x) // 3]))                 # the first cycle's peak sample
    width = GAP_WARN_STEPS + 3
    middle = peak // 2                                      # inside the first loading
    keep = np.ones(len(x), bool)
    keep[middle:middle + width] = False
    cut = RunData(run.time_s[keep], x[keep], run.force_N[keep], specimen=run.specimen, source=run.source)
    (line,) = [w for w in prepare(cut).warnings if "gap(s)" in w]
    assert line.startswith("1 gap(s)") and "straight line" in line and "turning point" not in line
    keep[peak - width:peak] = False                         # the samples before the peak: the turn after the gap
    cut = RunData(run.time_s[keep], x[keep], run.force_N[keep], specimen=run.specimen, source=run.source)
    gaps = [w for w in prepare(cut).warnings if "gap(s)" in w]
    assert len(gaps) == 2 and gaps[0].startswith("1 gap(s)") and "straight line" in gaps[0]
    assert gaps[1].startswith("1 gap(s)") and "ends at a turning point" in gaps[1]
    assert not [w for w in prepare(run).warnings if "gap(s)" in w]
