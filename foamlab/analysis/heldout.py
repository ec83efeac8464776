"""Held-out prediction: every block of a run predicted by the model refitted without it.

One definition for identification (the residual form the data choose) and diagnosis (an
extension must predict held-out blocks better than the model it extends).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from foamlab.analysis.design import ExtendedModel, Series, Solution
from foamlab.analysis.noise import ArWhitener
from foamlab.analysis.parallel import fork_map
from foamlab.analysis.solve import Fit, contact_of, model_like, varpro

#: Contiguous blocks of each run in the held-out check.
HELDOUT_FOLDS = 6
#: ...each made of blocks of about this many samples spread over the run (at least 8 per fold):
#: short, so no block just after a turning point decides the check alone (docs/analysis.md).
HELDOUT_BLOCK_SAMPLES = 10
HELDOUT_BLOCKS_PER_FOLD = 8
#: Off-specimen samples this close to a sample in contact stay in every fit (they place the contact).
CONTACT_EDGE_SAMPLES = 2
#: Iterations of the refit without the held-out blocks, the base's alpha/beta held...
HELDOUT_NFEV = 3
#: ...and re-estimated with the effects, from the model's own fit (diagnosis): the held-in
#: optimum lies near it (docs/analysis.md, "Held-out blocks").
HELDOUT_FREE_NFEV = 10


def folds(series: list[Series], n_folds: int = HELDOUT_FOLDS) -> list[list[np.ndarray]]:
    """Keep-masks per fold. Each run is cut into contiguous blocks of ~HELDOUT_BLOCK_SAMPLES
    samples (_blocks); fold k leaves out blocks k, k + n_folds, ... (interleaved), so every
    cycle keeps data that determine its own parameters and each held-out block is predicted,
    not extrapolated past the end of what was fitted. Samples measured off the specimen next
    to contact (CONTACT_EDGE_SAMPLES either side) stay in every fit: they say where the plate
    leaves the specimen, and a fit without them is free to put contact there. Those further off
    are held out and scored like any other: the model predicts the unloaded reading there, and
    an effect seen there (a drifting zero) is seen held out too (docs/analysis.md, "Held-out
    blocks")."""
    blocks = [_blocks(len(s), n_folds) for s in series]
    always = [_contact_edges(s.no_contact) if s.no_contact is not None else np.zeros(len(s), bool)
              for s in series]
    return [[(b % n_folds != k) | a for b, a in zip(blocks, always)] for k in range(n_folds)]


def heldout_rmse(fit: Fit, on: Fit | None = None, n_folds: int = HELDOUT_FOLDS,
                 reestimate: bool = False, workers: int | None = None) -> float:
    """RMSE of every block predicted by the model refitted without it.

    on: the same model on other (decimated) samples to do it on; the result, and each sample's
    held-out prediction error (``fit.heldout_residual``, NaN where not held out, for
    heldout_gain), are stored in ``fit``.
    reestimate: each refit re-estimates the base's alpha/beta with the effects on the held-in
    blocks alone, from the model's own fit (nothing is held at a value the held-out blocks
    helped fit: diagnosis); False, alpha/beta stay at the fit's (two bases alike:
    identification's choice of form).
    workers: processes for the re-estimating refits (None: every core; analysis.parallel).
    """
    mode = "base re-estimated" if reestimate else "base held"
    if fit.heldout_rmse is not None and fit.heldout_refit == mode:
        return fit.heldout_rmse
    work = on or fit
    keeps = folds(work.model.series, n_folds)
    refit = _refit_free if reestimate else _refit_without
    # the folds are independent fits: on the machine's cores where each costs a free refit
    done = fork_map(lambda keep: _predicted(refit(work, keep)), keeps, workers=workers if reestimate else 1)
    held = np.full(sum(len(s) for s in work.model.series), np.nan)
    for keep, (residual, used) in zip(keeps, done):
        out = ~np.concatenate(keep) & used
        held[out] = residual[out]
    fit.heldout_residual, fit.heldout_refit = held, mode
    scored = held[np.isfinite(held)]
    fit.heldout_rmse = float(np.sqrt(scored @ scored / max(len(scored), 1)))
    return fit.heldout_rmse


def _predicted(sol: Solution) -> tuple[np.ndarray, np.ndarray]:
    """A refit's residual on every sample and which samples it used (small: what a worker returns)."""
    return np.concatenate(sol.residuals), np.concatenate(sol.used)


@dataclass(frozen=True)
class HeldoutGain:
    """What a model gains over another on the same held-out blocks, and how surely.

    The gain is the drop of the held-out RMSE. Where the two models' held-out predictions differ
    by d, a sample's squared error drops by d^2 + 2 d e (e: the extending model's error), and of
    that only 2 d times the noise in e is random: both predictions come from refits without the
    sample, so d is fixed before its noise is drawn. The gain's standard error is that term's,
    with the noise's own correlation (AR, from the in-sample residuals). Neither the effect's
    concentration in a few blocks nor the models' systematic errors there count as noise: the
    spread of the gain block to block held both and refused large lags and softenings
    (docs/analysis.md, "Held-out blocks"). The gain passes beyond z standard errors."""

    before_rmse: float
    after_rmse: float
    gain_se: float              # N, standard error of before_rmse - after_rmse (nan: nothing to compare)
    z: float

    @property
    def passed(self) -> bool:
        margin = self.z * self.gain_se if self.z > 0 and np.isfinite(self.gain_se) else 0.0
        return self.before_rmse - self.after_rmse > margin


def heldout_gain(before: Fit, after: Fit, z: float, before_on: Fit | None = None,
                 after_on: Fit | None = None, workers: int | None = None) -> HeldoutGain:
    """The held-out gain of `after` over `before` (each held out on its `*_on` samples, the same
    blocks) and the standard error of its noise (HeldoutGain). Both models' refits re-estimate
    every nonlinear parameter, each from its own fit."""
    rb = heldout_rmse(before, before_on, reestimate=True, workers=workers)
    ra = heldout_rmse(after, after_on, reestimate=True, workers=workers)
    eb, ea = before.heldout_residual, after.heldout_residual
    if eb is None or ea is None or len(eb) != len(ea) or rb + ra <= 0:
        return HeldoutGain(rb, ra, float("nan"), z)
    both = np.isfinite(eb) & np.isfinite(ea)
    d = np.where(both, eb - ea, 0.0)
    se_squares = 2.0 * np.sqrt(_noise_variance(d, after_on or after)) / max(int(np.isfinite(eb).sum()), 1)
    return HeldoutGain(rb, ra, float(se_squares) / (rb + ra), z)     # rb - ra = (rb^2 - ra^2) / (rb + ra)


def _noise_variance(d: np.ndarray, fit: Fit) -> float:
    """Variance of sum(d * noise), the noise AR as the fit's in-sample residuals are
    (noise.ArWhitener): noise = w filtered by 1/A, so sum(d * noise) = sum(w * u) with u = d
    filtered by 1/A backwards in time, and its variance is var(w) |u|^2, run by run."""
    residuals = fit.solution.used_residuals
    whitener = ArWhitener.fit(residuals)
    w = whitener.apply(residuals)
    var_w = float(w @ w) / max(len(w), 1)
    a = np.concatenate([[1.0], -whitener.phi])
    total, first = 0.0, 0
    for s in fit.model.series:
        u = lfilter([1.0], a, d[first:first + len(s)][::-1])
        total += float(u @ u)
        first += len(s)
    return var_w * total


def _contact_edges(no_contact: np.ndarray, width: int = CONTACT_EDGE_SAMPLES) -> np.ndarray:
    """The off-specimen samples within `width` samples of one in contact."""
    contact = (~no_contact).astype(float)
    near = np.convolve(contact, np.ones(2 * width + 1), mode="same") > 0
    return no_contact & near


def _blocks(n: int, n_folds: int) -> np.ndarray:
    """Each of a run's n samples' block: n_folds x per-fold contiguous blocks of about
    HELDOUT_BLOCK_SAMPLES samples (at least HELDOUT_BLOCKS_PER_FOLD per fold)."""
    count = n_folds * max(HELDOUT_BLOCKS_PER_FOLD, int(round(n / (n_folds * HELDOUT_BLOCK_SAMPLES))))
    edges = np.linspace(0, n, count + 1).astype(int)
    return np.searchsorted(edges, np.arange(n), side="right") - 1


def _refit_free(fit: Fit, keep: list[np.ndarray]) -> Solution:
    """The fit redone without the held-out samples, every nonlinear parameter re-estimated from
    the fit's own values. Each model from its own fit: an effect the base imitates sits where
    the base bent itself, out of reach from the base's alpha/beta (a 100 %/cycle damping change
    refitted from them predicted 0.21 N against the base's 0.17 N; docs/analysis.md)."""
    model = model_like(fit, fit.model.series, free_base=True)      # alpha/beta start at the fit's
    return varpro(model, model.start(fit.eta), keep, max_nfev=HELDOUT_FREE_NFEV).solution


def _refit_without(fit: Fit, keep: list[np.ndarray]) -> Solution:
    """The fit redone without the held-out samples: the linear parameters exactly and the
    effect parameters by a few trust-region steps from the full-data optimum. The base
    model's alpha/beta stay at their full-data values, for both models alike: identification's
    choice between two bases (diagnosis re-estimates them: _refit_free)."""
    model = fit.model
    if model.free_base:
        model = ExtendedModel(model.series, fit.params, model.effect_types, model.settings,
                              effect_bounds=model.effect_bounds, masks=contact_of(fit, model.series))
    if not model.n_eta:
        return model.solve((), keep)
    return varpro(model, fit.eta, keep, max_nfev=HELDOUT_NFEV).solution
