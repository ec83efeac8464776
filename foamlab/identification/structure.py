"""The model structure the data determine (issue 19; docs/identification.md, "Structure").

The largest structure (by default 3 damping modes, 3 residual terms, 3 cycles with orders of
their own) is searched once, globally. Smaller ones are made from it by moves, each removing what
the data do not determine: the orders shared by every cycle (one beta per term, each cycle its
own amplitudes: the paper's Table 3 finds nearly the same orders in its three cycles), a damping
mode less, a residual term less, a cycle fewer with terms of its own. Each is refitted from the
larger one's values on the search's block means (a warm start: cheap), then scored by the
analysis core on the decimated run: RMSE, held-out RMSE (analysis.heldout, as diagnosis predicts), BIC.

A structure is admissible when no two of its terms cancel (two amplitudes of large opposite
value whose sum is small: a derivative of the model's terms in their order, not two terms of the
model) and the data determine every one of its parameters. The choice is the admissible structure
with the lowest BIC, or the one with the fewest parameters among those within BIC_TIE of it. The
moves are greedy: from the current structure, every move is tried and the best one taken while
it is better (admissible where the current one is not; else no worse than BIC_TIE).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import Callable

import numpy as np

from foamlab.analysis.design import ExtendedModel, Series
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import Fit, base_bounds, decimation
from foamlab.analysis.heldout import heldout_rmse
from foamlab.identification.joint import DecimatedProblem, params_of, ranked_searches
from foamlab.identification.statistics import information_criteria, parameter_uncertainty
from foamlab.identification.varpro import SeparableFit
from foamlab.model import ModelParameters
from foamlab.model.layout import Layout, Orders

#: Two amplitude terms cancel when their summed contribution is below this share of the larger
#: one's (measured: the default specimen's opposite-signed terms at beta -0.1 and 0.4 sum to 70 %
#: of the larger; cancelling pairs on the real Bluehill file to 0.1-5 %).
CANCEL_RATIO = 0.2
#: A structure with fewer parameters is preferred unless a larger one's BIC is lower by more than
#: this ("very strong" evidence, as diagnosis' DELTA_BIC_MIN).
BIC_TIE = 10.0
#: At most this many structures are fitted (the largest included).
MAX_CANDIDATES = 12


@dataclass(frozen=True)
class Candidate:
    """One structure tried: how it was made, its scores on the decimated run, its defects."""

    orders: Orders
    how: str                          # the move that made it ("the largest", "orders shared", ...)
    n_params: int                     # free parameters (the load cell's zero included)
    rmse: float                       # N, on the decimated run (the core's samples)
    heldout_rmse: float               # N, blocks predicted by the model fitted without them
    bic: float                        # Gaussian, on the decimated run's samples
    defects: tuple[str, ...] = ()     # why it is not admissible (cancelling terms, undetermined)

    @property
    def admissible(self) -> bool:
        return not self.defects

    def to_dict(self) -> dict:
        return {"orders": str(self.orders), "how": self.how, "n_params": self.n_params,
                "rmse": self.rmse, "heldout_rmse": self.heldout_rmse, "bic": self.bic,
                "defects": list(self.defects)}


@dataclass
class StructureChoice:
    """The structures tried and the one chosen, with why (forced: given by the caller)."""

    chosen: Orders
    why: str
    candidates: list[Candidate] = field(default_factory=list)
    forced: bool = False

    def to_dict(self) -> dict:
        return {"chosen": str(self.chosen), "forced": self.forced, "why": self.why,
                "candidates": [c.to_dict() for c in self.candidates]}

    def lines(self) -> list[str]:
        """The candidates as table rows (the chosen one marked)."""
        out = [f"    {'orders':<36}{'params':>7}{'RMSE':>9}{'held out':>10}{'BIC':>12}  how / defects"]
        for c in self.candidates:
            mark = "  <- chosen" if c.orders == self.chosen else ""
            note = c.how + (f"; {'; '.join(c.defects)}" if c.defects else "")
            out.append(f"    {str(c.orders):<36}{c.n_params:>7d}{c.rmse:>9.4g}{c.heldout_rmse:>10.4g}"
                       f"{c.bic:>12.1f}  {note}{mark}")
        return out


@dataclass
class _Trial:
    """A structure fitted on the search's block means, and its candidate."""

    problem: DecimatedProblem
    fit: SeparableFit
    fixed: np.ndarray
    candidate: Candidate
    weak: list[int]                   # amplitude columns by what to drop first (defective, smallest)
    starts: list[str]

    @property
    def lay(self) -> Layout:
        return self.problem.lay


def forced(orders: Orders) -> StructureChoice:
    return StructureChoice(orders, "given (--orders): no selection", forced=True)


def select_structure(fd: PreparedRun, largest: Orders, start: ModelParameters | None,
                     progress: Callable[[str, float], None] | None = None
                     ) -> tuple[StructureChoice, tuple, DecimatedProblem]:
    """Choose the structure (module docstring). Returns the choice, the chosen structure's
    optimum as the joint search yields it (a start for its polish) and its search problem."""
    big = DecimatedProblem(fd, largest)
    fit, fixed, names, *_ = next(ranked_searches(big, start, progress))
    scorer = _Scorer(fd)
    current = scorer.trial(big, fit, fixed, "the largest (global search)", names)
    tried = {largest: current}
    while len(tried) < MAX_CANDIDATES:
        if progress:
            progress(f"structure: from {current.candidate.orders}", 0.6)
        moves = [m for m in _moves(current) if m[0] not in tried][:MAX_CANDIDATES - len(tried)]
        if not moves:
            break
        trials = []
        for orders, theta0, how in moves:
            problem = DecimatedProblem(fd, orders, kin=current.problem)
            refit, refixed = problem.refine_locally(theta0)
            trials.append(scorer.trial(problem, refit, refixed, how, current.starts))
        tried.update((t.candidate.orders, t) for t in trials)
        best = min(trials, key=lambda t: _rank(t.candidate))
        if not _replaces(best.candidate, current.candidate):
            break
        current = best
    chosen, why = _choose([t.candidate for t in tried.values()])
    trial = tried[chosen]
    found = (trial.fit, trial.fixed, trial.starts, trial.problem.lower, trial.problem.upper,
             trial.problem.problem.nfev)
    return StructureChoice(chosen, why, [t.candidate for t in tried.values()]), found, trial.problem


def _rank(c: Candidate) -> tuple:
    """Best first: admissible, then fewer defects, then lower BIC."""
    return (not c.admissible, len(c.defects), c.bic)


def _replaces(smaller: Candidate, current: Candidate) -> bool:
    """Does a structure made by one move from the current one take its place?"""
    if smaller.admissible != current.admissible:
        return smaller.admissible
    if not smaller.admissible:
        return (len(smaller.defects), smaller.bic) < (len(current.defects), current.bic)
    return smaller.bic <= current.bic + BIC_TIE


def _choose(candidates: list[Candidate]) -> tuple[Orders, str]:
    admissible = [c for c in candidates if c.admissible]
    if not admissible:
        best = min(candidates, key=_rank)
        return best.orders, (f"no structure tried is free of defects; the fewest ({len(best.defects)}), "
                             "then the lowest BIC")
    low = min(c.bic for c in admissible)
    tied = [c for c in admissible if c.bic <= low + BIC_TIE]
    best = min(tied, key=lambda c: (c.n_params, c.bic))
    why = "the lowest BIC of the structures whose terms the data determine and none cancel"
    if best.bic > low:
        why = (f"the fewest parameters of the admissible structures within {BIC_TIE:g} of the lowest BIC "
               "(terms determined, none cancelling)")
    return best.orders, why


# ----------------------------------------------------------------------------- moves

def _moves(trial: _Trial) -> list[tuple[Orders, np.ndarray, str]]:
    """(orders, warm start of alpha and beta, how) of each structure one move smaller."""
    lay, theta = trial.lay, trial.fit.nonlinear
    orders = lay.orders
    p1, N, M, C = lay.P + 1, lay.N, lay.M, lay.C
    alphas, betas = theta[:2 * N].reshape(N, 2), theta[2 * N:]
    out = []
    if not lay.shared and C > 1:
        # the first cycle's orders for all: its terms are the largest, the best determined
        out.append((replace(orders, shared=True), np.concatenate([alphas.ravel(), betas[:M]]),
                    "orders shared by every cycle"))
    modes = [j - p1 for j in trial.weak if p1 <= j < p1 + N]
    if modes:
        out.append((replace(orders, N=N - 1), np.concatenate([np.delete(alphas, modes[0], 0).ravel(), betas]),
                    f"damping mode {modes[0] + 1} dropped"))
    terms = [j - p1 - N for j in trial.weak if j >= p1 + N]
    if M > 1 and terms:
        if lay.shared:
            m = terms[0] % M
            out.append((replace(orders, M=M - 1), np.concatenate([alphas.ravel(), np.delete(betas, m)]),
                        f"residual term {m + 1} dropped"))
        else:   # each cycle its weakest term
            drop = [next(t for t in terms if t // M == c) for c in range(C)]
            out.append((replace(orders, M=M - 1), np.concatenate([alphas.ravel(), np.delete(betas, drop)]),
                        "each cycle's weakest residual term dropped"))
    if C > 1:
        kept = betas if lay.shared else betas[:(C - 1) * M]
        out.append((replace(orders, C=C - 1), np.concatenate([alphas.ravel(), kept]),
                    f"cycles from {C - 1} on share the terms of cycle {C - 1}"))
    return out


# ----------------------------------------------------------------------------- scores

class _Scorer:
    """Each structure's scores by the analysis core on the decimated run (the samples
    diagnosis searches on): the linear parameters and the contact set solved for the
    structure's alpha and beta, the held-out blocks as diagnosis predicts them."""

    def __init__(self, fd: PreparedRun):
        self.fd = fd
        self.series: list[Series] = [fd.series.decimated(decimation([fd.series]))]

    def trial(self, problem: DecimatedProblem, fit: SeparableFit, fixed: np.ndarray, how: str,
              starts: list[str]) -> _Trial:
        params = params_of(self.fd, problem.lay, fit)
        model = ExtendedModel(self.series, params, [], free_base=True,
                              base_bounds=base_bounds(self.series, params))
        nu = model.start()
        core = Fit([], model, nu, np.zeros(0), model.solve(nu))
        n_params = problem.lay.n_linear + int(np.count_nonzero(~fixed)) + 1
        _, bic = information_criteria(core.rss, core.n, n_params)
        defects, weak = _defects(problem, fit, fixed)
        candidate = Candidate(problem.lay.orders, how, n_params, core.rmse, heldout_rmse(core), bic,
                              tuple(defects))
        return _Trial(problem, fit, fixed, candidate, weak, list(starts))


def _defects(problem: DecimatedProblem, fit: SeparableFit, fixed: np.ndarray) -> tuple[list[str], list[int]]:
    """What makes the structure inadmissible, and its amplitude columns by what to drop first:
    those of defective terms (undetermined, cancelling), then by the size of their contribution."""
    lay = problem.lay
    names = np.array(_design_names(lay) + [n for n, f in zip(_nonlinear_names(lay), fixed) if not f])
    jac = problem.jacobian(fit, fixed)
    values = np.concatenate([fit.linear, fit.nonlinear[~fixed]])
    lower, upper = problem.lower[~fixed], problem.upper[~fixed]
    ranges = np.concatenate([np.full(lay.n_linear, np.inf), upper - lower])
    unc = parameter_uncertainty(jac, fit.residual, values, list(names), ranges=ranges)
    p1 = lay.P + 1
    term_of = _term_of_columns(lay, fixed)                  # Jacobian column -> amplitude column
    bad = {int(term_of[i]) for i in np.flatnonzero(~unc.determined) if term_of[i] >= p1}
    defects = [f"{n} not determined" for n in names[~unc.determined]]
    design = problem.problem.design(fit.nonlinear)
    parts = design * fit.linear[None, :]
    size = np.linalg.norm(parts, axis=0)
    groups = [range(p1, p1 + lay.N), range(p1 + lay.N, lay.n_linear)]
    for group in groups:
        for i, j in itertools.combinations(group, 2):
            if min(size[i], size[j]) > 0 and np.linalg.norm(parts[:, i] + parts[:, j]) < CANCEL_RATIO * max(size[i], size[j]):
                defects.append(f"{names[i]} = {fit.linear[i]:.4g} and {names[j]} = {fit.linear[j]:.4g} cancel")
                bad.update((i, j))
    weak = sorted(range(p1, lay.n_linear), key=lambda j: (j not in bad, size[j]))
    return defects, weak


def _design_names(lay: Layout) -> list[str]:
    names = [f"k{i}" for i in range(lay.P + 1)] + [f"a{i + 1}" for i in range(lay.N)]
    return names + [f"r{c + 1}_{m + 1}" for c in range(lay.C) for m in range(lay.M)]


def _nonlinear_names(lay: Layout) -> list[str]:
    names = [f"alpha{i + 1}_{part}" for i in range(lay.N) for part in ("re", "im")]
    if lay.shared:
        return names + [f"beta{m + 1}" for m in range(lay.M)]
    return names + [f"beta{c + 1}_{m + 1}" for c in range(lay.C) for m in range(lay.M)]


def _term_of_columns(lay: Layout, fixed: np.ndarray) -> np.ndarray:
    """For each Jacobian column (linear, then free nonlinear): the amplitude column of its term
    (a shared order: its term's column in the first cycle; -1 for none)."""
    linear = np.arange(lay.n_linear)
    nonlinear = np.array([lay.column_of_nonlinear(j) for j in range(lay.n_nonlinear)])[~fixed]
    out = np.concatenate([linear, nonlinear])
    out[:lay.P + 1] = -1
    return out
