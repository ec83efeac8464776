"""What a run could have seen (issue 27 item 2): each cause's detection limit, reported with
the verdict, means what it says on runs foamlab never generated.

A clean run of tests/independent_model.py (regime A, seed 320, fixed before looking) is
diagnosed; each cause is then hidden by tests/independent_effects.py in the same run (same
seed: the same noise) at 0.5x and 1.5x the limit that diagnosis reported. At 1.5x the cause
must be named, at 0.5x not. Seed 320's figures for every cause, and machine_compliance (at
1.5x its limit in regime A, a 708 N/mm frame, named damping_cycle_change: the base imitates
a frame, issue 27), are in docs/analysis.md, "What a run could have seen".
"""

from __future__ import annotations

from types import SimpleNamespace

import independent_effects as ie
import numpy as np
import pytest
from diagnosis_support import VERDICT_ONLY

from foamlab.diagnosis import diagnose
from foamlab.diagnosis.causes import CAUSES
from foamlab.diagnosis.limits import UNCHECKED
from foamlab.gui.report import Report

SEED = 320
#: The limit's unit (the effect parameter's) -> the independent generator's (ie.UNITS).
TO_GENERATOR = {"direction_friction": 1.0, "channel_lag": 1000.0, "cycle_softening": 100.0}


@pytest.fixture(scope="module")
def limits():
    d = diagnose([ie.independent_run("A", SEED, {})])
    assert d.verdict == "none"
    return {limit.cause: limit for limit in d.limits}


def test_every_tested_cause_has_a_limit_in_words(limits):
    assert set(limits) == {"cycle_softening", "damping_cycle_change", "channel_lag", "force_zero_drift",
                           "machine_compliance", "direction_friction", "memory_lag"}
    for limit in limits.values():
        assert limit.limit > 0 and limit.stderr > 0 and limit.text.startswith("no ")
        assert not limit.unchecked and "unchecked" not in limit.text     # `none`: checked by injection
    assert limits["machine_compliance"].text.startswith("no frame softer than")
    assert limits["channel_lag"].text.endswith(" ms")


#: Friction at half its limit (0.49 N) sat on the rule's line on this seed (dBIC 9.9, then 12.9 after
#: session 13: a strict xfail here). Since friction acts only where the specimen itself pushes
#: (session 23, EffectChain._contact_force) it is -5.6 at 0.5x and 210.9 at 1.5x (77.7 before):
#: docs/analysis.md, "What a run could have seen".
#: Friction at half its limit is named in 2 of 10 of bench_detection_limits.py's seeds (issue 27 item 2
#: asks at most 1): on this seed its verdict turns on the CPU - Delta BIC -5.6 on session 30's host,
#: 14.1 on session 31's (AVX2 Zen 3; 11.9 there with OpenBLAS's Sandybridge kernels), fitted 0.70 N
#: for 0.49 N hidden. Known unmet, so not strict: it passes where the limit holds.
#: Session 43 (joint.evaluable leaves out the corner samples): named here, Delta BIC 22.7. The
#: search's first optimum now passes the evaluation check, where a corner sample failed it, and
#: identification keeps it (RMSE 0.1545 N; the second start's 0.1527 N before); the same fit on 31
#: of 32 other independent runs, a better one on the 32nd (docs/analysis.md).
FRICTION_AT_HALF = pytest.mark.xfail(reason="friction at 0.5 x its limit: named in 2/10 seeds of the limits "
                                            "benchmark (issue 27 item 2 not met); this seed turns on the CPU",
                                     strict=False)
CASES = [pytest.param(cause, multiple, named, marks=FRICTION_AT_HALF if (cause, multiple) == ("direction_friction", 0.5)
                      else ()) for cause in sorted(TO_GENERATOR) for multiple, named in [(0.5, False), (1.5, True)]]


@pytest.mark.parametrize("cause,multiple,named", CASES)
def test_a_cause_at_its_limit_times_1_5_is_named_and_at_half_is_not(limits, cause, multiple, named):
    size = limits[cause].limit * multiple * TO_GENERATOR[cause]
    # the verdict is the subject: the check of this run's own limits (15-25 s at 0.5 x) is not
    d = diagnose([ie.independent_run("A", SEED, {cause: size})], settings=VERDICT_ONLY)
    assert (d.verdict == cause) is named, (size, d.verdict, [(c.name, round(c.delta_bic, 1)) for c in d.tested[0]])
    # no check ran (VERDICT_ONLY; a named cause): the limits the base can hold say they are linearised
    for limit in d.limits:
        held = CAUSES[limit.cause].held_by_base() and limit.limit > 0
        assert limit.unchecked is held and limit.text.endswith(UNCHECKED) is held, limit.text
        assert limit.to_dict()["unchecked"] is held


def test_the_window_says_what_a_clean_run_could_have_seen():
    report = Report()
    report.set_diagnosis({"verdict": "none", "findings": [], "detection_limits": [
        {"cause": "direction_friction", "text": "no friction against the motion above 0.99 N"},
        {"cause": "channel_lag", "text": "no force channel lag above 27 ms"}]})
    assert "no friction against the motion above 0.99 N; no force channel lag above 27 ms" in report.verdict_text()
    assert ["detection_limit", "no force channel lag above 27 ms", "", "", ""] in report.csv_rows()


def test_limits_the_base_can_hold_are_checked_by_identification_and_only_raised(limits):
    """Cause.held_by_base: injected into the run's own fitted model and identification refitted
    (limits.checked); the others keep the linearised limit, unchecked."""
    for name, limit in limits.items():
        if CAUSES[name].held_by_base():
            assert limit.injections and limit.limit >= limit.linearised > 0, (name, limit)
            assert limit.to_dict()["injections"][0][0] == pytest.approx(limit.linearised)
        else:
            assert not limit.injections and limit.linearised != limit.linearised     # nan: not checked


def _placed(response, injections=3, linear=1e-3):
    """limits._Injector.place on a made-up noncentrality (size in linearised limits -> noise
    variances), no refits; the size and the sizes tried come back in linearised limits too."""
    from types import SimpleNamespace

    from foamlab.diagnosis.limits import _Injector
    from foamlab.diagnosis.settings import DiagnosisSettings
    injector = _Injector.__new__(_Injector)
    injector.base, injector.settings = SimpleNamespace(n=14157), DiagnosisSettings(limit_injections=injections)
    injector.noncentrality = lambda cause, size, refit=None: response(size / linear)
    size, tried = injector.place(CAUSES["cycle_softening"], linear)
    return size / linear, [(s / linear, lam) for s, lam in tried]


TARGET = (np.sqrt(10 + np.log(14157)) + 1.2816) ** 2        # the rule's 90 % noncentrality, q = 1


def test_a_limit_the_injection_confirms_stays():
    size, tried = _placed(lambda s: TARGET * s ** 2)
    assert size == pytest.approx(1.0) and len(tried) == 1


def test_a_limit_identification_absorbs_is_raised_to_where_it_is_seen():
    # a power law of slope 2 from an absorbed third: the target is reached at sqrt(3) x the linear limit
    size, tried = _placed(lambda s: TARGET * s ** 2 / 3)
    assert size == pytest.approx(np.sqrt(3), rel=1e-4) and len(tried) == 2
    # a step (a sample crossing the turn's drop, docs/analysis.md): halved between unseen and seen
    size, tried = _placed(lambda s: 5 * TARGET if s > 1.7 else -3.0)
    assert [round(s, 3) for s, _ in tried] == [1.0, 4.0, 2.0] and size == pytest.approx(2.0)


def test_a_limit_is_never_lowered_and_unseen_is_extrapolated():
    size, tried = _placed(lambda s: 0.01 * TARGET * s ** 2, injections=2)
    assert size > tried[-1][0] > 1.0


def test_an_injection_identification_cannot_fit_keeps_what_the_earlier_ones_showed():
    # unseen at 1 and 4 x the linearised limit, then a size the refit cannot fit: the limit is past
    # the last unseen one (the power law's 4 x), not the linearised limit nothing confirmed
    size, tried = _placed(lambda s: 0.0 if s < 10 else float("nan"), injections=4)
    assert [s for s, _ in tried] == [1.0, 4.0, 16.0] and size == pytest.approx(16.0)


def test_a_cause_of_either_sign_is_checked_on_both_and_has_a_limit_for_each(monkeypatch):
    """A damping change can rise or drop (its bounds): identification can take a drop into its own
    terms where it leaves a rise (independent A causal seeds 6000, 6004: a 20 %/cycle drop left only
    the noise, the clean runs' rise is seen from 14 %/cycle). Both signs are injected, each gets its
    own limit (one limit for both was too high for the other sign: named at half of it), and every
    injection is listed with its sign."""
    from foamlab.diagnosis import limits as L
    from foamlab.diagnosis.settings import DiagnosisSettings
    linear = 0.1

    def fake_init(self, ref, base, causes, settings):
        self.base, self.settings, self.reference = SimpleNamespace(n=14157), settings, 0.0
        self.base_white, self.sigma2, self.from_base = 0.0, 1.0, False      # the refits find the base's fit

    seen = lambda size: TARGET * (size / linear) ** 2 / (9.0 if size < 0 else 1.0)    # a drop: 1/9 seen
    monkeypatch.setattr(L._Injector, "__init__", fake_init)
    monkeypatch.setattr(L._Injector, "refit", lambda self, cause, size: L._Refit(0.0))
    monkeypatch.setattr(L._Injector, "noncentrality", lambda self, cause, size, refit=None: seen(size))
    drop, friction = CAUSES["damping_cycle_change"], CAUSES["direction_friction"]
    lims = [L.DetectionLimit(c.name, "", "", linear / 2, linear, c.limit_text(linear)) for c in (drop, friction)]
    out = {lim.cause: lim for lim in L.checked(lims, None, None, [drop, friction], DiagnosisSettings(limit_injections=4))}
    damping = out["damping_cycle_change"]
    assert damping.limit == pytest.approx(linear) and damping.limit_below == pytest.approx(3 * linear, rel=1e-3)
    assert [np.sign(s) for s, _ in damping.injections] == [1, -1, -1]
    assert damping.text == "no damping rise above +10 %/cycle, no drop below -30 %/cycle"
    assert damping.to_dict()["limit_below"] == pytest.approx(3 * linear, rel=1e-3)
    # friction has one sign: one injection, at +linear, confirmed
    friction = out["direction_friction"]
    assert friction.limit == pytest.approx(linear) and len(friction.injections) == 1 and np.isnan(friction.limit_below)


def test_where_the_refit_misses_the_runs_own_fit_injections_are_read_from_the_base(monkeypatch):
    """Identification's refit of a run can stop in a worse optimum than identification's own fit of
    that run (independent B paper 3077: 284 noise variances above its base; the injected runs' refits
    found the better one, so every injection's noncentrality read -250 where the effect was small,
    every limit came out 2-4 x its neighbours' and six causes were named at half their limit).
    There the check reads what identification leaves in the basin it found: the run as it is and
    each injection polished from the base (limits._Injector.lost)."""
    from foamlab.diagnosis import limits as L
    from foamlab.diagnosis.settings import DEFAULT
    from foamlab.identification import fit_run

    fit = fit_run(ie.independent_run("A", SEED, None, hz=2))
    base, ref = fit.free_core or fit.core_fit, fit.prepared
    worse = SimpleNamespace(solution=SimpleNamespace(used_residuals=[3 * r for r in base.solution.used_residuals]))
    monkeypatch.setattr(L, "refit_core", lambda run, orders: worse)
    monkeypatch.setattr(L._Injector, "_local", lambda self, run, refit, cause: float("inf"))   # the gate open
    friction = CAUSES["direction_friction"]
    injector = L._Injector(ref, base, [friction], DEFAULT)
    as_it_is = injector.refit(None, 0.0)
    assert injector.lost(as_it_is)
    injector.reference = as_it_is.white
    assert injector.noncentrality(friction, 1.0) == 0.0     # both refits in the worse optimum: nothing seen
    injector.from_base = True
    own = injector.refit(None, 0.0)
    assert not injector.lost(own) and own.white - injector.base_white < injector.sigma2     # the base's optimum
    injector.reference = own.white
    # a friction of 1 N: what the base's basin leaves of it, 67 noise variances on this 2 Hz run
    # (the base takes in a friction of 0.2 N whole)
    assert 20 < injector.noncentrality(friction, 1.0) < 200
    # checked switches by itself: its first injection reads the friction, not the worse optimum's 0
    lim = L.DetectionLimit(friction.name, "", "", 0.2, 1.0, friction.limit_text(1.0))
    (out,) = L.checked([lim], ref, base, [friction], DEFAULT)
    assert out.injections[0][0] == pytest.approx(1.0) and out.injections[0][1] > 20, out.injections


def test_a_lag_is_injected_as_a_real_channel_reads_it():
    """The check injects a channel lag as the force that late along the path (limits._Injector,
    analysis.prepared.force_late): on a run foamlab never made, what the independent generator's
    own delay adds (the specimen's force evaluated tau earlier), within a fifth of it (rms). The
    lag effect's batch form - the sampled force interpolated - is off by most of it: after a turn
    the force falls steeply within a step, and interpolating across the turn put 30-33 N at the
    sample after it where the delay puts 2-52 N (A causal 3068; docs/analysis.md, "A lag is read along
    the path")."""
    from foamlab.analysis.prepared import force_late
    from foamlab.diagnosis import limits as L
    from foamlab.diagnosis.settings import DEFAULT
    from foamlab.identification import fit_run
    from foamlab.model.effects import ChannelLag

    clean = ie.independent_run("A", SEED, None)
    truth = ie.independent_run("A", SEED, {"channel_lag": 40.0}).force_N - clean.force_N    # the same noise
    fit = fit_run(clean)
    lag = CAUSES["channel_lag"]
    injector = L._Injector(fit.prepared, fit.free_core or fit.core_fit, [lag], DEFAULT)
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))
    assert rms(truth) > 0.5                                   # N: the lag shows
    assert rms(injector._injected(lag, 0.040) - truth) < 0.2 * rms(truth)   # 0.05 of it on this run
    model = np.maximum(force_late(injector.base.params, fit.prepared, (0.0,))[0], 0.0)     # the fitted model now
    interpolated = ChannelLag(0.040).sensor_batch(clean.time_s, model) - model
    assert rms(interpolated - truth) > 0.4 * rms(truth)         # 0.54 of it on this run


def test_orders_identification_held_apart_are_held_in_the_linearised_limit():
    """A pair of nearly equal residual orders gives two nearly parallel columns: free, they take up
    a share of the softening no fit of the pair reaches (B paper seed 3045, chosen for its four
    held orders: se 0.00087 free, 0.00042 held, 0.00046 from the profile likelihood;
    docs/analysis.md, "Held orders and the quiet gate")."""
    from foamlab.analysis.solve import at_full_resolution, decimation
    from foamlab.diagnosis.limits import detection_limits
    from foamlab.diagnosis.run import _coalesced
    from foamlab.diagnosis.settings import DEFAULT
    from foamlab.identification import fit_run

    fit = fit_run(ie.independent_run("B", 3045, None, form="paper"))
    mask = _coalesced(fit, [])
    assert mask is not None and mask.sum() >= 2
    series = [fit.prepared.series]
    coarse = [s.decimated(decimation(series)) for s in series]
    base = at_full_resolution(fit.free_core, coarse)
    se = [detection_limits(coarse, base, [CAUSES["cycle_softening"]], DEFAULT, fit.free_core.n, m)[0].stderr
          for m in (None, mask)]
    assert se[1] < 0.7 * se[0], se
    assert _coalesced(fit, ["another run"]) is None       # several runs: a shared base, no identification's holds


def test_a_memory_lag_limit_is_where_its_own_effect_is_seen_not_its_slope():
    """A memory lag releases a turn's jump over tau: the sample after the turn sees exp(-dt / tau),
    flat at tau = 0, so the slope there promises too little (limits._sized). A causal, seed 3068 of
    the limits benchmark's fresh seeds (session 39): the slope said 107 ms, and the generator's lag
    at half of that (53 ms) was named. The limit from the effect at each size, before the check by
    injection (VERDICT_ONLY: what that check adds is test_limits_the_base_can_hold_...), at 0.5 x
    and 1.5 x."""
    run = lambda ms: ie.independent_run("A", 3068, {"memory_lag": ms} if ms else {}, form="causal")
    clean = diagnose([run(0.0)], settings=VERDICT_ONLY)
    limit = {lim.cause: lim for lim in clean.limits}["memory_lag"]
    assert clean.verdict == "none" and limit.limit < 0.5 * limit.linearised, limit
    assert limit.to_dict()["linearised"] == pytest.approx(limit.linearised)
    for multiple, named in ((0.5, False), (1.5, True)):
        d = diagnose([run(1000.0 * multiple * limit.limit)], settings=VERDICT_ONLY)
        assert (d.verdict == "memory_lag") is named, (multiple, limit.limit, d.verdict)
