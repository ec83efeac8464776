"""The residual form the data choose, on runs foamlab did not generate (tests/independent_model.py,
both forms written again from the paper: corner sums, no foamlab model code), and diagnosis on
top of either form (issue: "The paper's model as printed").

The sweeps over 20 seeds per form and regime are benchmarks/bench_forms.py (docs/benchmarks.md);
here a few seeds of each, including seed 12 of regime A, whose first peak lies 0.4 ms before a
sample that reads the peak within the 1 um encoder step.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import independent_effects as ie
import independent_model as im
import numpy as np
import pytest
from diagnosis_support import VERDICT_ONLY

from foamlab.analysis.noise import AT_NOISE_RATIO
from foamlab.diagnosis import diagnose
from foamlab.diagnosis.synthetic import hidden_effect_run
from foamlab.identification import fit_run
from foamlab.model import ModelParameters

ROOT = Path(__file__).resolve().parents[1]
REAL = Path(__file__).parent / "data" / "real" / "Specimen_RawData_6.csv"
TOLERANCE = 1.05
CASES = [("A", "paper", s) for s in (1, 2, 12)] + [("B", "paper", s) for s in (3, 14)] + \
        [("A", "causal", s) for s in (4, 12)] + [("B", "causal", s) for s in (5,)]


@pytest.mark.parametrize("regime,form,seed", CASES, ids=[f"{r}-{f}-{s}" for r, f, s in CASES])
def test_auto_keeps_the_form_the_run_was_made_in_and_reaches_the_noise(regime, form, seed):
    reg = im.REGIMES[regime].with_(form=form)
    run = im.generate(reg, seed)
    result = fit_run(run.to_rundata())
    scores = {s.form: s for s in result.form_choice.scores}
    assert result.params.residual_form == form, result.form_choice.reason()
    other = {"paper": "causal", "causal": "paper"}[form]
    if other in scores:
        assert scores[form].heldout_rmse < scores[other].heldout_rmse
    else:     # the kept form left only the noise: the other was not fitted, and the report says so
        assert result.form_choice.settled and "not fitted" in result.form_choice.reason()
        assert result.rmse <= AT_NOISE_RATIO * result.prepared.noise_N
    assert result.rmse / reg.noise_N <= TOLERANCE, f"{result.rmse / reg.noise_N:.3f} x the noise"


def test_fit_cli_json_says_which_form_was_kept_and_why_and_gives_the_paper_steps(tmp_path):
    run = im.generate(im.REGIME_B.with_(form="paper"), 2)
    path = tmp_path / "paper_B_2.csv"
    run.write_csv(path)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(path), "--json", "--no-store"],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=False, timeout=300)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    # the paper form, fitted first as the likelier, leaves only the noise: the causal is not fitted
    assert d["form"] == "paper" and d["forms"]["chosen"] == "paper" and d["forms"]["settled"]
    assert "not fitted" in d["forms"]["reason"] and [s["form"] for s in d["forms"]["scores"]] == ["paper"]
    assert all(d["statistics"][step]["rmse"] is not None for step in ("damping", "residual", "elastic", "joint"))
    forced = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(path), "--json", "--no-store",
                             "--form", "causal"], cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)
    assert forced.returncode == 0 and json.loads(forced.stdout)["form"] == "causal"
    bad = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(path), "--form", "static"],
                         cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "invalid choice" in bad.stderr and "Traceback" not in bad.stderr


def test_fit_cli_json_scores_both_forms_where_neither_leaves_only_the_noise():
    """The real Bluehill file (tests/data/real): no form fits it to the noise, so both are fitted,
    scored on held-out blocks, and the better predictor kept."""
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(REAL), "--json", "--no-store"],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=False, timeout=300)
    assert out.returncode == 0, out.stderr
    d = json.loads(out.stdout)
    scores = {s["form"]: s for s in d["forms"]["scores"]}
    assert set(scores) == {"causal", "paper"} and not d["forms"]["settled"] and "held-out" in d["forms"]["reason"]
    chosen, other = d["forms"]["chosen"], {"paper": "causal", "causal": "paper"}[d["forms"]["chosen"]]
    assert d["form"] == chosen and scores[chosen]["delta_bic"] == 0.0
    assert scores[chosen]["heldout_rmse"] < scores[other]["heldout_rmse"]


# -- diagnosis on the paper form ---------------------------------------------------------

PAPER = replace(ModelParameters.default(), residual_form="paper")
FAST = dict(sampling_hz=2.0)
#: Every cause hidden by tests/independent_effects.py in a paper-form run of regime B (three cycles
#: at 16 Hz), at the sizes of tests/test_diagnosis.py's causal runs (independent_effects.UNITS);
#: rate_dependence: runs at 90 and 180 mm/min. Seed 501, set before looking.
HIDDEN = [
    ("cycle_softening", 3.0),            # %/cycle
    ("damping_cycle_change", 100.0),     # %/cycle
    ("channel_lag", 100.0),              # ms
    # refused before session 14 on held-out 0.1489 >= 0.1488 N with Delta BIC 1078: the check never
    # scored the off-specimen samples, where a drift shows (docs/analysis.md)
    ("force_zero_drift", 0.4),           # N/min
    ("machine_compliance", 250.0),       # N/mm frame
    ("direction_friction", 3.0),         # N
    ("memory_lag", 300.0),               # ms
    ("rate_dependence", 0.5),            # exponent
    # a drop, as issue 27's blind runs had it: the third cycle's damping 40 % below the first's
    # (the causal form's base can take a drop whole: its limit says so, tests/test_detection_limits.py)
    ("damping_cycle_change", -20.0),     # %/cycle
]
SEED = 501


@pytest.mark.parametrize("cause,size", HIDDEN, ids=[c if s > 0 else f"{c}_drop" for c, s in HIDDEN])
def test_hidden_effect_on_a_paper_form_run_is_named(cause, size):
    if cause == "rate_dependence":
        runs = ie.rate_pair("B", SEED, size, form="paper")
    else:
        runs = [ie.independent_run("B", SEED, {cause: size}, form="paper")]
    d = diagnose(runs)
    assert d.verdict == cause, [(c.name, round(c.delta_bic, 1), c.reason) for r in d.tested for c in r]
    assert d.params.residual_form == "paper", d.base_form_reason
    assert d.to_dict()["base"]["form"] == "paper"


def test_clean_paper_form_runs_give_none_and_a_disturbance_is_unexplained():
    verdicts = [diagnose([hidden_effect_run(None, params=PAPER, seed=100 + s, sampling_hz=1.0)],
                         settings=VERDICT_ONLY).verdict for s in range(3)]
    assert verdicts.count("none") == len(verdicts), verdicts       # 20 of 20 in the benchmark
    d = diagnose([hidden_effect_run(None, params=PAPER, seed=5, periodic_N=1.0, period_s=30.0, **FAST)],
                 settings=VERDICT_ONLY)
    assert d.verdict == "unexplained"


def test_a_base_in_the_wrong_form_is_the_finding_not_a_catalogue_cause():
    """The user names the causal form for a paper-form run: the verdict says the residual
    follows the other form (with its gain), instead of blaming the nearest catalogue cause."""
    d = diagnose([hidden_effect_run(None, params=PAPER, seed=3, **FAST)], form="causal")
    assert d.verdict == "residual_form"
    first = d.to_dict()["findings"][0]
    assert first["effect"] == "residual_form" and first["form"] == "paper"
    assert first["gain"]["heldout_rmse_after"] < first["gain"]["heldout_rmse_before"]
    assert first["gain"]["delta_bic"] > 10
    assert np.isfinite(first["gain"]["rmse_after"])


def test_findings_on_the_worse_fitting_forms_base_are_checked_in_the_other_form():
    """Regime C (a specimen no setting was tuned on; its cases fixed before any diagnosis of it),
    seed 5122, softening 3 %/cycle hidden in the causal form. Identification keeps the causal base on
    held-out blocks, though the paper base fits the run better; on the causal base the rounds end on
    a damping change and a friction, neither hidden, which the paper base does not take. The other
    form is diagnosed because its base alone has the lower BIC (diagnosis.run._other_may_win), and
    names the softening alone at its size."""
    run = ie.independent_run("C", 5122, {"cycle_softening": 3.0}, form="causal")
    d = diagnose([run], settings=VERDICT_ONLY)
    assert d.verdict == "cycle_softening", [f.name for f in d.findings]
    assert [f.name for f in d.findings] == ["cycle_softening"]
    assert d.findings[0].values["values"]["s"] == pytest.approx(0.03, abs=0.003)
    assert d.final.rmse < 1.1 * im.NOISE_N


def test_a_form_twice_off_its_rival_on_the_gates_samples_gets_no_other_starts(monkeypatch):
    """With the form to choose, the second form's polish gets identification's other starts only
    where its first polish is within RIVAL_RATIO of the first form's fit. Both on the core fit's used
    samples: the first form's report over every sample is up to 8.5 x that where a lag misfits the
    turns (docs/analysis.md, "The rival a losing form is measured against"). A paper seed 1006 with a
    100 ms channel lag: the causal form's first polish is about 8 x off the paper form's core fit,
    and its other starts (and those of its other turn placement) cost a second for the form not kept."""
    from foamlab.identification import joint
    from foamlab.identification.fit import RIVAL_RATIO
    from foamlab.identification.forms import core_fit_of

    asked = []
    more = joint.JointSearch.more
    monkeypatch.setattr(joint.JointSearch, "more",
                        lambda self, count=1: (asked.append(self.lay.form), more(self, count))[1])
    fit = fit_run(ie.independent_run("A", 1006, {"channel_lag": 100.0}, form="paper"))
    (other,) = fit.alternatives
    assert fit.params.residual_form == "paper"
    losing, kept = core_fit_of(other).rmse, core_fit_of(fit).rmse
    assert losing > RIVAL_RATIO * kept, (losing, kept)
    assert "causal" not in asked, asked
