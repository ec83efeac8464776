"""Noise level from the data itself, whiteness tests, and AR prewhitening.

- noise_sigma: the load cell's white-noise level from second differences of the
  measured force (a slowly varying signal has second differences far below the
  noise at the sampling rates of a compression test), MAD-based so the jumps at
  turning points and contact changes do not count.
- whiteness: the Ljung-Box and the Wald-Wolfowitz runs tests on residuals.
- ArWhitener: an AR(p) filter (Yule-Walker, order by BIC) estimated on one residual
  series and applied to others, so nested models are compared on the same
  prewhitened scale (generalised least squares with the noise's correlation).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import erfc, gammaincc

MAD_TO_SIGMA = 1.0 / 0.6744897501960817
#: Highest AR order tried when prewhitening.
MAX_AR_ORDER = 6
#: Whiteness tests below this p-value mean structure (fit and diagnosis alike).
WHITE_P = 1e-3
#: Lags of the Ljung-Box test.
LJUNG_BOX_LAGS = 20


def noise_sigma(force: np.ndarray) -> float:
    """White-noise sigma of a sampled force from its second differences (MAD-based).

    For white noise of variance s^2, x[i-1] - 2 x[i] + x[i+1] has variance 6 s^2.
    """
    f = np.asarray(force, float)
    if len(f) < 5:
        return float("nan")
    d2 = np.diff(f, 2)
    return float(np.median(np.abs(d2 - np.median(d2))) * MAD_TO_SIGMA / np.sqrt(6.0))


def series_noise_sigma(forces: list[np.ndarray]) -> float:
    """Noise level of several runs' forces (pooled second differences)."""
    d2 = np.concatenate([np.diff(np.asarray(f, float), 2) for f in forces if len(f) >= 5])
    if len(d2) == 0:
        return float("nan")
    return float(np.median(np.abs(d2 - np.median(d2))) * MAD_TO_SIGMA / np.sqrt(6.0))


@dataclass
class Whiteness:
    ljung_box_p: float
    runs_p: float
    lag1_correlation: float

    @property
    def min_p(self) -> float:
        return min(self.ljung_box_p, self.runs_p)

    def to_dict(self) -> dict:
        return {"ljung_box_p": self.ljung_box_p, "runs_p": self.runs_p,
                "lag1_correlation": self.lag1_correlation}


#: A fit whose RMSE is within this factor of the noise, or whose residuals are white, leaves
#: nothing another start or structure could fit.
AT_NOISE_RATIO = 1.05


def at_the_noise(residual: np.ndarray, noise_N: float) -> bool:
    """Is what a fit leaves the load cell's noise?"""
    rmse = float(np.sqrt(np.mean(np.asarray(residual, float) ** 2)))
    return rmse <= AT_NOISE_RATIO * noise_N or whiteness(residual).min_p >= WHITE_P


def whiteness(residual: np.ndarray) -> Whiteness:
    r = np.asarray(residual, float)
    r = r - r.mean()
    if len(r) < 3 * LJUNG_BOX_LAGS or not np.any(r):
        return Whiteness(1.0, 1.0, 0.0)
    nonzero = r[r != 0]
    runs_p = runs_test_p(nonzero > 0) if len(nonzero) > 10 else 1.0
    lag1 = float(r[1:] @ r[:-1] / (r @ r))
    return Whiteness(ljung_box_p(r, LJUNG_BOX_LAGS), runs_p, lag1)


# The two tests are written out rather than taken from statsmodels (acorr_ljungbox,
# runstest_1samp): each is a few lines of numpy, and statsmodels' import (0.25-0.3 s with the
# pandas it pulls in) was a tenth of `foamlab fit` as a process. tests/test_noise.py checks
# both against statsmodels.

def ljung_box_p(r: np.ndarray, lags: int) -> float:
    """Ljung-Box p-value of a zero-mean series at ``lags`` (Q = n(n+2) sum rho_k^2 / (n-k),
    chi-squared with ``lags`` degrees of freedom; rho_k with the biased autocovariance)."""
    n = len(r)
    denom = float(r @ r)
    rho = np.array([r[k:] @ r[:n - k] for k in range(1, lags + 1)]) / denom
    q = n * (n + 2.0) * float(np.sum(rho ** 2 / (n - np.arange(1, lags + 1))))
    return float(gammaincc(lags / 2.0, q / 2.0))


def runs_test_p(above: np.ndarray) -> float:
    """Wald-Wolfowitz runs test of a two-valued sequence, two-sided normal p-value (with the
    0.5 continuity correction below 50 values, as SAS and statsmodels)."""
    above = np.asarray(above, bool)
    n, n_pos = len(above), int(above.sum())
    n_neg = n - n_pos
    runs = 1 + int(np.count_nonzero(above[1:] != above[:-1]))
    if n_pos == 0 or n_neg == 0:
        return float(2.0 ** (1 - min(n, 1024)) * 2)      # one run: binomial, as statsmodels
    npn = float(n_pos) * n_neg
    mean = 2.0 * npn / n + 1.0
    std = np.sqrt(2.0 * npn * (2.0 * npn - n) / n ** 2 / (n - 1.0))
    d = runs - mean
    if n < 50:
        d = d - 0.5 if d > 0.5 else d + 0.5 if d < 0.5 else 0.0
    return float(erfc(abs(d / std) / np.sqrt(2.0)))


@dataclass
class ArWhitener:
    """e[t] - sum_i phi_i e[t-i], applied within each series (no filtering across runs)."""

    phi: np.ndarray

    @property
    def order(self) -> int:
        return len(self.phi)

    @classmethod
    def fit(cls, residuals: list[np.ndarray], max_order: int = MAX_AR_ORDER) -> "ArWhitener":
        """Yule-Walker AR(p) of the pooled residuals, p = 0..max_order by BIC."""
        from statsmodels.regression.linear_model import yule_walker     # 0.25-0.3 s: diagnosis only

        r = np.concatenate([np.asarray(x, float) - np.mean(x) for x in residuals])
        n = len(r)
        if n < 10 * (max_order + 1) or not np.any(r):
            return cls(np.zeros(0))
        best = (n * np.log(r @ r / n), np.zeros(0))
        for p in range(1, max_order + 1):
            phi, sigma = yule_walker(r, order=p, method="mle", result_object=False)
            if not np.all(np.isfinite(phi)) or sigma <= 0:
                break
            bic = n * np.log(sigma ** 2) + p * np.log(n)
            if bic < best[0]:
                best = (bic, np.asarray(phi, float))
        return cls(best[1])

    def apply(self, residuals: list[np.ndarray]) -> np.ndarray:
        out = []
        p = self.order
        for x in residuals:
            x = np.asarray(x, float)
            if len(x) <= p:
                continue
            w = x[p:].copy()
            for i, ph in enumerate(self.phi, start=1):
                w -= ph * x[p - i:len(x) - i]
            out.append(w)
        return np.concatenate(out) if out else np.zeros(0)
