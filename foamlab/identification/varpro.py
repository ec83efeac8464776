"""Variable projection (Golub-Pereyra, Kaufman's Jacobian) on scipy.optimize.least_squares
(through analysis.solve.trust_region, the one call of it).

For a model y ~ Phi(theta) c, linear in c, the best c for given theta is a linear
least-squares solve, so only theta is searched by the trust-region method ('trf',
the lsqnonlin equivalent); the residual is r(theta) = (I - P(theta)) y with P the
projector on the columns of Phi. Kaufman's approximation of its Jacobian,
J_j = -(I - P) dPhi/dtheta_j c, needs only the derivative of the one column each
theta_j acts on. scipy has no variable-projection solver, hence this small layer.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg

from foamlab.analysis.solve import trust_region

#: Singular values below this fraction of the largest (column-scaled design) are
#: treated as zero: that combination of columns is not determined by the data.
RCOND = 1e-10


@dataclass
class LinearSolve:
    coef: np.ndarray
    residual: np.ndarray
    basis: np.ndarray          # orthonormal basis of the design's range (rank columns)


    @property
    def sse(self) -> float:
        return float(self.residual @ self.residual)


def solve_linear(design: np.ndarray, y: np.ndarray) -> LinearSolve:
    """Least squares by column-scaled, column-pivoted QR; columns that add nothing
    numerically (rank deficiency) get a zero coefficient."""
    norms = np.linalg.norm(design, axis=0)
    norms[norms == 0] = 1.0
    scaled = design / norms
    Q, R, piv = scipy.linalg.qr(scaled, mode="economic", pivoting=True, check_finite=False)
    diag = np.abs(np.diag(R))
    rank = int(np.count_nonzero(diag > (diag[0] * RCOND if len(diag) and diag[0] > 0 else np.inf)))
    Qr = Q[:, :rank]
    coef = np.zeros(design.shape[1])
    if rank:
        z = scipy.linalg.solve_triangular(R[:rank, :rank], Qr.T @ y, check_finite=False)
        coef[piv[:rank]] = z
    coef /= norms
    return LinearSolve(coef, y - design @ coef, Qr)


class GreedyBasis:
    """Forward selection of columns by orthogonal projection: the SSE gain of adding a
    column c to the current set is (q . r)^2 / (q . q), q = c minus its projection on
    the set, r the current residual - no refactorisation per candidate."""

    def __init__(self, fixed: np.ndarray, y: np.ndarray, orthonormal: bool = False):
        """fixed: the columns always in (orthonormal: already an orthonormal basis, y its residual)."""
        if orthonormal:
            self.Q, self.r = fixed, y
            return
        self.Q = np.linalg.qr(fixed)[0] if fixed.shape[1] else np.zeros((len(y), 0))
        self.r = y - self.Q @ (self.Q.T @ y)

    def _orth(self, c: np.ndarray) -> np.ndarray:
        q = c - self.Q @ (self.Q.T @ c)
        return q - self.Q @ (self.Q.T @ q)       # twice is enough (Kahan-Parlett)

    def gain(self, c: np.ndarray) -> float:
        """SSE gain of adding column c, or (c of shape (rows, k)) a group of columns at once."""
        if c.ndim == 2:
            trial = GreedyBasis(self.Q, self.r, orthonormal=True)
            for j in range(c.shape[1]):
                trial.add(c[:, j])
            return float(self.r @ self.r - trial.r @ trial.r)
        q = self._orth(c)
        qq = float(q @ q)
        if qq <= 1e-24 * max(float(c @ c), 1e-300):
            return 0.0
        return float(q @ self.r) ** 2 / qq

    def add(self, c: np.ndarray) -> None:
        if c.ndim == 2:
            for j in range(c.shape[1]):
                self.add(c[:, j])
            return
        q = self._orth(c)
        nq = np.linalg.norm(q)
        if nq <= 1e-12 * max(np.linalg.norm(c), 1e-300):
            return
        q /= nq
        self.Q = np.column_stack([self.Q, q])
        self.r = self.r - q * (q @ self.r)


@dataclass
class SeparableFit:
    nonlinear: np.ndarray
    linear: np.ndarray
    residual: np.ndarray
    nfev: int
    status: int
    message: str

    @property
    def sse(self) -> float:
        return float(self.residual @ self.residual)


class SeparableProblem:
    """min_theta || y - Phi(theta) c(theta) ||^2 with c(theta) solved exactly.

    design(theta) -> (n, L); derivatives(theta) -> (n, D), column d being
    d Phi[:, column_of[d]] / d theta_(its parameter); combine (n, D) -> (n, K) sums the
    columns of each theta_j (default: D = K, each theta_j moves one column, column_of[j]).
    """

    def __init__(self, design: Callable[[np.ndarray], np.ndarray],
                 derivatives: Callable[[np.ndarray], np.ndarray],
                 column_of: np.ndarray, y: np.ndarray,
                 combine: Callable[[np.ndarray], np.ndarray] | None = None,
                 prefetch: Callable[[np.ndarray], object] | None = None):
        """prefetch(theta): called before the residual at theta the optimizer asks for (a column
        cache filled with the derivatives too: the Jacobian follows most of its evaluations)."""
        self.prefetch = prefetch
        self.design = design
        self.derivatives = derivatives
        self.column_of = np.asarray(column_of, dtype=int)
        self.combine = combine or (lambda g: g)
        self.y = np.asarray(y, float)
        self._last_key: bytes | None = None
        self._last: LinearSolve | None = None
        self.nfev = 0

    def solve(self, theta: np.ndarray, prefetch: Callable[[np.ndarray], object] | None = None) -> LinearSolve:
        """The linear parameters at theta (the last theta's kept); prefetch(theta) first where it is new."""
        key = np.asarray(theta, float).tobytes()
        if key != self._last_key:
            if prefetch is not None:
                prefetch(theta)
            self._last = solve_linear(self.design(theta), self.y)
            self._last_key = key
            self.nfev += 1
        return self._last

    def residual(self, theta: np.ndarray) -> np.ndarray:
        return -self.solve(theta, self.prefetch).residual       # least_squares minimises |f|^2; sign irrelevant

    def jacobian(self, theta: np.ndarray) -> np.ndarray:
        sol = self.solve(theta)
        g = self.combine(self.derivatives(theta) * sol.coef[self.column_of])
        return g - sol.basis @ (sol.basis.T @ g)   # -(I - P) g, sign matching residual()

    def fit(self, theta0: np.ndarray, lower: np.ndarray, upper: np.ndarray,
            max_nfev: int | None = None, ftol: float = 1e-10, xtol: float = 1e-10) -> SeparableFit:
        theta0 = np.clip(np.asarray(theta0, float), lower, upper)
        if len(theta0) == 0:
            sol = self.solve(theta0)
            return SeparableFit(theta0, sol.coef, sol.residual, 1, 1, "linear only")
        res = trust_region(self.residual, theta0, self.jacobian, lower, upper, max_nfev=max_nfev, ftol=ftol,
                           xtol=xtol, gtol=1e-12)
        sol = self.solve(res.x)
        return SeparableFit(res.x, sol.coef, sol.residual, int(res.nfev), int(res.status),
                            str(res.message))
