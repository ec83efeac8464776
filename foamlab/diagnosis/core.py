"""Diagnosis: extend identification's fit by each candidate cause, and decide, in stages.

The base model is identification's fit (the analysis core's polish on every sample). Each
round of the search (``Procedure.round``) runs these stages:

1. search (extend.py): every applicable cause fitted on the decimated runs as an extension
   of the current model - screened with the base's alpha/beta held, probed jointly, and
   the settings' joint_candidates best fitted jointly to convergence; a cause the base imitates
   (Cause.imitated_by_base) always, and from several starts (extend.multistart) where that shows it;
2. compare (evidence.compare): Delta BIC and the likelihood-ratio p-value of each, on one
   prewhitened scale (an AR(p) filter fitted to the best model's residuals);
3. polish: the best and every strong candidate carried to every sample;
4. restart: an extension that leaves structure restarted from identification on the data
   with its effect taken out (the base may have bent its alpha/beta to mimic it);
5. fair comparison: the model without the new effect refitted from each strong
   extension's start, so the gain measured is the effect's, not the optimiser's luck;
6. decide: the acceptance rules (evidence.py, each returns its reason) in order -
   evidence, not pinned at a limit, effect determined, explains the structure, held-out
   prediction better; the best candidate passing all is a finding.

After the rounds, where the findings do not explain the structure the base leaves, pairs of
causes that mask each other are fitted jointly (stage 7, pairs.py).

Every other cause is tried again on top of a finding (up to settings.max_findings), until the model
leaves white residuals at the noise level; findings are listed best first (what each removed). Verdict: `none` when
nothing passes and the base residuals are white; the first finding when the extension
leaves white residuals or explains most of the structure above the noise; `unexplained`
otherwise (structure, and where it is).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Callable

import numpy as np
from threadpoolctl import threadpool_limits

from foamlab.analysis.heldout import heldout_rmse
from foamlab.analysis.noise import WHITE_P, series_noise_sigma, whiteness
from foamlab.analysis.parallel import fork_map, processes
from foamlab.analysis.prepared import PreparedRun
from foamlab.analysis.solve import (
    POLISH_NFEV,
    Fit,
    at_full_resolution,
    decimation,
)
from foamlab.diagnosis.causes import CAUSES, Cause
from foamlab.diagnosis.evidence import (
    compare,
    explained_share,
    explains,
    rule_effect_determined,
    rule_evidence,
    rule_explains,
    rule_heldout,
    rule_not_pinned,
)
from foamlab.diagnosis.extend import (
    MULTISTART_SIZES,
    PROBE_NFEV,
    fit_joint,
    multistart,
    probe,
    reidentify,
    screen,
    without,
)
from foamlab.diagnosis.limits import checked, detection_limits, left_on_top, opens_search, quiet
from foamlab.diagnosis.pairs import fit_pair, members, named, redundant_first, screened
from foamlab.diagnosis.residuals import analyse
from foamlab.diagnosis.result import Candidate, Diagnosis
from foamlab.diagnosis.settings import DEFAULT, DiagnosisSettings

def diagnose_prepared(runs: list[PreparedRun], base: Fit, causes: list[str] | None = None,
                      progress: Callable[[str, float], None] | None = None,
                      settings: DiagnosisSettings = DEFAULT, coalesced: np.ndarray | None = None) -> Diagnosis:
    """Diagnose prepared runs (the first the reference) from a base model fitted on all of them
    (identification's core fit for one run, analysis.solve.polish for several). progress:
    called with (stage, fraction 0..1). coalesced: the base's alpha/beta identification held apart
    (bool over them), held in the linearised detection limits (limits.detection_limits)."""
    procedure = Procedure(runs, base, causes, progress, settings, coalesced)
    return procedure.checked(procedure.run())


def counted(progress: Callable[[str, float], None], stage: str, cands: list[Candidate] | list[type[Cause]],
            total: int, start: float, end: float, before: int = 0) -> Callable[[int, object], None]:
    """A map's done callback naming each candidate (or cause) as its fit ends: stage with {} for its name,
    (k of total) counted from `before`, progress(stage, fraction) from start to end."""
    ended = iter(range(before + 1, total + 1))

    def done(i: int, _) -> None:
        k = next(ended)
        progress(f"{stage.format(cands[i].name)} ({k} of {total})", start + (end - start) * k / max(total, 1))
    return done


def removed_share(base: Fit, final: Fit, sigma: float) -> float:
    """The share of the base's residual sum of squares above the noise (sigma) that `final` removes."""
    excess = base.rss - base.n * sigma ** 2
    removed = base.rss - final.rss
    return 1.0 if removed >= excess else max(removed, 0.0) / excess


class Procedure:
    """One diagnosis: the runs, the model found so far, and what each round decided."""

    def __init__(self, runs: list[PreparedRun], base: Fit, causes: list[str] | None,
                 progress: Callable[[str, float], None] | None = None, settings: DiagnosisSettings = DEFAULT,
                 coalesced: np.ndarray | None = None):
        self.started = time.perf_counter()
        self.settings = settings
        self.report = progress or (lambda stage, fraction: None)
        self.round_no = 0
        self.ref, self.series = runs[0], [r.series for r in runs]
        self.sigma = series_noise_sigma([s.y for s in self.series])
        self.k = decimation(self.series)
        self.coarse = [s.decimated(self.k) for s in self.series]
        k = max(1, round(max(len(s) for s in self.series) / settings.multistart_samples))
        #: the runs the several starts of an effect the base imitates are fitted on (_imitated)
        self.fine = [s.decimated(k) for s in self.series] if k > 1 else self.series
        self.base = self.current = base
        self.coalesced = coalesced
        self.skipped: dict[str, str] = {}
        self.remaining: list[type[Cause]] = []
        for name in (list(CAUSES) if causes is None else list(causes)):
            why = CAUSES[name].applicable(self.series)
            if why:
                self.skipped[name] = why
            else:
                self.remaining.append(CAUSES[name])
        self.applicable = list(self.remaining)    # every cause these runs can test
        self.findings: list[Candidate] = []
        self.partial: list[Candidate] = []
        self.first_partial: list[Candidate] = []
        self.tested: list[list[Candidate]] = []
        #: Causes the base imitates whose joint fit in this round's search showed them (multistarted).
        self.shown: set[type[Cause]] = set()

    # -- helpers
    def _full(self, fit: Fit) -> Fit:
        return at_full_resolution(fit, self.series, POLISH_NFEV if self.k > 1 else 0)

    def _coarse(self, fit: Fit) -> Fit:
        return at_full_resolution(fit, self.coarse) if self.k > 1 else fit

    def _map(self, fn, items: list, *fits: Fit, done=None) -> list:
        """[fn(item) for item in items] on the machine's cores (analysis.parallel): the runs and
        these fits come back as themselves."""
        shared = [self.ref, *self.series, *self.coarse, *self.fine, self.base, self.current, *fits]
        return fork_map(fn, items, shared, self.settings.workers or None, done)

    def _progress(self, stage: str, within_round: float) -> None:
        """Rounds after the first are shorter (fewer causes left): the first gets most of the bar."""
        done = 0.0 if self.round_no <= 1 else 0.7 + 0.3 * (1 - 0.5 ** (self.round_no - 1))
        width = 0.7 if self.round_no <= 1 else 0.3 * 0.5 ** (self.round_no - 1)
        prefix = f"round {self.round_no}: " if self.round_no > 1 else ""
        self.report(prefix + stage, done + width * within_round)

    def _done(self) -> bool:
        """Nothing left to explain: the extended model leaves white noise at the noise level.
        Whiteness alone is not enough: a second cause can leave residuals the whiteness tests
        pass at 1.5 x the noise variance, or 1.01 x and far from white (docs/analysis.md,
        "Two causes"). Nor is the noise level alone: a second cause can leave the first's model at
        1.00 x the noise's variance (the estimate's own scatter) and clear the evidence rule by far
        (a 250 N/mm frame under softening: Delta BIC 257 on top), so a quiet model is searched again
        where a cause left would, linearised, clear the rule (limits.left_on_top, "The score test
        held inside the bounds")."""
        return bool(self.findings) and quiet(self.current, self.sigma, self.settings) and not left_on_top(
            self.coarse, self._coarse(self.current), self.series, self.current, self.remaining, self.settings)

    # -- the procedure
    @threadpool_limits.wrap(1, user_api="blas")
    def checked(self, d: Diagnosis) -> Diagnosis:
        """d (this procedure's) with its limits checked where one run shows nothing (limits.checked);
        apart from `run`: of two residual forms diagnosed, the kept one's only (docs/benchmarks.md)."""
        if len(self.series) != 1 or d.findings:
            return d
        stage = "what this run could have seen: limits checked by identification"
        self._progress(stage, 0.98)
        limits = checked(d.limits, self.ref, self.base, self.applicable, self.settings, self._map,
                         lambda k, n: self._progress(f"{stage} ({k} of {n})", 0.98 + 0.019 * k / n))
        return replace(d, limits=limits, seconds=time.perf_counter() - self.started)

    @threadpool_limits.wrap(1, user_api="blas")      # small dense solves: threads only contend
    def run(self) -> Diagnosis:
        """The verdict, the findings and the linearised limits (`checked` checks them)."""
        for _ in range(self.settings.max_findings):
            if not self.remaining or self._done():
                break
            self.round_no += 1
            cands, current_coarse = self.round()
            self.tested.append(cands)
            chosen = self.decide(cands, current_coarse)
            if chosen is None and self.partial and not self.findings:
                # no single cause explains the structure, but some explain a real part of it:
                # take the strongest provisionally and look for what explains the rest on top
                # (two effects at once); the set is named only if together they explain it
                chosen = max(self.partial, key=lambda c: c.share)
                self.first_partial = sorted(self.partial, key=lambda c: -c.share)
            if chosen is None:
                break
            self.findings.append(chosen)
            self.current = chosen.fit
            # every other cause is tried again on top: one the first hid (a friction under a lag)
            # had no evidence of its own in this round
            self.remaining = [c.cause for c in cands if c is not chosen]
        self.drop_redundant_first()
        self.pairs()
        return self.verdict()

    def _explained(self) -> bool:
        """The findings explain the structure the base leaves, as verdict() judges them."""
        share = removed_share(self.base, self.current, self.sigma)
        return bool(self.findings) and (share >= self.settings.explained_share_min
                                         or whiteness(self.current.solution.residual).min_p >= WHITE_P)

    def pairs(self) -> None:
        """Stage 7 (pairs.py): where the findings do not explain the structure the base leaves,
        the screened pairs of causes fitted jointly, best first; the first whose members each pass
        the rules on top of the other replaces the findings."""
        if not self.settings.pair_candidates or self._explained() or quiet(self.base, self.sigma, self.settings):
            return
        self._progress("pairs of causes that mask each other", 0.96)
        base_coarse = self._coarse(self.base)
        ranked = screened(self.coarse, base_coarse, self.applicable)[:self.settings.pair_candidates]
        fits = self._map(lambda p: fit_pair(self.coarse, base_coarse, p[1], p[2]), ranked, base_coarse)
        for coarse in sorted(fits, key=lambda f: f.rss):
            full = self._full(coarse)
            cands = members(self.series, full)
            self.tested.append(cands)
            if named(cands, full, self.base, self.sigma, self.settings, self._coarse):
                self.findings, self.current, self.first_partial, self.partial = cands, full, [], []
                return

    def drop_redundant_first(self) -> None:
        """A first finding the one on top of it made redundant (provisional, or imitating it: a damping
        drop for a frame) is dropped, and that finding judged alone against the base (pairs.redundant_first)."""
        if len(self.findings) != 2:
            return
        kept = redundant_first(self.series, self.current, self.base, self.findings, self.sigma, self.settings,
                               self._coarse)
        if kept is not None:
            self.findings, self.current, self.first_partial = [kept], kept.fit, []
            self.tested.append([kept])

    def round(self) -> tuple[list[Candidate], Fit]:
        """Stages 1-5 for every remaining cause on top of the current model."""
        current_coarse = self._coarse(self.current)
        cands = self.search(current_coarse)
        polished = [c for c in cands if c.before is self.current]
        if polished:
            compare(polished, self.current)
        self.restart(polished)
        if self.fair_comparison(polished):
            current_coarse = self._coarse(self.current)
            self.refit_from_new_base(cands, polished, current_coarse)
        return cands, current_coarse

    def search(self, current_coarse: Fit) -> list[Candidate]:
        """Stages 1-3: every cause probed on the decimated runs, the best fitted jointly,
        compared, and the best and every strong one carried to every sample.

        The costly fits (restarts, several starts: deep) only where the current model leaves
        structure, or where a candidate clears the Delta BIC bar on the decimated runs without
        them: the restarts also find the base better optima, which take such a gain away (a clean
        run, B seed 2018: frame compliance Delta BIC 35.8 decimated, 21.8 on every sample without
        them, 6.8 with). Also where a quiet model has a cause clearing the rule linearised on top
        (limits.opens_search)."""
        deep = opens_search(self.current, self.sigma, self.coarse, current_coarse, self.remaining, self.settings)
        probes, joint = self._probes(current_coarse, restarts=deep), {}
        coarse_cands = self._compared(probes, current_coarse, joint)
        if not deep and max((c.delta_bic for c in coarse_cands), default=0.0) > self.settings.delta_bic_min:
            deep = True      # only the causes identification absorbs are probed again
            coarse_cands = self._compared(self._probes(current_coarse, True, probes), current_coarse, joint)
        self.shown = set()
        reach = self.settings.multistart_reach * max((c.delta_bic for c in coarse_cands), default=0.0)
        work = []
        for i, c in enumerate(coarse_cands):
            if (c.cause.always_multistart and not self.findings) or (deep and
                    c.cause.imitated_by_base and 0 < c.delta_bic and (c.delta_bic >= reach or i == 0)):
                # one joint fit from the base stays in the base's basin: several starts (_imitated),
                # where the search's joint fit shows the effect and it could lead this round
                # (a weaker one is retried on top of the finding; docs/analysis.md, "Cost"); one the
                # base holds at any size always in the first round (on top of a finding: its cost)
                self.shown.add(c.cause)
                work.append(c)
            elif ((i < self.settings.full_candidates and c.delta_bic > 0)
                  or c.delta_bic > self.settings.delta_bic_min):
                work.append(c)

        def carried(c: Candidate) -> tuple[Fit, Fit]:
            if c.cause in self.shown:
                fit = self._imitated(c.cause, self.current, c.fit, c.cause.multistart_sizes or MULTISTART_SIZES)
                return fit, self._coarse(fit)
            return self._full(c.fit), c.fit

        done = lambda i, _: self._progress(f"carried {work[i].name} to every sample ({i + 1} of {len(work)})",
                                           0.6 + 0.3 * (i + 1) / max(len(work), 1))
        fits = dict(zip(map(id, work), self._map(carried, work, *(c.fit for c in work), done=done)))
        cands = []
        for c in coarse_cands:
            if id(c) in fits:
                fit, coarse = fits[id(c)]
                cands.append(Candidate(c.cause, fit, self.current, coarse_fit=coarse))
            else:    # keeps its decimated-scale evidence (weaker than it would be at full scale)
                c.coarse_fit = c.fit
                cands.append(c)
        return cands

    def _probes(self, current_coarse: Fit, restarts: bool, before: list[Fit] | None = None) -> list[Fit]:
        """Every remaining cause probed on the decimated runs (extend.probe); with ``before`` (the
        same probes without restarts), only those the restarts change are probed again."""
        accepted = [c.cause for c in self.findings]
        todo = [c for c in self.remaining if before is None or c.absorbed_by_identification]
        self._progress(f"testing {len(todo)} causes on the decimated runs at once", 0.0)
        done = counted(self._progress, "tested {}", todo, len(todo), 0.0, 0.6)
        probed = lambda cause: probe(self.ref, self.coarse, current_coarse, accepted + [cause], restarts=restarts)
        fresh = dict(zip(todo, self._map(probed, todo, current_coarse, done=done)))
        return [fresh[c] if c in fresh else before[i] for i, c in enumerate(self.remaining)]

    def _compared(self, probes: list[Fit], current_coarse: Fit, joint: dict[int, Fit]) -> list[Candidate]:
        """The strongest probes and every imitated cause's fitted jointly, compared with the
        current model, best first. joint: the joint fits so far by their probe's id (the caller
        keeps the probes), so a probe kept from an earlier call is not fitted again."""
        self._progress("fitting the strongest candidates jointly", 0.6)
        ranked = sorted(probes, key=lambda f: f.rss)
        chosen = [f for i, f in enumerate(ranked) if i < self.settings.joint_candidates or f.causes[-1].imitated_by_base]
        todo = [f for f in chosen if id(f) not in joint]
        joint.update(zip(map(id, todo), self._map(lambda f: fit_joint(self.coarse, f, current_coarse), todo,
                                                  current_coarse, *todo)))
        picked = set(map(id, chosen))
        coarse_cands = [Candidate(f.causes[-1], joint[id(f)] if id(f) in picked else f, current_coarse)
                        for f in ranked]
        compare(coarse_cands, current_coarse)
        return sorted(coarse_cands, key=lambda c: -c.delta_bic)

    def _imitated(self, cause: type[Cause], current: Fit, start: Fit | None = None,
                  sizes: tuple[float, ...] = MULTISTART_SIZES) -> Fit:
        """An effect the base imitates, fitted from several starts (extend.multistart) on the runs
        decimated to about settings.multistart_samples (the search's decimation loses part of its handle,
        the samples at high force), then polished on every sample."""
        fine = self.fine
        on = at_full_resolution(current, fine)
        found = multistart(fine, on, [c.cause for c in self.findings] + [cause], start, sizes)
        if found.rss < on.rss and on.n * np.log(on.rss / found.rss) > np.log(on.n):
            return self._full(found)
        return at_full_resolution(found, self.series)     # no gain worth a polish on every sample

    def restart(self, polished: list[Candidate]) -> None:
        """Stage 4: an extension that leaves structure may be stuck where the base bent itself:
        restarted from identification on the corrected data, best first, until one leaves
        white residuals."""
        ranked = sorted(polished, key=lambda c: -c.delta_bic)
        stop = next((i for i, c in enumerate(ranked)
                     if c.delta_bic <= 0 or whiteness(c.fit.solution.residual).min_p >= WHITE_P), len(ranked))
        todo = ranked[:stop]
        # each restart depends only on its own candidate: a batch as wide as the workers is restarted
        # at once, and taken in order up to the first that leaves white residuals (the rest unused)
        size = processes(self.settings.workers or None)
        for first in range(0, len(todo), size):
            batch = todo[first:first + size]
            done = counted(self._progress, "restarted {} from identification on the data without it", batch,
                           len(todo), 0.9, 0.92, first)
            fits = self._map(lambda c: reidentify(self.ref, self.series, c.fit), batch, *(c.fit for c in batch),
                             done=done)
            for c, fit in zip(batch, fits):
                c.fit = fit
                compare([c], self.current)
                if whiteness(c.fit.solution.residual).min_p >= WHITE_P:
                    return

    def fair_comparison(self, polished: list[Candidate]) -> bool:
        """Stage 5: an extension's fit may have found a better base model too (its alpha/beta
        started elsewhere); the model without the new effect gets the same start. True when
        that improved the current model (which then replaces it)."""
        improved = False
        strong = [c for c in polished if c.delta_bic > self.settings.delta_bic_min]
        # each refit depends only on its own candidate: on the machine's cores, then taken in order
        done = counted(self._progress, "fair comparison: the model without {} refitted from its start", strong,
                       len(strong), 0.92, 0.93)
        for alt in self._map(lambda c: without(self.series, c.fit), strong, *(c.fit for c in strong), done=done):
            if alt.rss < self.current.rss:
                self.current, improved = alt, True
        if improved and not self.findings:
            self.base = self.current
        return improved

    def refit_from_new_base(self, cands: list[Candidate], polished: list[Candidate], current_coarse: Fit) -> None:
        """A candidate fitted from the model the fair comparison replaced, and not better than
        the new one, is fitted again from it (or it would be judged against a base it never
        started from): the best ones jointly, the other polished ones briefly, the rest by a
        screening (alpha/beta held)."""
        accepted = [c.cause for c in self.findings]
        cur = self.current
        work = []
        for i, c in enumerate(sorted(polished, key=lambda c: -c.delta_bic)):
            below = c.fit.rss < cur.rss
            if below and cur.n * np.log(cur.rss / c.fit.rss) > self.settings.decisive_chi2:
                pass    # its own gain over the new base decides already: a refit changes no rule
            # a strong candidate still below the new base is refitted too: its gain over the old
            # base may be mostly the base's (alpha/beta it found by luck), and its effect's own
            # gain is only seen from the better base (docs/analysis.md, "Effects the base model imitates")
            elif c.cause in self.shown or not below or i < self.settings.full_candidates:
                work.append((c, i < self.settings.full_candidates))

        def again(job: tuple[Candidate, bool]) -> tuple[Fit | None, Fit]:
            c, full_budget = job
            if c.cause in self.shown:
                # from the new base: the screening's start and the effect value found before
                return None, self._imitated(c.cause, self.current, c.fit, sizes=())
            coarse = fit_joint(self.coarse, screen(self.coarse, current_coarse, accepted + [c.cause]),
                               current_coarse, None if full_budget else PROBE_NFEV)
            return coarse, self._full(coarse)

        done = counted(self._progress, "{} fitted again from the better base", [c for c, _ in work], len(work),
                       0.93, 0.95)
        for (c, _), (coarse, fit) in zip(work, self._map(again, work, current_coarse, *(c.fit for c, _ in work),
                                                         done=done)):
            if c.fit.rss >= self.current.rss or fit.rss < c.fit.rss:
                c.coarse_fit, c.fit = coarse, fit
            if coarse is None:      # several starts: found on other samples than the search's
                c.coarse_fit = self._coarse(c.fit)
        for c in polished:
            c.before = self.current
        compare(polished, self.current)
        rest = [c for c in cands if c not in polished]
        for c, fit in zip(rest, self._map(lambda c: screen(self.coarse, current_coarse, accepted + [c.cause]), rest,
                                          current_coarse)):
            c.fit, c.before = fit, current_coarse
        compare(rest, current_coarse)

    def decide(self, cands: list[Candidate], current_coarse: Fit) -> Candidate | None:
        """Stage 6: the acceptance rules, strongest candidate first; every candidate gets the
        reason it was or was not named. Passing all but explaining only part of the structure
        (in the first round) makes a partial finding."""
        chosen, checked = None, 0
        for c in sorted(cands, key=lambda c: -c.delta_bic):
            if chosen is not None:
                c.reason = "not checked: a stronger candidate passed"
                continue
            if c.delta_bic > self.settings.delta_bic_min and c.before is not self.current:
                # strong on the search's samples: judge it at full resolution
                c.fit, c.before = self._full(c.coarse_fit), self.current
                compare([c], self.current)
            c.reason = (rule_evidence(c, self.settings) or rule_not_pinned(c, self.settings)
                        or rule_effect_determined(c, self.settings))
            if c.reason:
                continue
            if checked >= self.settings.heldout_candidates:
                c.reason = "weaker than the candidates checked on held-out data"
                continue
            c.share = explained_share(c, self.current, self.sigma)
            c.reason = rule_explains(c, self.settings, first_round=not self.findings)
            if c.reason:
                continue
            checked += 1
            self._progress(f"held-out check of {c.name}", 0.95)
            # judged from the optimum it reports, as the model it extends is (current_coarse): from
            # the search's unpolished optimum a few refit steps can fall short of it by 2x
            c.coarse_fit = self._coarse(c.fit)
            c.reason = rule_heldout(c, self.current, current_coarse, self.settings)
            if c.reason:
                continue
            if not explains(c, self.settings):
                # real but partial: a part of the structure, reported, never the verdict
                c.reason = (f"partial: explains {c.share:.0%} of the structure left "
                            f"(< {self.settings.explained_share_min:.0%}); held-out RMSE lower")
                self.partial.append(c)
                continue
            c.passed = True
            chosen = c
        return chosen

    def verdict(self) -> Diagnosis:
        """The verdict from the findings, and the residual analysis before and after."""
        base, final, findings, partial = self.base, self.current, self.findings, self.partial
        base_analysis = analyse(self.series, base.solution.residuals, self.sigma, self.settings)
        final_analysis = (analyse(self.series, final.solution.residuals, self.sigma, self.settings)
                          if findings else base_analysis)
        share = removed_share(base, final, self.sigma)
        if findings and final_analysis.whiteness.min_p < WHITE_P and share < self.settings.explained_share_min:
            # provisional findings that together still leave most of the structure: partial only
            partial, findings, final = self.first_partial or findings, [], base
            final_analysis = base_analysis
        if findings:
            # best first: the finding that removed the most (the verdict names the larger cause)
            findings = sorted(findings, key=lambda c: -(c.before.rss - c.fit.rss))
            verdict, partial = findings[0].name, []
        else:
            verdict = "unexplained" if base_analysis.whiteness.min_p < WHITE_P else "none"
            if verdict == "unexplained":      # reported: held out as the candidates were
                coarse = self._coarse(base)
                heldout_rmse(base, coarse, reestimate=True, workers=self.settings.workers or None)
        self._progress("what this run could have seen", 0.98)
        limits = detection_limits(self.coarse, self._coarse(base), self.applicable, self.settings, n_full=base.n,
                                  coalesced=self.coalesced)
        return Diagnosis(
            verdict=verdict, limits=limits, findings=findings, partial=partial, tested=self.tested, skipped=self.skipped,
            base=base, final=final, base_analysis=base_analysis, final_analysis=final_analysis,
            final_whiteness=final_analysis.whiteness, explained_share=float(share), noise_sigma=self.sigma,
            series=self.series, params=base.params, seconds=time.perf_counter() - self.started,
            settings=self.settings,
        )
