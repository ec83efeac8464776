"""Diagnosis: the extended design equals the effects' own batch form, the statistics behave,
and hidden effects are named (offline: runs of tests/independent_model.py with the cause hidden
by tests/independent_effects.py, which shares no code with the model diagnosis fits)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import independent_effects as ie
import numpy as np
import pytest
from diagnosis_support import VERDICT_ONLY

from foamlab.diagnosis import CAUSES, diagnose
from foamlab.analysis.design import ExtendedModel, Series
from foamlab.analysis.noise import ArWhitener, noise_sigma, whiteness
from foamlab.diagnosis.limits import clearing_on_top
from foamlab.diagnosis.settings import DEFAULT
from foamlab.diagnosis.synthetic import hidden_effect_run
from foamlab.importers import load_run
from foamlab.model import ModelParameters, label_history, triangular_history
from foamlab.model.effects import EFFECTS, EffectChain, estimate_velocity, loading_rate

PARAMS = ModelParameters.default()
#: The protocol of the runs of foamlab's own generator below (clean, a disturbance): the paper's
#: three cycles at 2 Hz (1770 samples).
FAST = dict(sampling_hz=2.0)


def _series(t, x, y) -> Series:
    lab = label_history(x)
    return Series("s", t, x, y, lab, estimate_velocity(t, x, lab), loading_rate(t, x, lab.starts), 23.6)


# ----------------------------------------------------------------------------- the design

@pytest.mark.parametrize("name", list(EFFECTS))
def test_extended_design_is_the_effect_chain(name):
    """ExtendedModel.predict(theta, eta) == EffectChain([effect]).measured_force of the model."""
    t, x = triangular_history(58.0, 23.6 / 60, 2, 4.0)
    lab = label_history(x)
    effect = EFFECTS[name]()
    clean = EffectChain().measured_force(PARAMS, t, x, labels=lab)
    s = _series(t, x, clean)
    # (compliance: the loop closed to its fixed point, so the measured force is self-consistent)
    expected = EffectChain([effect]).measured_force(PARAMS, t, x, labels=lab, velocity=s.velocity)
    s.y = expected if name == "machine_compliance" else clean
    settings = {name: {k: v for k, v in effect.values.items() if k != effect.parameters[0].name}}
    model = ExtendedModel([s], PARAMS, [EFFECTS[name]], settings)
    theta = np.append(model.linear0, 0.0)
    got = model.predict(theta, effect.vector())[0]
    err = np.abs(got - expected)
    if name == "machine_compliance":
        # exact but where the effect holds the specimen still after a reversal (the frame
        # springing back): the memory columns there are linearised
        peaks = np.asarray(lab.peaks)
        near = np.min(np.abs(np.arange(len(t))[:, None] - peaks[None, :]), axis=1) <= 8
        assert np.max(err[~near]) < 0.05, np.max(err[~near])
        assert np.sqrt(np.mean(err ** 2)) < 0.05
    else:
        # identification's basis (exact Riemann-Liouville) vs the model's SOE operators
        assert np.max(err) < 2e-3 * np.max(np.abs(expected)), np.max(err)


def test_linear_parameters_are_recovered_by_the_projection():
    t, x = triangular_history(58.0, 23.6 / 60, 3, 2.0)
    y = EffectChain().measured_force(PARAMS, t, x, labels=label_history(x))
    model = ExtendedModel([_series(t, x, y)], PARAMS)
    sol = model.solve()
    assert np.sqrt(sol.rss() / len(t)) < 1e-3 * np.max(y)
    assert abs(sol.theta[-1]) < 1e-2          # no zero offset in noise-free model data


# ----------------------------------------------------------------------------- statistics

def test_noise_level_is_estimated_from_the_data_itself():
    rng = np.random.default_rng(4)
    t, x = triangular_history(58.0, 23.6 / 60, 3, 16.0)
    y = EffectChain().measured_force(PARAMS, t, x, labels=label_history(x))
    for sigma in (0.05, 0.2, 1.0):
        est = noise_sigma(y + rng.normal(0, sigma, len(y)))
        assert est == pytest.approx(sigma, rel=0.05)


def test_whiteness_and_prewhitening():
    rng = np.random.default_rng(1)
    e = rng.normal(size=5000)
    assert whiteness(e).min_p > 1e-3
    ar = np.zeros_like(e)
    for i in range(1, len(e)):
        ar[i] = 0.8 * ar[i - 1] + e[i]
    assert whiteness(ar).min_p < 1e-6
    w = ArWhitener.fit([ar])
    assert w.order >= 1 and w.phi[0] == pytest.approx(0.8, abs=0.05)
    assert whiteness(w.apply([ar])).min_p > 1e-3


# ----------------------------------------------------------------------------- hidden effects

#: Each cause hidden by tests/independent_effects.py (written again from the physics, no foamlab
#: model code) in regime A of tests/independent_model.py, causal residual, three cycles at 16 Hz,
#: at a size in physical units (independent_effects.UNITS) well above the detection limits of
#: docs/benchmarks.md; the paper form is tests/test_fit_forms.py's. Seed 500, set before looking;
#: the statistics over seeds are benchmarks/bench_detection_independent.py's.
HIDDEN = [
    ("cycle_softening", 3.0),            # %/cycle
    ("damping_cycle_change", 100.0),     # %/cycle
    ("channel_lag", 100.0),              # ms
    ("force_zero_drift", 0.4),           # N/min
    ("machine_compliance", 250.0),       # N/mm frame
    ("direction_friction", 3.0),         # N
    ("memory_lag", 300.0),               # ms
]
SEED = 500


@pytest.mark.parametrize("cause,size", HIDDEN, ids=[c for c, _ in HIDDEN])
def test_hidden_effect_is_named_and_the_extension_predicts_held_out_data_better(cause, size):
    d = diagnose([ie.independent_run("A", SEED, {cause: size}, form="causal")])
    assert d.verdict == cause, _summary(d)
    gain = d.to_dict()["findings"][0]["gain"]
    assert gain["heldout_rmse_after"] < gain["heldout_rmse_before"]
    assert gain["rmse_after"] < gain["rmse_before"]
    assert gain["delta_bic"] > 10
    fitted = d.findings[0].values["values"][CAUSES[cause].effect.parameters[0].name]
    assert fitted > 0, fitted                    # every size above is on the positive side


def test_damping_cycle_change_is_fitted_at_its_size():
    """Identification gives a per-cycle damping change to the earlier cycles' residual terms;
    the extension restarted from identification with the effect taken out finds its size. The
    base leans the screening to -5 %/cycle here: the restart is tried on the other side too
    (extend.probe), each from the base with the effect at that size first (extend._joint_at:
    from identification alone, the size was found on one CPU and not another)."""
    d = diagnose([ie.independent_run("B", SEED, {"damping_cycle_change": 100.0}, form="causal")])
    assert d.verdict == "damping_cycle_change", _summary(d)
    assert d.findings[0].values["values"]["d"] == pytest.approx(1.0, rel=0.1)


#: Runs of the detection benchmark (seeds fixed there) whose causal diagnosis, the form identification
#: chose, did not reach the noise (docs/analysis.md, "Two residual forms in a diagnosis"): a zero
#: drift whose paper-form diagnosis lost by a BIC of 5 000 (11.6 s of 22.7 s), and a paper-form
#: damping change, found by the causal diagnosis at 1.7 x the noise, whose paper-form diagnosis won.
OTHER_FORM = [({"force_zero_drift": 0.4}, 1008, "A", "causal", False),
              ({"damping_cycle_change": 30.0}, 1014, "A", "paper", True)]


@pytest.mark.parametrize("causes, seed, regime, form, paper_diagnosed", OTHER_FORM, ids=["lost", "won"])
def test_the_other_residual_form_is_diagnosed_only_where_it_can_win(causes, seed, regime, form, paper_diagnosed):
    stages = []
    d = diagnose([ie.independent_run(regime, seed, causes, form=form)], progress=lambda s, f: stages.append(s))
    (cause,) = causes
    assert d.verdict == cause and d.params.residual_form == form, _summary(d)
    assert any(s.startswith("paper form: ") for s in stages) == paper_diagnosed, sorted({s[:25] for s in stages})
    assert ("with the extension found" in d.base_form_reason) == paper_diagnosed, d.base_form_reason


#: Two causes hidden together (issue 16), one seed each, set before looking: both must be
#: findings (more pairs on independent runs: bench_detection_independent.py --two, docs/benchmarks.md;
#: an xfail from 25a097b until session 28, when both pairs were named).
TWO_CAUSES = [
    ("A", {"cycle_softening": 3.0, "force_zero_drift": 0.18}, 520),
    ("B", {"machine_compliance": 200.0, "cycle_softening": 3.0}, 521),
]


def test_two_causes_hidden_together_are_both_findings_each_with_its_own_gain():
    both = []
    for regime, causes, seed in TWO_CAUSES:
        d = diagnose([ie.independent_run(regime, seed, causes, form="causal")])
        names = [f.name for f in d.findings]
        if set(causes) <= set(names):
            both.append(names)
        assert d.verdict == names[0] and names[0] in causes, _summary(d)
        removed = [f.before.rss - f.fit.rss for f in d.findings]
        assert removed == sorted(removed, reverse=True)        # best first: the verdict is the larger
        for f in d.findings:                                   # each its own gain, on the model before it
            gain = f.gain()
            assert gain["rmse_after"] < gain["rmse_before"] and gain["delta_bic"] > 10
            assert gain["heldout_rmse_after"] < gain["heldout_rmse_before"]
    assert len(both) == len(TWO_CAUSES), both


def test_a_second_cause_under_a_first_at_the_noise_is_searched_for_and_named():
    """A 250 N/mm frame under a 3 %/cycle softening, regime A: independent A causal seed 4000 of
    the two-cause benchmark (seeds fixed there before looking). The softening alone leaves the
    model at the noise level (the search used to stop there: softening alone), yet the frame on top
    clears the evidence rule by far; the score test of the causes left (limits.clearing_on_top)
    sends the search on."""
    run = ie.independent_run("A", 4000, {"machine_compliance": 250.0, "cycle_softening": 3.0}, form="causal")
    d = diagnose([run])
    names = [f.name for f in d.findings]
    assert names[:2] == ["cycle_softening", "machine_compliance"], _summary(d)
    first = d.findings[0].fit
    # the old stop: the first finding's model within at_noise of the noise variance
    assert first.rss / (first.n * d.noise_sigma ** 2) - 1 < DEFAULT.at_noise
    frame = d.findings[1]
    assert frame.delta_bic > 10 * DEFAULT.delta_bic_min, _summary(d)
    assert frame.gain()["heldout_rmse_after"] < frame.gain()["heldout_rmse_before"]


def test_a_model_at_the_noise_is_not_searched_again_for_what_the_score_test_overpromises():
    """A 300 ms memory lag, independent A causal seed 1008 of the detection benchmark (seeds fixed
    there), found and its model at the noise. The score test of friction on top promised 62 noise
    variances (a Gauss-Newton step of alpha/beta thousands of times their range), 44 from the
    decimated run once held inside the bounds; every sample's, held inside them, 15 - what a fit of
    friction gains. A second round was searched for nothing (5 s of 14); now one round."""
    d = diagnose([ie.independent_run("A", 1008, {"memory_lag": 300.0}, form="causal")])
    assert [f.name for f in d.findings] == ["memory_lag"], _summary(d)
    assert len(d.tested) == 1, _summary(d)
    assert clearing_on_top(d.series, d.final, [CAUSES["direction_friction"]], DEFAULT, within_bounds=True) == []


def test_a_first_finding_the_second_made_redundant_is_dropped():
    """A 250 N/mm frame, independent A causal seed 1016 of the detection benchmark (seeds fixed
    there): the first round named a damping drop of 12 %/cycle, which imitates part of a frame,
    and the second the frame at its size on top of it. The verdict, the finding that removed
    the most, was the drop. Without the drop the final model is as good: the frame alone."""
    d = diagnose([ie.independent_run("A", 1016, {"machine_compliance": 250.0}, form="causal")], settings=VERDICT_ONLY)
    assert d.verdict == "machine_compliance" and len(d.findings) == 1, _summary(d)
    frame = d.findings[0]
    assert frame.before is d.base and frame.passed            # judged alone against the base
    assert 1.0 / frame.values["values"]["c_mm_per_N"] == pytest.approx(250.0, rel=0.25)
    dropped = [c for cands in d.tested for c in cands if c.name == "damping_cycle_change"]
    assert any(c.reason.startswith("made redundant by machine_compliance") for c in dropped), _summary(d)


def test_two_causes_that_mask_each_other_are_named_as_a_pair():
    """A channel lag reads the force late, lower while it rises and higher while it falls: a
    friction of the other sign. Hidden together, each is worth little alone: independent B paper
    seed 4002 of the two-cause benchmark (seeds fixed there before looking) was `unexplained`, a
    memory lag explaining 20 %. Stage 7 (diagnosis.pairs) on the run's base, the greedy rounds
    left out (max_findings 0: whether they leave a run to stage 7 turns on its last bits,
    docs/analysis.md, "Two causes on runs foamlab never made"): the screen's pair, fitted jointly,
    names both near their sizes, each on top of the other."""
    run = ie.independent_run("B", 4002, {"channel_lag": 100.0, "direction_friction": 3.0}, form="paper")
    d = diagnose([run], settings=dataclasses.replace(DEFAULT, max_findings=0))
    assert {f.name for f in d.findings} == {"channel_lag", "direction_friction"}, _summary(d)
    values = {f.name: f.values["values"] for f in d.findings}
    assert values["channel_lag"]["tau_s"] == pytest.approx(0.1, abs=0.03), values
    assert values["direction_friction"]["f_N"] == pytest.approx(3.0, abs=0.6), values
    for f in d.findings:                       # each its own gain on top of the other, held out too
        assert [c.name for c in f.before.causes] == [c for c in values if c != f.name]
        gain = f.gain()
        assert gain["delta_bic"] > 10 and gain["heldout_rmse_after"] < gain["heldout_rmse_before"]
    assert d.final.rmse < 1.05 * d.noise_sigma


RECORDED_SOFTENING = Path(__file__).parent / "data" / "recorded" / "serial_cycle_softening_10pct.csv"


def test_an_effect_pinned_at_the_limit_of_its_range_is_not_named():
    """A recording through the serial driver with 10 %/cycle softening hidden, on which
    damping_cycle_change fits better (delta BIC 376 vs 356) only at its -45 % limit: the data
    ask for more than a damping change can be, so the true cause is named."""
    d = diagnose([load_run(RECORDED_SOFTENING)])
    assert d.verdict == "cycle_softening", _summary(d)
    assert d.findings[0].values["values"]["s"] == pytest.approx(0.10, rel=0.25)
    stronger = [c for c in d.tested[0] if c.delta_bic > d.findings[0].delta_bic]
    assert all("limit of its range" in c.reason for c in stronger), _summary(d)


def test_rate_dependence_needs_two_speeds_and_is_named_with_them():
    """The damping scaled by (v / v_ref)^0.5 at 60 and 120 mm/min (regime A, seeds 510/511).
    The second run's turns are placed as the first run's fit fits them (PreparedRun.placed_for):
    placed at the extreme sample, the shared base fitted the second run at 7x the noise and a
    clean pair was 'unexplained'."""
    runs = ie.rate_pair("A", 510, 0.5, form="causal")
    one = diagnose(runs[:1], settings=VERDICT_ONLY)
    assert "rate_dependence" in one.skipped and one.verdict != "rate_dependence"
    d = diagnose(runs)
    assert d.verdict == "rate_dependence", _summary(d)
    f = d.findings[0]
    assert f.values["values"]["m"] == pytest.approx(0.5, abs=0.1)
    assert f.gain()["heldout_rmse_after"] < f.gain()["heldout_rmse_before"]


def test_a_disturbance_outside_the_catalogue_is_unexplained_and_located():
    run = hidden_effect_run(None, seed=5, periodic_N=1.0, period_s=30.0, **FAST)
    d = diagnose([run], settings=VERDICT_ONLY)
    assert d.verdict == "unexplained"
    out = d.to_dict()
    assert out["findings"][0]["effect"] == "unexplained" and out["findings"][0]["where"]
    assert d.final_analysis.periodicity.period_s == pytest.approx(30.0, rel=0.1)


def test_clean_runs_give_none():
    """No effect: 'none' in at least 5 of the first 6 seeded runs (the false-alarm rate on
    independent runs is benchmarks/bench_detection_independent.py's)."""
    seen = []
    # the first with the limits' check (its progress too), the others the verdict alone
    verdicts = [diagnose([hidden_effect_run(None, seed=100 + s, sampling_hz=1.0)],
                         progress=(lambda stage, f: seen.append((stage, f))) if s == 0 else None,
                         settings=DEFAULT if s == 0 else VERDICT_ONLY).verdict
                for s in range(6)]
    assert verdicts.count("none") >= 5, verdicts
    # the progress of the first: never backwards, says the probes start and names each candidate as
    # its probe ends (the probes run side by side: analysis.parallel)
    fractions = [f for _, f in seen]
    assert all(b >= a - 1e-12 for a, b in zip(fractions, fractions[1:])) and fractions[-1] == 1.0, seen
    stages = " | ".join(stage for stage, _ in seen)
    assert all(f"tested {name} (" in stages for name in ("cycle_softening", "channel_lag", "memory_lag")), stages
    assert stages.index("causes on the decimated runs at once") < stages.index("tested "), stages
    if verdicts[0] in ("none", "unexplained"):     # nothing found: the check's jobs counted as they end (most of a clean run's time)
        checks = [stage for stage, _ in seen if stage.startswith("what this run could have seen: limits checked")]
        n = int(checks[-1].split(" of ")[-1].rstrip(")"))
        assert checks[-1].endswith(f"({n} of {n})") and len(checks) == n + 1, checks


# ----------------------------------------------------------------------------- the real file

REAL = Path(__file__).parent / "data" / "real" / "Specimen_RawData_6.csv"


def test_the_real_file_memory_lag_predicts_held_out_blocks_better():
    """docs/findings.md: on the real Bluehill run the release after each reversal is the
    largest structure; memory_lag is the cause found (named when it explains at least half of
    the structure above the noise, else partial) and its held-out gain is real. Against its nearest
    rival, channel_lag (both explain a release after each reversal; Delta BIC 14 054 vs 3 138): the
    eight-cause ranking of the file is `foamlab diagnose`'s (docs/findings.md), 2x this test's time."""
    d = diagnose([load_run(REAL)], causes=["memory_lag", "channel_lag"])
    best = (d.findings or d.partial)[0]
    assert best.name == "memory_lag", _summary(d)
    gain = best.gain()
    assert gain["heldout_rmse_after"] < 0.7 * gain["heldout_rmse_before"], gain
    assert gain["rmse_after"] < gain["rmse_before"] and gain["delta_bic"] > 10
    tau = best.values["values"]["tau_s"]
    assert 0.05 < tau < 0.5, tau
    assert d.verdict in ("memory_lag", "unexplained")
    # what the model misses, in one sentence (issue 28): how large, where, and by cycle
    miss = d.base_analysis.miss()
    assert miss.where.startswith("the turning points") and len(miss.by_cycle_N) == 3, miss.sentence()
    assert d.to_dict()["base"]["miss"]["sentence"] == miss.sentence()


def test_the_miss_in_one_sentence():
    """Where: the turning points when they hold the most power per sample, else the region
    furthest from zero; by cycle: each cycle's RMS and its change per cycle (least squares)."""
    from foamlab.diagnosis.residuals import Region, ResidualAnalysis

    white = whiteness(np.random.default_rng(0).normal(size=200))
    halves = [("", c, d, 0.0, rms) for c, rms in ((1, 0.3), (2, 0.2), (3, 0.1)) for d in (1, -1)]
    region = Region("", 2, -1, 8.0, 9.0, 40, 0.24, 0.25, 12.0)
    an = ResidualAnalysis(0.2, 0.02, white, [region], [], None, halves, turning=(0.1, 0.05, 0.6))
    miss = an.miss()
    assert miss.by_cycle_N == (0.3, 0.2, 0.1) and miss.change_per_cycle == pytest.approx(-0.5)
    assert miss.sentence() == ("the model misses the measurement by 0.2 N RMS (10.0 x the noise), most at cycle 2 "
                               "unloading, x 8-9 mm (mean residual +0.24 N, +12 standard errors); by cycle "
                               "0.3 / 0.2 / 0.1 N RMS (-50% per cycle)")
    turning = ResidualAnalysis(0.2, 0.02, white, [region], [], None, halves, turning=(0.35, 0.006, 0.6))
    assert turning.miss().where.startswith("the turning points (35% of the residual power in the 0.6 s")


def _summary(d) -> list:
    return [(c.name, round(c.delta_bic, 1), c.reason) for r in d.tested for c in r]
