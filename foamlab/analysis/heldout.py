"""Held-out prediction: every block of a run predicted by the model refitted without it.

One definition for identification (the residual form the data choose) and diagnosis (an
extension must predict held-out blocks better than the model it extends).
"""

from __future__ import annotations

import numpy as np

from foamlab.analysis.design import ExtendedModel, Series, Solution
from foamlab.analysis.solve import Fit, contact_of, varpro

#: Contiguous blocks of each run in the held-out check.
HELDOUT_FOLDS = 6
#: ...each made of blocks of about this many samples spread over the run (at least 8 per fold):
#: short, so no block just after a turning point decides the check alone (docs/analysis.md).
HELDOUT_BLOCK_SAMPLES = 10
HELDOUT_BLOCKS_PER_FOLD = 8
#: Iterations of the refit without the held-out blocks.
HELDOUT_NFEV = 3


def folds(series: list[Series], n_folds: int = HELDOUT_FOLDS,
          blocks_per_fold: int | None = None) -> list[list[np.ndarray]]:
    """Keep-masks per fold. Each run is cut into n_folds x blocks_per_fold contiguous
    blocks (default: blocks of ~HELDOUT_BLOCK_SAMPLES samples); fold k leaves out blocks
    k, k + n_folds, ... (interleaved), so every cycle keeps data that determine its own
    parameters and each held-out block is predicted, not extrapolated past the end of
    what was fitted. Samples measured off the specimen stay in every fit: their force is
    the unloaded reading whatever the model, so they carry no information on its
    parameters, only where the plate leaves the specimen - a fit without them is free to
    put contact there (docs/analysis.md, "Held-out blocks")."""
    out = []
    for k in range(n_folds):
        masks = []
        for s in series:
            per_fold = blocks_per_fold or max(HELDOUT_BLOCKS_PER_FOLD,
                                               int(round(len(s) / (n_folds * HELDOUT_BLOCK_SAMPLES))))
            m = np.ones(len(s), dtype=bool)
            edges = np.linspace(0, len(s), n_folds * per_fold + 1).astype(int)
            for b in range(k, n_folds * per_fold, n_folds):
                m[edges[b]:edges[b + 1]] = False
            if s.no_contact is not None:
                m |= s.no_contact
            masks.append(m)
        out.append(masks)
    return out


def heldout_rmse(fit: Fit, on: Fit | None = None, n_folds: int = HELDOUT_FOLDS) -> float:
    """RMSE of every block predicted by the model refitted (all its parameters) without it.

    on: the same model on other (decimated) samples to do it on; the result is stored
    in ``fit``.
    """
    if fit.heldout_rmse is not None:
        return fit.heldout_rmse
    work = on or fit
    sq, count = 0.0, 0
    for keep in folds(work.model.series, n_folds):
        sol = _refit_without(work, keep)
        out = ~np.concatenate(keep) & np.concatenate(sol.used)
        r = np.concatenate(sol.residuals)[out]
        sq += float(r @ r)
        count += len(r)
    fit.heldout_rmse = float(np.sqrt(sq / max(count, 1)))
    return fit.heldout_rmse


def _refit_without(fit: Fit, keep: list[np.ndarray]) -> Solution:
    """The fit redone without the held-out samples: the linear parameters exactly and the
    effect parameters by a few trust-region steps from the full-data optimum. The base
    model's alpha/beta stay at their full-data values, for both models alike (refitting
    them per block would cost most of the diagnosis and moves them by a fraction of
    their standard error)."""
    model = fit.model
    if model.free_base:
        model = ExtendedModel(model.series, fit.params, model.effect_types, model.settings,
                              effect_bounds=model.effect_bounds, masks=contact_of(fit, model.series))
    if not model.n_eta:
        return model.solve((), keep)
    return varpro(model, fit.eta, keep, max_nfev=HELDOUT_NFEV).solution
