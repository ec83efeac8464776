"""The three force components of the paper, as functions (Eqs. 9, 11, 12)."""

from __future__ import annotations

import numpy as np
from scipy.special import gamma

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
    x = np.asarray(x, float)[..., None]
    r, b = np.asarray(r, float), np.asarray(beta, float)
    A, T = amplitude_mm, period_s
    u = np.clip(1.0 - x / (2 * A), 0.0, None)
    w = np.clip(0.5 - x / (2 * A), 0.0, None)
    terms = 2 * A * r * T ** (-b) / gamma(2 - b) * (u ** (1 - b) - 2 * w ** (1 - b))
    return terms.sum(axis=-1)


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
