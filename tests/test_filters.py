"""foamlab.model.filters against scipy.signal, which they stand in for on the fit path (the
import of scipy.signal costs 0.3-0.5 s of a `foamlab fit` process: docs/benchmarks.md)."""

import subprocess
import sys

import numpy as np
import pytest
from scipy.signal import lfilter, savgol_filter

from foamlab.model.filters import recursion, savgol

RNG = np.random.default_rng(20261129)
WALK = RNG.normal(size=601).cumsum()


@pytest.mark.parametrize("E, wn, wp, z0", [
    (0.9, 1.0, 0.0, 0.0),                      # real, one tap
    (0.97 - 0.02j, 0.3 + 0.1j, -0.2, 0.0),     # a damping mode: complex, two taps
    (0.5 + 0.4j, 1.0, 0.0, 2.0 - 1.0j),        # from a state: lfilter's zi = E z0
    (1e-300, 0.7, 0.1, 5.0),                   # a mode that forgets at once
])
def test_recursion_is_lfilter(E, wn, wp, z0):
    want = lfilter([wn, wp], [1.0, -E], WALK, zi=[E * z0])[0]
    got = recursion(E, WALK, wn, wp, z0)
    assert np.max(np.abs(got - want)) <= 1e-12 * np.max(np.abs(want))
    assert np.iscomplexobj(got) == np.iscomplexobj(want)


def test_recursion_of_nothing_is_nothing():
    assert recursion(0.5, np.zeros(0)).shape == (0,)


@pytest.mark.parametrize("window, order, deriv, delta", [
    (5, 2, 0, 1.0), (5, 2, 1, 1.0), (31, 2, 1, 1.0), (9, 3, 0, 1.0), (21, 1, 1, 0.0625), (3, 2, 0, 1.0),
    (601, 2, 0, 1.0),                          # one window: every sample from the edge fits
])
def test_savgol_is_scipy_interp_mode(window, order, deriv, delta):
    want = savgol_filter(WALK, window, order, deriv=deriv, delta=delta, mode="interp")
    got = savgol(WALK, window, order, deriv=deriv, delta=delta)
    # a 601-sample window's Vandermonde matrix is ill-conditioned: the two differ by 5e-12 there
    assert np.max(np.abs(got - want)) <= 1e-10 * np.max(np.abs(want))


@pytest.mark.parametrize("window, order", [(4, 2), (3, 3), (603, 2)])
def test_savgol_refuses_a_window_it_cannot_fit(window, order):
    with pytest.raises(ValueError, match="Savitzky-Golay"):
        savgol(WALK, window, order)


def test_the_fit_path_does_not_import_scipy_signal():
    code = ("import sys, foamlab.commands.fit, foamlab.identification, foamlab.importers; "
            "print('scipy.signal' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
