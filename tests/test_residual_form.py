"""The residual's two forms behind one switch (docs/model.md, "Two forms of the residual"):
the paper form against Eq. 11 written out here, batch against online, its behaviour on
histories Eq. 11 does not define, the fit's columns, and the form travelling in files."""

from dataclasses import replace

import numpy as np
import pytest
from scipy.special import gamma

from foamlab import FoamlabError
from foamlab.analysis.basis import ModelBasis
from foamlab.model import ModelParameters, SpecimenState, closed_form, evaluate, label_history, triangular_history
from foamlab.model.components import residual_static
from foamlab.model.layout import Orders
from tests.test_model import _any_history

A = 58.0
RATE = A / 147.5          # turning points on the 16 Hz grid


@pytest.fixture(scope="module")
def paper():
    return replace(ModelParameters.default(), residual_form="paper")


def eq11_by_hand(r, beta, x, A_mm, T_s):
    """Eq. 11 as printed (T^-beta per term), written out again."""
    out = np.zeros_like(x)
    for ri, bi in zip(r, beta):
        out += (2 * A_mm * ri * T_s ** (-bi) / gamma(2 - bi)
                * ((1 - x / (2 * A_mm)) ** (1 - bi) - 2 * np.clip(0.5 - x / (2 * A_mm), 0, None) ** (1 - bi)))
    return out


def test_paper_form_is_eq11_of_each_cycle_in_every_later_half_cycle(paper):
    """Eqs. 20b-f: after cycle k's peak its Eq. 11 (own stroke, own period) is added in every
    half-cycle, loading ones included."""
    t, x = triangular_history(A, RATE, 3, 16.0)
    resp = evaluate(paper, t, x)
    T = 2 * A / RATE
    expected = np.zeros_like(t)
    for k in range(3):
        r, beta = paper.residual_terms(k + 1)
        after = t > k * T + T / 2 + 1e-9
        expected[after] += eq11_by_hand(r, beta, x[after], A, T)
    assert np.abs(resp.residual - expected).max() <= 1e-9 * np.abs(expected).max()
    # and the closed form of the same model agrees (turning points on samples)
    assert np.abs(closed_form(paper, t, A, RATE, 3).force - resp.force).max() <= 1e-9 * np.abs(resp.force).max()
    # the forms differ where the paper reads V_R1(x) again: the second loading on
    causal = evaluate(ModelParameters.default(), t, x)
    first_unloading = (t > T / 2) & (t <= T)
    assert np.allclose(causal.residual[first_unloading], resp.residual[first_unloading], atol=1e-3)
    assert np.abs(causal.residual - resp.residual).max() > 1.0


def test_online_equals_batch_in_the_paper_form(paper):
    t = np.arange(0, 700, 1 / 16)
    x = _any_history(t)
    state = SpecimenState(paper, h_min=1 / 16)
    online = np.array([state.step(ti, xi).total for ti, xi in zip(t, x)])
    batch = evaluate(paper, t, x).force
    assert np.abs(online - batch).max() <= 1e-9 * np.abs(batch).max()


def test_paper_form_on_histories_eq11_does_not_define(paper):
    """docs/model.md: a dwell holds the residual (a function of x has no time), a cycle stopped
    early (an e-stop) uses the stroke it reached, and beyond an earlier cycle's stroke that
    cycle's term continues continuously (its second base is zero there)."""
    h = 1 / 16
    t = np.arange(0, 600, h)
    up = lambda t0, x0, v: x0 + v * (t - t0)
    # cycle 1 to 30 mm, back to 0 with a 40 s dwell at 10 mm; cycle 2 deeper, to 45 mm; back to 0
    x = np.select([t <= 75, t <= 125, t <= 165, t <= 190, t <= 302.5, t <= 415],
                  [up(0, 0, 0.4), up(75, 30, -0.4), 10.0, up(165, 10, -0.4), up(190, 0, 0.4), up(302.5, 45, -0.4)],
                  0.0)
    resp = evaluate(paper, t, x)
    labels = label_history(x)
    dwell = (t > 126) & (t < 164)
    assert np.ptp(resp.residual[dwell]) < 1e-12                            # static in a dwell
    r1, b1 = paper.residual_terms(1)
    expected_1 = eq11_by_hand(r1, b1, x, 30.0, 150.0)                      # stroke 30 mm, period 2 x 75 s
    beyond = (t > 190) & (t <= 302.5) & (x > 30.0)      # cycle 2 loading past cycle 1's stroke
    assert np.allclose(resp.residual[beyond], expected_1[beyond], rtol=1e-9, atol=1e-9)   # cycle 2 not yet unloading
    assert np.all(np.isfinite(resp.residual))
    assert len(labels.starts) == 2
    # continuous (though steep: (A - x)^(1 - beta)) where x passes the first cycle's stroke
    jumps = [np.abs(np.diff(residual_static(np.array([30.0 - e, 30.0 + e]), 30.0, 150.0, b1)[0], axis=0)).max()
             for e in (1e-3, 1e-6, 1e-9, 1e-12)]
    assert all(b < 0.5 * a for a, b in zip(jumps, jumps[1:])), jumps


def test_static_columns_and_their_derivative(paper):
    t, x = triangular_history(A, RATE, 4, 4.0)
    ref = evaluate(paper, t, x)
    lay = paper.layout
    assert lay.form == "paper" and lay.C == 3
    lin, nl = lay.from_flat(paper.to_vector())
    basis = ModelBasis(t, x, ref.labels, np.arange(len(t)), lay, paper.x_scale_mm, t[1] - t[0])
    assert np.abs(basis.force(lin, nl) - ref.force).max() <= 1e-9 * np.abs(ref.force).max()   # 4th cycle: 3rd's terms
    beta = np.array([0.8, 0.2, -0.6])
    _, d = residual_static(x, A, 300.0, beta, derivative=True)
    e = 1e-6
    numeric = (residual_static(x, A, 300.0, beta + e)[0] - residual_static(x, A, 300.0, beta - e)[0]) / (2 * e)
    assert np.abs(numeric - d).max() <= 1e-6 * np.abs(d).max()


def test_the_form_travels_in_files_and_bad_forms_are_refused(paper, tmp_path):
    path = tmp_path / "p.json"
    import json
    path.write_text(json.dumps(paper.to_dict()))
    assert ModelParameters.load(path).residual_form == "paper"
    assert ModelParameters.from_dict({"parameters": {"x_scale_mm": {"value": 58}, "k0": {"value": 1.0}},
                                      "form": "paper"}).residual_form == "paper"
    bad = paper.to_dict()
    bad["residual"]["form"] = "static"
    with pytest.raises(FoamlabError, match="residual form 'static'"):
        ModelParameters.from_dict(bad)
    with pytest.raises(FoamlabError):
        Orders(form="hybrid")
    assert paper.with_vector(paper.to_vector()).residual_form == "paper"
