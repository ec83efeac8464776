"""A fit ends on the contact set its own solution pushes on (analysis.solve.varpro).

Where the plate pushes follows from the solution (the specimen's own force positive, and the
total with the effects' added force). Inside an optimisation the set lags the parameters (each
solve keeps the best set it saw, which starts from far off need); a fit that ended there could
push where its own force is negative: on independent B causal 1004 with a 3 N friction, the
reloads' first samples in contact at an own force of -0.5 and -1.1 N, predicted off the specimen,
3-4 N off, once held out (docs/analysis.md, "The contact set its own solution pushes on").
"""

from __future__ import annotations

import numpy as np
import pytest

import independent_effects as ie
from foamlab.analysis.design import EffectChain, ExtendedModel
from foamlab.analysis.solve import contact_of, varpro
from foamlab.diagnosis.causes import CAUSES
from foamlab.identification.fit import fit_run


@pytest.fixture(scope="module")
def friction_model() -> ExtendedModel:
    run = ie.independent_run("B", 1004, {"direction_friction": 3.0}, form="causal", hz=16.0)
    base = fit_run(run).core_fit
    series = base.model.series
    cause = CAUSES["direction_friction"]
    return ExtendedModel(series, base.params, [cause.effect], {cause.effect.name: cause.settings(series)},
                         effect_bounds={cause.effect.name: cause.bounds()}, free_base=True,
                         base_bounds=base.model.base_bounds, masks=contact_of(base, series))


def _against_the_rule(model: ExtendedModel, nu: np.ndarray, sol) -> int:
    """Used samples whose contact differs from where the model's rule puts the plate for this solution."""
    phi, eta = model.split(nu)
    chain = EffectChain(model.effects(eta))
    count = 0
    for s, mask, used in zip(model.series, sol.masks, sol.used):
        cols, offset, x_s, _ = model._columns(s, chain, phi)
        count += int(np.sum((mask != model._pushes(cols, offset, x_s > 0, sol.theta))[used]))
    return count


def test_a_fit_ends_on_the_contact_set_its_own_solution_pushes_on(friction_model):
    fit = varpro(friction_model, friction_model.start(np.array([4.3])), max_nfev=20)
    assert _against_the_rule(friction_model, fit.nu, fit.solution) == 0
