"""The fitting core: one model (base + effects) fitted to all the samples of one or more runs.

Variable projection (scipy.optimize.least_squares, trust-region reflective, Kaufman's
Jacobian) over the nonlinear parameters nu = [alpha, beta of the base when free, the
effects' parameters], the linear ones (k, a, r, the load cell's zero) solved exactly,
the contact set (the plate cannot pull) iterated to consistency (design.py). The search
runs on a decimated copy of the series and is polished on every sample.

Identification ends with ``polish`` (its fit is the best optimum this core finds) and
diagnosis extends that fit; neither has a fitting loop of its own.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np
from scipy.optimize import least_squares

from foamlab.analysis.design import ExtendedModel, Series, Solution
from foamlab.model import ModelParameters
from foamlab.model.layout import nonlinear_bounds

#: Samples per run in the parameter search (decimated; decisions are made at full resolution).
SEARCH_SAMPLES = 3000
#: Iterations of the search of the base model (all its parameters free) on the decimated series.
BASE_NFEV = 20
#: Iterations of the full-resolution polish.
POLISH_NFEV = 6


@dataclass
class Fit:
    """A model (base or extension) fitted to all the data."""

    causes: list[type]                 # diagnosis' causes of the effects, in chain order
    model: ExtendedModel
    nu: np.ndarray                     # [phi if the base was free, effect parameters]
    stderr: np.ndarray                 # of the effect parameters
    solution: Solution
    heldout_rmse: float | None = None
    heldout_residual: np.ndarray | None = None  # each sample's held-out prediction error, NaN if not held out (heldout.py)
    heldout_refit: str = ""            # how the held-out refits treated the base's alpha/beta (heldout.py)
    status: int = 0                    # the optimizer's (scipy least_squares) at the end of this fit
    message: str = ""

    @classmethod
    def of(cls, causes: list[type], model: ExtendedModel, optimum: "Optimum") -> "Fit":
        return cls(causes, model, optimum.nu, optimum.stderr, optimum.solution,
                   status=optimum.status, message=optimum.message)

    @property
    def name(self) -> str:
        return self.causes[-1].name if self.causes else "base"

    @property
    def eta(self) -> np.ndarray:
        return self.model.split(self.nu)[1]

    @property
    def rss(self) -> float:
        return self.solution.rss()

    @property
    def n(self) -> int:
        return len(self.solution.residual)

    @property
    def rmse(self) -> float:
        return float(np.sqrt(self.rss / self.n))

    @property
    def params(self) -> ModelParameters:
        """The base model's parameters in this fit (effects aside)."""
        return self.model.parameters(self.nu, self.solution.theta)

    def jacobian(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Of the prediction in [the model's linear parameters (k, a, r), nu, the load cell's
        zero] at the solution (contact set held), at the rows of the first series (default:
        its used samples)."""
        sol = self.solution
        rows = np.flatnonzero(sol.used[0]) if rows is None else rows
        design = sol.designs[0][0][rows]
        deriv = self.model.prediction_derivatives(self.nu, sol)[rows]
        L = self.model.n_model
        return np.hstack([design[:, :L], deriv, design[:, L:L + 1]])

    def effect_values(self) -> list[dict]:
        """Fitted values of each effect in the chain, with standard errors."""
        out, i = [], 0
        for cls, e in zip(self.model.effect_types, self.model.effects(self.eta)):
            names = [p.name for p in cls.fitted_parameters()]
            se = dict(zip(names, self.stderr[i:i + len(names)]))
            out.append({"effect": cls.name, "values": dict(e.values), "stderr": se})
            i += len(names)
        return out


def loading_time_s(series: list[Series]) -> float:
    """Median duration of the reference run's loading half-cycles."""
    s = series[0].source
    d = [s.t[p] - s.t[a] for a, p in zip(s.labels.starts, s.labels.peaks) if p > a]
    return float(np.median(d)) if d else float(s.t[-1] - s.t[0])


def base_bounds(series: list[Series], params: ModelParameters) -> tuple[np.ndarray, np.ndarray]:
    """Identification's bounds of alpha and beta (from the loading time), widened to hold params."""
    lay = params.layout
    lo, hi = nonlinear_bounds(lay.orders, lay.C, loading_time_s(series))
    phi = lay.from_flat(params.to_vector())[1]
    return np.minimum(lo, phi), np.maximum(hi, phi)


@dataclass
class Optimum:
    """What one variable-projection run ended with (scipy's status and message kept)."""

    nu: np.ndarray
    stderr: np.ndarray                 # of the effect parameters (linear ones profiled out)
    solution: Solution
    status: int                        # scipy.optimize.least_squares: > 0 converged, 0 budget used up
    message: str
    nfev: int


#: Half-width of a held parameter's bounds (least squares needs lower < upper): identification
#: holds coalesced residual orders apart this way (identification.apart).
HOLD = 1e-9


def held(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Which parameters the bounds hold (within HOLD of a value): they do not move in a fit, so they
    take no share of the information (their Jacobian columns left out of a covariance)."""
    return np.asarray(upper, float) - np.asarray(lower, float) <= 4 * HOLD


def trust_region(fun: Callable, x0: np.ndarray, jac: Callable, lower: np.ndarray, upper: np.ndarray, *,
                 max_nfev: int | None = None, ftol: float = 1e-8, xtol: float = 1e-8, gtol: float = 1e-8):
    """The one call of scipy.optimize.least_squares in identification and analysis: trust-region
    reflective within the bounds, each parameter scaled by its Jacobian column (scipy's result)."""
    return least_squares(fun, x0, jac=jac, bounds=(lower, upper), method="trf", x_scale="jac",
                         max_nfev=max_nfev, ftol=ftol, xtol=xtol, gtol=gtol)


def varpro(model: ExtendedModel, nu0: np.ndarray, keep: list[np.ndarray] | None = None,
           max_nfev: int | None = None) -> Optimum:
    """Variable projection on nu (trust-region reflective, Kaufman's Jacobian)."""
    lo, hi = model.bounds()
    nu0 = np.clip(np.asarray(nu0, float), lo, hi)
    fun, jac = model.residual_fn(keep)
    r0 = fun(nu0)
    # stop when a step gains less than a tenth of the noise variance: below what the data resolve
    ftol = max(0.1 / max(len(r0), 1), 1e-10)
    res = trust_region(fun, nu0, jac, lo, hi, xtol=1e-8, ftol=ftol, max_nfev=max_nfev)
    sol = model.solve(res.x, keep)
    # standard errors of the effect parameters (linear parameters profiled out)
    r = res.fun
    dof = max(len(r) - model.n_linear - model.n_nonlinear, 1)
    s2 = float(r @ r) / dof
    stderr = np.full(model.n_eta, np.nan)
    if model.n_eta:
        free = ~held(lo, hi)
        try:
            J = np.asarray(res.jac)[:, free]
            se = np.zeros(len(free))
            se[free] = np.sqrt(np.maximum(np.diag(np.linalg.pinv(J.T @ J) * s2), 0.0))
            stderr = se[model.n_phi:]
        except np.linalg.LinAlgError:
            pass
    return Optimum(res.x, stderr, sol, int(res.status), str(res.message), int(res.nfev))


def decimation(series: list[Series]) -> int:
    """Decimation factor of the parameter search (about SEARCH_SAMPLES samples per run)."""
    return max(1, int(round(max(len(x) for x in series) / SEARCH_SAMPLES)))


def contact_of(fit: Fit, series: list[Series]) -> list[np.ndarray] | None:
    """The fit's contact set, if it was fitted on these very series (a start for a model
    that extends or refits it)."""
    same = len(fit.model.series) == len(series) and all(a is b for a, b in zip(fit.model.series, series))
    return [m.copy() for m in fit.solution.masks] if same else None


def model_like(fit: Fit, series: list[Series], free_base: bool | None = None) -> ExtendedModel:
    m = fit.model
    free = m.free_base if free_base is None else free_base
    return ExtendedModel(series, fit.params, m.effect_types, m.settings, effect_bounds=m.effect_bounds,
                         free_base=free,
                         base_bounds=bounds_like(m, series, fit.params) if free else None,
                         masks=contact_of(fit, series))


def bounds_like(m: ExtendedModel, series: list[Series], params: ModelParameters):
    """A model's own bounds of alpha and beta where it has them (orders held there stay held:
    identification.apart), else identification's."""
    return m.base_bounds if m.base_bounds is not None else base_bounds(series, params)


def at_full_resolution(fit: Fit, full: list[Series], polish_nfev: int = 0) -> Fit:
    """A fit found on decimated series, carried to the full ones (and polished there)."""
    if len(fit.model.series) == len(full) and all(a is b for a, b in zip(fit.model.series, full)):
        return fit
    model = model_like(fit, full)
    nu = np.concatenate([fit.model.split(fit.nu)[0] if model.free_base else [], fit.eta])
    if polish_nfev:
        return Fit.of(list(fit.causes), model, varpro(model, nu, max_nfev=polish_nfev))
    return Fit(list(fit.causes), model, nu, fit.stderr, model.solve(nu), status=fit.status, message=fit.message)


def solved_at(series: list[Series], params: ModelParameters) -> Fit:
    """The base model at these alpha and beta (free in the model: its Jacobian has them), the
    linear parameters and the contact set solved, nothing searched."""
    model = ExtendedModel(series, params, [], free_base=True, base_bounds=base_bounds(series, params))
    nu = model.start()
    return Fit([], model, nu, np.zeros(0), model.solve(nu))


def fit_base(series: list[Series], params: ModelParameters, bounds: tuple[np.ndarray, np.ndarray] | None = None
             ) -> Fit:
    """The base model on all runs: identification's alpha/beta polished with the rest (within
    ``bounds``, default identification's)."""
    model = ExtendedModel(series, params, [], free_base=True, base_bounds=bounds or base_bounds(series, params))
    return Fit.of([], model, varpro(model, model.start(), max_nfev=BASE_NFEV))


def polish(series: list[Series], params: ModelParameters,
           other_starts: Callable[[Fit], Iterable[ModelParameters]] | None = None,
           bounds: tuple[np.ndarray, np.ndarray] | None = None, nfev: int = POLISH_NFEV) -> Fit:
    """The base model on every sample of the runs, from ``params``: all of alpha and beta
    searched with the linear parameters, the contact set and the load cell's zero (on the
    decimated series, then polished on every sample). Identification's last step, and the
    base of a diagnosis of several runs.

    other_starts: given the first decimated fit, more starts to try (none when it needs
    none); the best decimated fit is the one carried to every sample. bounds: of alpha and
    beta (default identification's; identification.apart holds orders with them); nfev: the
    budget on every sample (a fit that is kept is carried on to convergence: ``converged``)."""
    k = decimation(series)
    coarse = [s.decimated(k) for s in series]
    best = fit_base(coarse, params, bounds)
    for start in (other_starts(best) if other_starts is not None else ()):
        other = fit_base(coarse, start, bounds)
        if other.rss < best.rss:
            best = other
    return at_full_resolution(best, series, nfev if k > 1 else 0)


def converged(fit: Fit, max_nfev: int) -> Fit:
    """The fit's optimizer carried on from where its budget stopped it, until it converges or
    max_nfev more evaluations are spent (its status then says it stopped). A fit that
    converged is returned as it is."""
    if fit.status > 0:
        return fit
    return Fit.of(list(fit.causes), fit.model, varpro(fit.model, fit.nu, max_nfev=max(int(max_nfev), 1)))
