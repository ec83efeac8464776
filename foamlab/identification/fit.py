"""fit_run: the whole identification of one run (docs/identification.md).

prepare (foamlab.analysis) -> the paper's three steps (start values, Table 5 per step)
-> joint refinement (global search of alpha and beta on the decimated run) -> the
analysis core's polish on every sample (foamlab.analysis.solve: all parameters, the
contact set, the load cell's zero; the fit diagnosis extends) -> the model's own
evaluation at every sample -> statistics, uncertainty, checks.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from scipy.stats import chi2
from threadpoolctl import threadpool_limits

from foamlab.analysis.noise import AT_NOISE_RATIO, at_the_noise
from foamlab.analysis.parallel import fork_ahead, fork_map, processes
from foamlab.analysis.prepared import PreparedRun, model_response, prepare
from foamlab.analysis.solve import Fit, converged, polish, solved_at
from foamlab.identification.apart import HeldApart, coalesced, hold_apart
from foamlab.identification.forms import choose as forms_choose
from foamlab.identification.forms import core_fit_of
from foamlab.identification.forms import likelier_first
from foamlab.identification.forms import settles as forms_settle
from foamlab.identification.joint import (
    AT_BOUND,
    MIN_CENSORED,
    REAL_MODE_RATIO,
    JointFit,
    JointSearch,
    evaluable,
    unpolished,
)
from foamlab.identification.paper import paper_steps
from foamlab.identification.parameters import Parameters
from foamlab.identification.result import FitReport, FittedSamples, FitWork, TurnSamples
from foamlab.identification.settings import DEFAULT, FitSettings
from foamlab.identification.statistics import (
    GoodnessOfFit,
    autocorrelation_time,
    information_criteria,
    parameter_uncertainty,
)
from foamlab.identification.structure import StructureChoice, forced, select
from foamlab.model import thermodynamic_checks
from foamlab.model.layout import (
    BETA_HI,
    BETA_LO,
    Orders,
    check_form,
    nonlinear_bounds,
)
from foamlab.rundata import RunData

Progress = Callable[[str, float], None]

#: An amplitude whose 95 % interval contains zero (|value| < this x stderr) is flagged.
ZERO_T_VALUE = 1.96


def fit_run(run: RunData, orders: Orders | str | tuple | None = None, progress: Progress | None = None,
            x_scale_mm: float | None = None, form: str = "auto", hold: bool = True,
            settings: FitSettings = DEFAULT) -> FitReport:
    """Identify the model's parameters from one run (any importer's RunData).

    orders: Orders(N, M, P[, C]), 'N,M,P' or a tuple; None (default): LARGEST (3,3,7,3), or 'auto'
    for a run of one load-unload cycle; 'auto':
    the structure the data determine, chosen from LARGEST down (identification.structure: no
    cancelling terms, every parameter determined; it fits 3-12 structures, 3-10 x the time).
    progress: called with (stage, fraction 0..1) as the fit advances.
    x_scale_mm: the elastic polynomial's scale (default: the run's largest compression).
    form: the residual form, 'causal' or 'paper', or 'auto': both fitted, the one that
    predicts held-out blocks better kept (identification.forms).
    hold: orders that coalesce held apart (identification.apart: what the report says); a
    forecast, which needs only the force, skips it (it costs a polish on every sample).
    settings: the optimizer's budgets (identification.settings).
    Raises FoamlabError (one line, what is missing) for runs that cannot be identified.
    """
    report = progress or (lambda stage, fraction: None)
    report("segmenting the run", 0.0)
    return fit_prepared(prepare(run, x_scale_mm=x_scale_mm), orders, progress, form, hold, settings)


def resumed(report: FitReport, run: RunData) -> FitReport:
    """A stored report (FitReport.load) with the working state diagnosis extends: the run prepared
    again and the analysis core's model at the report's alpha and beta, its linear parameters and
    contact set solved - nothing searched, the run is not fitted again. Its turns are placed as
    the fit placed them."""
    fd = prepare(run, x_scale_mm=report.params.x_scale_mm)
    if fd.nodes.between_samples != report.turns_between_samples:
        fd = fd.other_turns()
    if report.turns_flipped:
        fd = fd.with_flipped(report.turns_flipped)
    return report.with_work(prepared=fd, core_fit=solved_at([fd.series], report.params))


def fit_prepared(fd: PreparedRun, orders: Orders | str | tuple | None = None,
                 progress: Progress | None = None, form: str = "auto", hold: bool = True,
                 settings: FitSettings = DEFAULT) -> FitReport:
    """Identify the model on a prepared run (foamlab.analysis.prepare): the same as fit_run."""
    select = isinstance(orders, str) and orders.strip().lower() == AUTO_ORDERS
    # one load-unload cycle: the largest structure (23 parameters on one loading and unloading)
    # found damping pairs of +-1.1e5 N cancelling, and the selection costs under a second there
    select = select or (orders is None and len(fd.labels.starts) == 1)
    given = None if select else (_orders(orders) or LARGEST)
    orders = given or LARGEST
    report = progress or (lambda stage, fraction: None)
    started = time.perf_counter()
    with threadpool_limits(1, user_api="blas"):
        paper = paper_steps(fd, orders)          # the same in either form (identification.paper)
        # the likelier form first: one that leaves only the noise settles the choice alone
        forms = likelier_first(fd, orders, paper.start) if form == "auto" else (check_form(form),)
    select = given is None
    # with the form to choose, both are fitted in the largest structure and the structure the
    # data determine is selected in the form kept only (a selection costs two to three fits)
    steps = len(forms) + (select and len(forms) > 1)
    results = []
    for i, f in enumerate(forms):
        def scaled(stage: str, fraction: float, i=i, f=f) -> None:
            report(f"{f} form: {stage}" if len(forms) > 1 else stage, (i + fraction) / steps)
        # on the core fit's used samples: the measure the polish's gate compares with (a report's RMSE
        # over every sample is up to 8.5 x it where a lag misfits the turns; docs/analysis.md)
        rival = min((core_fit_of(r).rmse for r in results), default=np.inf)
        # the turns' placement is the path's, not the form's: a form starts where the last one placed them
        placed = results[-1].prepared if results and results[-1].prepared is not None else fd
        results.append(_fit_placed(placed, replace(orders, form=f), select and len(forms) == 1, scaled, paper,
                                   rival, hold, settings))
        if form == "auto" and forms_settle(results[-1]):
            break
    chosen = forms_choose(results, forced=form != "auto")
    if select and len(forms) > 1:
        choice, alternatives = chosen.form_choice, chosen.alternatives
        chosen = _fit_placed(chosen.prepared or fd, replace(orders, form=choice.chosen), True,
                             lambda stage, fraction: report(f"structure: {stage}", (steps - 1 + fraction) / steps),
                             paper, hold=hold, settings=settings)
        chosen = replace(chosen, form_choice=choice).with_work(alternatives=alternatives)
    report("done", 1.0)      # also where the first form settled the choice (the rest skipped)
    # the report of the whole fit: a new frozen record with the whole time (reports are not changed)
    return replace(chosen, elapsed_s=time.perf_counter() - started)


def refit_core(fd: PreparedRun, orders: Orders, settings: FitSettings = DEFAULT) -> Fit | None:
    """Identification's core fit of one form and structure on a prepared run: its starts, search
    and polish, the turns as placed, no orders held apart (diagnosis.limits refits a run with an
    effect injected, to see what of it identification takes into the model's own terms).
    _fit_structure's fits without its report, whose statistics the check does not read (a model
    evaluation and the standard errors: 8 % of a refit)."""
    with threadpool_limits(1, user_api="blas"):
        paper = paper_steps(fd, orders)
        search = JointSearch(fd, orders, paper.start, None)
        return _structure_fits(fd, paper, search, lambda stage, fraction: None, hold=False, settings=settings)[1]


def _fit_placed(fd: PreparedRun, orders: Orders, select: bool, progress: Progress, paper,
                rival: float = np.inf, hold: bool = True, settings: FitSettings = DEFAULT) -> FitReport:
    """One form's fit (select: of the structure the data determine, from orders down), with the
    placement of each turning point the samples cannot place fitted.

    Where the crosshead turned without a stop, the samples cannot say whether it turned at
    the sample at the extreme (a polyline of samples) or between two (a real machine): the
    model switches at the turn, so the samples next to it show which. Each such turn's
    placement is a parameter of the fit (counted in its degrees of freedom: _result), fitted
    by the likelihood: where the samples next to some turns misfit by more than
    TURN_MISFIT_MULTIPLE times the noise, those turns are placed the other way alone (a turn a
    fraction of a millisecond before the extreme sample: only that sample's force says it
    was already unloading); where they misfit more than their neighbours, every turn is; the
    placement whose whole run fits best is kept."""
    # the whole fit with every turn the other way needs nothing from the first fit: where the run
    # has turns without a stop it is fitted ahead on another core while the first fit shows
    # whether it is needed (the same computation; cancelled when not)
    other = fd.other_turns() if len(fd.nodes.turns_between) else None
    ahead = fork_ahead(lambda: _fit_prepared(other, orders, select, None, rival=rival, hold=hold, settings=settings),
                       [fd, fd.series, other, other.series]) if other is not None else None
    try:
        return _placed_best(fd, orders, select, progress, paper, rival, hold, settings, other, ahead)
    finally:
        if ahead is not None:
            ahead.cancel()


def _placed_best(fd: PreparedRun, orders: Orders, select: bool, progress: Progress, paper, rival: float,
                 hold: bool, settings: FitSettings, other: PreparedRun | None, ahead) -> FitReport:
    """_fit_placed's work: other is fd.other_turns() (None without turns without a stop), ahead its
    whole fit started on another core (None: fitted here when needed)."""
    # progress: the first fit to FIRST_SHARE, each other placement's an equal part of the rest
    result = _fit_prepared(fd, orders, select, lambda stage, f: progress(stage, FIRST_SHARE * f), paper,
                           rival, hold, settings)
    at_turns, around = _misfit_at_turns(result, fd)
    # a structure chosen with a turn misplaced can misfit everywhere, the turn's neighbours no more
    # than the rest (one cycle at 10 Hz: every structure 3-4 x the noise, 0.99 x placed the other way)
    lost = select and len(fd.nodes.turns_between) > 0 and result.rmse > FAR_FROM_NOISE * fd.noise_N
    placements = []
    # a form far off its rival's RMSE is not kept (forms.choose): its turns are not placed one by one
    near_rival = not np.isfinite(rival) or core_fit_of(result).rmse <= RIVAL_RATIO * rival   # no rival: no solve
    misplaced = _misplaced_turns(result, fd) if near_rival else ()
    if misplaced and len(misplaced) < len(fd.nodes.turns_between):
        placements.append((fd.with_flipped(tuple(sorted(set(fd.nodes.flipped) ^ set(misplaced)))), True))
    if at_turns > TURN_MISFIT_MULTIPLE * max(fd.noise_N, around) or lost:
        # the structure the data chose, or chosen again (with the turn misplaced, a 28 N miss at
        # one peak sample chose (0, 2): 4 x the noise placed right). Always a whole fit: the first
        # fit's parameters bend to the placement they were fitted with (independent A at twice its
        # speed, seed 641: they fit the other placement worse, yet its own fit is 0.154 N against
        # 0.193 N at 16 Hz, 0.152 N against 1.71 N at 2 Hz)
        placements.append((other, False))
    # one turn placed the other way: worth a whole fit only if the first fit, its turns placed this
    # way, already fits better (only the first placement is gated: the gate sees the first fit)
    placements = [placed for placed, gated in placements
                  if not (gated and not select and not _fits_better_placed(result, result.prepared or fd, placed))]

    def fitted(i: int, quiet: bool) -> FitReport:
        if placements[i] is other and ahead is not None:
            return ahead.result()
        def within(stage: str, fraction: float) -> None:
            progress(f"turns placed the other way: {stage}",
                     FIRST_SHARE + (1.0 - FIRST_SHARE) * (i + fraction) / len(placements))
        # result.orders is orders where the structure is not selected: the fit ahead's too
        return _fit_prepared(placements[i], orders if select else result.orders, select,
                             (lambda stage, f: None) if quiet else within, rival=rival, hold=hold, settings=settings)

    # independent whole fits: on the machine's cores (the same results; analysis.parallel)
    done = lambda i, _: progress("turns placed the other way: done", FIRST_SHARE + (1.0 - FIRST_SHARE) * (i + 1)
                                 / len(placements))
    if ahead is not None or len(placements) <= 1 or processes() <= 1:
        others = []
        for i in range(len(placements)):
            others.append(fitted(i, False))
            done(i, others[-1])
    else:
        others = fork_map(lambda i: fitted(i, True), range(len(placements)),
                          [*(p for q in (fd, *placements) for p in (q, q.series))], done=done)
    kept = result
    for alt in others:
        if alt.rmse < kept.rmse:
            kept = replace(alt, structure=alt.structure if select else result.structure,
                           notes=alt.notes + (f"{_placement(alt)}: the whole run fits {result.rmse:.4g} N "
                                              f"with every one placed {_rule(result)}",))
    progress("done", 1.0)
    return kept


def _fits_better_placed(result: FitReport, fd: PreparedRun, placed: PreparedRun) -> bool:
    """Whether the other placement is worth a whole fit: the fit's own parameters, evaluated
    with the turns placed the other way, already fit the run's samples better. A misplaced turn
    misfits its samples by several times the noise, and placing it right fixes them at the same
    parameters (independent A seed 12: a residual sum of squares of 2 743 N^2 -> 133 N^2); where
    the other placement fits worse there, the whole fit from the start (three steps, searches,
    hold) found a worse optimum too (seeds 4 of A, 3 of B: 0.659 and 0.154 N against 0.150 and
    0.152 N)."""
    other = np.maximum(model_response(result.params, placed).force, result.contact_zero_N)
    rss = lambda run, force: float(np.sum((run.f - force)[run.observed] ** 2))
    return rss(placed, other) < rss(fd, result.predicted_force_N)


def _rule(report: FitReport) -> str:
    return "between samples" if report.turns_between_samples else "at the sample at the extreme"


def _placement(report: FitReport) -> str:
    rule = _rule(report)
    if not report.turns_flipped:
        return f"turning points without a stop placed {rule}"
    at = ", ".join(f"{t:.4g}" for t in report.turns_flipped_s)
    return f"turning points without a stop placed {rule}, but {len(report.turns_flipped)} the other way (t = {at} s)"


def _misplaced_turns(result: FitReport, fd: PreparedRun) -> tuple[int, ...]:
    """The turning points (indices of fd.extremes) without a stop whose samples within one step
    misfit by more than TURN_MISFIT_MULTIPLE times the noise and the other turns' typical misfit.

    A turn the samples place wrongly is a single turn (where it fell between two samples); an
    effect at the turns - a channel lag, friction - misfits every turn alike, and placing some of
    them the other way would hide part of it from the diagnosis (independent A seed 301, 100 ms
    lag: three of six turns placed the other way for 1.2564 N against 1.2566 N, and the lag's
    Delta BIC fell from 125 to 16, cycle_softening named instead)."""
    r = fd.f - result.predicted_force_N
    misfit = []
    for when, k in zip(fd.nodes.turns_between, fd.nodes.turn_extremes):
        near = np.abs(fd.t - when) <= fd.native_step_s
        misfit.append((int(k), float(np.sqrt(np.mean(r[near] ** 2))) if near.any() else 0.0))
    typical = float(np.median([m for _, m in misfit])) if misfit else 0.0
    bar = TURN_MISFIT_MULTIPLE * max(fd.noise_N, typical)
    return tuple(k for k, m in misfit if m > bar)


#: The share of a form's progress its first fit takes; refits with turns placed otherwise the rest.
FIRST_SHARE = 0.6
#: The samples next to turns without a stop misfit by more than this many times the noise
#: and the samples around them: the turn is at the other place.
TURN_MISFIT_MULTIPLE = 3.0
#: ...or, where the structure is chosen, the whole fit is further than this from the noise.
FAR_FROM_NOISE = 1.5


#: A fit whose mean misfit over the TURN_AFTER_STEPS samples after each turn without a stop is
#: this unlikely as noise (chi-squared over the turns) is polished from every start of the search.
TURN_STRUCTURE_P = 1e-4
TURN_AFTER_STEPS = 4
#: More starts than the search has: all of them.
ALL_STARTS = 16


def _structure_after_turns(fit: Fit, fd: PreparedRun) -> bool:
    """Does the fit miss systematically just after the turns without a stop? Each turn's mean
    residual over the samples after it, in its noise standard error, squared and summed: chi-squared
    with one degree per turn where the fit is the model's (B causal 3058: identification's first
    optimum left -3.7, -2.1 and -1.8 noise over the four samples after each peak; the other basin 0)."""
    turns = fd.nodes.turns_between
    if not len(turns) or not fd.noise_N > 0:
        return False
    r = fit.solution.residuals[0]
    used = np.flatnonzero(fd.series.used)
    stat, dof = 0.0, 0
    for first in np.searchsorted(fd.t[used], turns, side="right"):   # the first used sample after each
        after = used[first:first + TURN_AFTER_STEPS]
        if len(after):
            stat += float(np.sum(r[after])) ** 2 / (len(after) * fd.noise_N ** 2)
            dof += 1
    return bool(dof and chi2.sf(stat, dof) < TURN_STRUCTURE_P)


def _misfit_at_turns(result: FitReport, fd: PreparedRun) -> tuple[float, float]:
    """RMS misfit of the samples within one step of a turn without a stop, and of the samples
    2-6 steps from one (an effect near the turns, e.g. a lag, misfits both alike)."""
    turns = fd.nodes.turns_between
    if not len(turns):
        return 0.0, 0.0
    distance = np.min(np.abs(fd.t[:, None] - turns[None, :]), axis=1) / fd.native_step_s
    r = fd.f - result.predicted_force_N
    rms = lambda m: float(np.sqrt(np.mean(r[m] ** 2))) if np.any(m) else 0.0
    return rms(distance <= 1.0), rms((distance > 2.0) & (distance <= 6.0))


def _fit_prepared(fd: PreparedRun, orders: Orders, select: bool, progress: Progress | None,
                  paper=None, rival: float = np.inf, hold: bool = True, settings: FitSettings = DEFAULT) -> FitReport:
    """One form's fit (select: of the structure the data determine). rival: the RMSE another
    form already reached; a first optimum further than RIVAL_RATIO from it gets no extra starts
    (they refine a local optimum's last percent, not a model twice off the data)."""
    report = progress or (lambda stage, fraction: None)
    started = time.perf_counter()
    # The matrices here are small: BLAS threads would only contend (and on a busy
    # machine they slow the fit down many times over).
    with threadpool_limits(1, user_api="blas"):
        report("the paper's three steps", 0.1)
        paper = paper if paper is not None else paper_steps(fd, orders)
        report("joint refinement", 0.3)
        if not select:
            search = JointSearch(fd, orders, paper.start, report)
            result = _fit_structure(fd, orders, paper, search, report, rival, hold, settings)
        else:
            result = _fit_selected(fd, orders, paper, report, rival, hold, settings)
    report("done", 1.0)
    return replace(result, elapsed_s=time.perf_counter() - started)


def _fit_selected(fd: PreparedRun, largest: Orders, paper, report: Progress, rival: float = np.inf,
                  hold: bool = True, settings: FitSettings = DEFAULT) -> FitReport:
    """The structure the data determine (identification.structure), carried to every sample."""

    def core_fit(orders: Orders, optima, given: bool):
        found = next(optima, None)
        if found is None:
            return None
        jf = unpolished(fd, orders.layout(fd.n_residual_cycles), found)
        if given:        # with identification's other starts (the search's next, the paper's)
            search = JointSearch(fd, orders, None, report, found=optima)
            return jf, _polished(fd, jf, search, paper if orders == largest else None, rival, settings.polish_nfev)
        return jf, polish([fd.series], jf.params, nfev=settings.polish_nfev)

    checked: dict[int, bool] = {}         # by id of the core's fit: its evaluation costs

    def reproduced(jf: JointFit, core: Fit) -> bool:
        if id(core) not in checked:
            checked[id(core)] = _from_core(fd, jf, core) is not None
        return checked[id(core)]

    selection = select(fd, largest, paper.start, core_fit, reproduced, report)
    chosen = selection.chosen
    steps = paper if chosen.orders == largest else paper_steps(fd, chosen.orders)   # its Table 5
    jf, base = chosen.joint, _real_modes(chosen.core)
    held, apart = _held_apart(fd, jf, base, report, settings) if hold else (None, None)
    free = base
    base = base if apart is not None else converged(base, settings.max_nfev)
    polished = held if apart is not None else _from_core(fd, jf, base)
    unreproduced = polished is None and not np.isfinite(jf.residual).all()
    if apart is not None:
        base = apart.fit
    elif unreproduced:
        # the model's evaluation (what the simulator runs) does not reproduce the core's fit; its
        # terms neither cancel nor escape the data (the selection's defects): the fit is kept
        polished = _from_core(fd, jf, base, reproduced=False)
    elif polished is None:    # identification's own full-resolution fit is the better (as given)
        polished, base = jf, None
    report("statistics", 0.9)
    largest = None
    first = selection.fitted[0]
    if first is not chosen:     # the largest structure's fit: what diagnosis extends
        own = _from_core(fd, first.joint, first.core) or _from_core(fd, first.joint, first.core, reproduced=False)
        largest = _result(fd, first.orders, paper, own, time.perf_counter(), first.core)
    warnings = _cancelling(base, apart, hold)
    if unreproduced:
        warnings.append("the model's own evaluation (what the simulator runs) does not reproduce this fit "
                        "within a tenth of its residual")
    return _result(fd, chosen.orders, steps, polished, time.perf_counter(), base, apart=apart, free=free,
                   warnings=warnings, structure=selection.choice(), largest=largest)


def _real_modes(base: Fit) -> Fit:
    """The core's fit with every damping mode whose oscillation the data do not support made real,
    as the search decides it (joint._real_modes: Im alpha = 0 costs less than ln(n) noise
    variances), the least oscillating first; the linear parameters re-solved. A structure fitted
    from a larger one's values has not had the search's test."""
    phi = base.model.split(base.nu)[0].copy()
    N = base.params.layout.N
    penalty = base.rss / base.n * np.log(base.n)
    for i in np.argsort(phi[1:2 * N:2] / np.maximum(phi[0:2 * N:2], 1e-300)):
        if phi[2 * i + 1] == 0.0:
            continue
        trial = phi.copy()
        trial[2 * i + 1] = 0.0
        sol = base.model.solve(trial)
        if sol.rss() > base.rss + penalty:
            break
        base, phi = Fit([], base.model, trial, base.stderr, sol, status=base.status, message=base.message), trial
    return base


def _polished(fd: PreparedRun, jf: JointFit, search: JointSearch, paper, rival: float = np.inf,
              nfev: int = DEFAULT.polish_nfev) -> Fit:
    """The core's polish of identification's fit on every sample, with identification's other
    starts, the better kept: the data call for another start when the first leaves structure
    above the noise (the search's next best optimum), and the decimated search can look white
    while the full run is off the noise (the paper's three-step start, exact in the paper form).
    Not for a first optimum further than RIVAL_RATIO from another form's RMSE (rival)."""
    base = polish([fd.series], jf.params,
                  lambda first: () if _at_the_noise(first, fd) or first.rmse > RIVAL_RATIO * rival
                  else search.more(EXTRA_STARTS), nfev=nfev)
    if base.rmse <= RIVAL_RATIO * rival and _structure_after_turns(base, fd):
        # the search refines the start whose short probe fits best, which need not reach the best
        # optimum: where the fit misses just after the turns, every other start is refined and
        # polished too, the best on every sample kept (docs/analysis.md, "B causal:
        # identification's basin"; at the noise on average, such a fit is not caught above)
        for start in search.more(ALL_STARTS):
            other = polish([fd.series], start, nfev=nfev)
            if other.rss < base.rss:
                base = other
    if paper is not None and paper.start is not None and \
            AT_NOISE_RATIO * fd.noise_N < base.rmse <= RIVAL_RATIO * rival:
        # the three steps are the same in either form: their start in the form fitted (polished
        # as it came, a causal start made a paper-form fit a causal one)
        other = polish([fd.series], replace(paper.start, residual_form=jf.params.residual_form), nfev=nfev)
        if other.rss < base.rss:
            base = other
    return base


def _fit_structure(fd: PreparedRun, orders: Orders, paper, search: JointSearch, report: Progress,
                   rival: float = np.inf, hold: bool = True, settings: FitSettings = DEFAULT) -> FitReport:
    """One structure: the search's best optimum polished, then carried to every sample by the
    analysis core."""
    jf, base, apart, free = _structure_fits(fd, paper, search, report, rival, hold, settings)
    report("statistics", 0.9)
    return _result(fd, orders, paper, jf, time.perf_counter(), base, apart=apart, free=free,
                   warnings=_cancelling(base, apart, hold), structure=forced(orders))


def _structure_fits(fd: PreparedRun, paper, search: JointSearch, report: Progress, rival: float = np.inf,
                    hold: bool = True, settings: FitSettings = DEFAULT
                    ) -> tuple[JointFit, Fit | None, HeldApart | None, Fit]:
    """_fit_structure's fits: (the fit in identification's terms, the core's fit - None where the
    model's own evaluation does not reproduce it -, the orders held apart or None, the core's fit
    with every order free)."""
    jf = search.fit()
    report("polish on every sample", 0.8)
    base = _polished(fd, jf, search, paper, rival, settings.polish_nfev)
    # a form far off its rival's RMSE is not kept (forms.choose): its terms are not held apart,
    # nor is it carried on to convergence
    near = base.rmse <= RIVAL_RATIO * rival
    held, apart = _held_apart(fd, jf, base, report, settings) if hold and near else (None, None)
    free = base
    if apart is not None:
        jf, base = held, apart.fit
    else:
        base = converged(base, settings.max_nfev) if near else base
        polished = _from_core(fd, jf, base)
        if polished is not None:
            jf = polished
        else:
            base = None
    return jf, base, apart, free


def _held_apart(fd: PreparedRun, jf: JointFit, base: Fit, report: Progress, settings: FitSettings = DEFAULT
                ) -> tuple[JointFit | None, HeldApart | None]:
    """The core's fit with the orders that coalesce held apart (identification.apart), in
    identification's terms; (None, None) when none are held."""
    report("orders that coalesce held apart", 0.85)
    apart = hold_apart(fd, base, settings.polish_nfev, settings.max_nfev)
    held = _from_core(fd, jf, apart.fit, held=apart.held) if apart is not None else None
    return (held, apart) if held is not None else (None, None)


def _cancelling(core: Fit | None, apart: HeldApart | None, hold: bool = True) -> list[str]:
    """Coalesced residual orders left free (holding them apart fitted worse than BIC_TIE, or a
    pair the hold did not reach) are said: which way that choice falls can turn on the last digit
    of a run's numbers, so the result must say which way it fell."""
    if core is None:
        return []
    held = apart.held if apart is not None else np.zeros(core.params.layout.n_nonlinear, bool)
    pairs = [(i, j) for i, j in coalesced(core) if not (held[i] and held[j])]
    if not pairs:
        return []
    phi = core.model.split(core.nu)[0]
    orders = ", ".join(f"{phi[i]:.4g} / {phi[j]:.4g}" for i, j in pairs)
    why = "held apart they fitted worse" if hold else "not held apart: every order fitted free, as asked"
    return [f"{len(pairs)} pair(s) of residual terms at nearly one order cancel (beta {orders}): "
            f"the data determine each pair's sum, not its terms; {why}"]


#: A polished fit further than this from the noise level, with structure left in its
#: residuals, is polished again from the search's next best start(s).
EXTRA_STARTS = 1
RIVAL_RATIO = 2.0


def _at_the_noise(base: Fit, fd: PreparedRun) -> bool:
    return at_the_noise(base.solution.residual, fd.noise_N)


#: The structure the selection starts from (issue 19): the paper's orders, three cycles with terms
#: of their own.
LARGEST = Orders()
#: The orders that ask for the structure the data determine.
AUTO_ORDERS = "auto"


def _orders(orders) -> Orders | None:
    if orders is None or isinstance(orders, Orders):
        return orders
    if isinstance(orders, str):
        return Orders.parse(orders)
    return Orders(*orders)


def _from_core(fd: PreparedRun, jf: JointFit, base: Fit, reproduced: bool = True,
               held: np.ndarray | None = None) -> JointFit | None:
    """The core's polished base in identification's terms (canonical order, the zero offset in
    k0, the Jacobian of every free parameter at the solution); None when the polish found no
    better optimum, or (reproduced) one the model's own evaluation cannot reproduce (see evaluable).
    held: orders the base was fitted with held (identification.apart; fixed, and kept even
    where the search's own fit had a lower residual: its terms cancel)."""
    lay = jf.layout
    sol = base.solution
    # the rows identification reports on: the cycles' samples the path determines
    rows = np.intersect1d(fd.observed, np.flatnonzero(fd.series.used))
    residual = sol.residuals[0][rows]
    if held is None and not np.mean(residual ** 2) < np.mean(jf.residual ** 2):
        return None
    theta, phi = sol.theta, base.model.split(base.nu)[0].copy()
    L = lay.n_linear
    fixed = np.zeros(lay.n_nonlinear, bool)
    im = np.arange(1, 2 * lay.N, 2)
    # a mode the search made real and the polish kept at Im alpha = 0, or one the polish took to
    # that bound itself (a structure fitted from a larger one's values): real
    at_bound = phi[im] <= AT_BOUND * nonlinear_bounds(lay.orders, lay.C, fd.loading_time_s)[1][im]
    fixed[im] = (jf.fixed_nonlinear[im] & (phi[im] <= REAL_MODE_RATIO * phi[im - 1])) | at_bound
    phi[fixed] = 0.0
    if held is not None:
        fixed |= held
    design = sol.designs[0][0][rows]                              # k, a, r columns, then the zero
    deriv = base.model.prediction_derivatives(base.nu, sol)[rows]
    out_of_contact = int(np.count_nonzero(~sol.masks[0][rows]))
    zero_fitted = out_of_contact >= MIN_CENSORED
    lin = theta[:L].copy()
    zero = float(theta[L])
    lin[0] += zero                       # identification's convention: reading = max(model, zero)
    perm = lay.canonical_permutation(lin, phi)
    nl_perm = perm[L:] - L
    columns = np.hstack([design[:, :L], deriv])[:, perm]
    keep = np.concatenate([np.ones(L, bool), ~fixed[nl_perm]])
    jacobian = columns[:, keep]
    if zero_fitted:
        jacobian = np.hstack([jacobian, design[:, L:L + 1]])
    lin, phi, fixed = lin[perm[:L]], phi[nl_perm], fixed[nl_perm]
    params = jf.params.with_vector(lay.to_flat(lin, phi))
    polished = JointFit(params, lay, lin, phi, fixed, zero, zero_fitted, jacobian, residual,
                        jacobian.shape[1], jf.nfev, jf.starts + ["polish on every sample (analysis core)"],
                        base.status, base.message)
    return polished if not reproduced or evaluable(fd, polished, rows) else None


def _result(fd: PreparedRun, orders: Orders, paper, jf: JointFit, started: float, base: Fit | None = None, *,
            apart: HeldApart | None = None, free: Fit | None = None, warnings: list[str] = (),
            structure: StructureChoice | None = None, largest: FitReport | None = None) -> FitReport:
    """The report of one structure's fit, built once (reports are frozen): apart, the orders held
    apart (identification.apart) with free, the fit with them free (diagnosis' base); warnings
    the fit's loops made; largest, the largest structure's report where another was chosen."""
    lay = jf.layout
    params = jf.params
    # what a load cell would read at every sample: the model's force, the unloaded reading
    # where the plate is off; exact (the core's columns: the Riemann-Liouville derivative of the
    # path through its corner nodes) when the core's fit is the result, else the causal
    # evaluation, which is exact only where no corner lies between samples
    response = model_response(params, fd)
    if base is not None:
        force = base.model.specimen_force(base.nu, base.solution.theta)[0] + jf.contact_zero_N
    else:
        force = response.force
    # every figure is this one evaluation of the model; each turn the samples cannot place has
    # its placement fitted (_fit_placed): a parameter each
    predicted = np.maximum(force, jf.contact_zero_N)
    turn_parameters = len(fd.nodes.turns_between)
    n_free = jf.n_free + turn_parameters
    y = fd.f[fd.observed]
    joint = GoodnessOfFit.of(y, predicted[fd.observed], n_free)
    first, last = int(fd.observed[0]), int(fd.observed[-1]) + 1
    whole = fd.f[first:last] - predicted[first:last]
    blocks = np.split(y - predicted[fd.observed], np.flatnonzero(np.diff(fd.observed) > 1) + 1)
    tau = autocorrelation_time(blocks)
    parameters, correlation, unc_warnings = _parameters(fd, orders, jf, tau)
    aic, bic = information_criteria(joint.sse, joint.n, n_free)
    names, values = parameters.names, parameters.column("value")
    lower, upper = nonlinear_bounds(orders, lay.C, fd.loading_time_s)
    out_warnings = list(fd.warnings) + list(paper.warnings) + unc_warnings
    out_warnings += _bound_warnings(names, values, lay, lower, upper)
    out_warnings += _zero_warnings(names, values, parameters.column("stderr"), lay)
    if tau > 2:
        out_warnings.append(f"residuals are autocorrelated (tau = {tau:.0f} samples): the plain standard "
                            "errors are optimistic; see the autocorrelation-corrected ones")
    notes = [f"{p.name} = 0 (fixed): {p.why}" for p in parameters.values() if p.name.startswith("alpha") and not p.vary]
    held = {p.name: p.value for p in parameters.values() if not p.vary and p.name.startswith("beta") and not p.tie}
    held_orders = apart.record(held, _free_values(fd, jf, apart)) if apart is not None else None
    if held_orders is not None:
        notes.append(held_orders.note())
    statistics = {name: step.stats for name, step in paper.steps.items()}
    statistics["joint"] = joint
    samples = FittedSamples(fd.t, fd.run.displacement_mm, fd.f, predicted, response.labels.cycle,
                            response.labels.direction, np.asarray(fd.observed), fd.nodes.t, fd.nodes.x,
                            np.asarray(fd.nodes.of_sample))
    return FitReport(
        source=fd.run.source, orders=orders, params=params, parameters=parameters, correlation=correlation,
        statistics=statistics, rmse=float(np.sqrt(np.mean(whole ** 2))), noise_N=float(fd.noise_N),
        constraints=thermodynamic_checks(params), warnings=tuple(out_warnings + list(warnings)), notes=tuple(notes),
        aic=float(aic), bic=float(bic), n_obs=int(joint.n), n_params=int(n_free),
        autocorrelation_time=float(tau), contact_zero_N=float(jf.contact_zero_N), status=int(jf.status),
        message=str(jf.message), samples=samples, turns=_turn_samples(fd.series.used[first:last], whole),
        structure=structure, starts=tuple(jf.starts), elapsed_s=time.perf_counter() - started,
        turns_between_samples=bool(fd.nodes.between_samples), run_samples=len(fd.t) + int(fd.off_schedule),
        turn_parameters=turn_parameters, turns_flipped=tuple(fd.nodes.flipped),
        turns_flipped_s=tuple(float(fd.t[fd.extremes[k][1]]) for k in fd.nodes.flipped),
        work=FitWork(fd, base, free if apart is not None else None, largest), held_orders=held_orders,
    )


def _free_values(fd: PreparedRun, jf: JointFit, apart: HeldApart) -> dict[str, float]:
    """The free fit's parameters by the report's names (canonical order: identification's)."""
    free = None if apart.free is None else _from_core(
        fd, jf, apart.free, reproduced=False, held=np.zeros(jf.layout.n_nonlinear, bool))
    if free is None:
        return {}
    return dict(zip(free.params.names(), (float(v) for v in free.params.to_vector())))


def _parameters(fd: PreparedRun, orders: Orders, jf: JointFit, tau: float
                ) -> tuple[Parameters, np.ndarray, list[str]]:
    """The parameters with their standard errors (and corrected for the residuals'
    autocorrelation time tau), bounds, held and tied ones and why; the correlation matrix and
    the uncertainty's warnings."""
    lay = jf.layout
    params = jf.params
    names = params.names()
    values = params.to_vector()
    # Jacobian columns: linear (design order), nonlinear, [z0]  ->  flat name order
    lin_idx, nl_idx = lay.flat_index_of_linear(), lay.flat_index_of_nonlinear()
    free = ~jf.fixed_nonlinear
    col_names = [names[i] for i in lin_idx] + [names[i] for i in nl_idx[free]]
    col_values = np.concatenate([jf.linear, jf.nonlinear[free]])
    if jf.zero_fitted:
        col_names.append("contact_zero_N")
        col_values = np.append(col_values, jf.contact_zero_N)
    lower, upper = nonlinear_bounds(orders, lay.C, fd.loading_time_s)
    ranges = np.concatenate([np.full(lay.n_linear, np.inf), (upper - lower)[free],
                             [np.inf] if jf.zero_fitted else []])
    # a parameter at a bound of its range is said so once (_bound_warnings), not also as not determined
    said = {names[i] for i, _, _ in _at_bounds(names, values, lay, lower, upper)}
    unc = parameter_uncertainty(jf.jacobian, jf.residual, col_values, col_names, ranges=ranges, said=said)
    order = np.concatenate([lin_idx, nl_idx[free]])       # flat index of each column
    stderr = np.full(len(names), np.nan)
    stderr[order] = unc.stderr[:len(order)]
    corr = np.full((len(names), len(names)), np.nan)
    corr[np.ix_(order, order)] = unc.correlation[:len(order), :len(order)]
    flat_lower, flat_upper = np.full(len(names), -np.inf), np.full(len(names), np.inf)
    flat_lower[nl_idx], flat_upper[nl_idx] = lower, upper
    varied = np.ones(len(names), bool)
    varied[nl_idx[jf.fixed_nonlinear]] = False
    # shared orders: a later cycle's beta is the first cycle's (the same parameter, its statistics)
    tied = {names[i]: names[j] for i, j in lay.tied().items()}
    for i, j in lay.tied().items():
        stderr[i], flat_lower[i], flat_upper[i], varied[i] = stderr[j], flat_lower[j], flat_upper[j], varied[j]
        corr[i, :], corr[:, i] = corr[j, :], corr[:, j]
    why = {n: "shared orders: every cycle's order is the first cycle's" for n in tied}
    for i in nl_idx[jf.fixed_nonlinear]:
        why[names[i]] = (f"the data do not support an oscillation of damping mode {names[i][5:-3]} (BIC), "
                         "so it is a real mode" if names[i].startswith("alpha") else
                         "held apart: free, its term coalesces with another (identification.apart)")
    parameters = Parameters.of(names, values, stderr, flat_lower, flat_upper, varied, stderr * np.sqrt(tau),
                               tied, why)
    return parameters, corr, unc.warnings


def _turn_samples(evidence: np.ndarray, residual: np.ndarray) -> TurnSamples:
    at_turns = residual[~evidence]
    kept = residual[evidence] if evidence.any() else residual
    return TurnSamples(len(at_turns), float(np.sqrt(np.mean(kept ** 2))),
                       float(np.abs(at_turns).max()) if len(at_turns) else 0.0)


def _at_bounds(names, values, lay, lower, upper) -> list[tuple[int, int, str]]:
    """(flat index, index in the bounds, 'lower' | 'upper') of each nonlinear parameter at a bound
    of its search range (a real mode's Im alpha = 0 is the model, not a limit)."""
    out = []
    for j, i in enumerate(lay.flat_index_of_nonlinear()):
        v, span = values[i], upper[j] - lower[j]
        if names[i].endswith("_im") and v <= lower[j] + 1e-9 * span:
            continue
        if v <= lower[j] + AT_BOUND * span or v >= upper[j] - AT_BOUND * span:
            out.append((int(i), j, "lower" if v <= lower[j] + AT_BOUND * span else "upper"))
    return out


def _bound_warnings(names, values, lay, lower, upper) -> list[str]:
    out = []
    for i, j, which in _at_bounds(names, values, lay, lower, upper):
        hint = (" (fractional orders are limited to beta < 1, Eq. 10)"
                if names[i].startswith("beta") and which == "upper" and upper[j] == BETA_HI else
                " (search range of beta)" if names[i].startswith("beta") and lower[j] == BETA_LO else
                " (decay rates are searched within 0.1..100 per loading time)")
        out.append(f"{names[i]} = {values[i]:.4g} sits at its {which} bound{hint}: the optimum is "
                   "outside the model's range; the value is not an estimate")
    return out


def _zero_warnings(names, values, stderr, lay) -> list[str]:
    zero = []
    for i in lay.flat_index_of_linear():
        n = names[i]
        if n.startswith("k"):
            continue
        s = stderr[i]
        if np.isfinite(s) and abs(values[i]) < ZERO_T_VALUE * s:
            zero.append(f"{n} = {values[i]:.3g} +/- {s:.2g}")
    if len(zero) == 1:
        return [f"{zero[0]} is indistinguishable from zero: its term adds nothing the data can see "
                "(consider a lower order)"]
    return [f"{', '.join(zero)} are indistinguishable from zero: their terms add nothing the data can "
            "see (consider a lower order)"] if zero else []
