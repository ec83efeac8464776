"""The crosshead's path as the model sees it: the measured displacement without its noise,
the corners it turns at between samples, and which samples the path determines.

Used by every fit (identification, diagnosis) through the prepared run (prepared.py).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_filter

from foamlab.analysis.basis import ModelBasis
from foamlab.model import HistoryLabels, labels_from_extrema
from foamlab.model.layout import Layout

#: The displacement that drives the model is the crosshead's path estimated from the
#: samples (displacement_path): a local cubic over this long a window, fitted within each
#: stretch between corners of x.
PATH_WINDOW_S = 2.0
PATH_ORDER = 3
#: A crosshead that reaches (leaves) a turning point closer than this fraction of a
#: sample step before (after) a sample did so at the sample: no corner node between.
CORNER_AT_SAMPLE = 0.02
#: Samples within this many sample steps before / after a corner of the crosshead's path
#: (a turning point, or where it arrived at or left one) are not evidence, unless the force
#: is steady over that whole window: no step larger than this many noise sigmas.
CORNER_STEPS_BEFORE, CORNER_STEPS_AFTER = 1.5, 2.5
STEADY_NOISE_MULTIPLE = 4.0
#: A displacement is measured (not an exact synthetic history) when more than this share of its
#: second differences is not zero - above EXACT_BEND of its range: the rounding of a file written
#: with 6 decimals (1e-6 mm) is not a bend, a 1 um encoder's step (1.7e-5 of 58 mm) is.
EXACT_BEND = 1e-7
MEASURED_BENDS = 0.05


def exact_history(x: np.ndarray) -> bool:
    """True for an exact piecewise-linear history (a synthetic one: its samples are its path,
    corners included), False for a measured displacement (estimated: displacement_path).

    An exact history bends only at its corners; a measured one at many samples (resolution,
    timing). A noise level of zero does not tell them apart: a 1 um encoder read on a regular
    clock has zero second differences at most samples, so its robust noise level is 0 too
    (docs/analysis.md, "The path").
    """
    x = np.asarray(x, float)
    if len(x) < 5:
        return True
    d2 = np.abs(np.diff(x, 2))
    return not bool(np.mean(d2 > EXACT_BEND * max(float(np.ptp(x)), 1.0)) > MEASURED_BENDS)


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
    x = np.asarray(x, float)
    return x.copy() if exact_history(x) else _smooth_between(np.asarray(t, float), x, corners)


def force_path(t: np.ndarray, x: np.ndarray, force: np.ndarray, corners) -> np.ndarray:
    """The measured force smoothed as the displacement's path is (the same corners and window;
    unchanged where the displacement is exact): the force a frame deflects under at once
    (machine_compliance at tau_frame_s = 0). The smoothing is linear, so the path less C times
    this is the path of the displacement less the frame's deflection, C F: it fits a machine
    that records the specimen's travel plus the frame's as well as one whose crosshead follows
    its command (docs/analysis.md, "The frame at once")."""
    force = np.asarray(force, float)
    return force.copy() if exact_history(x) else _smooth_between(np.asarray(t, float), force, corners)


def _smooth_between(t: np.ndarray, v: np.ndarray, corners) -> np.ndarray:
    """v by a Savitzky-Golay cubic over PATH_WINDOW_S within each stretch between corners (the
    corner samples as measured), on a uniform grid."""
    path = v.copy()
    n = len(v)
    step = float(np.median(np.diff(t)))
    window = int(round(PATH_WINDOW_S / step)) | 1
    bounds = np.unique(np.concatenate([[-1, n], np.asarray(corners, dtype=int)]))
    for a, b in zip(bounds[:-1], bounds[1:]):
        ts, xs = t[a + 1:b], v[a + 1:b]               # between two corners, both left out
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
    between_samples: bool = True  # turns without a stop are nodes between samples (else at one)
    # the instants of turns without a stop, where the samples cannot place them (the lines' meeting
    # point, or the extreme sample where they meet at it): fit.py fits the other placement there
    turns_between: np.ndarray = field(default_factory=lambda: np.zeros(0))
    turn_extremes: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # each one's turning point
    before_extreme: bool = False  # a turn whose lines meet at its extreme sample is just before it
    flipped: tuple[int, ...] = ()  # turning points placed the other way (fitted per turn: fit.py)

    @property
    def inserted(self) -> int:
        return len(self.t) - len(self.of_sample)

    @property
    def at_samples(self) -> np.ndarray:
        """The path at the samples (the displacement that drives the model there)."""
        return self.x[self.of_sample]

    def along(self, source: np.ndarray | None = None) -> np.ndarray:
        """The displacement at the nodes, or (source) another history on the samples there, taken
        piecewise linear between samples as the path is."""
        return self.x if source is None else np.interp(self.t, self.t[self.of_sample], source)

    def basis(self, samples: np.ndarray, layout: Layout, x_scale_mm: float, step_s: float,
              source: np.ndarray | None = None) -> ModelBasis:
        """The model's design matrix at these samples, its operators driven by the path
        through the nodes (identification's fits and diagnosis' extensions alike).

        source: another history on the samples to drive the memory operators with instead
        of the displacement (taken piecewise linear between samples, as the path is)."""
        return ModelBasis(self.t, self.along(source), self.labels, self.of_sample[np.asarray(samples, dtype=int)],
                          layout, x_scale_mm, step_s, self.corners)


def _lines_meet(t: np.ndarray, path: np.ndarray, first: int, last: int, v_in: float, v_out: float):
    """(time, x, sample it precedes) where the straight lines into and out of a turning point
    meet, when that falls between two samples from first - 1 to last + 1 (not within
    CORNER_AT_SAMPLE of one) and beyond the extreme samples; else None.

    A drive that reverses without stopping turns between two samples: the samples nearest
    the turn lie on the lines, and the model must switch (damping off, the residual memory
    on: Eq. 20) at the turn, not at a sample; switching at a sample puts the sample just
    after a turn on the wrong half-cycle (tens of newtons; docs/identification.md).
    """
    if v_in == v_out:
        return None
    a, b = first - 1, last + 1
    when = (path[b] - path[a] + v_in * t[a] - v_out * t[b]) / (v_in - v_out)
    x = path[a] + v_in * (when - t[a])
    if not min((x - path[first]) * v_in, (x - path[last]) * v_in) > 0:   # not beyond the extreme
        return None
    for lo in range(a, b):
        gap = t[lo + 1] - t[lo]
        if t[lo] + CORNER_AT_SAMPLE * gap < when < t[lo + 1] - CORNER_AT_SAMPLE * gap:
            return float(when), float(x), lo + 1
    return None


def _just_before(t: np.ndarray, path: np.ndarray, first: int, v_in: float, v_out: float):
    """A turn just before the extreme sample, which then lies on the outgoing line: the other
    placement of a turn whose lines meet at the sample within the encoder's resolution (a
    sample a fraction of a millisecond after the turn reads the peak, and only its force
    says on which side of the turn it was)."""
    if v_in == v_out:
        return None
    a = first - 1
    when = (path[first] - path[a] + v_in * t[a] - v_out * t[first]) / (v_in - v_out)
    gap = t[first] - t[a]
    when = float(np.clip(when, t[a] + 1e-3 * gap, t[first] - 1e-3 * gap))
    return when, float(path[first] - v_out * (t[first] - when)), first


def path_nodes(t: np.ndarray, path: np.ndarray, extremes: list[tuple[int, int, bool]],
               tol: float, between_samples: bool = True, before_extreme: bool = False,
               flipped: tuple[int, ...] = ()) -> PathNodes:
    """The crosshead's path with the corners the samples miss.

    A drive that reverses from rest arrives at a turning point between two samples,
    waits, and leaves between two samples; the straight lines through the samples cut
    both corners, and the residual's near-derivative memory responds to exactly that
    (docs/analysis.md, "The path"). extremes: (first, last, is_maximum) samples at each turning point. A
    stop is seen when there are several samples at the extreme or the one there is off
    both stretches' straight lines (by more than tol); then the arrival is where
    that line reaches the extreme and the departure where the outgoing line leaves it,
    each a node when it falls between two samples, and the model switches at the
    departure (the last node at the extreme, as model.label_history does). A path that
    turns without stopping turns where the lines into and out of the turning point meet
    (_lines_meet: between_samples) or at its extreme sample (a polyline made of its
    samples, as foamlab's own synthetic runs are); the samples alone cannot tell which.
    Where the lines meet at the extreme sample itself (within the encoder's resolution), a
    measured path's other placement (before_extreme) turns just before it (_just_before).
    flipped: turning points (indices of extremes) placed the other way from the rest (each
    turn's placement a parameter of the fit)."""
    n = len(t)
    inserts: list[tuple[float, float, int]] = []          # (time, x, sample it precedes)
    arrival, departure = {}, {}
    between: list[float] = []
    turn_of: list[int] = []

    def line(a: int, b: int):
        if not (0 <= a < n and 0 <= b < n and t[b] > t[a]):
            return None
        v = (path[b] - path[a]) / (t[b] - t[a])
        return (lambda when: path[a] + v * (when - t[a])), v

    for k, (first, last, _) in enumerate(extremes):
        place_between, place_before = ((not between_samples, not before_extreme) if k in flipped
                                       else (between_samples, before_extreme))
        x_ext = path[last]
        incoming, outgoing = line(first - 2, first - 1), line(last + 1, last + 2)
        if incoming is None or outgoing is None or incoming[1] == 0 or outgoing[1] == 0:
            continue
        on_in, on_out = (abs(incoming[0](t[first]) - path[first]) <= tol,
                         abs(outgoing[0](t[last]) - path[last]) <= tol)
        if (first == last and (on_in or abs(outgoing[0](t[first]) - path[first]) <= tol)
                or last == first + 1 and on_in and on_out):
            # turned without stopping (the samples at the extreme lie on the lines into and
            # out of it: one, or two that round to the same height), where the lines meet
            turn = _lines_meet(t, path, first, last, incoming[1], outgoing[1])
            if turn is not None:
                between.append(turn[0])
                turn_of.append(k)
            elif first == last:
                # the lines meet at the extreme sample: the turn is there or just before it, and
                # only the sample's force says which (B at 10 Hz: a turn 1.7 ms before, 28 N)
                between.append(float(t[first]))
                turn_of.append(k)
                if place_before:
                    turn = _just_before(t, path, first, incoming[1], outgoing[1])
            if turn is not None and (place_between or turn[0] not in between):
                departure[k] = len(inserts)
                inserts.append(turn)
            continue
        at = t[first - 1] + (x_ext - path[first - 1]) / incoming[1]
        if t[first - 1] < at < t[first] - CORNER_AT_SAMPLE * (t[first] - t[first - 1]):
            arrival[k] = len(inserts)
            inserts.append((at, x_ext, first))
        at = t[last + 1] - (path[last + 1] - x_ext) / outgoing[1]
        if t[last] + CORNER_AT_SAMPLE * (t[last + 1] - t[last]) < at < t[last + 1]:
            departure[k] = len(inserts)
            inserts.append((at, x_ext, last + 1))
    node_t, node_x, of_sample, minima, maxima, corners = _with_inserts(t, path, extremes, inserts,
                                                                       arrival, departure)
    labels = labels_from_extrema(len(node_t), minima, maxima)
    return PathNodes(node_t, node_x, of_sample, labels, np.unique(np.asarray(corners, dtype=int)),
                     between_samples, np.asarray(between, float), np.asarray(turn_of, int), before_extreme,
                     tuple(sorted(int(k) for k in flipped)))


def _with_inserts(t: np.ndarray, path: np.ndarray, extremes: list[tuple[int, int, bool]],
                  inserts: list[tuple[float, float, int]], arrival: dict[int, int], departure: dict[int, int]):
    """The samples and the inserted corners as one node sequence, with each turning point's
    node (minima, maxima) and the corner nodes."""
    n = len(t)
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
    return node_t, node_x, of_sample, minima, maxima, corners


def path_determined(t: np.ndarray, x: np.ndarray, force: np.ndarray, nodes: PathNodes,
                    noise_N: float) -> np.ndarray:
    """The samples whose model force the measured run determines.

    The crosshead stops, waits and reverses between two samples; where exactly, and how
    (it decelerates and accelerates), the samples do not say. Near a turning point the
    model's force changes by several newtons within a sample step (the damping stops, the
    residual's near-derivative memory starts), so there it depends on instants the data
    cannot resolve (docs/analysis.md, "The path"). Where the force is steady around a corner (the plate
    off the specimen at the end of an unloading) the instant does not matter: kept.
    These samples are predicted but not used as evidence (fits, statistics, held-out
    checks). An exact (synthetic) history has its corners at its samples: all are evidence.
    """
    t = np.asarray(t, float)
    y = np.asarray(force, float)
    n = len(t)
    used = np.ones(n, dtype=bool)
    if n < 3 or exact_history(x):
        return used
    h = float(np.median(np.diff(t)))
    step = np.abs(np.diff(y))
    steady = STEADY_NOISE_MULTIPLE * noise_N
    for tc in nodes.t[nodes.corners]:
        near = np.flatnonzero((t >= tc - CORNER_STEPS_BEFORE * h) & (t <= tc + CORNER_STEPS_AFTER * h))
        if not len(near):
            continue
        steps = step[max(near[0] - 1, 0):min(near[-1] + 1, n - 1)]     # into, inside and out of it
        if not len(steps) or steps.max() > steady:
            used[near] = False
    return used
