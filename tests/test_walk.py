"""A damping change identification takes up (the causal form), on runs foamlab never generated:
the search walks it out from zero (extend.walk) and the effect rule reads its distance from zero by
the likelihood ratio where the joint fit's standard error sits in a valley (evidence.profile_z).
Runs: tests/independent_model.py with tests/independent_effects.py's change, 16 Hz; the seeds and
size are the limits benchmark's (seed 3000 + i: A causal 3188 at 1.5 x its clean twin's rise limit),
where the search before the walk named nothing (docs/analysis.md, "A walk")."""

from __future__ import annotations

import independent_effects as ie
from diagnosis_support import VERDICT_ONLY

from foamlab.diagnosis import diagnose
from foamlab.diagnosis.causes import DampingCycleChange
from foamlab.diagnosis.evidence import profile_z
from foamlab.diagnosis.extend import walk
from foamlab.pipeline import fit_run


def test_a_walk_out_from_zero_ends_at_the_change_identification_took_up():
    size = 0.18202      # A causal 3188: the generator's d, 18.2 %/cycle
    fit = fit_run(ie.independent_run("A", 3188, {"damping_cycle_change": 100 * size}, form="causal", hz=16.0),
                  form="causal")
    base = fit.free_core or fit.core_fit
    series, causes = [fit.prepared.series], [DampingCycleChange]
    walked = walk(series, base, causes, DampingCycleChange.walk_sizes)
    assert (base.rss - walked.rss) / (base.rss / base.n) > 30
    assert 0.5 * size < walked.eta[-1] < 1.5 * size


def test_a_change_in_a_valley_is_named_by_its_likelihood_ratio():
    # A causal 3188, +18.2 %/cycle: fitted at about two thirds of it, where the base trades with it
    d = diagnose([ie.independent_run("A", 3188, {"damping_cycle_change": 18.20217704599866}, form="causal",
                                     hz=16.0)], settings=VERDICT_ONLY)
    named = [c for c in d.tested[0] if c.name == "damping_cycle_change"]
    assert d.verdict == "damping_cycle_change", [(c.name, round(c.delta_bic, 1), c.reason) for c in d.tested[0]]
    assert named[0].z_score < VERDICT_ONLY.effect_z_min
    assert profile_z(named[0]) >= VERDICT_ONLY.effect_z_min
