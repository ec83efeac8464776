"""Two causes that mask each other, fitted as a pair (stage 7 of core.Procedure).

The search adds one cause a round. Two causes whose signatures cancel are each worth little
alone, so neither is found. A channel lag reads the force late: lower while it rises, higher
while it falls, as a friction of the other sign does. On independent B seed 4004, a 100 ms lag
with a 3 N friction was diagnosed `none`: the lag alone had Delta BIC 28 and was refused on
held-out data, and the friction alone had -6.7. Fitted together, the pair took the residual sum
of squares from 100.6 to 88.3 N^2 (docs/analysis.md, "Two causes on runs foamlab never made").

Where no single cause explains the structure, every pair of the run's causes is screened. The
screen is the linear gain of the pair's columns at the base: every effect at zero, alpha/beta
projected out, on the acceptance rule's prewhitened scale (limits.whitened_at_zero). A pair
predicted to beat its better member by more than BIC's penalty for the other member's parameters
is fitted jointly, in both orders. It is named when each member passes the rules on top of the
other.
"""

from __future__ import annotations

import itertools
from typing import Callable

import numpy as np

from foamlab.analysis.design import Series
from foamlab.analysis.noise import ArWhitener
from foamlab.analysis.solve import Fit
from foamlab.diagnosis.causes import Cause
from foamlab.diagnosis.evidence import (
    compare,
    explained_share,
    explains,
    rule_effect_determined,
    rule_evidence,
    rule_heldout,
    rule_not_pinned,
)
from foamlab.diagnosis.extend import fit_joint, screen, without
from foamlab.diagnosis.limits import whitened_at_zero
from foamlab.diagnosis.result import Candidate
from foamlab.diagnosis.settings import DiagnosisSettings


def screened(series: list[Series], base: Fit, causes: list[type[Cause]]) -> list[tuple[float, type[Cause], type[Cause]]]:
    """(predicted gain over the better member in noise variances, a, b) of every pair whose
    predicted gain over its better member exceeds ln(n) per parameter of the other, best first."""
    whitener = ArWhitener.fit(base.solution.used_residuals)
    n_phi, rw, Jw = whitened_at_zero(series, base, causes, whitener)
    q, _ = np.linalg.qr(Jw[:, :n_phi])
    # what alpha/beta can take up is not the effects' (the base imitates some of them)
    apart = lambda a: a - q @ (q.T @ a)
    r, effects = apart(rw), apart(Jw[:, n_phi:])
    sigma2 = float(r @ r) / len(r)
    sizes = [len(c.effect.fitted_parameters()) for c in causes]
    columns = np.split(np.arange(sum(sizes)), np.cumsum(sizes)[:-1])

    def gain(cols: np.ndarray) -> float:
        coef = np.linalg.lstsq(effects[:, cols], r, rcond=None)[0]
        fitted = effects[:, cols] @ coef
        return float(fitted @ fitted) / sigma2

    alone = [gain(c) for c in columns]
    out = []
    for i, j in itertools.combinations(range(len(causes)), 2):
        extra = gain(np.concatenate([columns[i], columns[j]])) - max(alone[i], alone[j])
        other = sizes[j] if alone[i] >= alone[j] else sizes[i]
        if extra > other * np.log(len(r)):
            out.append((extra, causes[i], causes[j]))
    return sorted(out, key=lambda p: -p[0])


def fit_pair(series: list[Series], base: Fit, a: type[Cause], b: type[Cause]) -> Fit:
    """The pair fitted jointly from the base: one cause screened and fitted with everything free,
    then the other on top; both orders, the better kept (which member leads can decide the basin:
    B seed 4004, lag first 88.3 N^2, friction first 95.7)."""
    best = None
    for first, second in ((a, b), (b, a)):
        one = fit_joint(series, screen(series, base, [first]), base)
        both = fit_joint(series, screen(series, one, [first, second]), one)
        if best is None or both.rss < best.rss:
            best = both
    return best


def members(series: list[Series], pair: Fit) -> list[Candidate]:
    """Each member of a fitted pair as a candidate on top of the other: its fit the pair, before
    it the pair without it, refitted (extend.without)."""
    return [Candidate(cause, pair, without(series, pair, i), effect=i) for i, cause in enumerate(pair.causes)]


def named(cands: list[Candidate], pair: Fit, base: Fit, sigma: float, s: DiagnosisSettings,
          coarse: Callable[[Fit], Fit]) -> bool:
    """A pair's members judged by the rules, each on top of the other (its own gain, its own
    held-out prediction); together they must explain the structure the base leaves. coarse: a
    fit on the search's samples (the held-out check's)."""
    whole = Candidate(cands[-1].cause, pair, base)
    share = explained_share(whole, base, sigma)
    for c in cands:
        compare([c], c.before)
        c.share = share
        c.reason = rule_evidence(c, s) or rule_not_pinned(c, s) or rule_effect_determined(c, s)
    if not any(c.reason for c in cands) and not explains(whole, s):
        for c in cands:
            c.reason = f"the pair explains {share:.0%} of the structure (< {s.explained_share_min:.0%})"
    on_search = coarse(pair) if not all(c.reason for c in cands) else None     # once: one fit for both
    for c in cands:
        if not c.reason:
            c.coarse_fit = on_search
            c.reason = rule_heldout(c, c.before, coarse(c.before), s)
    if any(c.reason for c in cands):
        for c in cands:
            c.reason = c.reason or "a member of a pair whose other member failed"
        return False
    for c in cands:
        c.passed, c.reason = True, "named with the other member of a pair (stage 7)"
    return True


def redundant_first(series: list[Series], current: Fit, base: Fit, findings: list[Candidate], sigma: float,
                    s: DiagnosisSettings, coarse: Callable[[Fit], Fit]) -> Candidate | None:
    """The second of two findings judged alone against the base, when the first is redundant on
    top of it - the final model without the first is as good. The first can be provisional (a
    damping change fitted at a local optimum first lost to softening, then took its place:
    softening 2e-7 per cycle in the final model), or have passed every rule by imitating the
    second (a 250 N/mm frame, independent A causal 1016: a damping drop of 12 %/cycle first, the
    frame on top at its size, without which the drop gains nothing; docs/analysis.md). None when
    the first is not redundant or the second alone fails the rules; else the second, passed, and
    the first marked as dropped."""
    first, second = findings
    alone = without(series, current, 0)
    on_top = Candidate(first.cause, current, alone)
    compare([on_top], alone)
    if on_top.delta_bic > s.delta_bic_min:
        return None
    c = Candidate(second.cause, alone, base)
    compare([c], base)
    c.share = explained_share(c, base, sigma)
    c.coarse_fit = coarse(alone)
    c.reason = (rule_evidence(c, s) or rule_not_pinned(c, s) or rule_effect_determined(c, s)
                or rule_heldout(c, base, coarse(base), s))
    if c.reason or not explains(c, s):
        return None
    c.passed = True
    first.passed = False
    first.reason = (f"made redundant by {second.name}: without it the final model is as good "
                    f"(delta BIC {on_top.delta_bic:.1f} <= {s.delta_bic_min:g})")
    return c
