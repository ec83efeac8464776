"""The residual form as a finding: when the base was fitted in a form the user named
(`--form causal|paper`) and the data follow the other, that is what the base gets wrong -
said in so many words, not blamed on the nearest catalogue cause.

With `--form auto` (the default) identification has already kept the form that predicts
held-out blocks better (foamlab.identification.forms); diagnosis then only says which form
its base uses and why.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from foamlab.analysis.heldout import heldout_rmse
from foamlab.analysis.noise import ArWhitener
from foamlab.analysis.solve import Fit
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings
from foamlab.identification.fit import fit_prepared
from foamlab.identification.forms import core_fit_of
from foamlab.identification.result import FitReport
from foamlab.model.layout import RESIDUAL_FORMS

NAME = "residual_form"
MEANING = ("the residual force follows the other form: the paper's Eq. 11 in x in every later "
           "half-cycle (Eqs. 20b-f), or the causal Eq. 10 memory of the history")


@dataclass(frozen=True)
class FormFinding:
    """The other residual form fits the run better than the one the base was fitted in."""

    form: str                 # the form the data follow
    asked: str                # the form the base was fitted in
    before: Fit
    after: Fit
    delta_bic: float          # prewhitened, equal parameter counts: n log(RSS ratio)

    def description(self) -> str:
        return (f"the residual force follows the {self.form} form, not the {self.asked} one asked for: "
                f"RMSE {self.before.rmse:.4g} -> {self.after.rmse:.4g} N, held-out "
                f"{self.before.heldout_rmse:.4g} -> {self.after.heldout_rmse:.4g} N")

    def to_dict(self) -> dict:
        return {"effect": NAME, "form": self.form, "description": self.description(), "meaning": MEANING,
                "gain": {"rmse_before": self.before.rmse, "rmse_after": self.after.rmse,
                         "heldout_rmse_before": self.before.heldout_rmse,
                         "heldout_rmse_after": self.after.heldout_rmse, "delta_bic": self.delta_bic},
                "parameters": {}, "rank": 1, "named": True}


def base_form_reason(fit: FitReport) -> str:
    return fit.form_choice.reason() if fit.form_choice else f"{fit.params.residual_form} residual form"


def check_other_form(fit: FitReport, progress=None,
                     settings: DiagnosisSettings = DEFAULT) -> tuple[FitReport, FormFinding | None]:
    """For a fit in a form the user named: the other form fitted too; when it predicts held-out
    blocks better with very strong evidence (the rules of any extension), it becomes the base
    and the finding says so. Returns (the base to diagnose on, the finding or None)."""
    if fit.form_choice is None or not fit.form_choice.forced or fit.prepared is None:
        return fit, None
    asked = fit.params.residual_form
    other_form = next(f for f in RESIDUAL_FORMS if f != asked)
    other = fit_prepared(fit.prepared, replace(fit.orders, form=other_form), progress, form=other_form)
    before, after = core_fit_of(fit), core_fit_of(other)
    whitener = ArWhitener.fit(min(before, after, key=lambda f: f.rss).solution.used_residuals)
    wb, wa = whitener.apply(before.solution.used_residuals), whitener.apply(after.solution.used_residuals)
    delta_bic = float(len(wb) * np.log((wb @ wb) / max(float(wa @ wa), 1e-300)))
    if delta_bic > settings.delta_bic_min and heldout_rmse(after) < heldout_rmse(before):
        return other, FormFinding(other_form, asked, before, after, delta_bic)
    return fit, None
