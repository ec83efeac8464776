"""Diagnosis: fit the base model, test each candidate cause as an extension, decide.

Procedure (a nested-model test that does not cry wolf):

1. Base model: identification's fit, its alpha/beta polished together with k, a, r
   and the load cell's zero on all runs at once (contact clipping included).
2. Each applicable cause is fitted as an extension: first with the base's
   alpha/beta held (a scan of the effect's parameter, then least squares: cheap),
   then the most promising (JOINT_CANDIDATES) with everything free -- the base
   model may have bent its alpha/beta to mimic the effect. Variable projection
   throughout: the linear parameters are re-solved at every step.
3. Evidence, on the same prewhitened scale for every model (an AR(p) filter fitted
   to the best model's residuals): Delta BIC = n ln(RSS_before/RSS_after) - q ln n and
   the likelihood-ratio p-value. A candidate with Delta BIC > DELTA_BIC_MIN is
   checked on held-out data: each run is cut into contiguous blocks, held out
   HELDOUT_FOLDS interleaved groups at a time, each group predicted by the model
   refitted (all its parameters) without it; the candidate passes if its held-out
   RMSE is below the model's without it.
4. The best passing candidate is accepted; the others are tried again on top of it
   (up to MAX_FINDINGS findings).
5. Verdict: `none` when no candidate passes and the base residuals are white;
   the first finding's name when the accepted extension leaves white residuals or
   explains at least EXPLAINED_SHARE_MIN of the structure the base model left
   above the noise; `unexplained` otherwise (structure, and where it is).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
from scipy.stats import chi2
from threadpoolctl import threadpool_limits

from foamlab import FoamlabError
from foamlab.analysis.design import ExtendedModel, Series, Solution
from foamlab.analysis.noise import ArWhitener, Whiteness, series_noise_sigma, whiteness
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import (
    POLISH_NFEV,
    Fit,
    at_full_resolution,
    base_bounds,
    contact_of,
    decimation,
    model_like,
    varpro,
)
from foamlab.diagnosis.causes import CAUSES, Cause
from foamlab.diagnosis.residuals import ResidualAnalysis, analyse
from foamlab.identification.joint import search_start
from foamlab.identification.paper import paper_steps
from foamlab.model.layout import Orders
from foamlab.model import ModelParameters

#: A candidate must improve BIC (prewhitened residuals) by more than this ("very strong" evidence).
DELTA_BIC_MIN = 10.0
#: ...and its effect's (first) parameter must lie this many standard errors from zero. Measured
#: on clean recordings through the drivers: extensions 17-40 BIC points better than the base
#: with their effect at 0.4-3 standard errors (the base's alpha/beta improved in their fit);
#: the hidden effects named there lie 14-140 standard errors from zero.
EFFECT_Z_MIN = 3.0
#: ...and not end within this fraction of its range of a non-zero limit (see Candidate.pinned).
PINNED_FRACTION = 0.01
#: Whiteness tests below this p-value mean structure.
WHITE_P = 1e-3
#: Share of the base model's excess over the noise an extension must explain to be named
#: when its residuals are still not white.
EXPLAINED_SHARE_MIN = 0.5
#: ...a cause explaining at least this share (and passing the tests) is reported as partial.
PARTIAL_SHARE_MIN = 0.1
#: Contiguous blocks of each run in the held-out check.
HELDOUT_FOLDS = 6
#: ...each made of blocks of about this many samples spread over the run (at least 8 per fold).
#: Short blocks: a long block left out just after a turning point leaves that cycle's fast
#: residual terms to be extrapolated backwards from later samples; measured on 16 Hz runs of
#: ~900 samples, with blocks of 18 samples that one block decided the check (the right
#: extension's held-out RMSE 0.40 N in it, 0.055 N in the other folds), with ~5-9 none did.
HELDOUT_BLOCK_SAMPLES = 10
HELDOUT_BLOCKS_PER_FOLD = 8
#: Iterations of the refit without the held-out blocks.
HELDOUT_NFEV = 3
#: Candidates (by Delta BIC) that get the held-out check in each round.
HELDOUT_CANDIDATES = 3
MAX_FINDINGS = 3
#: After a finding, residual variance within this fraction of the noise variance is not
#: searched further (what is left is the fit's own imperfection, not a second cause).
NEAR_NOISE = 0.1
#: Candidates (by the screening's gain) refitted with the base model's alpha/beta free.
JOINT_CANDIDATES = 2
#: ...and of those, this many carried to full resolution (the others are judged on the search's samples).
FULL_CANDIDATES = 2
#: Iteration budgets of the screening (effect parameters only) and of the joint fits.
SCREEN_NFEV, PROBE_NFEV, JOINT_NFEV = 10, 4, 20
#: Iterations of the joint fit restarted from identification on corrected data.
RESTART_NFEV = 12


@dataclass
class Candidate:
    cause: type[Cause]
    fit: Fit
    before: Fit
    coarse_fit: Fit | None = None      # the same model on the decimated search samples
    share: float = float("nan")        # of the structure left above the noise it explains
    delta_bic: float = float("nan")
    lr_p: float = float("nan")
    passed: bool = False
    reason: str = ""

    @property
    def name(self) -> str:
        return self.cause.name

    @property
    def values(self) -> dict:
        return self.fit.effect_values()[-1]

    @property
    def z_score(self) -> float:
        """The effect's first parameter in standard errors from zero (nan: undetermined)."""
        v = self.values
        name = self.cause.effect.fitted_parameters()[0].name
        se = v["stderr"].get(name, float("nan"))
        return abs(v["values"][name]) / se if se and np.isfinite(se) and se > 0 else float("nan")

    @property
    def pinned(self) -> str:
        """'' - or which fitted parameter ended on a limit of its range other than zero.

        The optimum lies beyond what the effect can physically be (a damping change that
        would make a later cycle's damping vanish): the data ask for something else, which
        this effect imitates at its limit (measured: a cycle_softening of 10 %/cycle through
        a driver fitted as damping_cycle_change at its -0.45 bound, dBIC 337 vs 330).
        """
        lo, hi = self.cause.bounds()
        v = self.values["values"]
        for p, a, b in zip(self.cause.effect.fitted_parameters(), lo, hi):
            tol = PINNED_FRACTION * (b - a)
            for limit in (a, b):
                if limit != 0 and abs(v[p.name] - limit) <= tol:
                    return f"{p.name} = {v[p.name]:.4g} at the limit of its range ({limit:g})"
        return ""

    def description(self) -> str:
        v = self.values
        return self.cause.describe(v["values"], v["stderr"])

    def gain(self) -> dict:
        return {
            "rmse_before": self.before.rmse,
            "rmse_after": self.fit.rmse,
            "heldout_rmse_before": self.before.heldout_rmse,
            "heldout_rmse_after": self.fit.heldout_rmse,
            "delta_bic": self.delta_bic,
        }


@dataclass
class Diagnosis:
    verdict: str
    findings: list[Candidate]
    partial: list[Candidate]               # pass the tests but explain only part of the structure
    tested: list[list[Candidate]]          # every candidate of every round
    skipped: dict[str, str]                # cause -> why it was not tested
    base: Fit
    final: Fit
    base_analysis: ResidualAnalysis
    final_analysis: ResidualAnalysis
    final_whiteness: Whiteness
    explained_share: float
    noise_sigma: float
    series: list[Series]
    params: ModelParameters
    seconds: float = 0.0
    notes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """The JSON object of `foamlab diagnose --json` (see docs/DESIGN: verdict, findings)."""
        findings = []
        if self.verdict == "unexplained":
            findings.append({
                "effect": "unexplained",
                "gain": {"rmse_before": self.base.rmse, "rmse_after": self.final.rmse,
                         "heldout_rmse_before": self.base.heldout_rmse,
                         "heldout_rmse_after": self.final.heldout_rmse, "delta_bic": 0.0},
                "where": self.final_analysis.where(),
                "residuals": self.final_analysis.to_dict(),
                "explained_share": self.explained_share,
            })
        for i, c in enumerate(self.findings + self.partial):
            findings.append({
                "effect": c.name,
                "gain": c.gain(),
                "parameters": {k: {"value": v, "stderr": c.values["stderr"].get(k)}
                               for k, v in c.values["values"].items()},
                "description": c.description(),
                "meaning": c.cause.meaning,
                "p_value": c.lr_p,
                "rank": i + 1,
                "named": self.verdict == c.name,
                "explained_share": c.share,
            })
        return {"verdict": self.verdict, "findings": _jsonable(findings)}


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if np.isfinite(v) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


# ----------------------------------------------------------------------------- fitting

def _settings(causes: list[type[Cause]], series: list[Series]) -> dict:
    return {c.effect.name: c.settings(series) for c in causes}


def screen(series: list[Series], current: Fit, causes: list[type[Cause]]) -> Fit:
    """Fit base + causes with the base's alpha/beta held: the last cause's parameter scanned,
    then the effect parameters refined (cheap: only the linear parameters move with them)."""
    model = ExtendedModel(series, current.params, [c.effect for c in causes], _settings(causes, series),
                          effect_bounds={c.effect.name: c.bounds() for c in causes},
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


def without_last(series: list[Series], fit: Fit) -> Fit:
    """The fit's model without its last effect, refitted from the fit's alpha/beta."""
    m = fit.model
    model = ExtendedModel(series, fit.params, m.effect_types[:-1], m.settings, effect_bounds=m.effect_bounds,
                          free_base=True,
                          base_bounds=base_bounds(series, fit.params), masks=contact_of(fit, series))
    k = len(m.effect_types[-1].fitted_parameters())
    eta = fit.eta[:len(fit.eta) - k]
    return Fit.of(list(fit.causes[:-1]), model, varpro(model, model.start(eta), max_nfev=POLISH_NFEV))


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
        orders = Orders(N=lay.N, M=lay.M, P=lay.P)
        params = search_start(corrected, orders, paper_steps(corrected, orders).start)
    except FoamlabError:
        return fit
    restart = ExtendedModel(series, params, model.effect_types, model.settings, free_base=True,
                            effect_bounds=model.effect_bounds,
                            base_bounds=base_bounds(series, params), masks=contact_of(fit, series))
    out = Fit.of(list(fit.causes), restart, varpro(restart, restart.start(eta), max_nfev=max_nfev))
    return out if out.rss < fit.rss else fit


def probe(ref: PreparedRun, series: list[Series], current: Fit, causes: list[type[Cause]]) -> Fit:
    """A short fit of base + causes: screening, a joint probe and, for a last cause that
    identification's staged fit absorbs, a restart from identification with the effect
    taken out at a visible size (on the side the screening leaned to)."""
    screened = screen(series, current, causes)
    fit = fit_joint(series, screened, current, PROBE_NFEV)
    cause = causes[-1]
    if cause.absorbed_by_identification:
        lo, hi = cause.bounds()
        side = -1.0 if screened.eta[-1] < 0 and lo[0] < 0 else 1.0
        for size in (abs(cause.joint_start(series)), abs(cause.scale(series))):
            eta = fit.eta.copy()
            eta[-1] = float(np.clip(side * size, lo[0], hi[0]))
            fit = reidentify(ref, series, fit, eta)
    return fit


def folds(series: list[Series], n_folds: int = HELDOUT_FOLDS,
          blocks_per_fold: int | None = None) -> list[list[np.ndarray]]:
    """Keep-masks per fold. Each run is cut into n_folds x blocks_per_fold contiguous
    blocks (default: blocks of ~HELDOUT_BLOCK_SAMPLES samples); fold k leaves out blocks
    k, k + n_folds, ... (interleaved), so every cycle keeps data that determine its own
    parameters and each held-out block is predicted, not extrapolated past the end of
    what was fitted. Samples measured off the specimen stay in every fit: their force is
    the unloaded reading whatever the model, so they carry no information on its
    parameters, only where the plate leaves the specimen - a fit without them is free to
    put contact there (measured on the real file: blocks at the end of an unloading,
    predicted 5-11 N where the plate was off, decided the check for every model alike)."""
    out = []
    for k in range(n_folds):
        masks = []
        for s in series:
            per_fold = blocks_per_fold or max(HELDOUT_BLOCKS_PER_FOLD,
                                               int(round(len(s) / (n_folds * HELDOUT_BLOCK_SAMPLES))))
            m = np.ones(len(s), dtype=bool)
            edges = np.linspace(0, len(s), n_folds * per_fold + 1).astype(int)
            for b in range(k, n_folds * per_fold, n_folds):
                m[edges[b]:edges[b + 1]] = False
            if s.no_contact is not None:
                m |= s.no_contact
            masks.append(m)
        out.append(masks)
    return out


def heldout_rmse(fit: Fit, on: Fit | None = None, n_folds: int = HELDOUT_FOLDS) -> float:
    """RMSE of every block predicted by the model refitted (all its parameters) without it.

    on: the same model on other (decimated) samples to do it on; the result is stored
    in ``fit``.
    """
    if fit.heldout_rmse is not None:
        return fit.heldout_rmse
    work = on or fit
    sq, count = 0.0, 0
    for keep in folds(work.model.series, n_folds):
        sol = _refit_without(work, keep)
        out = ~np.concatenate(keep) & np.concatenate(sol.used)
        r = np.concatenate(sol.residuals)[out]
        sq += float(r @ r)
        count += len(r)
    fit.heldout_rmse = float(np.sqrt(sq / max(count, 1)))
    return fit.heldout_rmse


def _refit_without(fit: Fit, keep: list[np.ndarray]) -> Solution:
    """The fit redone without the held-out samples: the linear parameters exactly and the
    effect parameters by a few trust-region steps from the full-data optimum. The base
    model's alpha/beta stay at their full-data values, for both models alike (refitting
    them per block would cost most of the diagnosis and moves them by a fraction of
    their standard error)."""
    model = fit.model
    if model.free_base:
        model = ExtendedModel(model.series, fit.params, model.effect_types, model.settings,
                              effect_bounds=model.effect_bounds, masks=contact_of(fit, model.series))
    if not model.n_eta:
        return model.solve((), keep)
    return varpro(model, fit.eta, keep, max_nfev=HELDOUT_NFEV).solution


def _before_with_contact_of(before: Fit, fit: Fit) -> Solution:
    """The model without the candidate's effect, solved from the candidate's contact set (the
    better of that and its own solution). The active-set iteration ends in a fixed point that
    depends on its start: an extension that merely found a better contact set would
    otherwise be credited with it (measured on clean recordings: every candidate at ~0
    effect 17-41 BIC points better than the base, and one of them named)."""
    if not all(a is b for a, b in zip(before.model.series, fit.model.series)):
        return before.solution
    m = before.model
    again = ExtendedModel(m.series, m.params, m.effect_types, m.settings, free_base=m.free_base,
                          base_bounds=m.base_bounds, effect_bounds=m.effect_bounds,
                          masks=fit.solution.masks).solve(before.nu)
    return again if again.rss() < before.solution.rss() else before.solution


def _compare(cands: list[Candidate], before: Fit) -> None:
    """Delta BIC and LR p-value of each candidate against `before`, on one prewhitened scale."""
    best = min([c.fit for c in cands] + [before], key=lambda f: f.rss)
    whitener = ArWhitener.fit(best.solution.used_residuals)
    for c in cands:
        base = _before_with_contact_of(before, c.fit)
        wb = whitener.apply(base.used_residuals)
        rss_b, n = float(wb @ wb), len(wb)
        we = whitener.apply(c.fit.solution.used_residuals)
        rss_e = float(we @ we)
        q = c.fit.model.n_eta - before.model.n_eta
        lr = n * np.log(rss_b / rss_e) if rss_e > 0 and rss_b > 0 else 0.0
        # the fits minimise the plain residuals: a candidate that fits them worse than the
        # model it extends (a worse local optimum) has no evidence, whatever the filter
        # does to it (one AR filter can favour a residual that moved its error to low
        # frequencies); so the plain likelihood ratio bounds the prewhitened one
        n_raw = c.fit.n
        if c.fit.rss > 0 and base.rss() > 0:
            lr = min(lr, n_raw * np.log(base.rss() / c.fit.rss) * n / max(n_raw, 1))
        c.delta_bic = float(lr - q * np.log(n))
        c.lr_p = float(chi2.sf(max(lr, 0.0), q))


# ----------------------------------------------------------------------------- diagnose

def diagnose_prepared(runs: list[PreparedRun], base: Fit, causes: list[str] | None = None) -> Diagnosis:
    """Diagnose prepared runs (the first the reference) from a base model fitted on all of them
    (identification's core fit for one run, analysis.solve.polish for several)."""
    with threadpool_limits(1, user_api="blas"):    # small dense solves: threads only contend
        return _diagnose(runs, base, causes)


def _diagnose(runs: list[PreparedRun], base: Fit, causes: list[str] | None) -> Diagnosis:
    t0 = time.perf_counter()
    names = list(CAUSES) if causes is None else list(causes)
    ref, series = runs[0], [r.series for r in runs]
    sigma = series_noise_sigma([s.y for s in series])
    k = decimation(series)
    coarse = [x.decimated(k) for x in series]
    skipped = {}
    remaining: list[type[Cause]] = []
    for name in names:
        why = CAUSES[name].applicable(series)
        if why:
            skipped[name] = why
        else:
            remaining.append(CAUSES[name])

    findings: list[Candidate] = []
    partial: list[Candidate] = []
    first_partial: list[Candidate] = []
    tested: list[list[Candidate]] = []
    current = base
    for _ in range(MAX_FINDINGS):
        if not remaining:
            break
        if findings and (whiteness(current.solution.residual).min_p >= WHITE_P
                         or current.rss / current.n < (1 + NEAR_NOISE) * sigma ** 2):
            break        # the extended model leaves (nearly) white noise: nothing left to explain
        accepted = [c.cause for c in findings]
        current_coarse = at_full_resolution(current, coarse) if k > 1 else current
        # search on the decimated runs: every cause fitted with the base's alpha/beta held
        # (screen), then a short joint probe; the best probes are fitted to convergence
        probes = sorted((probe(ref, coarse, current_coarse, accepted + [cause]) for cause in remaining),
                        key=lambda f: f.rss)
        coarse_fits = [fit_joint(coarse, f, current_coarse) if i < JOINT_CANDIDATES else f
                       for i, f in enumerate(probes)]
        coarse_cands = [Candidate(f.causes[-1], f, current_coarse) for f in coarse_fits]
        _compare(coarse_cands, current_coarse)
        coarse_cands.sort(key=lambda c: -c.delta_bic)
        # decide at full resolution: the best candidates, and every strong one, polished there
        # (the others keep their decimated-scale evidence, weaker than it would be at full
        # scale); every strong one gets the fair comparison below
        cands = []
        for i, c in enumerate(coarse_cands):
            if (i < FULL_CANDIDATES and c.delta_bic > 0) or c.delta_bic > DELTA_BIC_MIN:
                full_fit = at_full_resolution(c.fit, series, POLISH_NFEV if k > 1 else 0)
                cands.append(Candidate(c.cause, full_fit, current, coarse_fit=c.fit))
            else:
                c.coarse_fit = c.fit
                cands.append(c)
        polished = [c for c in cands if c.before is current]
        if polished:
            _compare(polished, current)
        # an extension that leaves structure may be stuck where the base model bent itself:
        # restart it from identification on the corrected data, best first, until one
        # leaves white residuals
        for c in sorted(polished, key=lambda c: -c.delta_bic):
            if c.delta_bic <= 0 or whiteness(c.fit.solution.residual).min_p >= WHITE_P:
                break
            c.fit = reidentify(ref, series, c.fit)
            _compare([c], current)
            if whiteness(c.fit.solution.residual).min_p >= WHITE_P:
                break
        # fair comparison: an extension's fit may have found a better base model too (its
        # alpha/beta started elsewhere); the model without the new effect gets the same
        # start, so the gain measured is the effect's, not the optimiser's luck
        improved = False
        for c in polished:
            if c.delta_bic > DELTA_BIC_MIN:
                alt = without_last(series, c.fit)
                if alt.rss < current.rss:
                    current, improved = alt, True
        if improved:
            if not findings:
                base = current
            current_coarse = at_full_resolution(current, coarse) if k > 1 else current
            # a candidate fitted from the base this one replaced, and not better than it, is
            # fitted again from it (or it would be judged against a base it never started
            # from): the best ones by a joint fit, the other polished ones by a short one, the
            # rest by a screening (alpha/beta held)
            ranked = sorted(polished, key=lambda c: -c.delta_bic)
            for i, c in enumerate(ranked):
                if c.fit.rss >= current.rss:
                    again = fit_joint(coarse, screen(coarse, current_coarse, accepted + [c.cause]),
                                      current_coarse, None if i < FULL_CANDIDATES else PROBE_NFEV)
                    c.coarse_fit = again
                    c.fit = at_full_resolution(again, series, POLISH_NFEV if k > 1 else 0)
                c.before = current
            _compare(polished, current)
            for c in cands:
                if c not in polished:
                    c.fit = screen(coarse, current_coarse, accepted + [c.cause])
                    c.before = current_coarse
            _compare([c for c in cands if c not in polished], current_coarse)
        tested.append(cands)
        chosen = None
        checked = 0
        left = current.rss - current.n * sigma ** 2     # what the current model leaves above the noise
        for c in sorted(cands, key=lambda c: -c.delta_bic):
            if chosen is not None:
                c.reason = "not checked: a stronger candidate passed"
                continue
            if c.delta_bic > DELTA_BIC_MIN and c.before is not current:
                # strong on the search's samples: judge it at full resolution
                c.fit = at_full_resolution(c.coarse_fit, series, POLISH_NFEV if k > 1 else 0)
                c.before = current
                _compare([c], current)
            if c.delta_bic <= DELTA_BIC_MIN:
                c.reason = f"delta BIC {c.delta_bic:.1f} <= {DELTA_BIC_MIN:g}"
                continue
            if c.pinned:
                c.reason = f"{c.pinned}: the data ask for more than this cause can be"
                continue
            z = c.z_score
            if not z >= EFFECT_Z_MIN:
                # the fit improves, but the effect itself is not determined: the base model's
                # alpha/beta can take its place (its standard error is that of the joint fit)
                c.reason = f"effect not determined: {z:.2g} standard errors from zero (< {EFFECT_Z_MIN:g})"
                continue
            if checked >= HELDOUT_CANDIDATES:
                c.reason = "weaker than the candidates checked on held-out data"
                continue
            # a cause must explain the structure (leave white residuals, or explain most of
            # what the model leaves above the noise), not a sliver of something else
            c.share = share = 1.0 if left <= 0 else min((current.rss - c.fit.rss) / left, 1.0)
            explains = share >= EXPLAINED_SHARE_MIN or whiteness(c.fit.solution.residual).min_p >= WHITE_P
            if not explains and (findings or share < PARTIAL_SHARE_MIN):
                c.reason = f"explains {share:.0%} of the structure left (< {EXPLAINED_SHARE_MIN:.0%})"
                continue
            checked += 1
            # held out on the search's samples (every k-th): the same prediction error, cheaper
            before = heldout_rmse(current, current_coarse)
            after = heldout_rmse(c.fit, c.coarse_fit)
            better = after < before
            c.reason = "" if better else f"held-out RMSE not lower ({after:.4g} >= {before:.4g})"
            if better and not explains:
                # real but partial: a part of the structure, reported, never the verdict
                c.reason = (f"partial: explains {share:.0%} of the structure left "
                            f"(< {EXPLAINED_SHARE_MIN:.0%}); held-out RMSE lower")
                partial.append(c)
                continue
            c.passed = better
            if c.passed:
                chosen = c
        if chosen is None and partial and not findings:
            # no single cause explains the structure, but some explain a real part of it:
            # take the strongest provisionally and look for what explains the rest on top
            # (two effects at once); the set is named only if together they explain it
            chosen = max(partial, key=lambda c: c.share)
            first_partial = sorted(partial, key=lambda c: -c.share)
        if chosen is None:
            break
        findings.append(chosen)
        current = chosen.fit
        remaining = [c.cause for c in cands if c is not chosen and c.delta_bic > DELTA_BIC_MIN]

    final = current
    base_analysis = analyse(series, base.solution.residuals, sigma)
    final_analysis = analyse(series, final.solution.residuals, sigma) if findings else base_analysis
    white_final = final_analysis.whiteness
    excess = base.rss - base.n * sigma ** 2
    removed = base.rss - final.rss
    share = 1.0 if removed >= excess else max(removed, 0.0) / excess
    if findings and final_analysis.whiteness.min_p < WHITE_P and share < EXPLAINED_SHARE_MIN:
        # provisional findings that together still leave most of the structure: partial only
        partial, findings, final = first_partial or findings, [], base
        final_analysis = base_analysis
    white_final = final_analysis.whiteness
    if findings:
        verdict = findings[0].name
        partial = []
    else:
        verdict = "unexplained" if base_analysis.whiteness.min_p < WHITE_P else "none"
        if verdict == "unexplained":
            heldout_rmse(base, at_full_resolution(base, coarse) if k > 1 else base)
    return Diagnosis(
        verdict=verdict, findings=findings, partial=partial, tested=tested, skipped=skipped, base=base, final=final,
        base_analysis=base_analysis, final_analysis=final_analysis, final_whiteness=white_final,
        explained_share=float(share), noise_sigma=sigma, series=series, params=base.params,
        seconds=time.perf_counter() - t0,
    )
