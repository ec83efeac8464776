"""The model structure the data determine (issue 19; docs/identification.md, "Structure").

Structures are made from the largest (by default 3 damping modes, 3 residual terms, 3 cycles with
orders of their own) by moves, each removing something: the orders shared by every cycle (one
beta per term, each cycle its own amplitudes: the paper's Table 3 finds nearly the same orders in
its three cycles), a damping mode less, a residual term less, a cycle fewer with terms of its own.

1. The largest is fitted as a given structure is (global search, the analysis core's polish on
   every sample with identification's other starts).
2. Screening (``screen``): from that fit's values, every move is refitted on the search's block
   means (a warm start: cheap) and scored by the analysis core on the decimated run: RMSE,
   held-out RMSE (analysis.heldout, as diagnosis predicts), BIC. The best move is taken while it
   costs at most BIC_TIE (fewer parameters at no real cost); the screening's choice is the lowest
   BIC, or the fewest parameters within BIC_TIE of it.
3. The screening's choice is fitted on every sample. A fit is admissible when the data determine
   every one of its parameters and no two of its terms cancel (two amplitudes of large opposite
   value whose sum is small: a derivative of the model's terms in their order, not two terms of
   the model) or are one term seen twice (amplitudes correlated beyond TWIN_CORRELATION). While
   the fit is not, the structures that remove its defects are fitted (one move smaller: shared
   orders for a later cycle's, a damping mode or a residual term less for theirs; the same
   structure from another start when it is only a local optimum), at most MAX_FITTED in all; the
   smallest structure when none is admissible.
4. The result: the admissible fit with the lowest BIC, or the one with the fewest parameters
   within BIC_TIE of it; else the one with the fewest defects.

Only the fits on every sample judge admissibility: the search's optima are rougher (on the
simulated main job the search's optimum of the right structure had two terms of nearly one order
and a damping mode it could not place; the fit on every sample, from another start, had neither).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field, replace
from typing import Callable, Iterator

import numpy as np

from foamlab.analysis.design import Series
from foamlab.analysis.heldout import heldout_rmse
from foamlab.analysis.noise import at_the_noise
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import Fit, decimation, solved_at
from foamlab.identification.forms import heldout_of
from foamlab.identification.joint import AT_BOUND, REAL_MODE_RATIO, DecimatedProblem, JointFit, params_of, ranked_searches
from foamlab.identification.paper import paper_steps
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
#: The defect of a fit the model's own evaluation does not reproduce (joint.evaluable: terms at
#: extreme orders, beta near -3, are beyond the evaluation's operators; the simulator would run
#: another model).
NOT_REPRODUCED = "the model's own evaluation does not reproduce it"
#: With no admissible fit, the fits predicting held-out blocks within this factor of the best compete.
HELDOUT_NEAR = 1.1
#: A fit with every parameter determined is preferred to better-scoring ones with parameters the data
#: do not determine while it predicts held-out blocks within this factor of the best admissible fit.
HELDOUT_DETERMINED = 1.02
#: At most this many structures are screened (the largest included), and fitted on every sample.
MAX_SCREENED, MAX_FITTED = 10, 5
#: Two amplitudes of one component correlated beyond this are one term the data see twice (the
#: main job's fits: 0.997 between one term's amplitudes in consecutive cycles; 1.0000 where two
#: terms of nearly one order share what one of them would do).
TWIN_CORRELATION = 0.999


@dataclass(frozen=True)
class Candidate:
    """One structure tried: how it was made, its scores, its defects (fits on every sample only)."""

    orders: Orders
    how: str                          # the move that made it ("the largest", "orders shared", ...)
    stage: str                        # "screened" (search, decimated run) or "fitted" (every sample)
    n_params: int                     # free parameters (the load cell's zero included)
    rmse: float                       # N
    heldout_rmse: float               # N, blocks predicted by the model fitted without them
    bic: float
    defects: tuple[str, ...] = ()     # why a fit is not admissible (undetermined, cancelling)
    at_noise: bool = False            # what it leaves is the noise (analysis.noise.at_the_noise)

    @property
    def admissible(self) -> bool:
        """A fit on every sample with no large amplitudes that cancel, no term seen twice."""
        return self.stage == "fitted" and not any(_degenerating(d) for d in self.defects)

    @property
    def undetermined(self) -> int:
        """Its other defects: parameters the data do not determine, rates or orders at a bound, weak
        terms offsetting each other."""
        return sum(not _degenerating(d) for d in self.defects)

    def to_dict(self) -> dict:
        return {"orders": str(self.orders), "how": self.how, "stage": self.stage, "n_params": self.n_params,
                "rmse": self.rmse, "heldout_rmse": self.heldout_rmse, "bic": self.bic,
                "defects": list(self.defects)}


@dataclass
class StructureChoice:
    """The structures tried and the one chosen, with why (forced: given by the caller)."""

    chosen: Orders
    why: str
    candidates: list[Candidate] = field(default_factory=list)
    forced: bool = False
    taken: int = -1                   # the candidate whose fit is the result (-1: given, none tried)

    def to_dict(self) -> dict:
        return {"chosen": str(self.chosen), "forced": self.forced, "why": self.why,
                "candidates": [dict(c.to_dict(), chosen=i == self.taken) for i, c in enumerate(self.candidates)]}

    def lines(self) -> list[str]:
        """The candidates as table rows (the chosen one marked)."""
        out = [f"    {'orders':<50}{'stage':>9}{'params':>7}{'RMSE':>9}{'held out':>10}{'BIC':>12}  how; defects"]
        for i, c in enumerate(self.candidates):
            mark = "  <- chosen" if i == self.taken else ""
            note = c.how + (f"; {'; '.join(c.defects)}" if c.defects else "")
            out.append(f"    {str(c.orders):<50}{c.stage:>9}{c.n_params:>7d}{c.rmse:>9.4g}{c.heldout_rmse:>10.4g}"
                       f"{c.bic:>12.1f}  {note}{mark}")
        return out


def forced(orders: Orders) -> StructureChoice:
    return StructureChoice(orders, "given (--orders): no selection", forced=True)


@dataclass
class _Trial:
    """A structure fitted on the search's block means, and its candidate."""

    problem: DecimatedProblem
    fit: SeparableFit
    fixed: np.ndarray
    candidate: Candidate
    starts: list[str]

    @property
    def lay(self) -> Layout:
        return self.problem.lay

    def found(self) -> tuple:
        """The optimum as the joint search yields it (a start for the fit on every sample)."""
        p = self.problem
        return self.fit, self.fixed, self.starts, p.lower, p.upper, p.problem.nfev

    def by_size(self) -> list[int]:
        """Its amplitude columns, the smallest contribution (on the block means) first."""
        return _by_size(self.lay, self.problem.problem.design(self.fit.nonlinear) * self.fit.linear[None, :])


@dataclass
class _Fitted:
    """A structure fitted by the analysis core on every sample, judged."""

    joint: JointFit                   # identification's fit it continues (the search's optimum, polished or not)
    core: Fit                         # the core's fit on every sample
    candidate: Candidate
    weak: list[int]                   # amplitude columns by what to drop first
    optima: Iterator[tuple] = field(default_factory=lambda: iter(()), repr=False)   # its other starts

    @property
    def orders(self) -> Orders:
        return self.candidate.orders


@dataclass
class Selection:
    """The structures screened and fitted; which fit to take, in order of preference."""

    screened: list[Candidate]
    fitted: list[_Fitted]             # the screening's choice first, then the repairs
    kin: DecimatedProblem             # a search problem whose columns others reuse

    def choice(self) -> StructureChoice:
        """The fit chosen (module docstring), and why."""
        judged = [f.candidate for f in self.fitted]
        taken, why = _conclude(judged)
        return StructureChoice(judged[taken].orders, why, self.screened + judged, taken=len(self.screened) + taken)

    @property
    def chosen(self) -> "_Fitted":
        return self.fitted[_conclude([f.candidate for f in self.fitted])[0]]


@dataclass(frozen=True)
class Move:
    """A structure one move smaller and where its search starts."""

    orders: Orders
    start: np.ndarray                 # alpha and beta (the larger structure's, what remains)
    fixed: np.ndarray                 # held there (a real damping mode stays real)
    how: str


#: A structure fitted as identification fits it: (structure, its search's optima in order, whether
#: as a given structure is fitted - identification's full-resolution steps and its other starts -
#: or from the first optimum alone) -> (identification's joint fit, the core's fit on every sample),
#: None when no optimum is left.
CoreFit = Callable[[Orders, Iterator[tuple], bool], "tuple[JointFit, Fit] | None"]


def select(fd: PreparedRun, largest: Orders, start: ModelParameters | None, core_fit: CoreFit,
           reproduced: Callable[[JointFit, Fit], bool], progress: Callable[[str, float], None] | None = None
           ) -> Selection:
    """The largest fitted, the screening from its fit, the screening's choice fitted and repaired
    (module docstring). reproduced: does the model's own evaluation (what the simulator runs)
    reproduce a fit? Asked of fits without other degenerating defects (it costs an evaluation)."""
    big = DecimatedProblem(fd, largest)

    def fitted(orders: Orders, optima: Iterator[tuple], how: str, extra: bool) -> _Fitted | None:
        """The structure's next search optimum fitted (core_fit), judged; its remaining optima
        kept for a restart. None when no optimum is left."""
        out = core_fit(orders, optima, extra)
        if out is None:
            return None
        joint, core = out
        defects, weak = core_defects(core)
        if not any(_degenerating(d) for d in defects) and not reproduced(joint, core):
            defects.append(NOT_REPRODUCED)
        heldout = heldout_of(core)
        _, bic = information_criteria(core.rss, core.n, _n_params(core))
        return _Fitted(joint, core, Candidate(orders, how, "fitted", _n_params(core), core.rmse, heldout, bic,
                                              tuple(defects), at_the_noise(core.solution.residual, fd.noise_N)),
                       weak, optima)

    def optima(orders: Orders, *first: tuple, warm: Move | None = None) -> Iterator[tuple]:
        """A structure's starts: the given optima, a warm start (a larger fit's values, as they are:
        the core's polish moves them), then, asked for more, its global search's optima."""
        problem = DecimatedProblem(fd, orders, big) if orders != largest else big
        if warm is not None:
            first += ((problem.at(warm.start), warm.fixed, ["the larger fit's values"], problem.lower,
                       problem.upper, 0),)
        return itertools.chain(first, ranked_searches(problem, _start_of(fd, orders, largest, start), None))

    done = [fitted(largest, ranked_searches(big, start, progress), "the largest (global search)", True)]
    screened, choice = screen(fd, done[0], big, progress)
    if choice.candidate.orders != largest:
        done.append(fitted(choice.candidate.orders, optima(choice.candidate.orders, choice.found()),
                           "the screening's choice", False))
    current = done[-1]
    while current.candidate.defects and len(done) < MAX_FITTED:
        if progress:
            progress(f"structure: repairing {current.candidate.orders}", 0.7)
        trials = []
        if _degenerate(current.candidate):           # a local optimum: the same structure, another start
            trials.append(fitted(current.orders, current.optima, "the same, from another start", False))
        # smaller structures, unless the restart is admissible and the screening found them worse
        # by more than BIC_TIE (they would not be chosen)
        restarted = trials[0] if trials and trials[0] is not None and trials[0].candidate.admissible else None
        bic = {c.orders: c.bic for c in screened}
        for move in _repairs(current):
            if restarted and bic.get(move.orders, -np.inf) > bic.get(current.orders, np.inf) + BIC_TIE:
                continue
            if len(done) + len(trials) < MAX_FITTED and move.orders not in {f.orders for f in done + trials if f}:
                trials.append(fitted(move.orders, optima(move.orders, warm=move), move.how, False))
        trials = [t for t in trials if t is not None]
        if not trials:
            break
        done += trials
        current = min(trials, key=lambda f: (not f.candidate.admissible, len(f.candidate.defects), f.candidate.bic))
    # none admissible: the best fit's structure without any of its defective damping modes and
    # with a residual term less (the moves one at a time ran out), then the smallest (one damping
    # mode, one residual term, orders shared), whose terms real data determine where larger cancel
    best = min(done, key=lambda f: f.candidate.bic)
    for move in ([_pruned(best)] if best.candidate.defects else []) + [None]:
        if any(f.candidate.admissible for f in done):
            break
        orders = move.orders if move else replace(largest, N=min(largest.N, 1), M=min(largest.M, 1), shared=True)
        if orders not in {f.orders for f in done}:
            done.append(fitted(orders, optima(orders, warm=move), move.how if move else "the smallest (global search)",
                               move is None))
    return Selection(screened, done, big)


def _pruned(fitted: _Fitted) -> Move:
    """The structure of a fit without any of its defective damping modes (one kept) and, if one
    of its residual terms is defective, with a term less; from its values."""
    core = fitted.core
    lay = core.params.layout
    nonlinear = core.model.split(core.nu)[0]
    named = [d.split(" ", 1)[0] for d in fitted.candidate.defects]
    bad_modes = {_column_of_name(lay, n) - lay.P - 1 for n in named if n.startswith(("a", "alpha"))}
    for d in fitted.candidate.defects:              # the modes of cancelling or twin amplitudes
        for n in d.replace(",", " ").split():
            if n[:1] == "a" and n[1:].isdigit():
                bad_modes.add(int(n[1:]) - 1)
    keep = np.array([i not in bad_modes for i in range(lay.N)], dtype=bool)
    if lay.N and not keep.any():
        keep[max(range(lay.N), key=lambda i: fitted.weak.index(lay.P + 1 + i))] = True   # the strongest
    residual = any(n.startswith(("r", "beta")) for n in named) or any(" r" in d for d in fitted.candidate.defects)
    alphas, betas = nonlinear[:2 * lay.N].reshape(lay.N, 2), nonlinear[2 * lay.N:]
    M = lay.M - 1 if residual and lay.M > 1 else lay.M
    if M < lay.M:        # the weakest term (of every cycle, unless orders are shared)
        drop = _moves(lay, nonlinear, _real(lay, nonlinear), fitted.weak)
        betas = next(m.start[2 * lay.N:] for m in drop if m.orders.M < lay.M)
    orders = replace(lay.orders, N=int(keep.sum()), M=M)
    real = _real(lay, nonlinear)[:2 * lay.N].reshape(lay.N, 2)
    return Move(orders, np.concatenate([alphas[keep].ravel(), betas]),
                np.concatenate([real[keep].ravel(), np.zeros(len(betas), bool)]),
                "without its defective damping modes and a residual term")



def _degenerate(c: Candidate) -> bool:
    """Defects of a local optimum the same structure can leave: terms that cancel or that the data
    cannot tell apart (two terms of nearly one order)."""
    return any(_degenerating(d) for d in c.defects)


def _degenerating(defect: str) -> bool:
    return defect.endswith(" cancel") or "not told apart" in defect or defect == NOT_REPRODUCED


def _start_of(fd: PreparedRun, orders: Orders, largest: Orders, start: ModelParameters | None):
    """The paper's three-step start of a structure (the largest's is given)."""
    return start if orders == largest else paper_steps(fd, orders).start


def _conclude(judged: list[Candidate]) -> tuple[int, str]:
    """The fit chosen (module docstring) and why."""
    admissible = [i for i, c in enumerate(judged) if c.admissible]
    at_noise = [i for i, c in enumerate(judged) if c.at_noise]
    if at_noise:
        best = min(at_noise, key=lambda i: judged[i].bic)
        if not any(judged[i].bic <= judged[best].bic + BIC_TIE for i in admissible):
            # the data are fitted to the noise, but not without cancelling terms: the search did
            # not find such a structure's clean optimum (the independent generator's runs have
            # one); the fit at the noise is kept, its defects said
            return best, ("only fits whose terms cancel reach the noise (no start found one without): "
                          f"the lowest BIC of those ({'; '.join(judged[best].defects)})")
    if not admissible:
        # a structure without defects that predicts far worse is no answer either (the real
        # Bluehill file: the smallest 0.79 N against the largest's 0.20 N): of the fits that predict
        # held-out blocks within HELDOUT_NEAR of the best, the fewest defects
        fitted = [i for i, c in enumerate(judged) if c.stage == "fitted"] or list(range(len(judged)))
        good = min(judged[i].heldout_rmse for i in fitted)
        near = [i for i in fitted if judged[i].heldout_rmse <= HELDOUT_NEAR * good]
        best = min(near, key=lambda i: (len(judged[i].defects), judged[i].bic))
        return best, (f"no structure fitted is free of cancelling terms: of those predicting held-out blocks "
                      f"within {HELDOUT_NEAR - 1:.0%} of the best, the fewest defects ({len(judged[best].defects)})")
    # a fit whose every parameter is determined, predicting held-out blocks nearly as well as the
    # best, is the answer: a parameter the data do not determine is no result to report (the main
    # job's second damping mode: Delta BIC 23, held-out RMSE 0.1 % lower, its rate undetermined)
    good = min(judged[i].heldout_rmse for i in admissible)
    determined = [i for i in admissible
                  if not judged[i].undetermined and judged[i].heldout_rmse <= HELDOUT_DETERMINED * good]
    pool = determined or admissible
    low = min(judged[i].bic for i in pool)
    tied = [i for i in pool if judged[i].bic <= low + BIC_TIE]
    best = min(tied, key=lambda i: (judged[i].undetermined, judged[i].n_params, judged[i].bic))
    why = (f"no terms cancel, every parameter determined, held-out RMSE within {HELDOUT_DETERMINED - 1:.0%} "
           f"of the best; of those, within {BIC_TIE:g} of the lowest BIC, the fewest parameters" if determined else
           f"no terms cancel; of those, within {BIC_TIE:g} of the lowest BIC, the fewest parameters "
           "the data do not determine, then the fewest parameters")
    if judged[best].undetermined:
        why += f" ({'; '.join(judged[best].defects)})"
    return best, why


def screen(fd: PreparedRun, largest: _Fitted, big: DecimatedProblem,
           progress: Callable[[str, float], None] | None = None) -> tuple[list[Candidate], _Trial]:
    """Phase 1 (module docstring), from the largest structure's fit on every sample: each move
    refitted on the search's block means from the larger fit's values (a warm start) and scored
    by the core on the decimated run; returns the candidates screened and the screening's choice."""
    scorer = _Scorer(fd)
    theta = largest.core.model.split(largest.core.nu)[0]
    fixed = _real(big.lay, theta)
    current = scorer.trial(big, big.at(theta), fixed, "the largest, at its fit", largest.joint.starts)
    tried = {big.lay.orders: current}
    weak = largest.weak                      # its defective terms first
    while len(tried) < MAX_SCREENED:
        if progress:
            progress(f"structure: from {current.candidate.orders}", 0.6)
        moves = [m for m in _moves(current.lay, current.fit.nonlinear, current.fixed, weak)
                 if m.orders not in tried][:MAX_SCREENED - len(tried)]
        if not moves:
            break
        trials = []
        for move in moves:
            problem = DecimatedProblem(fd, move.orders, kin=big)
            trials.append(scorer.trial(problem, problem.local(move.start, move.fixed), move.fixed, move.how,
                                       current.starts))
        tried.update((t.candidate.orders, t) for t in trials)
        best = min(trials, key=lambda t: t.candidate.bic)
        if best.candidate.bic > current.candidate.bic + BIC_TIE:
            break
        current, weak = best, best.by_size()
    screened = [t.candidate for t in tried.values()]
    low = min(c.bic for c in screened)
    chosen = min((c for c in screened if c.bic <= low + BIC_TIE), key=lambda c: (c.n_params, c.bic))
    return screened, tried[chosen.orders]


def _repairs(fitted: _Fitted) -> list[Move]:
    """The moves that remove a defect of a fit: orders shared by every cycle when a later cycle's
    are not determined; a damping mode less when one is defective; a residual term less when one is."""
    core = fitted.core
    lay = core.params.layout
    nonlinear = core.model.split(core.nu)[0]
    moves = _moves(lay, nonlinear, _real(lay, nonlinear), fitted.weak)
    named = [d.split(" ", 1)[0] for d in fitted.candidate.defects]
    out = []
    if any(_cycle_of(n) > 1 for n in named):
        out += [m for m in moves if m.orders.shared and not lay.shared]
    odd = NOT_REPRODUCED in fitted.candidate.defects      # either kind of term dropped
    if odd or any(n.startswith("alpha") or (n[:1] == "a" and n[1:2].isdigit()) for n in named):
        out += [m for m in moves if m.orders.N < lay.N]
    if odd or any(n.startswith(("beta", "r")) for n in named):
        out += [m for m in moves if m.orders.M < lay.M]
    return out


def core_defects(core: Fit) -> tuple[list[str], list[int]]:
    """What makes a fit inadmissible - parameters the data do not determine, amplitude pairs that
    cancel - and its amplitude columns by what to drop first: those of defective terms, then by
    the size of their contribution. A real mode's Im alpha (at its bound 0) is not a parameter."""
    lay = core.params.layout
    theta = core.solution.theta
    phi = core.model.split(core.nu)[0]
    L = lay.n_linear
    names = np.array(_design_names(lay) + _nonlinear_names(lay) + ["zero"])
    lo, hi = core.model.bounds()
    keep = np.concatenate([np.ones(L, bool), ~_real(lay, phi), [True]])
    values = np.concatenate([theta[:L], phi, theta[L:L + 1]])
    ranges = np.concatenate([np.full(L, np.inf), hi[:len(phi)] - lo[:len(phi)], [np.inf]])
    unc = parameter_uncertainty(core.jacobian()[:, keep], core.solution.residual, values[keep],
                                list(names[keep]), ranges=ranges[keep])
    # an oscillation the data do not determine is a detail of its mode (a real one fits alike)
    undetermined = [n for n in names[keep][~unc.determined] if not n.endswith("_im")]
    defects = [f"{n} not determined" for n in undetermined]
    # a rate or order at its search bound: the optimum is outside the model's range
    span = hi[:len(phi)] - lo[:len(phi)]
    pinned = ((phi <= lo[:len(phi)] + AT_BOUND * span) | (phi >= hi[:len(phi)] - AT_BOUND * span)) & ~_real(lay, phi)
    pinned[1:2 * lay.N:2] = False            # Im alpha = 0 is a real mode, not a limit
    for n in names[L:L + len(phi)][pinned]:
        if n not in undetermined:
            defects.append(f"{n} at its search bound")
            undetermined.append(n)
    bad = {_column_of_name(lay, str(n)) for n in undetermined} - {-1}
    rows = np.flatnonzero(core.solution.used[0])
    parts = core.solution.designs[0][0][rows, :L] * theta[None, :L]
    for i, j, large in cancelling(lay, parts):
        defects.append(f"{names[i]} = {theta[i]:.4g} and {names[j]} = {theta[j]:.4g} "
                       + ("cancel" if large else "offset each other (each weaker than their component)"))
        bad.update((i, j))
    # two amplitudes the data cannot tell apart: two damping modes, or two terms of one cycle, of
    # nearly one rate or order (one term's amplitudes in two cycles may well be correlated so)
    corr = unc.correlation[:L, :L]            # the linear parameters lead the kept columns
    p1 = lay.P + 1 + lay.N
    cycles = [range(p1 + c * lay.M, p1 + (c + 1) * lay.M) for c in range(lay.C)]
    for group in [range(lay.P + 1, p1)] + cycles:
        for i, j in itertools.combinations(group, 2):
            if abs(corr[i, j]) > TWIN_CORRELATION and {i, j} - bad:
                defects.append(f"{names[i]} and {names[j]} are not told apart (correlation {corr[i, j]:+.4f})")
                bad.update((i, j))
    return defects, _by_size(lay, parts, bad)


def _real(lay: Layout, phi: np.ndarray) -> np.ndarray:
    """Nonlinear parameters at a real mode's Im alpha = 0 (its bound)."""
    out = np.zeros(len(phi), bool)
    im = np.arange(1, 2 * lay.N, 2)
    out[im] = phi[im] <= REAL_MODE_RATIO * phi[im - 1]
    return out


def _n_params(core: Fit) -> int:
    lay = core.params.layout
    return lay.n_linear + int(np.count_nonzero(~_real(lay, core.model.split(core.nu)[0]))) + 1


# ----------------------------------------------------------------------------- moves

def _moves(lay: Layout, nonlinear: np.ndarray, fixed: np.ndarray, weak: list[int]) -> list[Move]:
    """Each structure one move smaller, from the larger one's alpha and beta (weak: its amplitude
    columns by what to drop first)."""
    orders = lay.orders
    p1, N, M, C = lay.P + 1, lay.N, lay.M, lay.C
    alphas, betas = nonlinear[:2 * N].reshape(N, 2), nonlinear[2 * N:]
    real = fixed[:2 * N].reshape(N, 2)
    out = []

    def move(new: Orders, keep_modes: np.ndarray, kept_betas: np.ndarray, how: str) -> None:
        start = np.concatenate([alphas[keep_modes].ravel(), kept_betas])
        held = np.concatenate([real[keep_modes].ravel(), np.zeros(len(kept_betas), bool)])
        out.append(Move(new, start, held, how))

    every = np.ones(N, bool)
    if not lay.shared and C > 1:
        # the first cycle's orders for all: its terms are the largest, the best determined
        move(replace(orders, shared=True), every, betas[:M], "orders shared by every cycle")
    modes = [j - p1 for j in weak if p1 <= j < p1 + N]
    if modes:
        move(replace(orders, N=N - 1), np.arange(N) != modes[0], betas, f"damping mode {modes[0] + 1} dropped")
    terms = [j - p1 - N for j in weak if j >= p1 + N]
    if M > 1 and terms:
        if lay.shared:
            m = terms[0] % M
            move(replace(orders, M=M - 1), every, np.delete(betas, m), f"residual term {m + 1} dropped")
        else:   # each cycle its weakest term
            drop = [next(t for t in terms if t // M == c) for c in range(C)]
            move(replace(orders, M=M - 1), every, np.delete(betas, drop), "each cycle's weakest residual term dropped")
    if C > 1:
        move(replace(orders, C=C - 1), every, betas if lay.shared else betas[:(C - 1) * M],
             f"cycles from {C - 1} on share the terms of cycle {C - 1}")
    return out


def cancelling(lay: Layout, parts: np.ndarray) -> list[tuple[int, int, bool]]:
    """Amplitude columns (damping with damping, residual with residual) whose contributions cancel,
    and whether they are large: each larger than what their whole component does (two weak terms
    offsetting each other are terms the data barely see, not a derivative held up by two large
    amplitudes; on the independent generator's runs at 0.15 N fits at the noise had many such)."""
    p1 = lay.P + 1
    size = np.linalg.norm(parts, axis=0)
    out = []
    for group in (range(p1, p1 + lay.N), range(p1 + lay.N, lay.n_linear)):
        total = float(np.linalg.norm(parts[:, list(group)].sum(axis=1))) if len(group) else 0.0
        for i, j in itertools.combinations(group, 2):
            if min(size[i], size[j]) > 0 and \
                    np.linalg.norm(parts[:, i] + parts[:, j]) < CANCEL_RATIO * max(size[i], size[j]):
                out.append((i, j, max(size[i], size[j]) > total))
    return out


def _by_size(lay: Layout, parts: np.ndarray, bad: set[int] = frozenset()) -> list[int]:
    """Amplitude columns (damping and residual) by what to drop first: defective, then smallest."""
    size = np.linalg.norm(parts, axis=0)
    return sorted(range(lay.P + 1, lay.n_linear), key=lambda j: (j not in bad, size[j]))


def _design_names(lay: Layout) -> list[str]:
    names = [f"k{i}" for i in range(lay.P + 1)] + [f"a{i + 1}" for i in range(lay.N)]
    return names + [f"r{c + 1}_{m + 1}" for c in range(lay.C) for m in range(lay.M)]


def _column_of_name(lay: Layout, name: str) -> int:
    """The amplitude column of the term a parameter belongs to (-1: an elastic coefficient)."""
    digits = name.lstrip("abelphrt").split("_")
    if name.startswith(("a", "alpha")):
        return lay.P + int(digits[0])
    if name.startswith(("r", "beta")):
        c, m = int(digits[0]), int(digits[1])
        return lay.P + 1 + lay.N + (c - 1) * lay.M + (m - 1)
    return -1


def _nonlinear_names(lay: Layout) -> list[str]:
    """As FitReport names them (a shared order by its first cycle's name)."""
    names = [f"alpha{i + 1}_{part}" for i in range(lay.N) for part in ("re", "im")]
    cycles = 1 if lay.shared else lay.C
    return names + [f"beta{c + 1}_{m + 1}" for c in range(cycles) for m in range(lay.M)]


def _cycle_of(name: str) -> int:
    """The cycle a parameter belongs to (r2_1, beta3_2 -> 2, 3; 0 for none)."""
    if name.startswith(("r", "beta")) and "_" in name:
        return int(name.lstrip("abert").split("_")[0])
    return 0


# ----------------------------------------------------------------------------- screening scores

class _Scorer:
    """Each screened structure's scores by the analysis core on the decimated run (the samples
    diagnosis searches on): the linear parameters and the contact set solved for the
    structure's alpha and beta, the held-out blocks as diagnosis predicts them."""

    def __init__(self, fd: PreparedRun):
        self.fd = fd
        self.series: list[Series] = [fd.series.decimated(decimation([fd.series]))]

    def trial(self, problem: DecimatedProblem, fit: SeparableFit, fixed: np.ndarray, how: str,
              starts: list[str]) -> _Trial:
        params = params_of(self.fd, problem.lay, fit)
        core = solved_at(self.series, params)
        n_params = problem.lay.n_linear + int(np.count_nonzero(~fixed)) + 1
        _, bic = information_criteria(core.rss, core.n, n_params)
        candidate = Candidate(problem.lay.orders, how, "screened", n_params, core.rmse, heldout_rmse(core), bic)
        return _Trial(problem, fit, fixed, candidate, list(starts))
