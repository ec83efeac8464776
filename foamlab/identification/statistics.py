"""Fit statistics: the paper's Table 5, parameter uncertainty, identifiability, AIC/BIC.

Conventions (MATLAB's Curve Fitting Toolbox, which the paper used):
  SSE = sum r^2,  R^2 = 1 - SSE/SST,  adjusted R^2 = 1 - SSE (n - 1) / (SST (n - p)),
  RMSE = sqrt(SSE / (n - p))   (the standard error of the regression).

Standard errors are the usual linearisation s^2 (J^T J)^-1 with s^2 = SSE/(n - p)
at the optimum. They assume independent residuals; residuals of a smooth model
on a real curve are autocorrelated, which makes them optimistic, so an
effective-sample-size variant is reported too: each standard error times
sqrt(tau), tau = 1 + 2 sum_k rho_k the integrated autocorrelation time of the
residuals (Geyer's initial positive sequence).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: |correlation| above this: the pair is not separately determined (warning).
CORRELATION_LIMIT = 0.99
#: Relative singular value below which a direction of the scaled Jacobian is null.
NULL_RCOND = 1e-9


@dataclass(frozen=True)
class GoodnessOfFit:
    n: int
    p: int
    sse: float
    r2: float
    adj_r2: float
    rmse: float

    @classmethod
    def of(cls, data: np.ndarray, fitted: np.ndarray, n_params: int) -> "GoodnessOfFit":
        data = np.asarray(data, float)
        r = data - np.asarray(fitted, float)
        n = len(data)
        sse = float(r @ r)
        sst = float(np.sum((data - data.mean()) ** 2)) if n else 0.0
        dfe = n - n_params
        r2 = 1.0 - sse / sst if sst > 0 else float("nan")
        adj = 1.0 - sse * (n - 1) / (sst * dfe) if sst > 0 and dfe > 0 else float("nan")
        rmse = float(np.sqrt(sse / dfe)) if dfe > 0 else float("nan")
        return cls(n, n_params, sse, float(r2), float(adj), rmse)

    def to_dict(self) -> dict:
        def clean(v):
            return None if v is None or not np.isfinite(v) else float(v)
        return {"sse": clean(self.sse), "r2": clean(self.r2), "adj_r2": clean(self.adj_r2),
                "rmse": clean(self.rmse)}


def information_criteria(sse: float, n: int, p: int) -> tuple[float, float]:
    """Gaussian AIC and BIC (up to a constant shared by fits of the same data)."""
    if n <= 0 or sse <= 0:
        return float("nan"), float("nan")
    base = n * np.log(sse / n)
    return float(base + 2 * p), float(base + p * np.log(n))


def autocorrelation_time(residual_blocks: list[np.ndarray], max_lag: int = 2000) -> float:
    """Integrated autocorrelation time of residuals given as contiguous blocks."""
    blocks = [np.asarray(b, float) - np.mean(b) for b in residual_blocks if len(b) > 10]
    if not blocks:
        return 1.0
    var = sum(float(b @ b) for b in blocks)
    if var <= 0:
        return 1.0
    longest = max(len(b) for b in blocks)
    lags = min(max_lag, longest - 1)
    acf = np.zeros(lags + 1)
    for b in blocks:
        m = len(b)
        nfft = 1 << int(np.ceil(np.log2(2 * m)))
        spec = np.fft.rfft(b, nfft)
        ac = np.fft.irfft(spec * np.conj(spec), nfft)[:min(m, lags + 1)]
        acf[:len(ac)] += ac
    rho = acf / var
    # Geyer: sum pairs rho_{2k} + rho_{2k+1} while positive
    tau = -1.0
    for k in range(0, lags - 1, 2):
        pair = rho[k] + rho[k + 1]
        if pair <= 0:
            break
        tau += 2.0 * pair
    return float(max(tau, 1.0))


#: Why a parameter is not determined (one parameter, several).
INSENSITIVE = ("the data are insensitive to it", "the data are insensitive to them")
TRADES_OFF = ("it trades off exactly against other parameters", "they trade off exactly against other parameters")
TOO_WIDE = ("its 95 % interval is wider than its whole search range",
            "their 95 % intervals are wider than their whole search ranges")


@dataclass
class Uncertainty:
    stderr: np.ndarray            # nan where not determined
    correlation: np.ndarray       # nan rows/cols where not determined
    determined: np.ndarray        # bool
    sigma2: float
    warnings: list[str]


def parameter_uncertainty(jac: np.ndarray, residual: np.ndarray, values: np.ndarray,
                          names: list[str], n_free: int | None = None,
                          ranges: np.ndarray | None = None, said: set[str] = frozenset()) -> Uncertainty:
    """Covariance s^2 (J^T J)^-1 on the determined parameters, and warnings.

    A parameter is "not determined" when the data cannot locate it: a (numerically)
    zero Jacobian column, a large share of a null direction of the column-scaled
    Jacobian (it trades off exactly against others), or - for a parameter searched
    within bounds (``ranges`` = upper - lower) - a 95 % interval wider than the whole
    range. Those are held fixed for the covariance of the rest and reported without
    a standard error. Those in ``said`` (another warning says what is wrong with them: at a bound of
    their range) are not listed again.
    """
    n, p = jac.shape
    n_free = p if n_free is None else n_free
    ranges = np.full(p, np.inf) if ranges is None else np.asarray(ranges, float)
    sse = float(residual @ residual)
    sigma2 = sse / max(n - n_free, 1)
    warnings: list[str] = []
    # J = Q R: every quantity below depends on J only through R (J[:, idx]^T J[:, idx]
    # = R[:, idx]^T R[:, idx]), so the tall matrix is factorised once
    jac = np.linalg.qr(jac, mode="r") if n > p else jac
    norms = np.linalg.norm(jac, axis=0)
    big = norms.max() if p else 0.0
    determined = norms > big * 1e-14
    why = {}
    for i in np.flatnonzero(~determined):
        why[i] = INSENSITIVE
    while True:
        idx = np.flatnonzero(determined)
        if not len(idx):
            break
        js = jac[:, idx] / norms[idx]
        _, s, vt = np.linalg.svd(js, full_matrices=False)
        if s[-1] <= s[0] * NULL_RCOND:             # an exact trade-off: drop its main actor
            worst = idx[int(np.argmax(np.abs(vt[-1])))]
            determined[worst] = False
            why[worst] = TRADES_OFF
            continue
        inv = (vt.T / s**2) @ vt
        se = np.sqrt(np.clip(np.diag(inv), 0, None) * sigma2) / norms[idx]
        too_wide = 2 * 1.96 * se > ranges[idx]
        if too_wide.any():                         # drop the least determined, recompute
            k = int(np.argmax(np.where(too_wide, se / ranges[idx], -np.inf)))
            determined[idx[k]] = False
            why[idx[k]] = TOO_WIDE
            continue
        break
    # one line per reason (a long run's per-cycle terms made dozens of lines of one message)
    for reason in dict.fromkeys(why[i] for i in sorted(why)):
        which = [f"{names[i]} = {values[i]:.4g}" for i in sorted(why) if why[i] == reason and names[i] not in said]
        if not which:
            continue
        one = len(which) == 1
        warnings.append(f"{', '.join(which)} {'is' if one else 'are'} not determined: {reason[0 if one else 1]} "
                        "(held fixed for the other standard errors)")
    stderr = np.full(p, np.nan)
    corr = np.full((p, p), np.nan)
    idx = np.flatnonzero(determined)
    if len(idx):
        js = jac[:, idx] / norms[idx]
        _, s, vt = np.linalg.svd(js, full_matrices=False)
        inv = (vt.T / s**2) @ vt
        cov = sigma2 * inv / np.outer(norms[idx], norms[idx])
        se = np.sqrt(np.clip(np.diag(cov), 0, None))
        stderr[idx] = se
        with np.errstate(invalid="ignore", divide="ignore"):
            cc = cov / np.outer(se, se)
        corr[np.ix_(idx, idx)] = cc
        pairs = [f"{names[idx[a]]} and {names[idx[b]]} ({cc[a, b]:+.4f})" for a in range(len(idx))
                 for b in range(a + 1, len(idx)) if abs(cc[a, b]) > CORRELATION_LIMIT]
        # one line for all: the adjacent coefficients of a polynomial alone make several pairs
        if len(pairs) == 1:
            warnings.append(f"{pairs[0].replace(' (', ' are correlated (', 1)}: the data determine a "
                            "combination of them, not each one")
        elif pairs:
            warnings.append(f"{len(pairs)} pairs of parameters are correlated beyond +/-{CORRELATION_LIMIT:g}, "
                            f"the data determine combinations of them, not each one: {', '.join(pairs)}")
    return Uncertainty(stderr, corr, determined, sigma2, warnings)
