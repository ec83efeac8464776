"""diagnose(runs): identification's fit as the base model, then the diagnosis."""

from __future__ import annotations

from typing import Callable

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.noise import WHITE_P
from foamlab.analysis.prepared import PreparedRun, prepare
from foamlab.analysis.solve import POLISH_NFEV, Fit, at_full_resolution, decimation, held, polish
from foamlab.diagnosis.core import Procedure
from foamlab.diagnosis.extend import on_base
from foamlab.diagnosis.form import NAME, base_form_reason, check_other_form
from foamlab.diagnosis.result import Diagnosis
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings
from foamlab.identification import FitReport, fit_run
from foamlab.identification.fit import resumed
from foamlab.identification.statistics import information_criteria
from foamlab.rundata import RunData

Progress = Callable[[str, float], None]
#: Share of the progress a diagnosis that fits its run gives the fit.
FIT_SHARE = 0.15


def diagnose(runs: list[RunData], fit: FitReport | None = None,
             causes: list[str] | None = None, progress: Progress | None = None,
             form: str = "auto", settings: DiagnosisSettings = DEFAULT) -> Diagnosis:
    """Diagnose one run, or several runs of the same specimen (e.g. at other speeds).

    fit: identification's fit of the first run (the reference speed), as the run's own
    pipeline made it; identified here when not given. Its core fit is the base model of
    one run; with several runs the base is polished on all of them from its parameters.
    progress: called with (stage, fraction 0..1) as the work advances.
    form: the residual form of the base when it is fitted here ('auto': the data choose).
    A base in a form the user named is checked against the other form first (diagnosis.form).
    settings: the thresholds (foamlab.diagnosis.settings; docs/settings.md).
    """
    report = _forward(progress)
    if not runs:
        raise FoamlabError("no run to diagnose")
    names = _names(runs)
    if fit is None:
        fit = fit_run(runs[0], progress=lambda stage, f: report(f"fit: {stage}", FIT_SHARE * f), form=form)
    if fit.prepared is None:      # a stored fit: its working state is made again from its parameters
        fit = resumed(fit, runs[0])
    fit, form_finding = check_other_form(fit, lambda stage, f: report(f"the other residual form: {stage}",
                                                                         FIT_SHARE * f), settings)
    fit.prepared.series.name = names[0]
    # the other runs' turns are placed as each form's base fits them (_shared_base)
    rest = [prepare(r, name=n) for r, n in zip(runs[1:], names[1:])]
    start = FIT_SHARE if progress else 0.0
    kept = Procedure(*_base_of(fit, rest), causes, lambda stage, f: report(stage, start + (1.0 - start) * f),
                     settings, _coalesced(fit, rest))
    d = kept.run()
    d.base_form_reason = base_form_reason(fit)
    other = fit.alternatives[0] if fit.alternatives and form_finding is None else None
    begun = None
    if other is not None and d.verdict != "none" and not _at_the_noise(d):
        # its base on several runs is polished again with their turns placed for it (seconds)
        report(f"the other residual form ({other.params.residual_form}): its base, and whether it could explain "
               "the run better", report.fraction)
        other.prepared.series.name = names[0]
        begun = _base_of(other, rest)      # the other form's runs and base: for the check and its diagnosis
    if begun is not None and _other_may_win(d, begun, rest):
        # the form was chosen on the base alone; an effect the base cannot hold may have tipped
        # it (a paper-form run with a damping change: causal base 0.64 N held out, paper 3.1 N):
        # unless the extended model leaves only noise, the other form's base is diagnosed too
        # and the better extended model kept
        so_far = report.fraction
        second = Procedure(*begun, causes, lambda stage, f: report(f"{other.params.residual_form} form: {stage}",
                                                                   so_far + (1.0 - so_far) * f),
                           settings, _coalesced(other, rest))
        d2 = second.run()
        if bic(d2.final) < bic(d.final):
            kept = second
            d2.base_form_reason = (f"{other.params.residual_form} residual form: with the extension found it "
                                   f"explains the run better (BIC {bic(d2.final):.1f} vs {bic(d.final):.1f} in the "
                                   f"{fit.params.residual_form} form, which alone predicted held-out blocks better)")
            d = d2
    d = kept.checked(d)         # the limits of the form kept only
    if form_finding is not None:
        d.form_finding, d.verdict = form_finding, NAME
    d.notes += [f"{name}: {p.off_schedule} samples taken off the sampling schedule left out "
                "(their instants are unsure)" for name, p in zip(names, [fit.prepared] + rest) if p.off_schedule]
    report("done", 1.0)
    return d


class _forward:
    """The caller's progress, never backwards (a round or a form that ends early leaves its
    share unused); fraction: the last one reported."""

    def __init__(self, progress: Progress | None):
        self.progress, self.fraction = progress, 0.0

    def __call__(self, stage: str, fraction: float) -> None:
        self.fraction = max(self.fraction, fraction)
        if self.progress is not None:
            self.progress(stage, self.fraction)


def _base_of(fit: FitReport, rest: list) -> tuple[list[PreparedRun], Fit]:
    """The runs and the base a diagnosis from one identification's fit starts from: its core fit
    as the base of its own run, polished on all the runs from its parameters when there are
    several. The base is the largest structure's fit where identification chose a smaller one: a
    smaller structure drops what its data do not determine, and where an effect the model lacks
    bends the larger one's terms into cancelling pairs it is the coarser fit (measured: memory_lag
    0.3 s hidden, 2.6 N left against 0.53 N), on which the causes are not found; diagnosis judges
    them against all the model's terms. For the same reason it is the fit with every order free
    where identification held some apart."""
    fit = fit.largest or fit
    prepared = [fit.prepared] + rest
    if not rest and fit.core_fit is not None:
        return prepared, fit.free_core or fit.core_fit
    return _shared_base(prepared, fit.params)


def _coalesced(fit: FitReport, rest: list) -> np.ndarray | None:
    """The alpha/beta of _base_of's base (its free core) that identification held apart (bool over
    them), None where it held none or the base is another fit (several runs)."""
    fit = fit.largest or fit
    core, free = fit.core_fit, fit.free_core
    if rest or free is None or core is None or core.model.base_bounds is None:
        return None
    mask = held(*core.model.base_bounds)
    return mask if mask.any() and len(mask) == free.model.n_phi else None


#: Rounds of placing every run's turns by the shared base and polishing it again.
PLACEMENT_ROUNDS = 3


def _shared_base(prepared: list[PreparedRun], params) -> tuple[list[PreparedRun], Fit]:
    """The base of several runs with the parameters they share, each run's turns placed the way
    that base fits them (PreparedRun.placed_for), the first run's too: its own fit placed them for
    parameters bent to one run (independent A seeds 640/641 at 60 and 120 mm/min, 2 Hz: one turn
    of the first run the other way, the shared base 0.220 N; placed again, 0.154 N, noise 0.15 N).
    The other runs are first placed as the given parameters, the diagnosed form's, fit them (the
    other form's base was started from runs placed for the first form's)."""
    prepared = [prepared[0]] + [p.placed_for(params) for p in prepared[1:]]
    base = polish([p.series for p in prepared], params)
    for _ in range(PLACEMENT_ROUNDS):
        placed = [p.placed_for(base.params) for p in prepared]
        if all(a is b for a, b in zip(placed, prepared)):
            break
        prepared = placed
        base = polish([p.series for p in prepared], base.params)
    return prepared, base


def _other_may_win(d: Diagnosis, begun: tuple[list[PreparedRun], Fit], rest: list) -> bool:
    """Whether the other residual form's diagnosis can explain the run better: with findings, the
    other form's base (begun: _base_of) with them (one joint fit from their values) must come within
    settings.delta_bic_min of this diagnosis's BIC. Measured on the 160 one-run cases of the
    detection benchmark (docs/analysis.md, "Two residual forms in a diagnosis"): where the other
    form's diagnosis won, this fit was already thousands below; where it lost, thousands above.
    Without findings (`unexplained`), or with several runs, the other form is diagnosed; so it is
    where the other form's base alone fits the run better than this one's (BIC): the findings were
    then found on the worse base and may be the wrong ones (independent regime C, seed 5122, softening
    3 %/cycle in the causal form: the causal base, chosen on held-out blocks, at 585 N^2, the paper
    base at 373; causal found a damping change and a friction at 103, which the paper base does not
    take; the paper form's diagnosis names the softening at 41, the noise's level)."""
    if not d.final.causes or rest:
        return True
    prepared, base = begun
    if bic(base) < bic(d.base):
        return True
    series = [prepared[0].series]
    k = decimation(series)
    coarse = [s.decimated(k) for s in series]
    fit = at_full_resolution(on_base(coarse, d.final, at_full_resolution(base, coarse)), series,
                             POLISH_NFEV if k > 1 else 0)
    return bic(fit) < bic(d.final) + d.settings.delta_bic_min


def _at_the_noise(d: Diagnosis) -> bool:
    """The findings leave white residuals or residual variance near the noise's."""
    return bool(d.findings) and (d.final_whiteness.min_p >= WHITE_P
                                 or d.final.rmse ** 2 < (1 + d.settings.near_noise) * d.noise_sigma ** 2)


def bic(fit: Fit) -> float:
    """Gaussian BIC of a fitted (extended) model on the samples it used."""
    return information_criteria(fit.rss, fit.n, len(fit.solution.theta) + len(fit.nu))[1]


def _names(runs: list[RunData]) -> list[str]:
    out = []
    for i, r in enumerate(runs):
        name = r.source.replace("\\", "/").rsplit("/", 1)[-1] if r.source else f"run {i + 1}"
        if name in out:
            name = f"{name} ({i + 1})"
        out.append(name)
    return out
