"""A run prepared for fitting, once: what identification and diagnosis both take.

``prepare(run)`` checks the run and computes, once: the samples on the sampling schedule,
the segmentation and the model's half-cycle labels, the displacement path with its corner
nodes (path.py), the noise level (noise.py), the contact set measured, the decimated rows
and block means of identification's search, and ``series``: the run as every full fit
sees it (analysis.design.Series). Every limit here is a property of the run (its
sampling, its half-cycles, its noise); none is tuned to a data set. A run that cannot be
identified raises a FoamlabError that says what is missing, before any optimiser starts.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.design import Series
from foamlab.analysis.noise import noise_sigma
from foamlab.analysis.path import (
    PathNodes,
    displacement_path,
    exact_history,
    force_path,
    path_determined,
    path_nodes,
)
from foamlab.model import (
    HistoryLabels,
    ModelParameters,
    ModelResponse,
    evaluate,
    labels_from_extrema,
)
from foamlab.model.response import paper_residual
from foamlab.model.components import elastic_force
from foamlab.model.effects import estimate_velocity, loading_rate
from foamlab.model.turns import on_grid
from foamlab.rundata import RunData
from foamlab.segmentation import HalfCycle, Segmentation

#: The decimated fit keeps about this many samples per half-cycle (the curves are
#: smooth over a half-cycle; the final polish and the statistics use every sample).
FIT_SAMPLES_PER_HALF_CYCLE = 100
#: ...and at most about this many rows in all: a long run's search costs no more than a short
#: one's (the polish on every sample is what grows with the run).
FIT_ROWS_MAX = 2500
#: Block radius at most (samples since the last turning point) / this.
CUSP_DISTANCE_RATIO = 4
#: A force range smaller than this many times the force noise is "flat".
FLAT_FORCE_NOISE_MULTIPLE = 20.0
#: The model's response between the nodes of a path with corner nodes is computed on a
#: uniform grid this many times finer than the samples (model_response).
RESPONSE_REFINE = 8
#: A stretch without samples longer than this many sampling steps is said: the displacement across
#: it is a straight line between the samples either side, whatever the crosshead did (it may have
#: arrived at a turn and waited there), and the model's memory is computed on that line.
GAP_WARN_STEPS = 5


def model_response(params: ModelParameters, fd: "PreparedRun") -> ModelResponse:
    """The model at the run's samples, driven by the path with its corner nodes.

    Without corner nodes that is model.evaluate on the samples. With them, evaluate runs
    on a uniform grid RESPONSE_REFINE times finer than the samples through the nodes
    (a corner between two grid points is cut by at most that much) and the memory
    components come back to the samples by interpolation; the elastic force is exact."""
    t, x, nodes = fd.t, fd.x, fd.nodes
    if not nodes.inserted:
        return evaluate(params, t, x, fd.labels)
    grid, fine = _on_grid(params, fd)
    back = lambda values: np.interp(t, grid, values)
    # the paper form's residual has no memory: exact on the nodes themselves (on the grid its
    # stroke would be cut at the turn, and near the peak Eq. 11 is steep in the stroke)
    residual = (paper_residual(params, nodes.t, nodes.x, nodes.labels)[nodes.of_sample]
                if params.residual_form == "paper" else back(fine.residual))
    return ModelResponse(t, x, elastic_force(params, x), back(fine.damping), residual, fd.labels)


def force_late(params: ModelParameters, fd: "PreparedRun", delays_s: Sequence[float]) -> np.ndarray:
    """The model's force (unclipped) at the run's samples as a channel each of delays_s late reads
    it, one row each: the force at t - delay along the path with its corner nodes, on
    model_response's finer grid (evaluated once for all). Not the sampled force interpolated (the
    channel_lag effect's batch form): after a turn the force falls steeply within a sampling step,
    and a sample a lag after it reads the other branch (docs/analysis.md, "A lag is read along the path")."""
    grid, fine = _on_grid(params, fd)
    return np.array([np.interp(fd.t - delay, grid, fine.force) for delay in delays_s])


def _on_grid(params: ModelParameters, fd: "PreparedRun") -> tuple[np.ndarray, ModelResponse]:
    """The model on a uniform grid RESPONSE_REFINE times finer than the samples through the path's
    nodes, each turning point at the last grid point not after its node: (grid, response)."""
    grid, grid_x, labels = on_grid(fd.nodes.t, fd.nodes.x, fd.nodes.labels, fd.native_step_s / RESPONSE_REFINE)
    return grid, evaluate(params, grid, grid_x, labels)


@dataclass
class PreparedRun:
    run: RunData                  # on its sampling schedule (on_schedule)
    seg: Segmentation
    labels: HistoryLabels
    observed: np.ndarray          # sample indices of the half-cycles (objective rows)
    contact: np.ndarray           # bool per observed row: in contact (not the recovery region)
    fit_rows: np.ndarray          # sample indices of the decimated fit (in contact)
    corners: np.ndarray           # samples where x has a corner: turning points, dwell starts
    fit_force: np.ndarray         # force there: mean of the block of samples centred on it
    fit_count: np.ndarray         # samples in each block (the mean's weight)
    block_curvature: "BlockCurvature"  # model value at a row -> its block mean
    fit_step_s: float             # operator grid step of the decimated fit
    native_step_s: float
    x_scale_mm: float
    n_residual_cycles: int
    loading_time_s: float         # median duration of a loading half-cycle
    noise_N: float
    warnings: list[str]
    path_mm: np.ndarray           # the displacement that drives the model (displacement_path)
    nodes: PathNodes              # the same, with the corners between samples (path_nodes)
    block_q: int                  # samples per block of the decimated search
    half_id: np.ndarray           # per sample: its half-cycle as the model switches (-1: outside)
    series: Series                # the run as every full fit sees it (all samples, evidence)
    extremes: list[tuple[int, int, bool]]  # (first, last sample, is maximum) at each turning point
    corner_tol: float             # mm: a sample this close to a line lies on it (path_nodes)
    off_schedule: int = 0         # samples left out: taken off the sampling schedule

    def other_turns(self) -> "PreparedRun":
        """The same run with its turns without a stop at the other place: between samples where
        this one has them at a sample, or the other way round (path.path_nodes); a turn whose
        lines meet at its extreme sample is at that sample in either, so in the other it is
        just before it."""
        between = self.nodes.between_samples
        nodes = path_nodes(self.t, self.path_mm, self.extremes, self.corner_tol,
                           between_samples=not between, before_extreme=True)
        return replace(self, nodes=nodes, series=_series(self.run, self.series.name, self.labels, nodes,
                                                         self.seg.contact_lost, self.series.y_path))

    def with_flipped(self, flipped: tuple[int, ...]) -> "PreparedRun":
        """The same run with these turning points (indices of extremes) placed the other way from
        the rest (path.path_nodes): a placement fitted per turn."""
        nodes = path_nodes(self.t, self.path_mm, self.extremes, self.corner_tol,
                           between_samples=self.nodes.between_samples,
                           before_extreme=self.nodes.before_extreme, flipped=tuple(flipped))
        return replace(self, nodes=nodes, series=_series(self.run, self.series.name, self.labels, nodes,
                                                         self.seg.contact_lost, self.series.y_path))

    def placed_for(self, params: ModelParameters) -> "PreparedRun":
        """The run with its turns placed the way a fitted specimen's model fits it best: a second
        run of a specimen fitted on a first. The better of the two whole-run rules, then each turn
        the other way where that fits better (the samples next to a turn decide; elsewhere the
        placements predict alike). Independent A seeds 510/511 at 60 and 120 mm/min: placed at the
        extreme sample, the joint base of both runs fitted the second at 1.12 N (noise 0.15 N)
        even from the true parameters; placed by the rule, 0.150 N. At 2 Hz some turns fall within
        the encoder's resolution of a sample and others between two: one rule cannot place both."""
        def rss(fd: PreparedRun) -> float:
            r = (fd.f - np.maximum(model_response(params, fd).force, 0.0))[fd.observed]
            return float(np.sum((r - np.median(r)) ** 2))       # the other run's zero: its median
        best, score = min(((fd, rss(fd)) for fd in (self, self.other_turns())), key=lambda c: c[1])
        for k in best.nodes.turn_extremes:
            trial = best.with_flipped(tuple(sorted(set(best.nodes.flipped) ^ {int(k)})))
            trial_score = rss(trial)
            if trial_score < score:
                best, score = trial, trial_score
        return best

    def with_force(self, force: np.ndarray) -> "PreparedRun":
        """The same run (segmentation, path, labels) with another force: what a fit sees of
        the measurement with an effect taken out (diagnosis' restarts). Nothing re-segmented."""
        force = np.asarray(force, float)
        run = replace(self.run, force_N=force)
        fit_force, fit_count = _block_means(force, self.fit_rows, self.corners, self.half_id,
                                            ~self.seg.contact_lost, self.block_q)
        # the model's columns depend on the path only; the frame's force (compliance) on the force
        kept = {k: v for k, v in self.series._bases.items() if k[0] != "frame" and k[-1] is None}
        series = replace(self.series, y=force, _bases=kept,
                         y_path=force_path(self.t, self.run.displacement_mm, force, self.corners))
        return replace(self, run=run, fit_force=fit_force, fit_count=fit_count,
                       block_curvature=BlockCurvature.of(self.fit_rows, fit_count, self.block_q, self.half_id),
                       noise_N=noise_sigma(force), series=series)

    @property
    def t(self) -> np.ndarray:
        return self.run.time_s

    @property
    def x(self) -> np.ndarray:
        """The model's displacement input: the measured one without its noise."""
        return self.path_mm

    @property
    def f(self) -> np.ndarray:
        return self.run.force_N

    @property
    def contact_zero_N(self) -> float:
        return self.seg.contact_zero_N


@dataclass
class BlockCurvature:
    """The mean of a smooth curve over a block of 2r + 1 samples centred on a row is its
    value there plus f'' h^2 r (r + 1) / 6; with f'' from the second difference of the
    neighbouring rows (q samples away, same half-cycle) the model's row values become
    block means: F_block = F + c (F_prev - 2 F + F_next), c = r (r + 1) / (6 q^2).
    Without it, a fit to block means is biased where the force curves (the top of a
    loading), by more than the noise when blocks are ~1 s wide."""

    rows: np.ndarray              # indices (into the fit rows) that get a correction
    prev: np.ndarray
    next: np.ndarray
    coef: np.ndarray

    @classmethod
    def of(cls, fit_rows: np.ndarray, count: np.ndarray, q: int, half: np.ndarray) -> "BlockCurvature":
        n = len(fit_rows)
        r = (count - 1) // 2
        idx = np.arange(1, n - 1)
        ok = ((fit_rows[idx] - fit_rows[idx - 1] == q) & (fit_rows[idx + 1] - fit_rows[idx] == q)
              & (half[fit_rows[idx - 1]] == half[fit_rows[idx]]) & (half[fit_rows[idx + 1]] == half[fit_rows[idx]])
              & (r[idx] > 0))
        rows = idx[ok]
        return cls(rows, rows - 1, rows + 1, r[rows] * (r[rows] + 1) / (6.0 * q * q))

    def apply(self, values: np.ndarray) -> np.ndarray:
        """values: (rows, ...) model values at the rows -> block means."""
        out = values.copy()
        c = self.coef.reshape((-1,) + (1,) * (values.ndim - 1))
        out[self.rows] += c * (values[self.prev] - 2.0 * values[self.rows] + values[self.next])
        return out


def _block_means(f: np.ndarray, rows: np.ndarray, turning: np.ndarray, segment_id: np.ndarray,
                 usable: np.ndarray, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean force over a block of about q samples centred on each row, inside one
    half-cycle and in contact (symmetric, so its mean time is the row's time and the
    mean of a smooth curve is its value there to O(step^2)); turning points alone.

    The decimated fit then keeps nearly all the information of the full signal
    (block means have variance sigma^2 / count) at a fraction of the cost."""
    n = len(f)
    csum = np.concatenate([[0.0], np.cumsum(f)])
    half = (q - 1) // 2
    # samples since the last turning point: the memory terms have a cusp there
    # ((t - t_turn)^nu), so blocks close to one are narrower (radius <= distance / 4)
    turning = np.sort(np.asarray(turning, dtype=int))
    last_turn = turning[np.clip(np.searchsorted(turning, rows, side="right") - 1, 0, None)]
    since = np.where(rows >= last_turn, rows - last_turn, n)
    out = np.empty(len(rows))
    count = np.empty(len(rows), dtype=int)
    for j, i in enumerate(rows):
        r = int(min(half, since[j] // CUSP_DISTANCE_RATIO))
        # shrink the block until it stays in one half-cycle and in contact
        while r > 0:
            lo, hi = i - r, i + r
            if (lo >= 0 and hi < n and segment_id[lo] == segment_id[i] == segment_id[hi]
                    and usable[lo:hi + 1].all()):
                break
            r -= 1
        out[j] = (csum[i + r + 1] - csum[i - r]) / (2 * r + 1)
        count[j] = 2 * r + 1
    return out, count


def _turning_points(x: np.ndarray, seg: Segmentation) -> tuple[list[int], list[int], list[int]]:
    """Cycle starts (minima) and loading ends (maxima) as the model switches at them:
    the LAST sample at the extreme before the plate moves the other way (so a dwell at a
    turning point belongs to the half-cycle it ends, as in model.label_history); and the
    FIRST sample at each extreme (where a dwell begins: a corner of x as well).

    The segmentation places turning points on its smoothed displacement and trims holds
    by its smoothing window; here each is moved, within a few percent of a half-cycle
    around it, to the raw samples within 3 noise sigmas of the extreme."""
    noise = noise_sigma(x)
    tol = max(3.0 * noise, 1e-9 * max(seg.stroke_mm, 1.0))
    n = len(x)
    minima, maxima, dwell_starts = [], [], []

    def extreme(lo: int, hi: int, top: bool) -> tuple[int, int]:
        win = x[lo:hi]
        at = np.flatnonzero(win >= win.max() - tol) if top else np.flatnonzero(win <= win.min() + tol)
        return lo + int(at[0]), lo + int(at[-1])

    for c in seg.cycles:
        load = c.loading
        w = max(5, len(load) // 20)
        first, last = extreme(max(0, load.start - w), min(n, load.start + w + 1), top=False)
        minima.append(last)
        dwell_starts.append(first)
        peak = c.unloading.start if c.unloading is not None else load.stop - 1
        first, last = extreme(max(0, load.stop - 1 - w), min(n, peak + w + 1), top=True)
        maxima.append(last)
        dwell_starts.append(first)
    return minima, maxima, dwell_starts


def _sampling_notes(off_schedule: int, t: np.ndarray, observed: np.ndarray, step: float, extremes) -> list[str]:
    """The samples left out (taken off the sampling schedule) and the gaps (_gap_notes), said."""
    dropped = [f"{off_schedule} samples taken off the sampling schedule left out (their instants are unsure)"]
    return (dropped if off_schedule else []) + _gap_notes(t, observed, step, extremes)


def _gap_notes(t: np.ndarray, observed: np.ndarray, step: float, extremes) -> list[str]:
    """The stretches without samples longer than GAP_WARN_STEPS steps, said in one warning; those
    that end at a turning point in one of their own ([] if none): the crosshead may have arrived
    there during the gap and waited unseen, a path far from the straight line the fit takes."""
    rows = observed[:-1][np.diff(t[observed]) > GAP_WARN_STEPS * step]
    if not len(rows):
        return []
    steps = t[rows + 1] - t[rows]
    at_turn = np.array([any(first <= i + 1 <= last for first, last, _ in extremes) for i in rows])
    out = []
    for which, what in ((~at_turn, "the displacement across each is taken as a straight line"),
                        (at_turn, "each ends at a turning point, where the crosshead may have waited unseen, "
                                  "and the fit may be off from there on")):
        these = np.flatnonzero(which)
        if not len(these):
            continue
        longest = np.sort(these[np.argsort(steps[these])[::-1][:3]])    # the three longest, in time order
        where = ", ".join(f"{steps[k]:.3g} s after {t[rows[k]]:.4g} s" for k in longest)
        more = f" and {len(these) - len(longest)} more" if len(these) > len(longest) else ""
        out.append(f"{len(these)} gap(s) without samples longer than {GAP_WARN_STEPS} sampling steps "
                   f"({where}{more}): {what}")
    return out


def prepare(run: RunData, x_scale_mm: float | None = None, name: str = "") -> PreparedRun:
    """Segment the run and check that it can be identified (FoamlabError if not)."""
    run, off_schedule = on_schedule(run)
    n = len(run)
    if n < 20:
        raise FoamlabError(f"run has {n} samples: far too few to identify the model")
    f = run.force_N
    if not np.all(np.isfinite(f)):
        raise FoamlabError("run has NaN or infinite force values")
    noise = noise_sigma(f)
    lo, hi = np.percentile(f, [0.5, 99.5])
    if hi - lo <= max(FLAT_FORCE_NOISE_MULTIPLE * noise, 1e-9 * max(1.0, abs(hi))):
        raise FoamlabError(f"force is flat: it spans {hi - lo:.3g} N, within its noise ({noise:.2g} N); "
                           "the specimen was not loaded or the force channel is not connected")
    seg = run.segments()
    cycles, halves = seg.cycles, seg.half_cycles
    if not cycles or cycles[0].unloading is None:
        have = ", ".join(h.label for h in halves) or "none"
        raise FoamlabError(f"no complete cycle: identification needs at least one loading and its "
                           f"unloading; found {have}")
    minima, maxima, dwell_starts = _turning_points(run.displacement_mm, seg)
    labels = labels_from_extrema(n, minima, maxima)
    # (first, last, is_maximum) at each turning point, in the order _turning_points found them
    extremes = [(dwell_starts[2 * c], minima[c], False) for c in range(len(minima))] + \
               [(dwell_starts[2 * c + 1], maxima[c], True) for c in range(len(maxima))]

    # every sample from the first cycle's start to the end of the last half-cycle,
    # dwells at turning points included: the causal model covers them, and a dwell
    # (relaxation, or the damping creep of Eq. 9) is information, not a gap
    own_halves: list[HalfCycle] = [h for h in halves if h.cycle >= 1]
    mask = np.zeros(n, dtype=bool)
    mask[minima[0]:own_halves[-1].stop] = True
    observed = np.flatnonzero(mask)
    contact = ~seg.contact_lost[observed]
    if contact.sum() < 50:
        raise FoamlabError(f"only {int(contact.sum())} samples in contact with the specimen; "
                           "nothing to identify")

    native = float(np.median(np.diff(run.time_s)))
    half_samples = min(len(h) for h in own_halves)
    q = max(1, half_samples // FIT_SAMPLES_PER_HALF_CYCLE, len(observed) // FIT_ROWS_MAX)
    in_contact = observed[contact]
    # decimated rows: the samples nearest to the operators' grid (every q-th sample
    # from the first cycle's start on a regular clock), plus the turning points
    fit_step = native * q
    nearest = _nearest_on_grid(run.time_s, run.time_s[minima[0]], fit_step)
    corners = np.unique(np.asarray(maxima + minima + dwell_starts))
    fit_rows = np.intersect1d(np.union1d(nearest, corners), in_contact)
    # half-cycles as the model switches them: (cycle, direction) of the labels
    half_id = np.where(mask, labels.cycle * 2 + (labels.direction < 0), -1)
    fit_force, fit_count = _block_means(run.force_N, fit_rows, corners, half_id, ~seg.contact_lost, q)
    curvature = BlockCurvature.of(fit_rows, fit_count, q, half_id)

    xs = run.displacement_mm[observed]
    x_scale = float(x_scale_mm) if x_scale_mm else float(np.max(np.abs(xs)))
    if not x_scale > 0:
        raise FoamlabError("displacement never leaves zero: nothing to identify")
    warnings = list(seg.notes)
    if seg.leading_unloading is not None:
        warnings.append("the run starts with an unloading (before the first loading); it is left out")
    n_res = sum(1 for c in cycles if c.unloading is not None)
    path = displacement_path(run.time_s, run.displacement_mm, corners)
    corner_tol = max(3.0 * noise_sigma(run.displacement_mm), 1e-9 * max(seg.stroke_mm, 1.0))
    loading_times = [run.time_s[c.loading.stop - 1] - run.time_s[c.loading.start] for c in cycles]
    warnings += _sampling_notes(off_schedule, run.time_s, observed, native, extremes)
    # a measured displacement turns between its samples; an exact one (a polyline of its
    # samples: foamlab's own synthetic runs) at them - the fit checks the other (other_turns)
    nodes = path_nodes(run.time_s, path, sorted(extremes), corner_tol,
                       between_samples=not exact_history(run.displacement_mm))
    return PreparedRun(
        run=run, seg=seg, labels=labels, observed=observed, contact=contact,
        fit_rows=fit_rows, corners=corners, fit_force=fit_force, fit_count=fit_count,
        block_curvature=curvature, fit_step_s=fit_step, native_step_s=native,
        x_scale_mm=x_scale, n_residual_cycles=n_res,
        loading_time_s=float(np.median(loading_times)), noise_N=noise, warnings=warnings,
        path_mm=path, nodes=nodes, block_q=q, half_id=half_id, extremes=sorted(extremes), corner_tol=corner_tol,
        series=_series(run, name, labels, nodes, seg.contact_lost,
                       force_path(run.time_s, run.displacement_mm, run.force_N, corners)), off_schedule=off_schedule,
    )


#: A sample taken this far (as a fraction of the sampling step) off its schedule is left out
#: (on_schedule) when at most this share of the samples are.
OFF_SCHEDULE, RARE_OFF_SCHEDULE = 0.5, 0.02


def _nearest_on_grid(t: np.ndarray, t0: float, step: float) -> np.ndarray:
    """Index of the sample nearest to each instant t0 + k * step up to the last sample."""
    grid_t = t0 + step * np.arange(int((t[-1] - t0) / step) + 1)
    nearest = np.clip(np.searchsorted(t, grid_t), 1, len(t) - 1)
    nearest -= (grid_t - t[nearest - 1]) < (t[nearest] - grid_t)
    return nearest


def on_schedule(run: RunData) -> tuple[RunData, int]:
    """The run without the samples taken off its sampling schedule, and how many there were.

    A request that stalls leaves a gap, then samples bunched; the instant of the samples
    around the stall is unsure by the stall (S x its wall time on a machine run at speedup
    S): one such sample bends the estimated path for a second around it (docs/analysis.md,
    "The path"). Samples whose interval to a neighbour is off the sampling step by more than OFF_SCHEDULE
    of it are left out - only when they are rare (a regular clock that stalled): a clock
    irregular by design (logging on change) is kept as it is.
    """
    t = np.asarray(run.time_s, float)
    if len(t) < 10:
        return run, 0
    dt = np.diff(t)
    h = float(np.median(dt))
    off = np.abs(dt - h) > OFF_SCHEDULE * h
    bad = np.zeros(len(t), dtype=bool)
    bad[1:] |= off
    bad[:-1] |= off
    if not bad.any() or bad.mean() > RARE_OFF_SCHEDULE:
        return run, 0
    return run.take(~bad), int(bad.sum())


def _series(run: RunData, name: str, labels: HistoryLabels, nodes: PathNodes,
            contact_lost: np.ndarray, y_path: np.ndarray) -> Series:
    """The run as every full fit sees it: the model driven by the path at the samples, the
    samples that path determines as evidence, the crosshead's velocity and speed."""
    t = np.asarray(run.time_s, float)
    y = np.asarray(run.force_N, float)
    x = nodes.at_samples
    velocity = estimate_velocity(t, x, labels)
    moving = np.abs(velocity) > 0.5 * np.percentile(np.abs(velocity), 95)
    speed = float(np.median(np.abs(velocity[moving]))) * 60.0 if np.any(moving) else 0.0
    return Series(name=name or run.source or "run", t=t, x=x, y=y, labels=labels, nodes=nodes,
                  x_measured=np.asarray(run.displacement_mm, float), y_path=y_path,
                  evidence=path_determined(t, run.displacement_mm, y, nodes, noise_sigma(y)),
                  no_contact=np.asarray(contact_lost, bool),
                  velocity=velocity, rate=loading_rate(t, x, labels.starts), speed_mm_min=speed)
