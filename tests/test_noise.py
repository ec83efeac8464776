"""The whiteness tests written out in foamlab.analysis.noise agree with statsmodels' (the
library they replace on `foamlab fit`'s path for its import cost)."""

from __future__ import annotations

import numpy as np
import pytest
from statsmodels.sandbox.stats.runs import runstest_1samp
from statsmodels.stats.diagnostic import acorr_ljungbox

from foamlab.analysis.noise import LJUNG_BOX_LAGS, ljung_box_p, runs_test_p, whiteness


def ar1(n: int, phi: float, seed: int) -> np.ndarray:
    e = np.random.default_rng(seed).normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    return x - x.mean()


@pytest.mark.parametrize("n,phi", [(100, 0.0), (4763, 0.0), (4763, 0.05), (500, 0.3), (80, -0.2)])
def test_ljung_box_matches_statsmodels(n, phi):
    r = ar1(n, phi, seed=n)
    expected = float(acorr_ljungbox(r, lags=[LJUNG_BOX_LAGS], return_df=True)["lb_pvalue"].iloc[0])
    assert ljung_box_p(r, LJUNG_BOX_LAGS) == pytest.approx(expected, rel=1e-9, abs=1e-300)


@pytest.mark.parametrize("n,phi", [(12, 0.0), (30, 0.5), (49, 0.0), (50, 0.0), (4763, 0.0), (2000, 0.2)])
def test_runs_test_matches_statsmodels(n, phi):
    r = ar1(n, phi, seed=7 + n)
    r = r[r != 0]
    expected = float(runstest_1samp(r, cutoff=0.0)[1])
    assert runs_test_p(r > 0) == pytest.approx(expected, rel=1e-9, abs=1e-300)


def test_one_run_is_the_binomial_tail():
    ones = np.ones(20)
    assert runs_test_p(ones > 0) == pytest.approx(float(runstest_1samp(ones, cutoff=0.0)[1]))


def test_correlated_residuals_are_not_white_and_noise_is():
    assert whiteness(ar1(4000, 0.0, seed=1)).min_p > 1e-3
    assert whiteness(ar1(4000, 0.3, seed=2)).min_p < 1e-6
