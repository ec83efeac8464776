"""What this run could have seen: for each cause, the smallest size its diagnosis would name.

The acceptance rule's evidence is a likelihood ratio: an effect of size eta whose standard
error at the base fit is se gives LR ~ chi2(1, (eta / se)^2), named when LR - q ln(n) exceeds
settings.delta_bic_min. The limit is the size named in 90 % of runs like this one:
se * (sqrt(delta_bic_min + q ln n) + z_0.9). se comes from the information the run holds at
the base fit: the Jacobian of the base with the effect added at zero, alpha/beta free (a base
that imitates the effect takes its share of the information), the linear parameters
projected out (variable projection), on the prewhitened scale the rule uses.

A linearised limit promises too much where identification takes the effect into the model's
own terms through another optimum than the base's (a damping change in the causal form: 11 %/cycle
on B causal 3010 leaves nothing, where the limit said 7 %/cycle is seen; a lag under a sample).
An effect that grows faster than its size near zero (Cause.nonlinear_in_size: a memory lag) has
a slope there that promises too little; its limit is the size whose own effect reaches the target
with the base linearised (_sized), and then checked as below.
For the causes that can happen to (Cause.held_by_base) the limit is checked by injection
(checked): the effect added to the run's own fitted model, identification refitted on that run,
and the limit raised to the size whose left-over evidence reaches the rule's target where the
search would look for it: a quiet refit with no cause clearing the rule linearised on top keeps the
search in its basin (docs/analysis.md, "Limits checked by identification", "Held orders and the
quiet gate"). Where the refit of the run as it is misses identification's own fit of it, the
injections are read in the basin identification found ("A refit that misses the run's own fit").
Where no injection checks the limit of such a cause (a cause was named, several runs diagnosed
together, the check off), its text says it is linearised and unchecked (UNCHECKED).
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Callable, NamedTuple

import numpy as np
from scipy.optimize import lsq_linear
from scipy.stats import norm

from foamlab import FoamlabError
from foamlab.analysis.design import ExtendedModel, Series
from foamlab.analysis.noise import WHITE_P, ArWhitener, series_noise_sigma, whiteness
from foamlab.analysis.parallel import serial_map
from foamlab.analysis.prepared import PreparedRun, force_late
from foamlab.analysis.solve import Fit, at_full_resolution, bounds_like, contact_of, converged, decimation, held, polish
from foamlab.diagnosis.causes import Cause
from foamlab.diagnosis.settings import DiagnosisSettings
from foamlab.identification.fit import refit_core
from foamlab.identification.settings import DEFAULT as FIT

#: The limit is the size named in this share of runs like this one.
DETECTED_SHARE = 0.9
#: An injection at the linearised limit leaving this share of the target confirms it.
CONFIRMED_SHARE = 0.8
#: Growth of the size between two injections at most (a power law of slope 2 in between).
MAX_GROWTH = 4.0
#: Factors of the linearised limit an effect nonlinear in its size is evaluated at, smallest first.
SIZE_FACTORS = (0.125, 0.25, 0.4, 0.6, 0.8, 1.0)
#: Said after a limit of a cause the base can hold where no injection checked it (a cause was named,
#: several runs, or the check off): the checked limits of clean A causal 3500 are 1.4-4.6 x the
#: linearised ones (docs/analysis.md, "Unchecked limits say so").
UNCHECKED = " (linearised, unchecked: the size named can be larger)"


@dataclass(frozen=True)
class DetectionLimit:
    """The smallest size of one cause this run's diagnosis names in DETECTED_SHARE of runs."""

    cause: str
    parameter: str
    unit: str
    stderr: float      # of the effect parameter at the base fit (its unit)
    limit: float       # in the parameter's unit; nan where the run holds no information on it
    text: str          # in words and physical units: "no friction above 0.31 N"
    #: the checks by injection (checked): (size, what identification left of it in noise variances)
    injections: tuple[tuple[float, float], ...] = ()
    linearised: float = float("nan")   # the limit from the slope at zero, where checked or sized (else nan)
    #: a cause of either sign checked by injection (checked): limit is its rise's, this its drop's
    #: (a magnitude: the change below zero); nan for the others (limit holds for both, or one sign)
    limit_below: float = float("nan")
    #: a linearised limit of a cause the base can hold (Cause.held_by_base) that no injection checked
    unchecked: bool = False

    def to_dict(self) -> dict:
        finite = lambda v: float(v) if np.isfinite(v) else None
        return {"cause": self.cause, "parameter": self.parameter, "unit": self.unit,
                "stderr": finite(self.stderr), "limit": finite(self.limit), "text": self.text,
                "linearised": finite(self.linearised), "limit_below": finite(self.limit_below),
                "unchecked": self.unchecked,
                "injections": [[float(a), finite(b)] for a, b in self.injections]}


def detection_limits(series: list[Series], base: Fit, causes: list[type[Cause]], settings: DiagnosisSettings,
                     n_full: int | None = None, coalesced: np.ndarray | None = None) -> list[DetectionLimit]:
    """The limit of each cause (its first fitted parameter) on these runs at the base fit.

    series may be the search's decimated ones (base fitted on them): the information of every
    sample, n_full of them, is then the decimated samples' times n_full / n (the standard error
    over its square root) - a Jacobian on every sample costs seconds per cause.
    coalesced: the base's alpha/beta identification held apart (bool over them; None: none), held
    here too: linearised, a pair of nearly equal orders takes up a share of an effect that no fit
    of the pair reaches (B paper 3045, softening: se 0.00087 with them free, 0.00042 held, 0.00046
    from the profile likelihood; docs/analysis.md, "Held orders and the quiet gate")."""
    whitener = ArWhitener.fit(base.solution.used_residuals)
    n = n_full or base.n
    thin = np.sqrt(base.n / n)
    out = []
    for cause in causes:
        at_zero = _at_zero(series, base, [cause], whitener, coalesced)
        se = _stderr_at_zero(at_zero) * thin
        q = len(cause.effect.fitted_parameters())
        multiple = _multiple(settings, q, n)
        limit = se * multiple if np.isfinite(se) else float("nan")
        linearised = float("nan")
        if cause.nonlinear_in_size and np.isfinite(limit) and limit > 0:
            linearised, limit = limit, _sized(at_zero, q, multiple ** 2 * base.n / n, limit)
        p = cause.effect.fitted_parameters()[0]
        unchecked = bool(cause.held_by_base() and np.isfinite(limit) and limit > 0)
        text = _worded(cause, limit, unchecked=unchecked) if np.isfinite(limit) \
            else f"{cause.name}: not determined by this run"
        out.append(DetectionLimit(cause.name, p.name, p.unit, float(se), float(limit), text, linearised=linearised,
                                  unchecked=unchecked))
    return out


def _worded(cause: type[Cause], limit: float, below: float | None = None, unchecked: bool = False) -> str:
    """The limit in words (Cause.limit_text), marked UNCHECKED where no injection checked it."""
    return cause.limit_text(limit, below) + (UNCHECKED if unchecked else "")


def _multiple(settings: DiagnosisSettings, q: int, n: int) -> float:
    """The limit in standard errors: an effect this many from zero is named in DETECTED_SHARE of
    runs (its square: the noncentrality of the rule's test there)."""
    return float(np.sqrt(settings.delta_bic_min + q * np.log(n)) + norm.ppf(DETECTED_SHARE))


def _stderr_at_zero(at_zero: _AtZero) -> float:
    """Standard error of the cause's first parameter with the effect at zero and the base free
    (but the coalesced alpha/beta)."""
    first, rw, Jw = at_zero.n_phi, at_zero.rw, at_zero.Jw     # the effect's first follows alpha/beta
    sigma2 = float(rw @ rw) / max(len(rw) - Jw.shape[1], 1)
    try:
        cov = np.linalg.pinv(Jw.T @ Jw) * sigma2
    except np.linalg.LinAlgError:
        return float("nan")
    v = cov[first, first]
    return float(np.sqrt(v)) if np.isfinite(v) and v > 0 else float("nan")


def _sized(at_zero: _AtZero, k: int, target: float, linear: float) -> float:
    """The size whose own effect, not its slope at zero, reaches the target noncentrality (on these
    series' scale) with the base linearised: the effect at that size on the variable-projection
    residual, prewhitened, less what the base's free alpha/beta take up. For an effect that grows
    faster than its size (a memory lag: the jump at a turn released over tau reaches the sample after
    it as exp(-dt / tau), flat at zero) the slope at zero promises too little; named at half its
    linearised limit in 6 of 20 runs (docs/analysis.md, "A memory lag's limit by its size").
    Searched on a grid of factors of the linearised limit, log-log interpolated; never above it
    (linear: the linearised limit; k: the cause's fitted parameters, the last of at_zero's)."""
    model, nu, white, rw, Jw = at_zero.model, at_zero.nu, at_zero.white, at_zero.rw, at_zero.Jw
    fun = at_zero.fun
    r0 = fun(nu)
    others = Jw[:, :-k]                        # the free alpha/beta and the fit's own effects, whitened
    q, _ = np.linalg.qr(others) if others.shape[1] else (np.zeros((len(rw), 0)), None)
    sigma2 = float(rw @ rw) / max(len(rw) - Jw.shape[1], 1)
    first = model.n_nonlinear - k

    def lam(size: float) -> float:
        at = nu.copy()
        at[first] = size
        d = white(r0 - fun(at))
        d = d - q @ (q.T @ d)
        return float(d @ d) / sigma2

    prev = None
    for factor in SIZE_FACTORS:
        size = linear * factor
        value = lam(size)
        if not np.isfinite(value):
            return linear
        if value >= target:
            if prev is None or prev[1] <= 0:
                return size
            slope = np.log(value / prev[1]) / np.log(size / prev[0])
            return float(prev[0] * (target / prev[1]) ** (1 / slope)) if slope > 0 else size
        prev = (size, value)
    return linear


def whitened_at_zero(series: list[Series], base: Fit, causes: list[type[Cause]], whitener: ArWhitener,
                     coalesced: np.ndarray | None = None) -> tuple[int, np.ndarray, np.ndarray]:
    """The fit (the base, or a base with effects) extended by the causes, each new effect at zero:
    (how many of its alpha/beta are free, its residual and its variable-projection Jacobian - the
    free alpha/beta, the fit's own effects at their values, then each new effect's parameters -
    prewhitened). Parameters the bounds hold (identification's orders held apart) do not move in
    any fit: a column of theirs would take up information the rule's fits cannot; coalesced:
    alpha/beta left out as well (bool over them; detection_limits)."""
    at_zero = _at_zero(series, base, causes, whitener, coalesced)
    return at_zero.n_phi, at_zero.rw, at_zero.Jw


class _AtZero(NamedTuple):
    """The base extended by causes at zero (_at_zero): the model, its parameters, its residual
    function, the prewhitening, how many alpha/beta are free, the whitened residual and
    variable-projection Jacobian (free parameters only), and the steps the free parameters' bounds
    allow from nu (lower, upper)."""

    model: ExtendedModel
    nu: np.ndarray
    fun: Callable[[np.ndarray], np.ndarray]
    white: Callable[[np.ndarray], np.ndarray]
    n_phi: int
    rw: np.ndarray
    Jw: np.ndarray
    steps: tuple[np.ndarray, np.ndarray]


def _at_zero(series: list[Series], base: Fit, causes: list[type[Cause]], whitener: ArWhitener,
             coalesced: np.ndarray | None = None) -> _AtZero:
    """whitened_at_zero's work, with what _sized needs beside it (one Jacobian for both)."""
    model, nu, free, white, n_phi = _extended(series, base, causes, whitener, coalesced)
    fun, jac = model.residual_fn()
    r, J = fun(nu), jac(nu)[:, free]
    lower, upper = model.bounds()
    steps = (np.minimum(lower[free] - nu[free], 0.0), np.maximum(upper[free] - nu[free], 0.0))
    return _AtZero(model, nu, fun, white, n_phi, white(r),
                   np.column_stack([white(J[:, j]) for j in range(J.shape[1])]), steps)


def _extended(series: list[Series], base: Fit, causes: list[type[Cause]], whitener: ArWhitener,
              coalesced: np.ndarray | None = None):
    """The base extended by the causes at zero (whitened_at_zero): (model, nu, the free parameters
    (bool over nu), the prewhitening of a residual vector, how many alpha/beta are free)."""
    params, own = base.params, base.model
    model = ExtendedModel(series, params, list(own.effect_types) + [c.effect for c in causes],
                          {**own.settings, **{c.effect.name: c.settings(series) for c in causes}},
                          effect_bounds={**own.effect_bounds, **{c.effect.name: c.bounds() for c in causes}},
                          free_base=True, base_bounds=bounds_like(own, series, params), masks=contact_of(base, series))
    nu = model.start(np.concatenate([base.eta, np.zeros(model.n_eta - len(base.eta))]))
    free = ~held(*model.bounds())
    if coalesced is not None:
        free[:len(coalesced)] &= ~np.asarray(coalesced, bool)
    lengths = [int(m.sum()) for m in model.rows()]
    cuts = np.cumsum(lengths)[:-1]
    white = lambda v: whitener.apply(np.split(v, cuts))
    return model, nu, free, white, int(free[:model.n_phi].sum())


def gain_on_top(series: list[Series], fit: Fit, cause: type[Cause], whitener: ArWhitener,
                within_bounds: bool = False) -> float:
    """What one more cause would gain on top of the fit, linearised (a score test): the likelihood
    ratio, in noise variances, of its columns at zero with alpha/beta and the fit's own effects free
    and the linear parameters projected out, on the acceptance rule's prewhitened scale.

    within_bounds: the linearised step held inside the parameters' bounds (bounded least squares),
    where a direction of alpha/beta the run leaves ill-determined otherwise takes a step thousands of
    times its range and promises what no fit reaches (a 300 ms memory lag found, A causal 1008:
    friction 62 unbounded, 14.9 bounded, 15 fitted). The stop gate asks it so; the search's depth and
    the limits' check keep the free step their limits were measured with (held, the 1.5 x rows fell:
    docs/analysis.md, "The score test held inside the bounds")."""
    at = _at_zero(series, fit, [cause], whitener)
    q, rw, Jw = len(cause.effect.fitted_parameters()), at.rw, at.Jw
    s2 = float(rw @ rw) / len(rw)
    if within_bounds:      # an effect zero at its bound cannot step below it: the one-sided rule too
        lower, upper = at.steps
        with_cause = lsq_linear(Jw, -rw, bounds=(lower, upper), method="bvls").cost
        without = lsq_linear(Jw[:, :-q], -rw, bounds=(lower[:-q], upper[:-q]), method="bvls").cost \
            if Jw.shape[1] > q else 0.5 * float(rw @ rw)
        return 2.0 * (without - with_cause) / s2
    coef = np.linalg.lstsq(Jw, rw, rcond=None)[0]
    if cause.bounds()[0][0] >= 0.0 >= -coef[-q]:       # Gauss-Newton's step: the residual's Jacobian is -df
        # one-sided: an effect that is zero at its bound gains nothing where the data pull it below
        # (a frame of negative compliance flagged 110 on a 1 Hz softened run; fitted, -3.8)
        return 0.0
    fitted = Jw @ coef
    base = Jw[:, :-q] @ np.linalg.lstsq(Jw[:, :-q], rw, rcond=None)[0]
    return (float(fitted @ fitted) - float(base @ base)) / s2


def clearing_on_top(series: list[Series], fit: Fit, causes: list[type[Cause]], settings: DiagnosisSettings,
                    n_full: int | None = None, within_bounds: bool = False) -> list[type[Cause]]:
    """The causes whose gain on top of the fit, linearised (gain_on_top), would clear the evidence
    rule: Delta BIC = gain - q ln n above settings.delta_bic_min. series may be the search's
    decimated ones, the fit on them: every sample's information is then the decimated samples'
    times n_full / n (as detection_limits)."""
    whitener = ArWhitener.fit(fit.solution.used_residuals)
    return [c for c in causes
            if _clears(_gain(series, fit, c, whitener, n_full, within_bounds), c, settings, n_full or fit.n)]


def left_on_top(coarse: list[Series], on: Fit, series: list[Series], fit: Fit, causes: list[type[Cause]],
                settings: DiagnosisSettings) -> list[type[Cause]]:
    """The causes that would clear the rule on top of the fit, their score's step inside the bounds:
    screened on the decimated runs `coarse` (the fit carried to them `on`), decided on every sample
    (the decimated, scaled score promised friction 44 where every sample's gave 15, and its fit 15;
    docs/analysis.md, "The score test held inside the bounds"). About 0.2 s a cause."""
    screened = clearing_on_top(coarse, on, causes, settings, fit.n, within_bounds=True)
    return clearing_on_top(series, fit, screened, settings, within_bounds=True) if screened else []


def _gain(series: list[Series], fit: Fit, cause: type[Cause], whitener: ArWhitener, n_full: int | None,
          within_bounds: bool = False) -> float:
    """gain_on_top on the scale of n_full samples (the fit's own where None)."""
    return gain_on_top(series, fit, cause, whitener, within_bounds) * (n_full or fit.n) / fit.n


def _clears(gain: float, cause: type[Cause], settings: DiagnosisSettings, n: int) -> bool:
    return gain - len(cause.effect.fitted_parameters()) * np.log(n) > settings.delta_bic_min


def quiet(fit: Fit, sigma: float, settings: DiagnosisSettings) -> bool:
    """The fit leaves white noise at the noise level sigma (or any residuals at it)."""
    excess = fit.rss / (fit.n * sigma ** 2) - 1
    return bool(excess < settings.at_noise or (
        excess < settings.near_noise and whiteness(fit.solution.residual).min_p >= WHITE_P))


def opens_search(fit: Fit, sigma: float, coarse: list[Series], on: Fit, causes: list[type[Cause]],
                 settings: DiagnosisSettings) -> bool:
    """Does the search look past the fit's basin (its restarts and several starts)? Where the fit is
    not quiet, or a cause clears the evidence rule linearised on top of it (the score test on the
    decimated runs `coarse`, the fit carried to them `on`; the causes in order, the first that
    clears ends it). The noise level's estimate scatters by +-5 % of the variance on clean runs:
    quiet alone would hide an effect the base took up (docs/analysis.md, "Held orders and the
    quiet gate")."""
    if not settings.deep_only_on_structure or not quiet(fit, sigma, settings):
        return True
    whitener = ArWhitener.fit(on.solution.used_residuals)
    return any(_clears(_gain(coarse, on, c, whitener, fit.n), c, settings, fit.n) for c in causes)


def checked(limits: list[DetectionLimit], ref: PreparedRun, base: Fit, causes: list[type[Cause]],
            settings: DiagnosisSettings, fmap=None, progress=None) -> list[DetectionLimit]:
    """The limits of the causes the base can take into its own terms (Cause.held_by_base) checked by
    injection, at most settings.limit_injections refits each: a limit is only raised, never lowered
    (a refit can find the base a better optimum by luck; it cannot make an effect more visible).
    ref: the run (one) as prepared, base: its base fit on every sample; fmap(fn, items, done=None): a
    map (the diagnosis' forked one) calling done(i, result) as each item ends; progress(k, n): k of
    the check's n jobs done (the refit of the run as it is, each cause's first injection, then each
    cause's placement) - the check is most of a clean run's diagnosis (docs/benchmarks.md)."""
    todo = [c for c in causes if c.held_by_base() and settings.limit_injections > 0]
    by_name = {c.name: c for c in todo}
    # a cause with both signs is checked on each, and has a limit for each: identification can take
    # a change of one sign into its own terms and not the other's (independent A causal seeds 6000,
    # 6004: a damping drop of 20 %/cycle left only the noise; their clean runs' rise is seen from
    # 14-15 %/cycle, the drop from 31-36)
    jobs = [(lim, sign) for lim in limits if lim.cause in by_name and np.isfinite(lim.limit) and lim.limit > 0
            for sign in by_name[lim.cause].signs()]
    if not jobs:
        return limits
    injector = _Injector(ref, base, causes, settings)
    fmap = fmap or serial_map
    total = 1 + 2 * len(jobs)
    ended = iter(range(1, total + 1))
    tick = (lambda i, result: progress(next(ended), total)) if progress else None
    # the refit of the run as it is and the first injection of each cause are independent: one map
    firsts = [(None, 0.0)] + [(by_name[lim.cause], sign * lim.limit) for lim, sign in jobs]
    first = fmap(lambda job: injector.refit(*job), firsts, done=tick)
    if injector.lost(first[0]):
        # the search missed the run's own optimum: what identification leaves is read in the basin
        # it found, the run as it is and each first injection polished from the base (_Injector.lost)
        injector.from_base = True
        first = fmap(lambda job: injector.refit(*job), firsts)
    injector.reference = first[0].white
    # the ladders furthest from their target first: they have the most refits left, and a long one
    # started last keeps one core busy alone at the end
    order = sorted(range(len(jobs)), key=lambda k: injector.share(by_name[jobs[k][0].cause], first[k + 1]))
    ladders = fmap(lambda k: injector.place(by_name[jobs[k][0].cause], jobs[k][0].limit, first[k + 1], jobs[k][1]),
                   order, done=tick)
    placed = [side for _, side in sorted(zip(order, ladders), key=lambda kv: kv[0])]
    sides: dict[str, list] = {}
    for (lim, _), side in zip(jobs, placed):
        sides.setdefault(lim.cause, []).append(side)
    out = []
    for lim in limits:
        if lim.cause not in sides:
            out.append(lim)
            continue
        (size, _), *drop = sides[lim.cause]           # each sign's own limit: one can be 3 x the other
        below = float(drop[0][0]) if drop else float("nan")
        tried = tuple(t for _, side in sides[lim.cause] for t in side)
        # a check whose every injection could not be fitted leaves the linearised limit unchecked
        unchecked = not any(np.isfinite(lam) for _, lam in tried)
        text = _worded(by_name[lim.cause], size, below, unchecked) if np.isfinite(size) else lim.text
        out.append(replace(lim, limit=float(size), text=text, injections=tried, linearised=lim.limit,
                           limit_below=below, unchecked=unchecked))
    return out


@dataclass(frozen=True)
class _Refit:
    """Identification's refit of the run with an effect injected: its prewhitened residual sum of
    squares, and what the diagnosis' search would see of the effect on top of it where it stays in
    the refit's own basin (the gate closed: the refit quiet and no cause clearing the rule
    linearised), in noise variances (inf: the gate open, the search looks further)."""

    white: float
    local: float = float("inf")


class _Injector:
    """The run's own fitted model with one cause's effect added at a size, and what identification's
    refit of that run leaves of it: the noncentrality of the evidence rule's test, in noise variances
    on the rule's prewhitened scale, against the same refit of the run as it is (from_base: each
    polished from the base instead of searched, where the search missed the run's own fit: lost)."""

    def __init__(self, ref: PreparedRun, base: Fit, causes: list[type[Cause]], settings: DiagnosisSettings):
        self.ref, self.base, self.causes, self.settings = ref, base, causes, settings
        self.orders = base.params.layout.orders
        self.whitener = ArWhitener.fit(base.solution.used_residuals)
        white = self.whitener.apply(base.solution.used_residuals)
        self.base_white = float(white @ white)
        self.sigma2 = self.base_white / max(len(white) - base.solution.theta.size, 1)
        self.reference = float("nan")     # refit(None).white: set by checked
        self.from_base = False            # refits from the base, not searched: set by checked (lost)

    def refit(self, cause: type[Cause] | None, size: float) -> _Refit:
        """Identification's refit of the run with the cause's effect added to its fitted model at
        this size (None: the run as it is). white nan where the injected run cannot be fitted (a
        size the model cannot make, a run the refit cannot identify): the check then stops; a
        first injection's leaves the linearised limit, a later one what the earlier ones showed."""
        force = self.ref.series.y + (self._injected(cause, size) if cause is not None else 0.0)
        if not np.all(np.isfinite(force)):
            return _Refit(float("nan"))
        run = self.ref.with_force(force)
        try:
            fit = self._from_base(run) if self.from_base else refit_core(run, self.orders)
        except (FoamlabError, np.linalg.LinAlgError):
            return _Refit(float("nan"))
        if fit is None:
            return _Refit(float("nan"))
        white = self.whitener.apply(fit.solution.used_residuals)
        return _Refit(float(white @ white), self._local(run, fit, cause) if cause is not None else float("inf"))

    def _injected(self, cause: type[Cause], size: float) -> np.ndarray:
        """What the cause at this size adds to the run's force, on the run's own fitted model: the
        effect added to it; a reading late (Cause.reads_late) read along the path that late, as a
        real channel is (the effect's batch form put 30-33 N at the sample after a turn where an
        independent lag puts 2-52 on A causal 3068; docs/analysis.md, "A lag is read along the path")."""
        b, s = self.base, self.ref.series
        if cause.reads_late:
            late, now = np.maximum(force_late(b.params, self.ref, (size, 0.0)), 0.0)
            return late - now
        m = ExtendedModel([s], b.params, list(b.model.effect_types) + [cause.effect],
                          {**b.model.settings, cause.effect.name: cause.settings([s])},
                          effect_bounds={**b.model.effect_bounds, cause.effect.name: cause.bounds()},
                          masks=contact_of(b, [s]))
        with_it, without = (m.predict(b.solution.theta, np.concatenate([b.eta, [v]]))[0] for v in (size, 0.0))
        return with_it - without

    def lost(self, refit: _Refit) -> bool:
        """The refit of the run as it is ended further above identification's own fit of it (the base)
        than an injection is placed to (1 - CONFIRMED_SHARE of the rule's target): the search missed
        the run's optimum, and a difference of two refits counts that miss where one refit finds the
        optimum and the other does not (independent B paper 3077: 284 noise variances above the base,
        every limit 2-4 x its neighbours', six causes named at half their limit)."""
        gap = (refit.white - self.base_white) / self.sigma2
        return bool(gap > (1 - CONFIRMED_SHARE) * _multiple(self.settings, 1, self.base.n) ** 2)

    def _from_base(self, run: PreparedRun) -> Fit:
        """Identification's polish of the run from the base's alpha/beta (its basin), carried to
        convergence: what a fit that starts where identification ended on the run as it is takes in."""
        return converged(polish([run.series], self.base.params, nfev=FIT.polish_nfev), FIT.max_nfev)

    def _local(self, run: PreparedRun, fit: Fit, cause: type[Cause]) -> float:
        """The cause's linearised gain on top of the refit where the search would stay in the refit's
        basin (opens_search, as Procedure.search asks it); inf where it would look further."""
        s = run.series
        k = decimation([s])
        coarse = [s.decimated(k)] if k > 1 else [s]
        on = at_full_resolution(fit, coarse)
        order = [cause] + [c for c in self.causes if c is not cause]
        if opens_search(fit, series_noise_sigma([s.y]), coarse, on, order, self.settings):
            return float("inf")
        return _gain(coarse, on, cause, ArWhitener.fit(on.solution.used_residuals), fit.n)

    def noncentrality(self, cause: type[Cause], size: float, refit: _Refit | None = None) -> float:
        """What the refit leaves of the effect where the search would see it, in noise variances
        (refit: the injection's, if done)."""
        refit = self.refit(cause, size) if refit is None else refit
        return min((refit.white - self.reference) / self.sigma2, refit.local)

    def share(self, cause: type[Cause], refit: _Refit) -> float:
        """What the refit leaves of the effect as a share of the cause's target (inf: nan, not
        checked further)."""
        lam = self.noncentrality(cause, 0.0, refit)
        return lam / self._target(cause) if np.isfinite(lam) else np.inf

    def _target(self, cause: type[Cause]) -> float:
        return _multiple(self.settings, len(cause.effect.fitted_parameters()), self.base.n) ** 2

    def place(self, cause: type[Cause], linear: float, refit: _Refit | None = None, sign: float = 1.0
              ) -> tuple[float, tuple[tuple[float, float], ...]]:
        """The size (a magnitude, injected with this sign) whose injection leaves the target: the
        linearised limit where an injection there confirms it; otherwise grown (a power law of slope
        2, at most MAX_GROWTH a step) until one is seen, then halved in log size between the last
        unseen and the first seen; the limit is the log-log interpolation of the two nearest (the
        seen one where that is not a power law). The tries are (signed size, what was left)."""
        lo_bound, hi_bound = (float(b[0]) for b in cause.bounds())
        top = hi_bound if sign > 0 else -lo_bound
        target = self._target(cause)
        grow = lambda size, lam: min(size * min(np.sqrt(target / max(lam, target / 16)), MAX_GROWTH), top)
        tried = [(linear, self.noncentrality(cause, sign * linear, refit))]
        if not tried[0][1] < CONFIRMED_SHARE * target:       # confirmed, or nan: not checked
            return linear, _signed(tried, sign)
        lo, hi = tried[0], None
        while len(tried) < self.settings.limit_injections:
            size = grow(*lo) if hi is None else float(np.sqrt(lo[0] * hi[0]))
            if size <= lo[0]:
                break                   # at the effect's largest size
            lam = self.noncentrality(cause, sign * size)
            tried.append((size, lam))
            if not np.isfinite(lam):
                break                   # identification cannot fit it: what the earlier ones showed stands
            if lam >= target:
                hi = tried[-1]
            else:
                lo = tried[-1]
            if abs(lam / target - 1) <= 1 - CONFIRMED_SHARE:
                break                   # at the target, as closely as an injection confirms one
        if hi is None:                  # not seen yet: the power law's size past the last unseen one
            return max(linear, grow(*lo)), _signed(tried, sign)
        slope = (np.log(hi[1] / lo[1]) / np.log(hi[0] / lo[0])) if lo[1] > 0 else np.inf
        size = lo[0] * (target / lo[1]) ** (1 / slope) if 0.5 <= slope <= 12 else hi[0]
        return float(max(linear, size)), _signed(tried, sign)


def _signed(tried: list[tuple[float, float]], sign: float) -> tuple[tuple[float, float], ...]:
    return tuple((sign * size, lam) for size, lam in tried)
