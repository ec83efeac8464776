"""What identification needs from a run, checked once: cycles, labels, samples to fit.

Every limit here is a property of the run (its sampling, its half-cycles, its
noise); none is tuned to a data set. A run that cannot be identified raises a
FoamlabError that says what is missing, before any optimiser starts.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import savgol_filter

from foamlab import FoamlabError
from foamlab.identification.basis import Layout, ModelBasis
from foamlab.model import HistoryLabels, ModelParameters, ModelResponse, evaluate, labels_from_extrema
from foamlab.model.components import elastic_force
from foamlab.rundata import RunData
from foamlab.segmentation import HalfCycle, Segmentation, segment

#: The decimated fit keeps about this many samples per half-cycle (the curves are
#: smooth over a half-cycle; the final polish and the statistics use every sample).
FIT_SAMPLES_PER_HALF_CYCLE = 100
#: Block radius at most (samples since the last turning point) / this.
CUSP_DISTANCE_RATIO = 4
#: A force range smaller than this many times the force noise is "flat".
FLAT_FORCE_NOISE_MULTIPLE = 20.0
#: The displacement that drives the model is the crosshead's path estimated from the
#: samples (displacement_path): a local cubic over this long a window, fitted within each
#: stretch between corners of x.
PATH_WINDOW_S = 2.0
PATH_ORDER = 3
#: A crosshead that reaches (leaves) a turning point closer than this fraction of a
#: sample step before (after) a sample did so at the sample: no corner node between.
CORNER_AT_SAMPLE = 0.02
#: The model's response between the nodes of a path with corner nodes is computed on a
#: uniform grid this many times finer than the samples (model_response).
RESPONSE_REFINE = 8


@dataclass(frozen=True)
class Orders:
    """Model orders: N damping modes, M residual terms per cycle, elastic polynomial order P."""

    N: int = 3
    M: int = 3
    P: int = 7

    def __post_init__(self) -> None:
        if self.N < 0 or self.M < 0 or self.P < 1:
            raise FoamlabError(f"orders N={self.N}, M={self.M}, P={self.P}: need N >= 0, M >= 0, P >= 1")
        if self.N > 6 or self.M > 6 or self.P > 12:
            raise FoamlabError(f"orders N={self.N}, M={self.M}, P={self.P}: at most N=6, M=6, P=12 "
                               "(higher orders are not identifiable from one run)")

    @classmethod
    def parse(cls, text: str) -> "Orders":
        """'N,M,P', e.g. '3,3,7' (the paper's orders)."""
        parts = [p.strip() for p in str(text).split(",")]
        try:
            n, m, p = (int(v) for v in parts)
        except ValueError:
            raise FoamlabError(f"orders {text!r}: expected three integers N,M,P, e.g. 3,3,7") from None
        return cls(n, m, p)

    def __str__(self) -> str:
        return f"N={self.N}, M={self.M}, P={self.P}"


def noise_sigma(f: np.ndarray) -> float:
    """White-noise sigma from second differences (robust to the curve itself)."""
    if len(f) < 4:
        return 0.0
    d2 = np.diff(f, 2)
    return float(1.4826 * np.median(np.abs(d2 - np.median(d2))) / np.sqrt(6.0))


#: A displacement is measured (not an exact synthetic history) when more than this share of its
#: second differences is not zero.
MEASURED_BENDS = 0.05


def exact_history(x: np.ndarray) -> bool:
    """True for an exact piecewise-linear history (a synthetic one: its samples are its path,
    corners included), False for a measured displacement (estimated: displacement_path).

    An exact history bends only at its corners; a measured one at many samples (resolution,
    timing). A noise level of zero does not tell them apart: a 1 um encoder read on a regular
    clock has zero second differences at most samples, so its robust noise level is 0 too
    (measured: serial recordings at speedup 2; its 1 um staircase through the residual's
    near-derivative cost 0.015 N rms, and clean runs were named a cause).
    """
    x = np.asarray(x, float)
    if len(x) < 5:
        return True
    d2 = np.abs(np.diff(x, 2))
    return not bool(np.mean(d2 > 1e-9 * max(float(np.ptp(x)), 1.0)) > MEASURED_BENDS)


def displacement_path(t: np.ndarray, x: np.ndarray, corners) -> np.ndarray:
    """The displacement as the model should see it: the measured one without its noise.

    A displacement reading is a measurement too: the encoder's resolution (1 um) and the
    jitter of the instant each sample was taken are noise. The residual term's fractional
    derivative (beta up to ~0.8, nearly a derivative) turns white displacement noise into
    force noise, ~140 N per mm rms for the default specimen at 16 Hz: 1 um of resolution
    alone costs 0.05 N, a load cell's whole noise, and the fit cannot reach the force noise.
    Between two corners of x (turning points, dwell starts) a crosshead's path is smooth,
    so there it is estimated by a Savitzky-Golay cubic over PATH_WINDOW_S, on a uniform grid
    (a missed sample is a straight line between its neighbours, as the crosshead moved).
    The corner samples stay as measured: the crosshead turns somewhere between a corner and
    its neighbours, which no smooth curve through them would respect. An exact history (no
    noise: synthetic data) is returned unchanged.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    path = x.copy()
    n = len(x)
    if exact_history(x):
        return path
    step = float(np.median(np.diff(t)))
    window = int(round(PATH_WINDOW_S / step)) | 1
    bounds = np.unique(np.concatenate([[-1, n], np.asarray(corners, dtype=int)]))
    for a, b in zip(bounds[:-1], bounds[1:]):
        ts, xs = t[a + 1:b], x[a + 1:b]               # between two corners, both left out
        if len(ts) < 2 or not ts[-1] > ts[0]:
            continue
        n_grid = int(round((ts[-1] - ts[0]) / step)) + 1
        w = min(window, n_grid if n_grid % 2 else n_grid - 1)
        if w <= PATH_ORDER + 1:
            continue                                      # too short to estimate: as measured
        grid = np.linspace(ts[0], ts[-1], n_grid)
        path[a + 1:b] = np.interp(ts, grid, savgol_filter(np.interp(grid, ts, xs), w, PATH_ORDER,
                                                          mode="interp"))
    return path


@dataclass
class PathNodes:
    """The displacement path as nodes: the samples plus the instants, between two samples,
    where the crosshead reached a turning point and where it left it (path_nodes)."""

    t: np.ndarray
    x: np.ndarray
    of_sample: np.ndarray         # node index of each sample
    labels: HistoryLabels         # the model's half-cycles on the nodes
    corners: np.ndarray           # node indices where x has a corner (turning points, arrivals)

    @property
    def inserted(self) -> int:
        return len(self.t) - len(self.of_sample)

    @property
    def at_samples(self) -> np.ndarray:
        """The path at the samples (the displacement that drives the model there)."""
        return self.x[self.of_sample]

    def basis(self, samples: np.ndarray, layout: Layout, x_scale_mm: float, step_s: float,
              source: np.ndarray | None = None) -> ModelBasis:
        """The model's design matrix at these samples, its operators driven by the path
        through the nodes (identification's fits and diagnosis' extensions alike).

        source: another history on the samples to drive the memory operators with instead
        of the displacement (taken piecewise linear between samples, as the path is)."""
        drive = self.x if source is None else np.interp(self.t, self.t[self.of_sample], source)
        return ModelBasis(self.t, drive, self.labels, self.of_sample[np.asarray(samples, dtype=int)], layout,
                          x_scale_mm, step_s, self.corners)


def path_nodes(t: np.ndarray, path: np.ndarray, extremes: list[tuple[int, int, bool]],
               tol: float) -> PathNodes:
    """The crosshead's path with the corners the samples miss.

    A drive that reverses from rest arrives at a turning point between two samples,
    waits, and leaves between two samples; the straight lines through the samples cut
    both corners, and the residual's near-derivative memory responds to exactly that
    (measured: 0.7-1.4 N at the first samples after a turning point, 16 Hz, default
    specimen). extremes: (first, last, is_maximum) samples at each turning point. A
    stop is seen when there are several samples at the extreme or the one there is off
    both stretches' straight lines (by more than tol); then the arrival is where
    that line reaches the extreme and the departure where the outgoing line leaves it,
    each a node when it falls between two samples, and the model switches at the
    departure (the last node at the extreme, as model.label_history does). A path that
    turns without stopping (a triangle sampled anywhere) keeps its samples as nodes."""
    n = len(t)
    inserts: list[tuple[float, float, int]] = []          # (time, x, sample it precedes)
    arrival, departure = {}, {}

    def line(a: int, b: int):
        if not (0 <= a < n and 0 <= b < n and t[b] > t[a]):
            return None
        v = (path[b] - path[a]) / (t[b] - t[a])
        return (lambda when: path[a] + v * (when - t[a])), v

    for k, (first, last, _) in enumerate(extremes):
        x_ext = path[last]
        incoming, outgoing = line(first - 2, first - 1), line(last + 1, last + 2)
        if incoming is None or outgoing is None or incoming[1] == 0 or outgoing[1] == 0:
            continue
        if first == last and min(abs(incoming[0](t[first]) - path[first]),
                                 abs(outgoing[0](t[first]) - path[first])) <= tol:
            continue                           # on one of the lines: turned without stopping
        at = t[first - 1] + (x_ext - path[first - 1]) / incoming[1]
        if t[first - 1] < at < t[first] - CORNER_AT_SAMPLE * (t[first] - t[first - 1]):
            arrival[k] = len(inserts)
            inserts.append((at, x_ext, first))
        at = t[last + 1] - (path[last + 1] - x_ext) / outgoing[1]
        if t[last] + CORNER_AT_SAMPLE * (t[last + 1] - t[last]) < at < t[last + 1]:
            departure[k] = len(inserts)
            inserts.append((at, x_ext, last + 1))
    before = np.array([i[2] for i in inserts], dtype=int)
    of_sample = np.arange(n) + np.searchsorted(np.sort(before), np.arange(n), side="right")
    node_t = np.empty(n + len(inserts))
    node_x = np.empty(n + len(inserts))
    node_t[of_sample], node_x[of_sample] = t, path
    # an inserted node sits right before the sample it precedes (two inserts before one
    # sample - a departure and the next arrival - cannot happen: a half-cycle has samples)
    insert_node = {j: int(of_sample[b]) - 1 for j, (_, _, b) in enumerate(inserts)}
    for j, (at, xv, _) in enumerate(inserts):
        node_t[insert_node[j]], node_x[insert_node[j]] = at, xv
    minima, maxima, corners = [], [], []
    for k, (first, last, top) in enumerate(extremes):
        turn = insert_node[departure[k]] if k in departure else int(of_sample[last])
        (maxima if top else minima).append(turn)
        corners += [turn, insert_node[arrival[k]] if k in arrival else int(of_sample[first])]
    labels = labels_from_extrema(len(node_t), minima, maxima)
    return PathNodes(node_t, node_x, of_sample, labels, np.unique(np.asarray(corners, dtype=int)))


def model_response(params: ModelParameters, fd: "FitData") -> ModelResponse:
    """The model at the run's samples, driven by the path with its corner nodes.

    Without corner nodes that is model.evaluate on the samples. With them, evaluate runs
    on a uniform grid RESPONSE_REFINE times finer than the samples through the nodes
    (a corner between two grid points is cut by at most that much) and the memory
    components come back to the samples by interpolation; the elastic force is exact."""
    t, x, nodes = fd.t, fd.x, fd.nodes
    if not nodes.inserted:
        return evaluate(params, t, x, fd.labels)
    step = fd.native_step_s / RESPONSE_REFINE
    grid = nodes.t[0] + step * np.arange(int(np.ceil((nodes.t[-1] - nodes.t[0]) / step)) + 1)
    grid_x = np.interp(grid, nodes.t, nodes.x)
    # each turning point at the last grid point not after its node (there x is at the extreme)
    at = lambda idx: [int(np.searchsorted(grid, nodes.t[i] + 1e-9 * step, side="right")) - 1 for i in idx]
    labels = labels_from_extrema(len(grid), at(nodes.labels.starts), at(nodes.labels.peaks))
    fine = evaluate(params, grid, grid_x, labels)
    back = lambda values: np.interp(t, grid, values)
    return ModelResponse(t, x, elastic_force(params, x), back(fine.damping), back(fine.residual), fd.labels)


@dataclass
class FitData:
    run: RunData
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
    nodes: "PathNodes"            # the same, with the corners between samples (path_nodes)

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


def prepare(run: RunData, x_scale_mm: float | None = None) -> FitData:
    """Segment the run and check that it can be identified (FoamlabError if not)."""
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
    seg = segment(run)
    cycles = seg.cycles
    halves = seg.half_cycles
    if len(halves) == 1:
        raise FoamlabError(f"run has a single half-cycle ({halves[0].direction}); identification "
                           "needs at least two cycles (loading, unloading, second loading)")
    if len(cycles) < 2 or cycles[0].unloading is None:
        have = ", ".join(h.label for h in halves) or "none"
        raise FoamlabError(f"too few cycles: identification needs at least two (the paper's Eq. 15 "
                           f"subtracts the first unloading from the second loading); found {have}")
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

    dt = np.diff(run.time_s)
    native = float(np.median(dt))
    half_samples = min(len(h) for h in own_halves)
    q = max(1, half_samples // FIT_SAMPLES_PER_HALF_CYCLE)
    in_contact = observed[contact]
    # decimated rows: the samples nearest to the operators' grid (every q-th sample
    # from the first cycle's start on a regular clock), plus the turning points
    fit_step = native * q
    t0 = run.time_s[minima[0]]
    grid_t = t0 + fit_step * np.arange(int((run.time_s[-1] - t0) / fit_step) + 1)
    nearest = np.clip(np.searchsorted(run.time_s, grid_t), 1, n - 1)
    nearest -= (grid_t - run.time_s[nearest - 1]) < (run.time_s[nearest] - grid_t)
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
    warnings = []
    if seg.leading_unloading is not None:
        warnings.append("the run starts with an unloading (before the first loading); it is left out")
    n_res = sum(1 for c in cycles if c.unloading is not None)
    path = displacement_path(run.time_s, run.displacement_mm, corners)
    corner_tol = max(3.0 * noise_sigma(run.displacement_mm), 1e-9 * max(seg.stroke_mm, 1.0))
    loading_times = [run.time_s[c.loading.stop - 1] - run.time_s[c.loading.start] for c in cycles]
    return FitData(
        run=run, seg=seg, labels=labels, observed=observed, contact=contact,
        fit_rows=fit_rows, corners=corners, fit_force=fit_force, fit_count=fit_count,
        block_curvature=curvature, fit_step_s=fit_step, native_step_s=native,
        x_scale_mm=x_scale, n_residual_cycles=n_res,
        loading_time_s=float(np.median(loading_times)), noise_N=noise, warnings=warnings,
        path_mm=path, nodes=path_nodes(run.time_s, path, sorted(extremes), corner_tol),
    )
