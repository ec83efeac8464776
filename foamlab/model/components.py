"""The three force components of the paper, as functions (Eqs. 9, 11, 12)."""

from __future__ import annotations

import numpy as np
from scipy.special import digamma, gamma, gammaln

from foamlab.model.params import ModelParameters


def elastic_force(params: ModelParameters, x) -> np.ndarray:
    """Eq. 12 in the scaled variable x/x_scale: E = sum_i k_i (x/x_scale)^i."""
    return np.polynomial.polynomial.polyval(np.asarray(x, float) / params.x_scale_mm, params.elastic_k)


def damping_closed_form(params: ModelParameters, x, rate_mm_s: float) -> np.ndarray:
    """Eq. 9 for a loading ramp at constant rate from x = 0 (real part: conjugate pairs)."""
    x = np.asarray(x, float)[..., None]
    v = float(rate_mm_s)
    a, al = params.damping_a, params.damping_alpha
    terms = v * a * (x / (v * al) - (1.0 - np.exp(-al * x / v)) / al**2)
    return np.real(terms.sum(axis=-1))


def residual_eq11(r, beta, x, amplitude_mm: float, period_s: float) -> np.ndarray:
    """Eq. 11: residual force during the unloading of a triangular cycle of period T.

    Uses T^-beta_i per term (the paper prints T^-beta without the index).
    """
    values, _ = residual_static(x, amplitude_mm, period_s, beta)
    return values @ np.asarray(r, float)


def residual_static(x, stroke_mm: float, period_s: float, beta, derivative: bool = False):
    """Eq. 11 per unit r, as the paper's form uses it: a function of the displacement x
    (relative to the cycle's start) with the cycle's own stroke A and period T, for each
    beta: 2 A T^-beta / Gamma(2 - beta) ((1 - x/2A)^nu - 2 (1/2 - x/2A)_+^nu), nu = 1 - beta.

    Returns (len(x), len(beta)) values and, with derivative, their d/dbeta (else None).
    Beyond the stroke (x > A) the second base is 0: the function continues continuously;
    a cycle without a stroke (A <= 0) or a period has no residual force."""
    x = np.atleast_1d(np.asarray(x, float))[:, None]
    b = np.atleast_1d(np.asarray(beta, float))[None, :]
    A, T = float(stroke_mm), float(period_s)
    if not (A > 0 and T > 0):
        zeros = np.zeros((x.shape[0], b.shape[1]))
        return zeros, (zeros.copy() if derivative else None)
    nu = 1.0 - b
    u = np.clip(1.0 - x / (2 * A), 0.0, None)
    w = np.clip(0.5 - x / (2 * A), 0.0, None)
    pref = 2 * A * np.exp(-b * np.log(T) - gammaln(2 - b))
    pu, pw = u ** nu, w ** nu
    shape = pu - 2 * pw
    values = pref * shape
    if not derivative:
        return values, None
    # d/dbeta: the prefactor's (-log T + psi(2 - beta)) and the bases' -p log(base), 0 log 0 = 0
    log = lambda base: np.log(np.where(base > 0, base, 1.0))
    d_shape = -pu * log(u) + 2 * pw * log(w)
    return values, pref * ((digamma(2 - b) - np.log(T)) * shape + d_shape)


def rl_derivative_piecewise_linear(t, t0: float, corners, slope_changes, beta: float) -> np.ndarray:
    """Exact Riemann-Liouville D^beta (lower terminal t0) of a piecewise-linear x with
    x(t0) = 0: x = sum_j ds_j (t - c_j)_+ , so D^beta x = sum_j ds_j (t - c_j)_+^nu / Gamma(nu + 1),
    nu = 1 - beta. The closed form behind Eq. 11, valid for any piecewise-linear history."""
    t = np.asarray(t, float)
    nu = 1.0 - beta
    out = np.zeros_like(t)
    for c, ds in zip(corners, slope_changes):
        if c < t0:
            continue
        out += ds * np.clip(t - c, 0.0, None) ** nu
    return out / gamma(nu + 1.0)
