"""Evidence for a candidate: information criteria on one prewhitened scale, held-out
prediction, and the acceptance rules. Each rule is a small function that returns why a
candidate fails it ('' when it passes), so the report can say why every candidate was or
was not named."""

from __future__ import annotations

import numpy as np
from scipy.stats import chi2, norm

from foamlab.analysis.design import ExtendedModel, Solution
from foamlab.analysis.heldout import heldout_gain
from foamlab.analysis.noise import WHITE_P, ArWhitener, whiteness
from foamlab.analysis.solve import Fit
from foamlab.diagnosis.extend import without
from foamlab.diagnosis.result import Candidate
from foamlab.diagnosis.settings import DiagnosisSettings

def _before_with_contact_of(before: Fit, fit: Fit) -> Solution:
    """The model without the candidate's effect, solved from the candidate's contact set (the
    better of that and its own solution). The active-set iteration ends in a fixed point that
    depends on its start: an extension that merely found a better contact set would
    otherwise be credited with it (docs/analysis.md, "The acceptance rules")."""
    if not all(a is b for a, b in zip(before.model.series, fit.model.series)):
        return before.solution
    m = before.model
    again = ExtendedModel(m.series, m.params, m.effect_types, m.settings, free_base=m.free_base,
                          base_bounds=m.base_bounds, effect_bounds=m.effect_bounds,
                          masks=fit.solution.masks).solve(before.nu)
    return again if again.rss() < before.solution.rss() else before.solution


def compare(cands: list[Candidate], before: Fit) -> None:
    """Delta BIC and LR p-value of each candidate against `before`, on one prewhitened scale."""
    best = min([c.fit for c in cands] + [before], key=lambda f: f.rss)
    whitener = ArWhitener.fit(best.solution.used_residuals)
    for c in cands:
        base = _before_with_contact_of(before, c.fit)
        wb = whitener.apply(base.used_residuals)
        rss_b, n = float(wb @ wb), len(wb)
        we = whitener.apply(c.fit.solution.used_residuals)
        rss_e = float(we @ we)
        q = c.fit.model.n_eta - before.model.n_eta
        lr = n * np.log(rss_b / rss_e) if rss_e > 0 and rss_b > 0 else 0.0
        # the fits minimise the plain residuals: a candidate that fits them worse than the
        # model it extends (a worse local optimum) has no evidence, whatever the filter
        # does to it (one AR filter can favour a residual that moved its error to low
        # frequencies); so the plain likelihood ratio bounds the prewhitened one
        n_raw = c.fit.n
        if c.fit.rss > 0 and base.rss() > 0:
            lr = min(lr, n_raw * np.log(base.rss() / c.fit.rss) * n / max(n_raw, 1))
        c.delta_bic = float(lr - q * np.log(n))
        c.lr_p = float(chi2.sf(max(lr, 0.0), q))


# ----------------------------------------------------------------------------- acceptance rules

def rule_evidence(c: Candidate, s: DiagnosisSettings) -> str:
    """Very strong evidence: Delta BIC (prewhitened residuals) above s.delta_bic_min."""
    return "" if c.delta_bic > s.delta_bic_min else f"delta BIC {c.delta_bic:.1f} <= {s.delta_bic_min:g}"


def rule_not_pinned(c: Candidate, s: DiagnosisSettings) -> str:
    pinned = c.pinned(s.pinned_fraction)
    return f"{pinned}: the data ask for more than this cause can be" if pinned else ""


def rule_effect_determined(c: Candidate, s: DiagnosisSettings) -> str:
    """The fit improves, but is the effect itself determined? The base model's alpha/beta can
    take its place (its standard error is that of the joint fit; docs/findings.md). Where that
    standard error says no, the likelihood ratio against the model without the effect, refitted
    from the candidate's start, says (profile_z): a damping change identification takes up is
    fitted in a valley along which the base trades with it, and the standard error read at its
    floor counts its width (A causal 3188, +18.2 %/cycle: d = 0.116, 2.9 standard errors, Delta
    BIC 40.1; docs/analysis.md, "A walk")."""
    z = c.z_score
    if z >= s.effect_z_min or profile_z(c) >= s.effect_z_min:
        return ""
    return f"effect not determined: {z:.2g} standard errors from zero (< {s.effect_z_min:g})"


def profile_z(c: Candidate) -> float:
    """The effect's distance from zero in its own basin as a normal deviate: the likelihood ratio
    of the candidate against its model without the effect, refitted from the candidate's alpha/beta
    and other effects (extend.without), turned into the z of the same p-value."""
    alt = without(c.fit.model.series, c.fit, c.effect)
    against = Candidate(c.cause, c.fit, alt)
    compare([against], alt)
    return float(norm.isf(against.lr_p / 2)) if np.isfinite(against.lr_p) else float("nan")


def explained_share(c: Candidate, current: Fit, sigma: float) -> float:
    """The share of what the current model leaves above the noise that the candidate removes."""
    left = current.rss - current.n * sigma ** 2
    return 1.0 if left <= 0 else min((current.rss - c.fit.rss) / left, 1.0)


def explains(c: Candidate, s: DiagnosisSettings) -> bool:
    """Most of the structure left, or white residuals: a cause, not a sliver of something else."""
    return c.share >= s.explained_share_min or whiteness(c.fit.solution.residual).min_p >= WHITE_P


def rule_explains(c: Candidate, s: DiagnosisSettings, first_round: bool) -> str:
    """Named causes must explain the structure; in the first round a real part of it (at least
    s.partial_share_min) may be reported as partial."""
    if explains(c, s) or (first_round and c.share >= s.partial_share_min):
        return ""
    return f"explains {c.share:.0%} of the structure left (< {s.explained_share_min:.0%})"


def rule_heldout(c: Candidate, current: Fit, current_coarse: Fit, s: DiagnosisSettings) -> str:
    """Held out on the search's samples (every k-th): the same prediction error, cheaper. The
    candidate must predict the held-out blocks better, by s.heldout_margin_z standard errors of
    the noise in the gain (analysis.heldout.HeldoutGain; docs/settings.md says why that many). Each fold's refit
    re-estimates the base's alpha/beta and the effect on the held-in blocks, each model from its
    own fit (analysis.heldout)."""
    g = heldout_gain(current, c.fit, s.heldout_margin_z, current_coarse, c.coarse_fit, s.workers or None)
    c.heldout_gain_se = g.gain_se
    if g.passed:
        return ""
    margin = f" by {g.z:g} standard errors of its gain ({g.gain_se:.2g} N)" if g.z > 0 else ""
    return f"held-out RMSE not lower{margin} ({g.after_rmse:.4g} vs {g.before_rmse:.4g} N)"
