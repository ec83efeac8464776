"""The model, once: closed forms vs the causal time-domain evaluation, batch vs online."""

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.model import (
    ModelParameters,
    SpecimenState,
    closed_form,
    evaluate,
    label_history,
    residual_eq11,
    thermodynamic_checks,
    triangular_history,
)
from foamlab.model.operators import FractionalOperator, SumOfExponentials

A = 58.0
RATE = A / 147.5          # corners fall on the 16 Hz grid: the closed form is then exact
# Stated tolerance (docs/model.md): time-domain vs closed form within 1e-5 of the peak force
TOLERANCE = 1e-5


@pytest.fixture(scope="module")
def params():
    return ModelParameters.default()


def test_default_specimen_is_realistic(params):
    t, x = triangular_history(A, 23.6 / 60, 3, 16.0)
    r = evaluate(params, t, x)
    f = r.measured_force
    peaks = [f[r.cycle == c].max() for c in (1, 2, 3)]
    assert peaks[0] > peaks[1] > peaks[2]            # first loading above the later ones
    assert 100 < peaks[0] < 0.6 * 500                # well under a 500 N load cell
    for c in (2, 3):                                  # contact lost at the start of cycles 2-3
        start = r.labels.starts[c - 1]
        assert not r.contact[start + 16]
        assert r.contact[r.labels.peaks[c - 1]]
    # hysteresis: unloading below loading at mid-stroke in every cycle
    for c in (1, 2, 3):
        m = r.cycle == c
        load = m & (r.direction == 1) & (np.abs(x - A / 2) < 0.3)
        unload = m & (r.direction == -1) & (np.abs(x - A / 2) < 0.3)
        assert f[load].mean() > f[unload].mean() + 5
    assert all(thermodynamic_checks(params).values())


def test_time_domain_matches_closed_form_on_triangle(params):
    t, x = triangular_history(A, RATE, 3, 16.0)
    td = evaluate(params, t, x)
    cf = closed_form(params, t, A, RATE, 3)
    scale = np.abs(cf.force).max()
    assert td.labels.starts == cf.labels.starts and td.labels.peaks == cf.labels.peaks
    for comp in ("elastic", "damping", "residual"):
        err = np.abs(getattr(td, comp) - getattr(cf, comp)).max()
        assert err <= TOLERANCE * scale, (comp, err)


def test_eq11_is_the_closed_form_of_the_first_unloading(params):
    t, x = triangular_history(A, RATE, 1, 16.0)
    T = 2 * A / RATE
    cf = closed_form(params, t, A, RATE, 1)
    m = (t > T / 2) & (t <= T)
    eq11 = residual_eq11(params.residual_r[0], params.residual_beta[0], x[m], A, T)
    assert np.allclose(eq11, cf.residual[m], atol=1e-9 * np.abs(eq11).max())


def _any_history(t):
    """Pauses, a stop mid-loading, unequal speeds, contact with x clipped at 0."""
    v = np.interp(t, [0, 50, 60, 120, 200, 260, 300, 400, 700],
                  [0.4, 0.4, 0.0, 0.4, -0.6, 0.0, 0.8, -0.3, -0.3])
    return np.clip(np.concatenate([[0], np.cumsum(v[1:] * np.diff(t))]), 0, None)


def test_online_state_equals_batch_on_any_history(params):
    t = np.arange(0, 700, 1 / 16)
    x = _any_history(t)
    assert len(label_history(x).starts) >= 2
    state = SpecimenState(params, h_min=1 / 16)
    online = np.array([state.step(ti, xi).total for ti, xi in zip(t, x)])
    batch = evaluate(params, t, x).force
    assert np.abs(online - batch).max() <= 1e-6 * np.abs(batch).max()


def test_cycles_sharing_terms_equal_the_online_state_one_memory_each(params):
    """Cycles beyond the identified ones share the last one's terms: evaluate sums their memories
    in one operator (time linear in the run); the simulator's online state keeps one per cycle."""
    t = np.arange(0, 520, 1 / 16)
    stroke = 20.0 + 8.0 * np.sin(0.05 * t)        # seven cycles, each to its own depth
    x = stroke * (1 - np.abs(((t / 37.0) % 2.0) - 1.0))
    assert len(label_history(x).starts) >= params.n_residual_cycles + 3
    state = SpecimenState(params, h_min=1 / 16)
    online = np.array([state.step(ti, xi).total for ti, xi in zip(t, x)])
    batch = evaluate(params, t, x).force
    assert np.abs(online - batch).max() <= 1e-6 * np.abs(batch).max()


def test_irregular_clock_is_resampled_within_half_a_percent(params):
    # a really irregular clock (+-33 % steps) is evaluated on a uniform grid and
    # interpolated back; the online stepper takes every true step
    rng = np.random.default_rng(1)
    t = np.cumsum(rng.uniform(0.025, 0.05, 16000))
    x = _any_history(t)
    state = SpecimenState(params, h_min=0.02)
    online = np.array([state.step(ti, xi).total for ti, xi in zip(t, x)])
    batch = evaluate(params, t, x).force
    assert np.abs(online - batch).max() <= 5e-3 * np.abs(batch).max()


def test_soe_kernel_accuracy():
    from scipy.special import gamma

    s = np.logspace(-3, 4, 300)
    for f in (0.01, 0.3, 0.7, 0.96):
        soe = SumOfExponentials(f, 1e-3, 1e4)
        assert np.abs(soe.kernel(s) / (s ** (f - 1) / gamma(f)) - 1).max() < 1e-5


def test_fractional_operator_known_values():
    # D^beta of x = t is t^(1-beta)/Gamma(2-beta); beta = 0 is x itself, beta = -1 its integral
    from scipy.special import gamma

    h = 0.01
    t = np.arange(0, 50, h)
    for beta in (0.9, 0.5, 0.0, -0.4, -1.0, -1.96):
        y = FractionalOperator(beta, h, 50).batch(h, t)
        exact = t ** (1 - beta) / gamma(2 - beta)
        assert np.abs(y - exact).max() <= 1e-4 * np.abs(exact).max() + 1e-9, beta


def test_parameters_round_trip_and_bad_input(params, tmp_path):
    again = params.with_vector(params.to_vector())
    assert np.allclose(again.to_vector(), params.to_vector())
    assert len(params.names()) == len(params.to_vector())
    d = ModelParameters.from_dict(params.to_dict())
    assert np.allclose(d.to_vector(), params.to_vector())
    bad = tmp_path / "bad.json"
    bad.write_text("{\"x_scale_mm\": 1}")
    with pytest.raises(FoamlabError):
        ModelParameters.load(bad)
    with pytest.raises(FoamlabError):
        ModelParameters.load(tmp_path / "missing.toml")
