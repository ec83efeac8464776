"""The two digital filters foamlab runs on every fit: a first-order recursion (the memory
operators' exact step) and Savitzky-Golay smoothing (segmentation, the path, velocities).

Why not scipy.signal's lfilter and savgol_filter: importing scipy.signal pulls in scipy.stats
and parses ~800 docstrings, 0.3-0.5 s of the 2-3 s a `foamlab fit` process takes (issue 26,
docs/benchmarks.md "Fit time"). The recursion is LAPACK's banded triangular solve (scipy.linalg,
already loaded by scipy.optimize), the same forward substitution lfilter runs, at its speed.
Savitzky-Golay is a least-squares polynomial per window: its weights are one pseudo-inverse
(numpy); tests/test_filters.py holds both to scipy.signal's results.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import get_lapack_funcs


def recursion(E: complex, x: np.ndarray, wn: complex = 1.0, wp: complex = 0.0,
              z0: complex = 0.0) -> np.ndarray:
    """z_n = E z_n-1 + wn x_n + wp x_n-1 for n = 0..len(x)-1, with x_-1 = 0 and z_-1 = z0
    (lfilter([wn, wp], [1, -E], x, zi=[E z0])): the lower bidiagonal system
    z_n - E z_n-1 = u_n solved by forward substitution."""
    x = np.asarray(x)
    u = wn * x
    if wp != 0:
        u[1:] += wp * x[:-1]
    if not len(u):
        return u
    u = np.atleast_1d(u).astype(np.result_type(u, E, z0, float))
    u[0] += E * z0
    ab = np.empty((2, len(u)), dtype=u.dtype)
    ab[1] = -E                                   # the sub-diagonal; the diagonal is unit
    tbtrs, = get_lapack_funcs(("tbtrs",), (ab, u))
    z, info = tbtrs(ab, u[:, None], uplo="L", diag="U")
    if info != 0:
        raise ArithmeticError(f"first-order recursion: LAPACK tbtrs info {info}")
    return z[:, 0]


def savgol(y: np.ndarray, window: int, order: int, deriv: int = 0, delta: float = 1.0) -> np.ndarray:
    """Savitzky-Golay filter of a 1-D y (scipy.signal.savgol_filter(..., mode="interp")): the
    deriv-th derivative of the least-squares polynomial of the given order over each odd
    window, at its centre; the first and last half-windows from the polynomial of the first
    and last whole window."""
    y = np.asarray(y, dtype=float)
    if window % 2 == 0 or window <= order or window > len(y):
        raise ValueError(f"Savitzky-Golay: window {window} must be odd, > order {order} "
                         f"and <= the {len(y)} samples")
    half = window // 2
    scale = math.factorial(deriv) / delta ** deriv
    # row deriv of the pseudo-inverse of the Vandermonde matrix of offsets -half..half
    weights = np.linalg.pinv(np.vander(np.arange(-half, half + 1.0), order + 1, increasing=True))[deriv]
    out = np.empty_like(y)
    out[half:len(y) - half] = np.correlate(y, weights * scale, mode="valid")
    offsets = np.arange(window, dtype=float)
    for lo, at in ((0, offsets[:half]), (len(y) - window, offsets[window - half:])):
        poly = np.polynomial.Polynomial.fit(offsets, y[lo:lo + window], order, domain=[0, window - 1],
                                            window=[0, window - 1])
        out[lo + at.astype(int)] = poly.deriv(deriv)(at) / delta ** deriv if deriv else poly(at)
    return out
