"""Joint refinement of all parameters on the raw signal of all half-cycles.

1. Variable projection on a decimated copy of the in-contact samples (about
   FIT_SAMPLES_PER_HALF_CYCLE per half-cycle; the model is continuous in time, so
   the same model runs on a coarser operator grid): only the decay rates alpha and
   fractional orders beta are searched, the linear k, a, r are solved exactly.
   Starts: the paper's three-step values and two forward selections; the best after a
   short run is continued.
2. Polish at full resolution on every sample of the half-cycles, all parameters
   at once, with the load cell's contact loss in the measurement model: a plate
   that has lost contact reads the unloaded value z0, so the prediction is
   max(model force, z0) (a censored observation, not a dropped one; z0 is fitted
   with the rest when enough samples are out of contact). Analytic Jacobian:
   the design columns for k, a, r and each column's derivative for alpha, beta.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass
from typing import Callable, Iterable

import numpy as np

from foamlab.analysis.basis import ModelBasis
from foamlab.analysis.prepared import PreparedRun, model_response
from foamlab.analysis.solve import trust_region
from foamlab.identification.paper import alpha_candidates, beta_candidates
from foamlab.identification.varpro import (
    GreedyBasis,
    SeparableFit,
    SeparableProblem,
    solve_linear,
)
from foamlab.model import ModelParameters
from foamlab.model.layout import Layout, Orders, nonlinear_bounds

#: Budget of the short runs that pick the better start, and of the continuation.
PROBE_NFEV, FIT_NFEV = 6, 40
#: Budget of the full-resolution polish (it starts next to the optimum).
POLISH_NFEV = 3
#: Far jumps refitted per round of the global search, the most promising (lowest SSE
#: before refitting) first.
MAX_JUMPS = 2
#: Fit the unloaded reading z0 only with at least this many samples out of contact.
MIN_CENSORED = 20
#: A damping mode whose Im alpha ends below this fraction of its Re alpha stays real (fixed).
REAL_MODE_RATIO = 1e-6
#: A rate or order within this fraction of its search range from a bound sits at it.
AT_BOUND = 1e-6


@dataclass
class JointFit:
    params: ModelParameters
    layout: Layout
    linear: np.ndarray
    nonlinear: np.ndarray
    fixed_nonlinear: np.ndarray   # bool: held fixed (Im alpha of a mode made real)
    contact_zero_N: float
    zero_fitted: bool
    jacobian: np.ndarray          # full-resolution, at the solution (rows = fd.observed)
    residual: np.ndarray          # measured - prediction at fd.observed
    n_free: int
    nfev: int
    starts: list[str]
    status: int = 0               # scipy least_squares' at the end (> 0 converged)
    message: str = ""


def greedy_start(basis: ModelBasis, w: np.ndarray, blocks: Callable, y: np.ndarray, orders: Orders,
                 loading_time_s: float, residual_first: bool = False) -> np.ndarray:
    """Forward selection: add damping modes and each cycle's residual terms one at a
    time, each the candidate (decay rate / fractional order from a data-scaled grid)
    that lowers the SSE most with all linear coefficients re-solved exactly. The
    order of the two groups matters (the first chosen explain what they can), so
    both orders serve as starts."""
    lay = basis.layout
    sel = GreedyBasis(w[:, None] * blocks(basis.elastic), y)
    alphas: list[np.ndarray] = []
    betas = np.zeros((lay.C, lay.M))
    grid = np.array([b[0] for b in beta_candidates()])

    def pick_damping():
        for _ in range(lay.N):
            cands = [c for c in alpha_candidates(loading_time_s)
                     if not any(np.array_equal(c, a) for a in alphas)]
            cols = [w * blocks(basis.damping_column(c[0] + 1j * c[1])[0]) for c in cands]
            k = int(np.argmax([sel.gain(col) for col in cols]))
            alphas.append(cands[k])
            sel.add(cols[k])

    def pick_residual():
        # shared orders: one group of columns (the term in every cycle) per candidate order
        groups = [range(lay.C)] if lay.shared else [[c] for c in range(lay.C)]
        for cycles in groups:
            cols = np.stack([w[:, None] * blocks(basis.residual_columns(c, grid)[0]) for c in cycles], axis=2)
            cols = cols[:, :, 0] if cols.shape[2] == 1 else cols
            free = np.ones(len(grid), bool)
            for m in range(lay.M):
                gains = [sel.gain(cols[:, i]) if free[i] else -1.0 for i in range(len(grid))]
                k = int(np.argmax(gains))
                betas[list(cycles), m] = grid[k]
                free[k] = False
                sel.add(cols[:, k])

    for step in ((pick_residual, pick_damping) if residual_first else (pick_damping, pick_residual)):
        step()
    return np.concatenate([np.concatenate(alphas) if alphas else np.zeros(0),
                           betas[0] if lay.shared else betas.ravel()])


@dataclass
class _Slot:
    """One damping mode (alpha re, im) or one residual term (beta) and its grid."""

    sl: slice
    column: list[int]                          # design columns it moves (a shared order: one per cycle)
    grid: np.ndarray                           # (G, size) candidate values
    columns: Callable[[], np.ndarray]          # (rows, G, len(column)) weighted columns of the grid


def _slots(lay: Layout, basis: ModelBasis, w: np.ndarray, blocks: Callable, loading_time_s: float) -> list[_Slot]:
    out = []
    alpha_grid = np.array(alpha_candidates(loading_time_s))
    beta_grid = np.array(beta_candidates())
    for i in range(lay.N):
        out.append(_Slot(slice(2 * i, 2 * i + 2), [lay.column_of_nonlinear(2 * i)], alpha_grid,
                         lambda: w[:, None, None] * blocks(np.column_stack(
                             [basis.damping_column(a + 1j * b)[0] for a, b in alpha_grid]))[:, :, None]))
    parameter, column = lay.derivative_pairs
    for j in range(2 * lay.N, lay.n_nonlinear):
        moved = column[parameter == j]
        cycles = (moved - (lay.P + 1 + lay.N)) // lay.M
        out.append(_Slot(slice(j, j + 1), [int(k) for k in moved], beta_grid,
                         lambda cycles=cycles: np.stack(
                             [w[:, None] * blocks(basis.residual_columns(int(c), beta_grid[:, 0])[0])
                              for c in cycles], axis=2)))
    return out


def _scan(problem: SeparableProblem, theta: np.ndarray, slots: list[_Slot]):
    """Coordinate-wise global moves: each slot in turn goes to the grid value that
    lowers the SSE most with all others fixed (linear terms re-solved). Also returns,
    per slot, its best grid value far from where it is (at least two grid steps away)
    and that SSE: the other side of the landscape, for jumps followed by a refit.

    With the other columns fixed, the SSE of a candidate column c is
    |r|^2 - (q.r)^2/(q.q), q = c minus its projection on them, r the residual
    without it: one factorisation per slot, not per candidate (a shared order moves one
    column per cycle: the projection on the span of its q's)."""
    theta = theta.copy()
    design = problem.design(theta)
    y = problem.y
    best = problem.solve(theta).sse
    far = []
    for slot in slots:
        others = np.delete(design, slot.column, axis=1)
        Q = solve_linear(others, y).basis
        r = y - Q @ (Q.T @ y)
        cand = slot.columns()
        flat = cand.reshape(len(y), -1)
        sse = float(r @ r) - _explained((flat - Q @ (Q.T @ flat)).reshape(cand.shape), r)
        start = theta[slot.sl].copy()
        k = int(np.argmin(sse))
        if sse[k] < best:
            best = float(sse[k])
            theta[slot.sl] = slot.grid[k]
            design[:, slot.column] = cand[:, k]
        spacing = _grid_spacing(slot.grid)
        far_idx = [g for g in range(len(slot.grid)) if _distance(slot.grid[g], start, spacing) >= 2]
        if far_idx:
            g = min(far_idx, key=lambda i: sse[i])
            th = theta.copy()
            th[slot.sl] = slot.grid[g]
            far.append((float(sse[g]), th))
        else:
            far.append((np.inf, None))
    return theta, best, far


def _explained(q: np.ndarray, r: np.ndarray) -> np.ndarray:
    """Per candidate g, the squared norm of r's projection on the span of q[:, g, :]."""
    if q.shape[2] == 1:
        qq = np.einsum("ig,ig->g", q[:, :, 0], q[:, :, 0])
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(qq > 0, (q[:, :, 0].T @ r) ** 2 / qq, 0.0)
    out = np.empty(q.shape[1])
    for g in range(q.shape[1]):
        coef = solve_linear(q[:, g, :], r).coef
        fitted = q[:, g, :] @ coef
        out[g] = float(fitted @ fitted)
    return out


def _grid_spacing(grid: np.ndarray) -> float:
    g = np.asarray(grid, float)
    if g.shape[1] == 1:
        return float(np.min(np.diff(np.unique(g[:, 0]))))
    return float(np.min(np.diff(np.unique(np.log(g[:, 0])))))


def _distance(value, current, spacing: float) -> float:
    """Grid steps between two values of a slot (decay rates on a log scale; real vs
    oscillating counts as two steps)."""
    value, current = np.asarray(value, float), np.asarray(current, float)
    if len(value) == 1:
        return float(abs(value[0] - current[0]) / spacing)
    steps = abs(np.log(value[0]) - np.log(max(current[0], 1e-12))) / spacing
    return float(steps + (0 if (value[1] > 0) == (current[1] > 1e-3 * current[0]) else 2))


def _globalise(problem: SeparableProblem, fit, slots, lower, upper, ftol: float, rounds: int = 2):
    """Global moves the local refinement cannot make, kept while the SSE drops by more
    than a tenth of the noise variance. Local refinement stalls where a term sits in
    the wrong place (a term whose best amplitude is ~0 has no gradient in its rate or
    order; two coinciding terms sit on a ridge; a term can explain the wrong feature).
    Each round: the coordinate scan, then a short refit from each of the few most
    promising far jumps (a slot moved to the other side of its grid)."""
    for _ in range(rounds):
        noise_var = fit.sse / max(len(problem.y), 1)
        theta, sse, far = _scan(problem, fit.nonlinear, slots)
        starts = [theta] if sse < fit.sse - 0.1 * noise_var else []
        jumps = sorted((f for f in far if f[1] is not None), key=lambda f: f[0])
        starts += [th for _, th in jumps[:MAX_JUMPS]]
        best = fit
        for th in starts:
            refit = problem.fit(th, lower, upper, max_nfev=PROBE_NFEV, ftol=ftol, xtol=1e-6)
            if refit.sse < best.sse:
                best = refit
        if best.sse >= fit.sse - 0.1 * noise_var:
            break
        fit = problem.fit(best.nonlinear, lower, upper, max_nfev=FIT_NFEV, ftol=ftol, xtol=1e-6)
    return fit


def _layout(fd: PreparedRun, orders: Orders) -> Layout:
    return orders.layout(fd.n_residual_cycles)


class DecimatedProblem:
    """One structure's search problem on the run's block means (the decimated rows): alpha and
    beta searched, k, a, r solved exactly. What every start of the global search, and every
    structure the selection tries, is fitted on."""

    def __init__(self, fd: PreparedRun, orders: Orders, kin: "DecimatedProblem | None" = None):
        """kin: another structure's problem on the same run (its columns are reused when the
        cycles and elastic order agree)."""
        self.fd, self.orders = fd, orders
        self.lay = lay = _layout(fd, orders)
        self.lower, self.upper = nonlinear_bounds(orders, lay.C, fd.loading_time_s)
        if kin is not None and kin.lay.same_columns(lay):
            self.coarse = kin.coarse.with_layout(lay)
        else:
            self.coarse = fd.nodes.basis(fd.fit_rows, lay, fd.x_scale_mm, fd.fit_step_s)
        self.w = np.sqrt(fd.fit_count)[:, None]         # block means: weight sqrt(samples)
        self.blocks = fd.block_curvature.apply          # model at the rows -> model block means
        w, blocks, coarse = self.w, self.blocks, self.coarse
        self.problem = SeparableProblem(lambda th: w * blocks(coarse.design(th)),
                                        lambda th: w * blocks(coarse.design_derivatives(th)),
                                        lay.derivative_pairs[1], w[:, 0] * fd.fit_force, lay.combine,
                                        prefetch=coarse.design_derivatives)
        # stop when an iteration gains less than a tenth of the noise variance (the
        # weighted SSE is ~ rows x sigma^2): further progress is below what the data resolve
        self.ftol = 0.1 / len(self.problem.y)
        self._slots: list[_Slot] | None = None

    @property
    def slots(self) -> list[_Slot]:
        if self._slots is None:
            self._slots = _slots(self.lay, self.coarse, self.w[:, 0], self.blocks, self.fd.loading_time_s)
        return self._slots

    def greedy(self, residual_first: bool) -> np.ndarray:
        return greedy_start(self.coarse, self.w[:, 0], self.blocks, self.problem.y, self.orders,
                            self.fd.loading_time_s, residual_first)

    def probe(self, theta0: np.ndarray) -> SeparableFit:
        return self.problem.fit(theta0, self.lower, self.upper, max_nfev=PROBE_NFEV, ftol=self.ftol, xtol=1e-6)

    def refine(self, theta0: np.ndarray) -> tuple[SeparableFit, np.ndarray]:
        """The local fit continued, the global moves, the real modes: (fit, fixed nonlinear)."""
        problem, lower, upper, ftol = self.problem, self.lower, self.upper, self.ftol
        fit = problem.fit(theta0, lower, upper, max_nfev=FIT_NFEV, ftol=ftol, xtol=1e-6)
        fit = _globalise(problem, fit, self.slots, lower, upper, ftol)
        return self.real_modes(fit)

    def at(self, theta: np.ndarray) -> SeparableFit:
        """The problem at these alpha and beta, nothing searched (the linear parameters solved)."""
        theta = np.clip(np.asarray(theta, float), self.lower, self.upper)
        sol = self.problem.solve(theta)
        return SeparableFit(theta, sol.coef, sol.residual, 0, 1, "another fit's values, not searched")

    def local(self, theta0: np.ndarray, fixed: np.ndarray) -> SeparableFit:
        """The local fit alone (the ``fixed`` nonlinear parameters held at theta0), without global
        moves: a warm start's continuation."""
        if not fixed.any():
            return self.problem.fit(theta0, self.lower, self.upper, max_nfev=FIT_NFEV, ftol=self.ftol, xtol=1e-6)
        free = ~fixed
        sub, expand = _restricted(self.problem, fixed, np.asarray(theta0, float))
        fit = sub.fit(theta0[free], self.lower[free], self.upper[free], max_nfev=FIT_NFEV, ftol=self.ftol, xtol=1e-6)
        return SeparableFit(expand(fit.nonlinear), fit.linear, fit.residual, fit.nfev, fit.status, fit.message)

    def real_modes(self, fit: SeparableFit) -> tuple[SeparableFit, np.ndarray]:
        """The damping modes whose oscillation the data do not support made real: (fit, fixed)."""
        return _real_modes(self.problem, self.lay, fit, self.lower, self.upper, self.ftol)

    def jacobian(self, fit: SeparableFit, fixed: np.ndarray) -> np.ndarray:
        """Of the weighted residual in (k, a, r, the free alpha and beta), at the fit."""
        problem = self.problem
        g = problem.combine(problem.derivatives(fit.nonlinear) * fit.linear[problem.column_of])
        return np.hstack([problem.design(fit.nonlinear), g[:, ~fixed]])


def ranked_searches(search: DecimatedProblem, start: ModelParameters | None,
                    progress: Callable[[str, float], None] | None,
                    other_starts: Iterable[tuple[str, np.ndarray]] = ()):
    """The global search of alpha and beta on the decimated run, from each start in turn, best
    short probe first: yields (fit, fixed nonlinear, the starts' names, the lower and upper
    bounds, the evaluations so far). other_starts: (name, alpha and beta) tried too."""
    candidates: list[tuple[str, np.ndarray]] = list(other_starts)
    if start is not None:
        candidates.append(("paper three-step", search.lay.from_flat(start.to_vector())[1]))
    for name, residual_first in (("forward selection", False), ("forward selection, residual first", True)):
        candidates.append((name, search.greedy(residual_first)))
    probes = []
    for name, theta0 in candidates:
        probes.append((search.probe(theta0), name))
        if progress:
            progress(f"joint fit: start '{name}'", 0.5 + 0.1 * len(probes))
    for best, best_name in sorted(probes, key=lambda fr: fr[0].sse):
        fit, fixed = search.refine(best.nonlinear)
        yield (fit, fixed, [f"{n}{' (chosen)' if n == best_name else ''}" for _, n in probes],
               search.lower, search.upper, search.problem.nfev)


def search_start(fd: PreparedRun, orders: Orders, start: ModelParameters | None = None) -> ModelParameters:
    """The global search's best optimum as parameters, without the full-resolution steps: a
    start for a fit that continues on every sample (diagnosis' restarts)."""
    fit, *_ = next(ranked_searches(DecimatedProblem(fd, orders), start, None))
    return params_of(fd, _layout(fd, orders), fit)


def unpolished(fd: PreparedRun, lay: Layout, found: tuple) -> JointFit:
    """A search optimum (as ranked_searches yields it) as a joint fit, without identification's
    full-resolution steps: the analysis core has carried it to every sample (its residual is
    not known here: the core's fit replaces it)."""
    fit, fixed, starts, _, _, nfev = found
    return JointFit(params_of(fd, lay, fit), lay, fit.linear, fit.nonlinear, fixed, fd.contact_zero_N, False,
                    np.zeros((0, 0)), np.array([np.inf]), lay.n_linear + int(np.count_nonzero(~fixed)), nfev,
                    list(starts), fit.status, fit.message)


def params_of(fd: PreparedRun, lay: Layout, fit: SeparableFit) -> ModelParameters:
    """A search's optimum as the model's parameters."""
    return _template(fd, lay).with_vector(lay.to_flat(fit.linear, fit.nonlinear))


class JointSearch:
    """The global search, ranked by start, continued as far as it is asked: ``fit()`` polishes
    the best evaluable optimum (identification's answer), ``more(count)`` yields the next
    optima as parameters (other starts for the core's polish when the first leaves
    structure) without searching again."""

    def __init__(self, fd: PreparedRun, orders: Orders, start: ModelParameters | None,
                 progress: Callable[[str, float], None] | None = None, found: Iterable[tuple] = (),
                 kin: DecimatedProblem | None = None, other_starts: Iterable[tuple[str, np.ndarray]] = ()):
        """found: optima of this structure already searched (the structure selection's), tried
        before the ranked search's, which then runs only if asked for more (on kin's columns);
        other_starts: (name, alpha and beta) the ranked search probes too."""
        self.fd, self.lay, self.progress = fd, _layout(fd, orders), progress

        def search():                 # a generator: nothing is computed until it is asked for
            yield from ranked_searches(DecimatedProblem(fd, orders, kin), start, progress, other_starts)

        self._ranked = itertools.chain(found, search())

    def fit(self) -> JointFit:
        # the best start is continued; should its optimum be one the model cannot evaluate
        # (see evaluable), the next best start is, and so on
        first = None
        for fit, fixed, names, lower, upper, nfev in self._ranked:
            if self.progress:
                self.progress("joint fit: full-resolution polish", 0.8)
            jf = _polish(self.fd, self.lay, fit.linear, fit.nonlinear, fixed, lower, upper, nfev, names)
            first = first or jf
            if evaluable(self.fd, jf):
                return jf
        return first

    def more(self, count: int = 1):
        for _, (fit, *_) in zip(range(count), self._ranked):
            yield params_of(self.fd, self.lay, fit)


def joint_fit(fd: PreparedRun, orders: Orders, start: ModelParameters | None,
              progress: Callable[[str, float], None] | None = None) -> JointFit:
    return JointSearch(fd, orders, start, progress).fit()


#: Samples this many steps from a corner of the path are not in the evaluation check.
CORNER_STEPS = 2.0


def evaluable(fd: PreparedRun, jf: "JointFit", rows: np.ndarray | None = None) -> bool:
    """Does the model's own evaluation (foamlab.model.evaluate: the operators the simulator
    steps, ~1e-7 relative accuracy) reproduce the fit within a tenth of the noise, or of what
    the fit leaves where that is more? The fit's columns are exact, so it can find optima that
    cancel huge terms: two residual terms of one cycle at nearly the same order (near beta = -3
    the columns grow like t^4) with amplitudes +-1e5 whose difference is the force. No
    evaluation in finite precision reproduces such a model, and the simulator cannot run it.
    (On the real Bluehill file, 0.25 N from the model, every fit's evaluation differed by
    ~0.02 N rms: a tenth of its noise, 0.0014 N, rejected them all.)
    rows: those jf.residual is on (default fd.observed). The samples next to a corner of the path
    are left out: the model's causal evaluation cuts a corner between samples by up to a tenth of
    a step, 2.6 N at one sample of a causal-form run whose other samples agree within 0.004 N -
    a check on every sample rejected every search optimum of such runs (docs/analysis.md,
    "The evaluation check at the corners")."""
    rows = fd.observed if rows is None else rows
    keep = ~_near_corners(fd)[rows]
    rows, residual = rows[keep], jf.residual[keep]
    response = model_response(jf.params, fd)
    predicted = np.maximum(response.force, jf.contact_zero_N)[rows]
    fitted = fd.f[rows] - residual
    left = float(np.sqrt(np.mean(residual ** 2))) if np.all(np.isfinite(residual)) else 0.0
    tolerance = 0.1 * max(fd.noise_N, 1e-4 * float(np.ptp(fd.f)), left)
    return bool(np.sqrt(np.mean((predicted - fitted) ** 2)) <= tolerance)


def _near_corners(fd: PreparedRun) -> np.ndarray:
    """bool over the run's samples: within CORNER_STEPS sampling steps of a corner of the path."""
    near = np.zeros(len(fd.t), bool)
    for tc in fd.nodes.t[fd.nodes.corners]:
        near |= np.abs(fd.t - tc) <= CORNER_STEPS * fd.native_step_s
    return near


def _restricted(problem: SeparableProblem, fixed: np.ndarray, base: np.ndarray):
    """The same problem with the nonlinear parameters marked ``fixed`` held at ``base``."""
    free = ~fixed

    def expand(th):
        full = base.copy()
        full[free] = th
        return full

    sub = SeparableProblem(lambda th: problem.design(expand(th)),
                           lambda th: problem.derivatives(expand(th)),
                           problem.column_of, problem.y, lambda g: problem.combine(g)[:, free],
                           prefetch=(lambda th: problem.prefetch(expand(th))) if problem.prefetch else None)
    return sub, expand


def _real_modes(problem: SeparableProblem, lay: Layout, fit, lower, upper, ftol: float):
    """Make a damping mode real (Im alpha = 0, one parameter fewer) when the data do not
    support its oscillation by BIC: fixing it costs less than ln(rows) noise variances.

    A real mode's Im alpha = 0 sits on its bound, where the estimate is not regular (it
    wanders above zero and inflates the errors of a and Re alpha); choosing the order of
    the model there is the honest way to the efficient estimate. Modes are tried in
    order of Im/Re, the least oscillating first."""
    fixed = np.zeros(lay.n_nonlinear, bool)
    penalty = fit.sse / len(problem.y) * np.log(len(problem.y))
    al = fit.nonlinear[:2 * lay.N].reshape(lay.N, 2)
    for i in np.argsort(al[:, 1] / al[:, 0]):
        trial = fixed.copy()
        trial[2 * i + 1] = True
        base = fit.nonlinear.copy()
        base[trial] = 0.0
        sub, expand = _restricted(problem, trial, base)
        free = ~trial
        refit = sub.fit(base[free], lower[free], upper[free], max_nfev=PROBE_NFEV, ftol=ftol, xtol=1e-6)
        if refit.sse > fit.sse + penalty:
            break
        fixed = trial
        fit = SeparableFit(expand(refit.nonlinear), refit.linear, refit.residual, refit.nfev,
                           refit.status, refit.message)
    return fit, fixed


def _polish(fd: PreparedRun, lay: Layout, linear: np.ndarray, nonlinear: np.ndarray, fixed: np.ndarray,
            lower: np.ndarray, upper: np.ndarray, nfev: int, starts: list[str]) -> JointFit:
    full = fd.nodes.basis(fd.observed, lay, fd.x_scale_mm, fd.native_step_s)
    y = fd.f[fd.observed]
    free = ~fixed
    pair_cols = lay.derivative_pairs[1]
    L, K = lay.n_linear, int(free.sum())
    z0 = fd.contact_zero_N
    base = np.clip(nonlinear, lower, upper)
    # z0 is identifiable only if the model goes out of contact on enough samples
    censored = np.count_nonzero(full.force(linear, base) <= z0)
    fit_zero = censored >= MIN_CENSORED

    def unpack(p):
        nl = base.copy()
        nl[free] = p[L:L + K]
        return p[:L], nl, (p[L + K] if fit_zero else z0)

    def fun(p):
        lin, nl, zero = unpack(p)
        full.design_derivatives(nl)         # the column cache filled for the Jacobian that follows
        return np.maximum(full.force(lin, nl), zero) - y

    def jac(p):
        lin, nl, zero = unpack(p)
        design = full.design(nl)
        out = np.empty((len(y), L + K + int(fit_zero)))
        out[:, :L] = design
        out[:, L:L + K] = lay.combine(full.design_derivatives(nl) * lin[pair_cols])[:, free]
        off = (design @ lin) <= zero
        out[off, :L + K] = 0.0
        if fit_zero:
            out[:, -1] = off.astype(float)
        return out

    p0 = np.concatenate([linear, base[free]] + ([[z0]] if fit_zero else []))
    lo = np.concatenate([np.full(L, -np.inf), lower[free]] + ([[-np.inf]] if fit_zero else []))
    hi = np.concatenate([np.full(L, np.inf), upper[free]] + ([[np.inf]] if fit_zero else []))
    res = trust_region(fun, p0, jac, lo, hi, max_nfev=POLISH_NFEV, ftol=1e-10, xtol=1e-10, gtol=1e-12)
    lin, nl, zero = unpack(res.x)
    # the canonical order (modes by decay rate, terms by order) permutes parameters;
    # the Jacobian at the solution comes from the solver, its columns permuted alike
    perm = lay.canonical_permutation(lin, nl)
    nl_perm = perm[L:] - L
    jac_col = np.full(L + lay.n_nonlinear, -1)           # full index -> solver column
    jac_col[:L] = np.arange(L)
    jac_col[L + np.flatnonzero(free)] = L + np.arange(K)
    keep = [jac_col[f] for f in perm if jac_col[f] >= 0] + ([L + K] if fit_zero else [])
    jacobian = np.asarray(res.jac)[:, keep]
    lin, nl, fixed = lin[perm[:L]], nl[nl_perm], fixed[nl_perm]
    params = _template(fd, lay).with_vector(lay.to_flat(lin, nl))
    return JointFit(params, lay, lin, nl, fixed, float(zero), fit_zero, jacobian, -np.asarray(res.fun),
                    len(res.x), nfev + int(res.nfev), starts, int(res.status), str(res.message))


def _template(fd: PreparedRun, lay: Layout) -> ModelParameters:
    return ModelParameters(
        x_scale_mm=fd.x_scale_mm, elastic_k=np.zeros(lay.P + 1), damping_a=np.zeros(lay.N),
        damping_alpha=np.zeros(lay.N, complex), residual_r=np.zeros((lay.C, lay.M)),
        residual_beta=np.zeros((lay.C, lay.M)), residual_form=lay.form, shared_orders=lay.shared,
        description=f"identified by foamlab fit from {fd.run.source or 'a run'}")
