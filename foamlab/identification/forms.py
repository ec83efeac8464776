"""The residual form the data choose (`foamlab fit --form auto`, the default).

The two forms of the residual force (docs/model.md) have the same parameters and the
same count, so neither is favoured by its size: each is fitted in full and the one that
predicts held-out blocks of the run better is kept (foamlab.analysis.heldout, the check
diagnosis applies to its extensions). BIC is reported beside it; with equal parameter
counts its difference is n log(RSS ratio), the same ranking on all the samples.

A first form that leaves only the noise (RMSE within AT_NOISE_RATIO of the noise level and
white residuals) settles the choice: the other, with as many parameters, could at best tie,
and is not fitted (40 % of `foamlab fit`; the causal form on independent paper-form runs, A and
B seeds 1-3: 3.5-8 x the noise, never white). The likelier form is fitted first (likelier_first:
a short probe of each from the paper's three-step start, 0.04 s), so a run of either form can
settle with one fit; the order changes what is fitted, never which form is kept.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from foamlab.analysis.design import ExtendedModel
from foamlab.analysis.heldout import heldout_rmse
from foamlab.analysis.noise import AT_NOISE_RATIO, WHITE_P, whiteness
from foamlab.analysis.solve import Fit, at_full_resolution, decimation
from foamlab.identification.joint import DecimatedProblem
from foamlab.model.layout import RESIDUAL_FORMS

if TYPE_CHECKING:
    from foamlab.analysis.prepared import PreparedRun
    from foamlab.identification.result import FitReport
    from foamlab.model import ModelParameters
    from foamlab.model.layout import Orders


@dataclass(frozen=True)
class FormScore:
    """One form fitted to the run: how well it fits and how well it predicts."""

    form: str
    rmse: float                  # whole run, N
    heldout_rmse: float          # every held-out block predicted by the model refitted without it, N
    bic: float


@dataclass(frozen=True)
class FormChoice:
    """Which residual form the fit uses, and why."""

    chosen: str
    scores: tuple[FormScore, ...]
    forced: bool                 # the user named the form (--form): no choice was made
    settled: bool = False        # the chosen form left only the noise: the other was not fitted

    def score(self, form: str) -> FormScore | None:
        return next((s for s in self.scores if s.form == form), None)

    @property
    def delta_bic(self) -> float | None:
        """BIC of the best other form minus the chosen one's (> 0: the chosen is better)."""
        others = [s.bic for s in self.scores if s.form != self.chosen]
        mine = self.score(self.chosen)
        return min(others) - mine.bic if others and mine else None

    def reason(self) -> str:
        mine = self.score(self.chosen)
        if self.settled and mine is not None:
            return (f"{self.chosen} residual form: it leaves only the noise (RMSE {mine.rmse:.4g} N, white "
                    f"residuals), so the other form was not fitted")
        if self.forced or mine is None or len(self.scores) < 2:
            return f"{self.chosen} residual form (asked for with --form)"
        others = ", ".join(f"{s.heldout_rmse:.4g} N {s.form}" for s in self.scores if s.form != self.chosen)
        return (f"{self.chosen} residual form: it predicts held-out blocks better "
                f"({mine.heldout_rmse:.4g} N vs {others}; dBIC {self.delta_bic:.1f})")


def likelier_first(fd: "PreparedRun", orders: "Orders", start: "ModelParameters | None") -> tuple[str, ...]:
    """The residual forms, the one that fits better after a short probe from ``start`` (the
    paper's three-step values, the same in either form) first. On 20 independent runs (both forms,
    regimes A and B, seeds 1-5) the form generated was first in all, its probe's SSE 2-600 x lower.
    Without a start (the three steps found none) the forms in their usual order."""
    if start is None:
        return RESIDUAL_FORMS
    sse = {}
    for form in RESIDUAL_FORMS:
        problem = DecimatedProblem(fd, replace(orders, form=form))
        sse[form] = problem.probe(problem.lay.from_flat(start.to_vector())[1]).sse
    return tuple(sorted(RESIDUAL_FORMS, key=lambda f: sse[f]))


def core_fit_of(result: "FitReport") -> Fit:
    """The analysis core's fit behind a result; when identification kept its own optimum, the
    core's model at those parameters (the linear ones and the contact set solved: what the
    held-out check refits anyway, so no search is needed)."""
    if result.core_fit is not None:
        return result.core_fit
    model = ExtendedModel([result.prepared.series], result.params)
    return Fit([], model, np.zeros(0), np.zeros(0), model.solve())


def score(result: "FitReport") -> FormScore:
    return FormScore(result.params.residual_form, float(result.rmse), heldout_of(core_fit_of(result)),
                     float(result.bic))


def heldout_of(core: Fit) -> float:
    """Held out on the search's samples (every k-th), as diagnosis does: the same prediction
    error at a fraction of the cost (kept with the fit: asked again, it is not recomputed)."""
    series = core.model.series
    coarse = at_full_resolution(core, [s.decimated(decimation(series)) for s in series])
    return heldout_rmse(core, coarse)


def settles(result: "FitReport") -> bool:
    """The fit leaves only the noise: RMSE within AT_NOISE_RATIO of the run's noise level, and
    white residuals (analysis.noise). Both, since either alone can hold for a form that misses."""
    fd = result.prepared
    if fd is None or result.rmse > AT_NOISE_RATIO * fd.noise_N:
        return False
    residual = (fd.f - result.predicted_force_N)[fd.observed]
    return whiteness(residual).min_p >= WHITE_P


def choose(results: list["FitReport"], forced: bool) -> "FitReport":
    """The result whose form predicts held-out blocks best, with every form's score and the
    others' results attached (the report shows both forms' statistics)."""
    scores = [score(r) for r in results] if len(results) > 1 else [
        FormScore(results[0].params.residual_form, float(results[0].rmse), float("nan"), float(results[0].bic))]
    best = min(range(len(results)), key=lambda i: scores[i].heldout_rmse) if len(results) > 1 else 0
    chosen = results[best]
    settled = len(results) == 1 and not forced
    choice = FormChoice(chosen.params.residual_form, tuple(scores), forced, settled)
    return replace(chosen, form_choice=choice).with_work(
        alternatives=tuple(r for i, r in enumerate(results) if i != best))
