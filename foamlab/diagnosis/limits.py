"""What this run could have seen: for each cause, the smallest size its diagnosis would name.

The acceptance rule's evidence is a likelihood ratio: an effect of size eta whose standard
error at the base fit is se gives LR ~ chi2(1, (eta / se)^2), named when LR - q ln(n) exceeds
settings.delta_bic_min. The limit is the size named in 90 % of runs like this one:
se * (sqrt(delta_bic_min + q ln n) + z_0.9). se comes from the information the run holds at
the base fit: the Jacobian of the base with the effect added at zero, alpha/beta free (a base
that imitates the effect takes its share of the information), the linear parameters
projected out (variable projection), on the prewhitened scale the rule uses.

A linearised limit: where the base imitates an effect through a valley of local optima
(compliance), the search may miss an effect above it; tests/test_detection_limits.py injects
into the run's own fitted model at 0.5x and 1.5x the limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.stats import norm

from foamlab.analysis.design import ExtendedModel, Series
from foamlab.analysis.noise import ArWhitener
from foamlab.analysis.solve import Fit, bounds_like, contact_of
from foamlab.diagnosis.causes import Cause
from foamlab.diagnosis.settings import DiagnosisSettings

#: The limit is the size named in this share of runs like this one.
DETECTED_SHARE = 0.9


@dataclass(frozen=True)
class DetectionLimit:
    """The smallest size of one cause this run's diagnosis names in DETECTED_SHARE of runs."""

    cause: str
    parameter: str
    unit: str
    stderr: float      # of the effect parameter at the base fit (its unit)
    limit: float       # in the parameter's unit; nan where the run holds no information on it
    text: str          # in words and physical units: "no friction above 0.31 N"

    def to_dict(self) -> dict:
        finite = lambda v: float(v) if np.isfinite(v) else None
        return {"cause": self.cause, "parameter": self.parameter, "unit": self.unit,
                "stderr": finite(self.stderr), "limit": finite(self.limit), "text": self.text}


def detection_limits(series: list[Series], base: Fit, causes: list[type[Cause]],
                     settings: DiagnosisSettings, n_full: int | None = None) -> list[DetectionLimit]:
    """The limit of each cause (its first fitted parameter) on these runs at the base fit.

    series may be the search's decimated ones (base fitted on them): the information of every
    sample, n_full of them, is then the decimated samples' times n_full / n (the standard error
    over its square root) - a Jacobian on every sample costs seconds per cause."""
    whitener = ArWhitener.fit(base.solution.used_residuals)
    n = n_full or base.n
    thin = np.sqrt(base.n / n)
    out = []
    for cause in causes:
        se = _stderr_at_zero(series, base, cause, whitener) * thin
        q = len(cause.effect.fitted_parameters())
        multiple = np.sqrt(settings.delta_bic_min + q * np.log(n)) + norm.ppf(DETECTED_SHARE)
        limit = se * multiple if np.isfinite(se) else float("nan")
        p = cause.effect.fitted_parameters()[0]
        text = cause.limit_text(limit) if np.isfinite(limit) else f"{cause.name}: not determined by this run"
        out.append(DetectionLimit(cause.name, p.name, p.unit, float(se), float(limit), text))
    return out


def _stderr_at_zero(series: list[Series], base: Fit, cause: type[Cause], whitener: ArWhitener) -> float:
    """Standard error of the cause's first parameter with the effect at zero and the base free."""
    model, rw, Jw = whitened_at_zero(series, base, [cause], whitener)
    sigma2 = float(rw @ rw) / max(len(rw) - Jw.shape[1], 1)
    try:
        cov = np.linalg.pinv(Jw.T @ Jw) * sigma2
    except np.linalg.LinAlgError:
        return float("nan")
    first = model.n_phi       # the effect's first parameter follows alpha/beta
    v = cov[first, first]
    return float(np.sqrt(v)) if np.isfinite(v) and v > 0 else float("nan")


def whitened_at_zero(series: list[Series], base: Fit, causes: list[type[Cause]], whitener: ArWhitener
                     ) -> tuple[ExtendedModel, np.ndarray, np.ndarray]:
    """The fit (the base, or a base with effects) extended by the causes, each new effect at zero:
    (the model, its residual and its variable-projection Jacobian - alpha/beta, the fit's own
    effects at their values, then each new effect's parameters - prewhitened)."""
    params, own = base.params, base.model
    model = ExtendedModel(series, params, list(own.effect_types) + [c.effect for c in causes],
                          {**own.settings, **{c.effect.name: c.settings(series) for c in causes}},
                          effect_bounds={**own.effect_bounds, **{c.effect.name: c.bounds() for c in causes}},
                          free_base=True, base_bounds=bounds_like(own, series, params), masks=contact_of(base, series))
    nu = model.start(np.concatenate([base.eta, np.zeros(model.n_eta - len(base.eta))]))
    fun, jac = model.residual_fn()
    r, J = fun(nu), jac(nu)
    lengths = [int(m.sum()) for m in model.rows()]
    cuts = np.cumsum(lengths)[:-1]
    white = lambda v: whitener.apply(np.split(v, cuts))
    return model, white(r), np.column_stack([white(J[:, j]) for j in range(J.shape[1])])


def gain_on_top(series: list[Series], fit: Fit, cause: type[Cause], whitener: ArWhitener) -> float:
    """What one more cause would gain on top of the fit, linearised (a score test): the likelihood
    ratio, in noise variances, of its columns at zero with alpha/beta and the fit's own effects free
    and the linear parameters projected out, on the acceptance rule's prewhitened scale."""
    _, rw, Jw = whitened_at_zero(series, fit, [cause], whitener)
    q = len(cause.effect.fitted_parameters())
    coef = np.linalg.lstsq(Jw, rw, rcond=None)[0]
    if cause.bounds()[0][0] >= 0.0 >= -coef[-q]:       # Gauss-Newton's step: the residual's Jacobian is -df
        # one-sided: an effect that is zero at its bound gains nothing where the data pull it below
        # (a frame of negative compliance flagged 110 on a 1 Hz softened run; fitted, -3.8)
        return 0.0
    fitted = Jw @ coef
    base = Jw[:, :-q] @ np.linalg.lstsq(Jw[:, :-q], rw, rcond=None)[0]
    return (float(fitted @ fitted) - float(base @ base)) / (float(rw @ rw) / len(rw))


def clearing_on_top(series: list[Series], fit: Fit, causes: list[type[Cause]], settings: DiagnosisSettings,
                    n_full: int | None = None) -> list[type[Cause]]:
    """The causes whose gain on top of the fit, linearised (gain_on_top), would clear the evidence
    rule: Delta BIC = gain - q ln n above settings.delta_bic_min. series may be the search's
    decimated ones, the fit on them: every sample's information is then the decimated samples'
    times n_full / n (as detection_limits)."""
    whitener = ArWhitener.fit(fit.solution.used_residuals)
    n = n_full or fit.n
    return [c for c in causes if gain_on_top(series, fit, c, whitener) * n / fit.n
            - len(c.effect.fitted_parameters()) * np.log(n) > settings.delta_bic_min]
