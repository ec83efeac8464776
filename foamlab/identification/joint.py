"""Joint refinement of all parameters on the raw signal of all half-cycles.

1. Variable projection on a decimated copy of the in-contact samples (about
   FIT_SAMPLES_PER_HALF_CYCLE per half-cycle; the model is continuous in time, so
   the same model runs on a coarser operator grid): only the decay rates alpha and
   fractional orders beta are searched, the linear k, a, r are solved exactly.
   Starts: the paper's three-step values, and a start built from the run's time
   scale alone; the better after a short run is continued.
2. Polish at full resolution on every sample of the half-cycles, all parameters
   at once, with the load cell's contact loss in the measurement model: a plate
   that has lost contact reads the unloaded value z0, so the prediction is
   max(model force, z0) (a censored observation, not a dropped one; z0 is fitted
   with the rest when enough samples are out of contact). Analytic Jacobian:
   the design columns for k, a, r and each column's derivative for alpha, beta.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
from scipy.optimize import least_squares

from foamlab.identification.basis import Layout, ModelBasis
from foamlab.identification.data import FitData, Orders
from foamlab.identification.paper import (
    alpha_candidates,
    alpha_candidates_from,
    beta_candidates,
    nonlinear_bounds,
)
from foamlab.identification.varpro import GreedyBasis, SeparableProblem
from foamlab.model import ModelParameters

#: Budget of the short runs that pick the better start, and of the continuation.
PROBE_NFEV, FIT_NFEV = 8, 40
#: Budget of the full-resolution polish (it starts next to the optimum).
POLISH_NFEV = 4
#: Two modes closer than this (relative) or two orders closer than this are one term twice.
DEGENERATE_RELATIVE, DEGENERATE_BETA = 0.02, 0.02
#: Fit the unloaded reading z0 only with at least this many samples out of contact.
MIN_CENSORED = 20


@dataclass
class JointFit:
    params: ModelParameters
    layout: Layout
    linear: np.ndarray
    nonlinear: np.ndarray
    contact_zero_N: float
    zero_fitted: bool
    jacobian: np.ndarray          # full-resolution, at the solution (rows = fd.observed)
    residual: np.ndarray          # measured - prediction at fd.observed
    n_free: int
    nfev: int
    starts: list[str]


def generic_start(orders: Orders, n_cycles: int, loading_time_s: float) -> np.ndarray:
    """Nonlinear start from the run's time scale only: decay rates spread over
    1..30 per loading time (alternately real and oscillating), orders spread over
    the residual's range."""
    rates = np.geomspace(1.0, 30.0, orders.N) / loading_time_s if orders.N else np.zeros(0)
    alphas = []
    for i, re in enumerate(rates):
        alphas += [re, re if i % 2 else 0.0]
    betas = np.linspace(-1.5, 0.8, orders.M) if orders.M > 1 else np.full(orders.M, 0.3)
    return np.concatenate([np.asarray(alphas, float), np.tile(betas, n_cycles)])


def greedy_start(basis: ModelBasis, w: np.ndarray, y: np.ndarray, orders: Orders,
                 loading_time_s: float) -> np.ndarray:
    """Forward selection: add damping modes, then each cycle's residual terms, one at a
    time, each the candidate (decay rate / fractional order from a data-scaled grid)
    that lowers the SSE most with all linear coefficients re-solved exactly."""
    lay = basis.layout
    sel = GreedyBasis(w[:, None] * basis.elastic, y)
    alphas: list[np.ndarray] = []
    for _ in range(lay.N):
        cands = [c for c in alpha_candidates(loading_time_s)
                 if not any(np.array_equal(c, a) for a in alphas)]
        cols = [w * basis.damping_column(c[0] + 1j * c[1])[0] for c in cands]
        k = int(np.argmax([sel.gain(col) for col in cols]))
        alphas.append(cands[k])
        sel.add(cols[k])
    betas = np.zeros((lay.C, lay.M))
    grid = np.array([b[0] for b in beta_candidates()])
    for c in range(lay.C):
        cols = w[:, None] * basis.residual_columns(c, grid)[0]
        free = np.ones(len(grid), bool)
        for m in range(lay.M):
            gains = [sel.gain(cols[:, i]) if free[i] else -1.0 for i in range(len(grid))]
            k = int(np.argmax(gains))
            betas[c, m] = grid[k]
            free[k] = False
            sel.add(cols[:, k])
    return np.concatenate([np.concatenate(alphas) if alphas else np.zeros(0), betas.ravel()])


def _degenerate(lay: Layout, nonlinear: np.ndarray) -> list[int]:
    """Nonlinear indices of one member of each coincident pair: two damping modes with
    (nearly) the same alpha, or two residual terms of a cycle with the same beta. Such a
    pair with opposite amplitudes is the derivative of one term (a ridge of the SSE the
    trust region stalls on); moving one member elsewhere lets it leave."""
    out = []
    al = nonlinear[:2 * lay.N].reshape(lay.N, 2)
    for i in range(lay.N):
        for j in range(i):
            if abs(complex(*al[i]) - complex(*al[j])) <= DEGENERATE_RELATIVE * abs(complex(*al[j])):
                out.append(2 * i)
                break
    beta = nonlinear[2 * lay.N:].reshape(lay.C, lay.M)
    for c in range(lay.C):
        for i in range(lay.M):
            if any(abs(beta[c, i] - beta[c, j]) <= DEGENERATE_BETA for j in range(i)):
                out.append(2 * lay.N + c * lay.M + i)
    return out


def _reseed(problem: SeparableProblem, lay: Layout, fit, lower, upper, ftol: float, rounds: int = 2):
    """Move one member of each coincident pair to the candidate that lowers the SSE most
    (others fixed), refit, keep the result if the SSE is lower."""
    for _ in range(rounds):
        bad = _degenerate(lay, fit.nonlinear)
        if not bad:
            break
        theta = fit.nonlinear.copy()
        for j in bad:
            if j < 2 * lay.N:
                cands = [c for c in alpha_candidates_from(lower[j], upper[j])]
                def trial(c, j=j):
                    th = theta.copy()
                    th[j:j + 2] = c
                    return th
            else:
                cands = [b for b in beta_candidates()]
                def trial(c, j=j):
                    th = theta.copy()
                    th[j] = c[0]
                    return th
            theta = min((trial(c) for c in cands), key=lambda th: problem.solve(th).sse)
        refit = problem.fit(theta, lower, upper, max_nfev=FIT_NFEV, ftol=ftol, xtol=1e-6)
        if refit.sse >= fit.sse:
            break
        fit = refit
    return fit


def _layout(fd: FitData, orders: Orders) -> Layout:
    return Layout(P=orders.P, N=orders.N, M=orders.M, C=fd.n_residual_cycles)


def joint_fit(fd: FitData, orders: Orders, start: ModelParameters | None,
              progress: Callable[[str, float], None] | None = None) -> JointFit:
    lay = _layout(fd, orders)
    lower, upper = nonlinear_bounds(orders, lay.C, fd.loading_time_s)
    coarse = ModelBasis(fd.t, fd.x, fd.labels, fd.fit_rows, lay, fd.x_scale_mm, fd.fit_step_s)
    w = np.sqrt(fd.fit_count)[:, None]         # block means: weight sqrt(samples)
    problem = SeparableProblem(lambda th: w * coarse.design(th), lambda th: w * coarse.design_derivatives(th),
                               np.array([lay.column_of_nonlinear(j) for j in range(lay.n_nonlinear)], int),
                               w[:, 0] * fd.fit_force)
    candidates: list[tuple[str, np.ndarray]] = []
    if start is not None:
        candidates.append(("paper three-step", lay.from_flat(start.to_vector())[1]))
    candidates.append(("forward selection", greedy_start(coarse, w[:, 0], problem.y, orders,
                                                         fd.loading_time_s)))
    # stop when an iteration gains less than a tenth of the noise variance (the
    # weighted SSE is ~ rows x sigma^2): further progress is below what the data resolve
    ftol = 0.1 / len(problem.y)
    probes = []
    for name, theta0 in candidates:
        probes.append((problem.fit(theta0, lower, upper, max_nfev=PROBE_NFEV, ftol=ftol, xtol=1e-6),
                       name))
        if progress:
            progress(f"joint fit: start '{name}'", 0.5 + 0.1 * len(probes))
    best, best_name = min(probes, key=lambda fr: fr[0].sse)
    fit = problem.fit(best.nonlinear, lower, upper, max_nfev=FIT_NFEV, ftol=ftol, xtol=1e-6)
    fit = _reseed(problem, lay, fit, lower, upper, ftol)
    nfev = problem.nfev
    if progress:
        progress("joint fit: full-resolution polish", 0.8)
    return _polish(fd, lay, fit.linear, fit.nonlinear, lower, upper,
                   nfev, [f"{n}{' (chosen)' if n == best_name else ''}" for _, n in probes])


def _polish(fd: FitData, lay: Layout, linear: np.ndarray, nonlinear: np.ndarray,
            lower: np.ndarray, upper: np.ndarray, nfev: int, starts: list[str]) -> JointFit:
    full = ModelBasis(fd.t, fd.x, fd.labels, fd.observed, lay, fd.x_scale_mm, fd.native_step_s)
    y = fd.f[fd.observed]
    nl_cols = np.array([lay.column_of_nonlinear(j) for j in range(lay.n_nonlinear)], int)
    L, K = lay.n_linear, lay.n_nonlinear
    z0 = fd.contact_zero_N
    # z0 is identifiable only if the model goes out of contact on enough samples
    censored = np.count_nonzero(full.force(linear, np.clip(nonlinear, lower, upper)) <= z0)
    fit_zero = censored >= MIN_CENSORED

    def unpack(p):
        return p[:L], p[L:L + K], (p[L + K] if fit_zero else z0)

    def fun(p):
        lin, nl, zero = unpack(p)
        return np.maximum(full.force(lin, nl), zero) - y

    def jac(p):
        lin, nl, zero = unpack(p)
        design = full.design(nl)
        out = np.empty((len(y), L + K + int(fit_zero)))
        out[:, :L] = design
        out[:, L:L + K] = full.design_derivatives(nl) * lin[nl_cols]
        off = (design @ lin) <= zero
        out[off, :L + K] = 0.0
        if fit_zero:
            out[:, -1] = off.astype(float)
        return out

    p0 = np.concatenate([linear, np.clip(nonlinear, lower, upper)] + ([[z0]] if fit_zero else []))
    lo = np.concatenate([np.full(L, -np.inf), lower] + ([[-np.inf]] if fit_zero else []))
    hi = np.concatenate([np.full(L, np.inf), upper] + ([[np.inf]] if fit_zero else []))
    res = least_squares(fun, p0, jac=jac, bounds=(lo, hi), method="trf", x_scale="jac",
                        max_nfev=POLISH_NFEV, ftol=1e-10, xtol=1e-10, gtol=1e-12)
    lin, nl, zero = unpack(res.x)
    # the canonical order (modes by decay rate, terms by order) permutes parameters;
    # the Jacobian at the solution comes from the solver, its columns permuted alike
    perm = lay.canonical_permutation(lin, nl)
    lin, nl = lin[perm[:L]], nl[perm[L:L + K] - L]
    jacobian = np.asarray(res.jac)[:, np.concatenate([perm, [L + K]] if fit_zero else [perm])]
    flat = lay.to_flat(lin, nl)
    template = ModelParameters(
        x_scale_mm=fd.x_scale_mm, elastic_k=np.zeros(lay.P + 1), damping_a=np.zeros(lay.N),
        damping_alpha=np.zeros(lay.N, complex), residual_r=np.zeros((lay.C, lay.M)),
        residual_beta=np.zeros((lay.C, lay.M)),
        description=f"identified by foamlab fit from {fd.run.source or 'a run'}")
    params = template.with_vector(flat)
    return JointFit(params, lay, lin, nl, float(zero), fit_zero, jacobian, -np.asarray(res.fun),
                    len(res.x), nfev + int(res.nfev), starts)
