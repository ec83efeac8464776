"""A solve's contact set is the one its own solution pushes on (ExtendedModel._active_set).

Where the plate pushes follows from the solution (the specimen's own force positive, and the
total with the effects' added force). A solve that kept an earlier iterate's set because it fitted
better let a fit push where its own force is negative: a friction of 4.3 N with the elastic curve
1.2 N low fitted each reload's first sample in contact in sample, and predicted it off the specimen,
3.4-3.7 N off, once held out (independent B causal 1004, docs/analysis.md, "The contact set its
own solution pushes on").
"""

from __future__ import annotations

import numpy as np
import pytest

import independent_effects as ie
from foamlab.analysis.design import EffectChain, ExtendedModel
from foamlab.analysis.solve import contact_of
from foamlab.diagnosis.causes import CAUSES
from foamlab.identification.fit import fit_run


@pytest.fixture(scope="module")
def friction_model() -> ExtendedModel:
    run = ie.independent_run("B", 1004, {"direction_friction": 3.0}, form="causal", hz=16.0)
    base = fit_run(run).core_fit
    series = base.model.series
    cause = CAUSES["direction_friction"]
    return ExtendedModel(series, base.params, [cause.effect], {cause.effect.name: cause.settings(series)},
                         effect_bounds={cause.effect.name: cause.bounds()}, masks=contact_of(base, series))


def _pushes(model: ExtendedModel, eta: np.ndarray, theta: np.ndarray) -> list[np.ndarray]:
    """Where the model's rule puts the plate on the specimen for this solution."""
    phi, eta = model.split(eta)
    chain = EffectChain(model.effects(eta))
    out = []
    for s in model.series:
        cols, offset, x_s, _ = model._columns(s, chain, phi)
        out.append(model._pushes(cols, offset, x_s > 0, theta))
    return out


def test_each_solve_keeps_the_contact_set_its_own_solution_pushes_on(friction_model):
    flipped = 0
    previous = None
    for f in (4.3, 1.0, 3.0, 0.0):       # each solve starts from the last one's set (continuation)
        eta = np.array([f])
        sol = friction_model.solve(eta)
        rule = _pushes(friction_model, eta, sol.theta)
        for mask, pushes, used in zip(sol.masks, rule, sol.used):
            assert np.array_equal(mask[used], pushes[used]), \
                f"friction {f} N: {int(np.sum(mask[used] != pushes[used]))} used samples in contact against the rule"
        if previous is not None:
            flipped += sum(int(np.sum(a != b)) for a, b in zip(previous, sol.masks))
        previous = sol.masks
    assert flipped > 0       # the frictions move the contact set: the solves had to iterate it
