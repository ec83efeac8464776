"""Residual orders held apart where a fit's terms coalesce into a cancelling pair (issue 19).

Two residual terms of one cycle at nearly one order with large amplitudes of opposite sign are
one term and its derivative in the order (x^b ln x): the run determines what they add up to, not
two orders. The search can end there although orders further apart fit as well: on the README
main job r1_1 = -1.7 / r1_2 = 1.5 at beta -0.235 / -0.245 (earlier fits +-153), where orders
0.3 apart, centred where the run fits best, fit better by 4 chi2 with amplitudes -0.35 / 0.26; on
the real Bluehill file +-596 became 1.6 / -2.4 (docs/identification.md, "Orders held apart").

Such a pair's orders are held SPREAD apart, centred where the decimated run fits best with the
other parameters as fitted, the fit polished by the analysis core with them held; it is kept when
its BIC (two parameters fewer per pair) is within BIC_TIE of the free fit's. The held orders are
reported as held, not fitted: the data do not determine them.
"""

from __future__ import annotations

import itertools
import re
from dataclasses import dataclass

import numpy as np

from foamlab.analysis.design import Series
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import (
    HOLD,
    POLISH_NFEV,
    Fit,
    at_full_resolution,
    converged,
    decimation,
    fit_base,
    polish,
    solved_at,
)
from foamlab.identification.statistics import information_criteria
from foamlab.identification.structure import BIC_TIE, cancelling
from foamlab.model.layout import BETA_HI, BETA_LO

#: How far apart a coalesced pair's orders are held (0.2-0.5 fit the main job alike, within 1.3
#: chi2; closer pairs' amplitudes still cancel).
SPREAD = 0.3
#: Two orders of one cycle closer than this are one order seen twice.
COALESCED = 0.05
#: Centres tried for a pair, about the pair's own order.
CENTRES = np.arange(-0.6, 0.61, 0.15)
#: Rounds of holding (a held pair can leave another cycle's terms to coalesce).
ROUNDS = 3

#: The rule a held fit is kept by (the structure selection's: fewest parameters within BIC_TIE).
RULE = f"kept when its BIC is within {BIC_TIE:g} of the free fit's (fewer parameters at no real cost)"


@dataclass(frozen=True)
class HeldApart:
    """A fit with some residual orders held apart, and what it cost."""

    fit: Fit
    held: np.ndarray                  # bool over the base's nonlinear parameters (alpha, beta)
    dchi2: float                      # its RSS minus the free fit's, in noise variances
    bic: float = np.nan               # its BIC and the free fit's, on the same samples
    free_bic: float = np.nan
    free: Fit | None = None           # the free fit it was compared with

    def record(self, held: dict[str, float], free_values: dict[str, float]) -> "HeldOrders":
        """The report's record of the choice (held: the held orders by their names in the result;
        free_values: the free fit's parameters by the same names)."""
        lay = self.fit.params.layout
        free = self.free if self.free is not None else self.fit
        return HeldOrders(held=dict(held), dchi2=float(self.dchi2), bic=float(self.bic), free_bic=float(self.free_bic),
                          rmse_N=float(np.sqrt(self.fit.rss / self.fit.n)), free_rmse_N=float(np.sqrt(free.rss / free.n)),
                          samples=int(self.fit.n), n_params=_n_params(lay, self.held),
                          free_n_params=_n_params(lay, np.zeros_like(self.held)),
                          free_values=dict(free_values), rule=RULE)


@dataclass(frozen=True)
class HeldOrders:
    """Residual orders held apart: a structure choice by the selection rule, what it cost in
    likelihood, and the free fit it was chosen over (identification.apart)."""

    held: dict[str, float]            # the held orders by name: their held values
    dchi2: float                      # held RSS minus free RSS, in noise variances
    bic: float                        # the held fit's BIC and the free fit's (same samples)
    free_bic: float
    rmse_N: float                     # both fits' RMSE on the samples both were fitted on
    free_rmse_N: float
    samples: int
    n_params: int                     # the core's parameters (the held orders not counted)
    free_n_params: int
    free_values: dict[str, float]     # the free fit's parameters, by the report's names
    rule: str

    def to_dict(self) -> dict:
        return {"held": self.held, "rule": self.rule, "dchi2": self.dchi2, "delta_bic": self.bic - self.free_bic,
                "samples": self.samples,
                "held_fit": {"rmse": self.rmse_N, "bic": self.bic, "n_params": self.n_params},
                "free_fit": {"rmse": self.free_rmse_N, "bic": self.free_bic, "n_params": self.free_n_params,
                             "values": self.free_values}}

    def brief(self) -> str:
        return (f"chi2 {self.dchi2:+.1f}, BIC {self.bic - self.free_bic:+.1f} against the free fit "
                f"({self.rule}; --full shows both)")

    def lines(self) -> list[str]:
        """Both fits side by side and the free fit's values of the held orders' terms."""
        out = [f"[[Orders held apart]] {self.rule}; on the {self.samples} samples both were fitted on:",
               f"    {'fit':<8}{'params':>8}{'RMSE':>12}{'BIC':>14}",
               f"    {'held':<8}{self.n_params:>8}{self.rmse_N:>12.5g}{self.bic:>14.2f}  (kept)",
               f"    {'free':<8}{self.free_n_params:>8}{self.free_rmse_N:>12.5g}{self.free_bic:>14.2f}"]
        cycles = {_cycle(name) for name in self.held}
        terms = [n for n in self.free_values if _cycle(n) in cycles]
        if terms:
            out.append("    the free fit's terms of those cycles: "
                       + ", ".join(f"{n} {self.free_values[n]:.4g}" for n in terms))
        return out

    def note(self) -> str:
        """The note a fit result carries."""
        values = ", ".join(f"{n} = {v:.3g}" for n, v in self.held.items())
        return (f"{values} held (fixed) {SPREAD:g} apart: free, their terms coalesce into one order whose "
                "amplitudes cancel (the data determine the terms' sum, not their orders); held where the run "
                f"fits best, chi2 {self.dchi2:+.1f} against the free fit")


def _cycle(name: str) -> str | None:
    """The cycle of a residual term's parameter name (r2_1, beta2_1: '2'), else None."""
    match = re.fullmatch(r"(?:r|beta)(\d+)_\d+", name)
    return match.group(1) if match else None


def hold_apart(fd: PreparedRun, free: Fit, polish_nfev: int = POLISH_NFEV, max_nfev: int = 0) -> HeldApart | None:
    """The free fit's coalesced residual pairs held apart (module docstring); None when it has
    none or holding them costs more than BIC_TIE. The rounds run on the decimated run (as the
    search does), the last one is carried to every sample (polish_nfev evaluations, then on to
    convergence within max_nfev more) and judged there."""
    if not coalesced(free):
        return None
    lay = free.params.layout
    coarse = [fd.series.decimated(decimation([fd.series]))]
    held = np.zeros(lay.n_nonlinear, bool)
    fit, reference = free, _bic(solved_at(coarse, free.params), held)
    for _ in range(ROUNDS):
        pairs = [p for p in coalesced(fit) if not held[list(p)].any()]
        if not pairs:
            break
        trial_held = held.copy()
        phi = _placed(coarse, fit, pairs, trial_held)
        trial = fit_base(coarse, fit.model.parameters(phi, fit.solution.theta), _holding(free, phi, trial_held))
        if _bic(trial, trial_held) > reference + BIC_TIE:
            break
        fit, held = trial, trial_held
    if not held.any():
        return None
    fit = at_full_resolution(fit, [fd.series], polish_nfev)
    # the polish on every sample can take another cycle's pair together: held too, once
    extra = [p for p in coalesced(fit) if not held[list(p)].any()]
    if extra:
        more = held.copy()
        phi = _placed(coarse, fit, extra, more)
        trial = polish([fd.series], fit.model.parameters(phi, fit.solution.theta), bounds=_holding(free, phi, more),
                       nfev=polish_nfev)
        if _bic(trial, more) <= _bic(fit, held):
            fit, held = trial, more
    if _bic(fit, held) > _bic(free, np.zeros_like(held)) + BIC_TIE:
        return None
    fit = converged(fit, max_nfev) if max_nfev else fit     # kept: carried on to convergence
    return HeldApart(fit, held, (fit.rss - free.rss) / fd.noise_N ** 2, _bic(fit, held),
                     _bic(free, np.zeros_like(held)), free)


def _holding(free: Fit, phi: np.ndarray, held: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Identification's bounds of alpha and beta with the held ones pinned at phi."""
    lo, hi = (b.copy() for b in free.model.base_bounds)
    lo[held], hi[held] = phi[held] - HOLD, phi[held] + HOLD
    return np.minimum(lo, phi), np.maximum(hi, phi)


def coalesced(fit: Fit) -> list[tuple[int, int]]:
    """Pairs of residual orders (indices in the base's nonlinear parameters) whose terms cancel or
    whose orders coincide within one cycle."""
    lay = fit.params.layout
    theta = fit.solution.theta
    phi = fit.model.split(fit.nu)[0]
    rows = np.flatnonzero(fit.solution.used[0])
    parts = fit.solution.designs[0][0][rows, :lay.n_linear] * theta[None, :lay.n_linear]
    first = lay.P + 1 + lay.N
    order = lay.derivative_pairs[0][2 * lay.N:]       # the beta of each residual amplitude column
    cols = {(i - first, j - first) for i, j, _ in cancelling(lay, parts) if i >= first}
    for c in range(lay.C):
        for m1, m2 in itertools.combinations(range(c * lay.M, (c + 1) * lay.M), 2):
            if abs(phi[order[m1]] - phi[order[m2]]) < COALESCED:
                cols.add((m1, m2))
    pairs = {tuple(sorted((int(order[i]), int(order[j])))) for i, j in cols}
    return sorted(p for p in pairs if p[0] != p[1])


def _placed(coarse: list[Series], fit: Fit, pairs: list[tuple[int, int]], held: np.ndarray) -> np.ndarray:
    """The fit's alpha and beta with each pair's orders SPREAD apart about the centre where the
    decimated run fits best (linear parameters re-solved, the rest as fitted); marks them held."""
    phi = fit.model.split(fit.nu)[0].copy()
    half = SPREAD / 2
    for i, j in pairs:
        if held[i] or held[j]:
            continue
        centre = 0.5 * (phi[i] + phi[j])
        best = (np.inf, centre)
        for c in np.clip(centre + CENTRES, BETA_LO + half, BETA_HI - half):
            trial = phi.copy()
            trial[i], trial[j] = c - half, c + half
            rss = solved_at(coarse, fit.model.parameters(trial, fit.solution.theta)).rss
            best = min(best, (rss, float(c)))
        phi[i], phi[j] = best[1] - half, best[1] + half
        held[[i, j]] = True
    return phi


def _n_params(lay, held: np.ndarray) -> int:
    """The core's free parameters (linear, alpha and beta, the zero) less the held orders."""
    return lay.n_linear + lay.n_nonlinear - int(held.sum()) + 1


def _bic(fit: Fit, held: np.ndarray) -> float:
    return information_criteria(fit.rss, fit.n, _n_params(fit.params.layout, held))[1]

