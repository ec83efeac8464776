"""The paper's three-step identification (section 4, Eqs. 15-19 and 26-28).

1. Each half-cycle is resampled on one displacement grid (S bins of width dx over
   the displacement range all the used half-cycles share), leaving out the
   recovery (contact-loss) samples and the first cycle's linear region
   (assumption (a)). Bin means, so the grid values average the noise.
2. The data of each component are differences of half-cycles:
     damping   V_D  = F_L2 - F_U1                      (Eq. 15)
     residual  V_R1 = F_L2 - F_L1, V_Rk = F_Uk - F_U(k-1)  (Eqs. 16-18)
     elastic   E    = F_L1 - V_D                       (Eq. 19)
3. Each is fitted separately with scipy.optimize.least_squares ('trf'): damping
   by Eq. 9 (N decaying modes, Re alpha > 0; Eq. 26), each cycle's residual by
   Eq. 11 (M terms; Eq. 27), the elastic polynomial by Eq. 12 (order P; Eq. 28,
   linear, so scipy.optimize.lsq_linear 'trf').

Starting values come from the data: the time scale of a loading half-cycle sets
a log-spaced grid of decay rates, the fractional orders a grid over their
range; modes/terms are added greedily (each candidate's linear coefficients
solved exactly: variable projection), then all are refined together.

These differences hold exactly when the residual of a cycle is the same function of x in
every later half-cycle: the paper form (Eqs. 20b-f as printed), not the causal one (Eq. 10;
docs/model.md, inconsistency 5). The steps do not depend on the form fitted: they give the
paper's numbers and STARTING values in either; the joint refinement fits the form's model.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
from scipy.optimize import lsq_linear

from foamlab.analysis.prepared import PreparedRun
from foamlab.identification.statistics import GoodnessOfFit
from foamlab.identification.varpro import GreedyBasis, SeparableProblem, solve_linear
from foamlab.model import ModelParameters, damping_closed_form, residual_eq11
from foamlab.model.layout import (
    ALPHA_HI,
    ALPHA_LO,
    BETA_HI,
    BETA_LO,
    Orders,
    nonlinear_bounds,
)
from foamlab.segmentation import HalfCycle

#: Grid bins: about one per this many samples of the sparsest half-cycle...
SAMPLES_PER_BIN = 4
#: ...within these limits (S of Eqs. 26-28).
MIN_BINS, MAX_BINS = 20, 300
#: The shared displacement range must cover this fraction of the stroke.
MIN_SHARED_FRACTION = 0.2
FD_STEP = 1e-6
#: Iteration budget of each step's local refinement (start values, not the final fit).
STEP_MAX_NFEV = 60


def alpha_candidates(loading_time_s: float) -> list[np.ndarray]:
    """(re, im) starting candidates: log-spaced decay rates, real or oscillating."""
    return alpha_candidates_from(ALPHA_LO / loading_time_s, ALPHA_HI / loading_time_s)


def alpha_candidates_from(lo: float, hi: float) -> list[np.ndarray]:
    """7 log-spaced decay rates inside (lo, hi), each real, or oscillating at 1x or 3x."""
    res = np.geomspace(lo, hi, 9)[1:-1]
    return [np.array([re, ratio * re]) for re in res for ratio in (0.0, 1.0, 3.0)]


def beta_candidates() -> list[np.ndarray]:
    return [np.array([b]) for b in np.linspace(-2.0, 0.9, 9)]


@dataclass
class StepResult:
    name: str
    x: np.ndarray                 # grid (mm)
    data: np.ndarray              # component data from half-cycle differences
    fitted: np.ndarray
    n_params: int
    stats: GoodnessOfFit
    values: dict = field(default_factory=dict)


@dataclass
class PaperResult:
    start: ModelParameters | None
    steps: dict[str, StepResult]
    warnings: list[str]
    grid: np.ndarray | None = None


class _ColumnFamily:
    """Fixed columns plus groups of columns, group g a function of theta[g*size:(g+1)*size]."""

    def __init__(self, fixed: np.ndarray | None, column: Callable[[np.ndarray], np.ndarray],
                 group_size: int, n_rows: int):
        self.fixed = np.zeros((n_rows, 0)) if fixed is None else fixed
        self.column = column
        self.size = group_size

    def design(self, theta: np.ndarray) -> np.ndarray:
        groups = np.asarray(theta, float).reshape(-1, self.size)
        cols = [self.column(g)[:, None] for g in groups]
        return np.hstack([self.fixed] + cols)

    def derivatives(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, float)
        out = np.empty((self.fixed.shape[0], len(theta)))
        for j in range(len(theta)):
            g = j // self.size
            grp = theta[g * self.size:(g + 1) * self.size].copy()
            h = FD_STEP * max(abs(grp[j % self.size]), 1e-3)
            up, dn = grp.copy(), grp.copy()
            up[j % self.size] += h
            dn[j % self.size] -= h
            out[:, j] = (self.column(up) - self.column(dn)) / (2 * h)
        return out

    def column_of(self, n_theta: int) -> np.ndarray:
        return self.fixed.shape[1] + np.arange(n_theta) // self.size


def fit_separable(family: _ColumnFamily, y: np.ndarray, n_groups: int,
                  candidates: list[np.ndarray], lower: np.ndarray, upper: np.ndarray):
    """Greedy data-driven start (add the group that lowers the SSE most), then 'trf'."""
    sel = GreedyBasis(family.fixed, y)
    cols = [family.column(c) for c in candidates]
    chosen: list[np.ndarray] = []
    used = np.zeros(len(candidates), bool)
    for _ in range(n_groups):
        gains = [sel.gain(col) if not used[i] else -1.0 for i, col in enumerate(cols)]
        k = int(np.argmax(gains))
        used[k] = True
        chosen.append(candidates[k])
        sel.add(cols[k])
    theta0 = np.concatenate(chosen) if chosen else np.zeros(0)
    problem = SeparableProblem(family.design, family.derivatives,
                               family.column_of(len(theta0)), y)
    # a tenth of the noise variance per iteration is below what the data resolve
    return problem.fit(theta0, lower, upper, max_nfev=STEP_MAX_NFEV, ftol=0.1 / len(y), xtol=1e-6)


def resample_on_grid(x: np.ndarray, f: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin means of f, placed at the bin centres by interpolation on the bins' mean x;
    NaN outside the displacement range the half-cycle covers."""
    S = len(edges) - 1
    idx = np.searchsorted(edges, x, side="right") - 1
    ok = (idx >= 0) & (idx < S)
    counts = np.bincount(idx[ok], minlength=S)
    sx = np.bincount(idx[ok], weights=x[ok], minlength=S)
    sf = np.bincount(idx[ok], weights=f[ok], minlength=S)
    full = counts > 0
    centres = 0.5 * (edges[1:] + edges[:-1])
    out = np.full(S, np.nan)
    if full.sum() < 2:
        return out
    mx, mf = sx[full] / counts[full], sf[full] / counts[full]
    order = np.argsort(mx)
    inside = (centres >= mx.min()) & (centres <= mx.max())
    out[inside] = np.interp(centres[inside], mx[order], mf[order])
    return out


def _usable(fd: PreparedRun, half: HalfCycle) -> tuple[np.ndarray, np.ndarray]:
    sl = half.slice
    keep = ~fd.seg.contact_lost[sl]
    lin = fd.seg.first_cycle_linear_region
    if lin is not None and half.cycle == 1 and half.is_loading:
        idx = np.arange(half.start, half.stop)
        keep &= ~((idx >= lin[0]) & (idx < lin[1]))
    return fd.x[sl][keep], fd.f[sl][keep]


def _unit_damping(alpha: complex) -> ModelParameters:
    return ModelParameters(x_scale_mm=1.0, elastic_k=[0.0], damping_a=[1.0], damping_alpha=[alpha],
                           residual_r=np.zeros((1, 0)), residual_beta=np.zeros((1, 0)))


def _rate(fd: PreparedRun, half: HalfCycle) -> float:
    sl = half.slice
    return float(abs(np.polyfit(fd.t[sl], fd.x[sl], 1)[0]))


def paper_steps(fd: PreparedRun, orders: Orders) -> PaperResult:
    """The three steps on the run's half-cycles; start values for the joint fit."""
    cycles = fd.seg.cycles
    C = orders.residual_cycles(fd.n_residual_cycles)
    warnings: list[str] = []
    if len(cycles) < 2:
        # Eq. 15 (damping) and Eq. 16 (the first residual) subtract the first unloading and
        # loading from the second loading: a single cycle has no difference to take
        warnings.append("the paper's three steps skipped: they take differences with a second cycle "
                        "(Eqs. 15-16); a single cycle is fitted by the joint search alone")
        return PaperResult(None, {}, warnings)
    used: dict[str, HalfCycle] = {"L1": cycles[0].loading, "U1": cycles[0].unloading,
                                  "L2": cycles[1].loading}
    for c in range(2, C + 1):
        used[f"U{c}"] = cycles[c - 1].unloading
    lattice = _Lattice.of(fd, used, warnings)
    if lattice is None:
        return PaperResult(None, {}, warnings)
    steps: dict[str, StepResult] = {}
    lower_all, upper_all = nonlinear_bounds(orders, C, fd.loading_time_s)
    vd_data = (lattice.F["L2"] - lattice.F["U1"])[lattice.main]
    steps["damping"], alphas, a = _step_damping(fd, orders, lattice, used["L2"], vd_data,
                                                lower_all, upper_all)
    steps["residual"] = _step_residual(fd, orders, lattice, C, warnings)
    steps["elastic"] = _step_elastic(fd, orders, lattice, vd_data)
    start = ModelParameters(
        x_scale_mm=fd.x_scale_mm, elastic_k=steps["elastic"].values["k"], damping_a=a,
        damping_alpha=alphas[:, 0] + 1j * alphas[:, 1],
        residual_r=steps["residual"].values["r"], residual_beta=steps["residual"].values["beta"],
        residual_form=orders.form, shared_orders=orders.shared and C > 1,
        description="start values: the paper's three-step identification",
    )
    return PaperResult(start, steps, warnings, lattice.grid)


@dataclass(frozen=True)
class _Lattice:
    """One displacement lattice (bin width dx) for all half-cycles used; each difference uses
    the bins where both of its half-cycles have data. `main`: the bins L1, U1 and L2 share."""

    centres: np.ndarray
    F: dict[str, np.ndarray]
    main: np.ndarray

    @property
    def grid(self) -> np.ndarray:
        return self.centres[self.main]

    @classmethod
    def of(cls, fd: PreparedRun, used: dict[str, HalfCycle], warnings: list[str]) -> "_Lattice | None":
        data = {k: _usable(fd, h) for k, h in used.items()}
        short = [k for k, (xv, _) in data.items() if len(xv) < 2 * MIN_BINS]
        if short:
            warnings.append(f"paper's three steps skipped: half-cycle(s) {', '.join(short)} have too few "
                            "samples in contact")
            return None
        x_lo = min(float(np.min(xv)) for xv, _ in data.values())
        x_hi = max(float(np.max(xv)) for xv, _ in data.values())
        density = min(len(xv) / max(float(np.ptp(xv)), 1e-12) for xv, _ in data.values())
        S_total = int(np.clip(density * (x_hi - x_lo) / SAMPLES_PER_BIN, MIN_BINS, MAX_BINS))
        edges = np.linspace(x_lo, x_hi, S_total + 1)
        centres = 0.5 * (edges[1:] + edges[:-1])
        F = {k: resample_on_grid(xv, fv, edges) for k, (xv, fv) in data.items()}
        main = np.isfinite(F["L1"]) & np.isfinite(F["U1"]) & np.isfinite(F["L2"])
        stroke = fd.seg.stroke_mm
        shared = float(np.ptp(centres[main])) if main.sum() >= 2 else 0.0
        if main.sum() < MIN_BINS or shared < MIN_SHARED_FRACTION * stroke:
            warnings.append(f"paper's three steps skipped: L1, U1 and L2 share only {shared:.3g} mm "
                            f"of displacement in contact (stroke {stroke:.3g} mm)")
            return None
        return cls(centres, F, main)


def _step_damping(fd: PreparedRun, orders: Orders, lattice: _Lattice, L2: HalfCycle,
                  vd_data: np.ndarray, lower_all, upper_all) -> tuple[StepResult, np.ndarray, np.ndarray]:
    """Step 1: damping, Eq. 15 data, Eq. 9 model (Eq. 26)."""
    grid = lattice.grid
    S = len(grid)
    v2 = _rate(fd, L2)
    x_rel = grid - fd.x[L2.start]
    fam = _ColumnFamily(None, lambda g: damping_closed_form(_unit_damping(g[0] + 1j * g[1]), x_rel, v2),
                        2, S)
    if orders.N:
        fit = fit_separable(fam, vd_data, orders.N, alpha_candidates(fd.loading_time_s),
                            lower_all[:2 * orders.N], upper_all[:2 * orders.N])
        alphas = fit.nonlinear.reshape(-1, 2)
        a = fit.linear
        vd_fit = vd_data - fit.residual
    else:
        alphas, a, vd_fit = np.zeros((0, 2)), np.zeros(0), np.zeros(S)
    step = StepResult("damping", grid, vd_data, vd_fit, 3 * orders.N,
                      GoodnessOfFit.of(vd_data, vd_fit, 3 * orders.N),
                      {"a": a, "alpha": alphas[:, 0] + 1j * alphas[:, 1]})
    return step, alphas, a


def _step_residual(fd: PreparedRun, orders: Orders, lattice: _Lattice, C: int,
                   warnings: list[str]) -> StepResult:
    """Step 2: residual of each cycle, Eqs. 16-18 data, Eq. 11 model (Eq. 27)."""
    cycles, F = fd.seg.cycles, lattice.F
    r_all = np.zeros((C, orders.M))
    b_all = np.zeros((C, orders.M))
    res_x, res_data, res_fit = [], [], []
    for c in range(1, C + 1):
        vr = F["L2"] - F["L1"] if c == 1 else F[f"U{c}"] - F[f"U{c - 1}"]
        ok = np.isfinite(vr)
        if ok.sum() < MIN_BINS:
            warnings.append(f"paper's step 2: cycle {c}'s residual has only {int(ok.sum())} shared "
                            "grid points; its terms start from cycle 1's")
            r_all[c - 1], b_all[c - 1] = r_all[0], b_all[0]
            continue
        xr_grid, vr = lattice.centres[ok], vr[ok]
        cyc = cycles[c - 1]
        s, p = cyc.loading.start, cyc.unloading.start
        A = float(fd.x[p] - fd.x[s])
        T = 2.0 * float(fd.t[p] - fd.t[s])
        xr = xr_grid - fd.x[s]
        fam_r = _ColumnFamily(None, lambda g, xr=xr, A=A, T=T: residual_eq11([1.0], g, xr, A, T), 1,
                              len(xr))
        if orders.M and orders.shared and c > 1:
            # orders shared by every cycle: the later cycles' amplitudes at the first one's orders
            fit = solve_linear(fam_r.design(b_all[0]), vr)
            r_all[c - 1], b_all[c - 1] = fit.coef, b_all[0]
            res_fit.append(vr - fit.residual)
        elif orders.M:
            fit = fit_separable(fam_r, vr, orders.M, beta_candidates(),
                                np.full(orders.M, BETA_LO), np.full(orders.M, BETA_HI))
            r_all[c - 1], b_all[c - 1] = fit.linear, fit.nonlinear
            res_fit.append(vr - fit.residual)
        else:
            res_fit.append(np.zeros(len(vr)))
        res_x.append(xr_grid)
        res_data.append(vr)
    res_data_all = np.concatenate(res_data) if res_data else np.zeros(0)
    res_fit_all = np.concatenate(res_fit) if res_fit else np.zeros(0)
    n_res = orders.M * len(res_data) + (orders.M if orders.shared else orders.M * len(res_data))
    return StepResult("residual", np.concatenate(res_x) if res_x else np.zeros(0),
                      res_data_all, res_fit_all, n_res,
                      GoodnessOfFit.of(res_data_all, res_fit_all, n_res), {"r": r_all, "beta": b_all})


def _step_elastic(fd: PreparedRun, orders: Orders, lattice: _Lattice, vd_data: np.ndarray) -> StepResult:
    """Step 3: elastic, Eq. 19 data, Eq. 12 model (Eq. 28): linear least squares."""
    grid = lattice.grid
    e_data = lattice.F["L1"][lattice.main] - vd_data
    vander = np.vander(grid / fd.x_scale_mm, orders.P + 1, increasing=True)
    k = lsq_linear(vander, e_data, method="trf").x
    e_fit = vander @ k
    return StepResult("elastic", grid, e_data, e_fit, orders.P + 1,
                      GoodnessOfFit.of(e_data, e_fit, orders.P + 1), {"k": k})
