"""Fitting a candidate cause as an extension of the current model (the stages of a search).

screen: the effect's parameter scanned and refined with the base's alpha/beta held (cheap);
fit_joint: everything free (the base may have bent its alpha/beta to mimic the effect);
reidentify: a restart from identification's search on the data with the effect taken out;
walk: the effect's profile walked out from zero, each size's fit continued from the last;
probe: the three, short, for one cause; without: the model without one of its effects, refitted;
on_base: a fit's effects on another base.
All fits are the analysis core's (foamlab.analysis.solve.varpro).
"""

from __future__ import annotations

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.design import ExtendedModel, Series
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import (
    HOLD,
    POLISH_NFEV,
    Fit,
    base_bounds,
    bounds_like,
    contact_of,
    model_like,
    varpro,
)
from foamlab.diagnosis.causes import Cause
from foamlab.identification.joint import search_start
from foamlab.identification.paper import paper_steps

#: Iteration budgets of the screening (effect parameters only) and of the joint fits.
SCREEN_NFEV, PROBE_NFEV, JOINT_NFEV = 10, 4, 20
#: Iterations of the joint fit restarted from identification on corrected data.
RESTART_NFEV = 12
#: Iterations of each step of a walk (the effect held at one size, the rest polished from the last).
WALK_NFEV = 10
#: A walk goes no further on a side once its fit is this many noise variances worse than its best.
WALK_RISE = 1000.0
#: Multiples of its scale an effect the base imitates is started from in the search (multistart).
MULTISTART_SIZES = (0.1, 1.0)


def _settings(causes: list[type[Cause]], series: list[Series]) -> dict:
    return {c.effect.name: c.settings(series) for c in causes}


def screen(series: list[Series], current: Fit, causes: list[type[Cause]]) -> Fit:
    """Fit base + causes with the base's alpha/beta held: the last cause's parameter scanned,
    then the effect parameters refined (cheap: only the linear parameters move with them)."""
    model = ExtendedModel(series, current.params, [c.effect for c in causes], _settings(causes, series),
                          effect_bounds={c.effect.name: c.bounds() for c in causes},
                          base_bounds=current.model.base_bounds,     # orders held stay held when freed
                          masks=contact_of(current, series))
    prev = current.eta
    trials = [np.concatenate([prev, row]) for row in causes[-1].starts(series)]
    rss = [model.solve(eta).rss() for eta in trials]
    return Fit.of(list(causes), model, varpro(model, trials[int(np.argmin(rss))], max_nfev=SCREEN_NFEV))


def fit_joint(series: list[Series], start: Fit, current: Fit, max_nfev: int | None = None) -> Fit:
    """Fit base + causes with everything free (alpha, beta, effect and linear parameters).

    The base model can mimic an effect by bending its own alpha/beta (a fast damping
    mode and an order-near-1 residual term together act like friction at one speed);
    then the screening, with alpha/beta held, sees little, and a joint fit started
    at the screening's near-zero value stays there. So a cause the screening did not
    see starts from a visible size of its effect (both signs if it has two), and
    alpha/beta unbend as it grows.
    """
    model = model_like(start, series, free_base=True)
    if start.model.free_base:                 # continue a joint fit
        starts = [start.nu]
    else:
        eta0 = start.eta.copy()
        starts = [model.start(eta0)]
        seen = current.n * np.log(current.rss / start.rss) > np.log(current.n)
        if not seen:
            size = abs(start.causes[-1].joint_start(series))
            lo, hi = start.causes[-1].bounds()
            starts = []
            for side in ((1.0, -1.0) if lo[0] < 0 < hi[0] else (1.0,)):
                eta0[-1] = float(np.clip(side * size, lo[0], hi[0]))
                starts.append(model.start(eta0))
    best = None
    for nu0 in starts:
        optimum = varpro(model, nu0, max_nfev=max_nfev or JOINT_NFEV)
        if best is None or optimum.solution.rss() < best.solution.rss():
            best = optimum
    if best.solution.rss() > start.rss:
        # every start from a visible size ended in a worse local minimum than the screening
        # (a lag of seconds): the screening's fit is the extension's best, keep it
        return start
    return Fit.of(list(start.causes), model, best)


def multistart(series: list[Series], current: Fit, causes: list[type[Cause]], start: Fit | None = None,
               sizes: tuple[float, ...] = (), max_nfev: int = JOINT_NFEV) -> Fit:
    """The joint fit of an effect the base imitates (Cause.imitated_by_base), from several starts.

    The base bends alpha/beta and its linear terms to hold such an effect, so the joint
    objective has a valley of local minima along the effect's size (compliance against the
    elastic curve's shape): one start, from the screening, stops in the base's own basin.
    Started also from ``sizes`` (multiples of the effect's scale) and from ``start``'s effect
    value (a fit found from another base), the best is kept.
    """
    cause = causes[-1]
    screened = screen(series, current, causes)
    # the screening's own start: the search's joint probe has tried it already (start given there)
    best = fit_joint(series, screened, current, max_nfev) if sizes == () or start is None else screened
    model = model_like(screened, series, free_base=True)
    lo, hi = cause.bounds()
    scale = abs(cause.scale(series))
    values = [side * m * scale for m in sizes for side in ((1.0, -1.0) if lo[0] < 0 < hi[0] else (1.0,))]
    if start is not None:
        values.append(float(start.eta[-1]))
    for value in values:
        eta0 = screened.eta.copy()
        eta0[-1] = float(np.clip(value, lo[0], hi[0]))
        fit = Fit.of(list(causes), model, varpro(model, model.start(eta0), max_nfev=max_nfev))
        if fit.rss < best.rss:
            best = fit
    return best


def walk(series: list[Series], current: Fit, causes: list[type[Cause]], sizes: tuple[float, ...]) -> Fit:
    """The last cause's effect walked out from zero on each side it can take (its sizes in order):
    held at each size, the rest polished from the fit at the size before (continuation), until the
    fit is WALK_RISE noise variances worse than the best on that side; the best size's fit, the
    effect then freed. Identification takes a damping change into its own terms through another
    optimum than the base's: a start at one size lands in a basin the base left (B causal 3202,
    +21.7 %/cycle: polished from the base at 15 %/cycle 288 noise variances worse than the base,
    at 20 % 37 better), where the walk follows one basin out (docs/analysis.md, "A walk")."""
    cause = causes[-1]
    lo, hi = (float(b[0]) for b in cause.bounds())
    free = {c.effect.name: c.bounds() for c in causes}
    model_at = lambda bounds, fit: ExtendedModel(
        series, current.params, [c.effect for c in causes], _settings(causes, series), effect_bounds=bounds,
        free_base=True, base_bounds=bounds_like(current.model, series, current.params),
        masks=[m.copy() for m in fit.solution.masks])
    s2 = current.rss / current.n
    best = None
    for side in (1.0, -1.0) if lo < 0 < hi else (1.0,):
        at, floor = current, np.inf
        for size in (float(np.clip(side * m, lo, hi)) for m in sizes):
            model = model_at({**free, cause.effect.name: (np.array([size - HOLD]), np.array([size + HOLD]))}, at)
            nu = np.concatenate([at.model.split(at.nu)[0], at.eta[:model.n_eta - 1], [size]])   # phi0 if held
            at = Fit.of(list(causes), model, varpro(model, nu, max_nfev=WALK_NFEV))
            best = at if best is None or at.rss < best.rss else best
            floor = min(floor, at.rss)
            if at.rss > floor + WALK_RISE * s2 or size in (lo, hi):
                break
    freed = model_at(free, best)
    return Fit.of(list(causes), freed, varpro(freed, best.nu, max_nfev=RESTART_NFEV))


def without(series: list[Series], fit: Fit, index: int = -1) -> Fit:
    """The fit's model without one of its effects (default: the last), refitted from the fit's
    alpha/beta and the other effects' values."""
    m = fit.model
    index %= len(m.effect_types)
    sizes = [len(e.fitted_parameters()) for e in m.effect_types]
    first = sum(sizes[:index])
    model = ExtendedModel(series, fit.params, m.effect_types[:index] + m.effect_types[index + 1:], m.settings,
                          effect_bounds=m.effect_bounds, free_base=True,
                          base_bounds=bounds_like(m, series, fit.params), masks=contact_of(fit, series))
    eta = np.delete(fit.eta, np.arange(first, first + sizes[index]))
    causes = list(fit.causes[:index]) + list(fit.causes[index + 1:])
    return Fit.of(causes, model, varpro(model, model.start(eta), max_nfev=POLISH_NFEV))


def on_base(series: list[Series], fit: Fit, base: Fit, max_nfev: int = JOINT_NFEV) -> Fit:
    """The fit's effects on another base (the other residual form's): the base's alpha/beta and
    the effects from the fit's values, everything refitted jointly."""
    causes = list(fit.causes)
    model = ExtendedModel(series, base.params, [c.effect for c in causes], _settings(causes, series),
                          effect_bounds={c.effect.name: c.bounds() for c in causes}, free_base=True,
                          base_bounds=bounds_like(base.model, series, base.params), masks=contact_of(base, series))
    return Fit.of(causes, model, varpro(model, model.start(np.asarray(fit.eta, float)), max_nfev=max_nfev))


def reidentify(ref: PreparedRun, series: list[Series], fit: Fit, eta: np.ndarray | None = None,
               max_nfev: int = RESTART_NFEV) -> Fit:
    """The fit restarted from identification run on the data with its effects taken out.

    A base model that has bent its alpha/beta to mimic an effect sits in a local
    minimum the joint fit cannot leave; identification's own multi-start search on
    the corrected data (measured minus what the effects add, at the fit's values or
    at ``eta``; the reference run as prepared, its force replaced) finds the base the
    effect leaves behind, and the joint fit continues from there.
    """
    model = fit.model
    theta = fit.solution.theta
    phi = model.split(fit.nu)[0]
    eta = fit.eta if eta is None else np.asarray(eta, float)
    base_part = phi if model.free_base else []
    with_effects, without = (model.predict(theta, np.concatenate([base_part, e]))
                             for e in (eta, np.zeros(model.n_eta)))
    # the prediction is on the series' samples: the reference run's when not decimated
    effect = np.zeros(len(ref.series))
    effect[series[0].samples] = with_effects[0] - without[0]
    if series[0].obs is not None:                 # decimated: the effect between its samples
        effect = np.interp(ref.series.t, series[0].t, with_effects[0] - without[0])
    lay = fit.params.layout
    try:
        corrected = ref.with_force(ref.series.y - effect)
        orders = lay.orders
        params = search_start(corrected, orders, paper_steps(corrected, orders).start)
    except FoamlabError:
        return fit
    restart = ExtendedModel(series, params, model.effect_types, model.settings, free_base=True,
                            effect_bounds=model.effect_bounds,
                            base_bounds=base_bounds(series, params), masks=contact_of(fit, series))
    out = Fit.of(list(fit.causes), restart, varpro(restart, restart.start(eta), max_nfev=max_nfev))
    return out if out.rss < fit.rss else fit


def probe(ref: PreparedRun, series: list[Series], current: Fit, causes: list[type[Cause]],
          restarts: bool = True) -> Fit:
    """A short fit of base + causes: screening, a joint probe and, for a last cause that
    identification's staged fit absorbs (and ``restarts``), a walk out from zero where the cause
    has one (Cause.walk_sizes) and a restart from identification with the effect taken out at a
    visible size (on the side the screening leaned to)."""
    screened = screen(series, current, causes)
    fit = fit_joint(series, screened, current, PROBE_NFEV)
    cause = causes[-1]
    if cause.absorbed_by_identification and restarts:
        lo, hi = cause.bounds()
        side = -1.0 if screened.eta[-1] < 0 and lo[0] < 0 else 1.0
        tries = [side * abs(cause.joint_start(series)), side * abs(cause.scale(series))]
        if lo[0] < 0 < hi[0]:
            # the screening's lean is the base's, which has taken the effect up: a large change the
            # base holds can lean it the wrong way (independent B seed 1004, damping +100 %/cycle:
            # screened at -5 %); the scale is tried on the other side too
            tries.append(-side * abs(cause.scale(series)))
        for value in tries:
            eta = fit.eta.copy()
            eta[-1] = float(np.clip(value, lo[0], hi[0]))
            fit = reidentify(ref, series, _joint_at(series, fit, eta), eta)
    if cause.walk_sizes and restarts:
        # beside the restarts, not before them: their path from the probe is kept whole (A causal seed
        # 500, +100 %/cycle: continued from the walk's 50 %/cycle they ended at a third of it)
        walked = walk(series, current, causes, cause.walk_sizes)
        fit = walked if walked.rss < fit.rss else fit
    return fit


def _joint_at(series: list[Series], fit: Fit, eta: np.ndarray) -> Fit:
    """The joint fit continued from the fit's own base with the effect set to eta, if better.
    Identification on the corrected data can start far off (a base that holds the effect bends
    the correction too); the fit's own base, the effect at its size, reaches it in a few steps
    (independent A seed 500, damping +100 %/cycle: rss 66 -> 56.6 in 12 steps, d = 1.03, where
    the restart from identification needed 40 steps and only on some CPUs)."""
    model = model_like(fit, series, free_base=True)
    nu0 = model.start(fit.eta) if not fit.model.free_base else fit.nu.copy()
    nu0[model.n_phi:] = eta
    out = Fit.of(list(fit.causes), model, varpro(model, nu0, max_nfev=RESTART_NFEV))
    # a fit that slid back towards zero answered "not at this size": its gain is the base's own
    # optimum found by luck (A seed 500, zero drift 0.4 N/min: d 0.3 -> 0.035 moved the base
    # 0.202 -> 0.186 N, a basin the drift then fitted worse in), not the effect's
    kept = out.eta[-1] * eta[-1] > 0 and abs(out.eta[-1]) >= KEPT_SHARE * abs(eta[-1])
    return out if kept and out.rss < fit.rss else fit


#: A joint fit started with the effect at a size is kept only if the effect stays at this share of it.
KEPT_SHARE = 0.5
