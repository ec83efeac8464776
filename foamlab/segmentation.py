"""Cycles and half-cycles of a run, from the displacement alone.

What is found, and how (every threshold comes from the data, none from the file):

- Turning points: a hysteresis ("zig-zag") detector on the displacement. A
  reversal counts only once the plate has come back by more than
  ``hysteresis_mm`` = max(5 % of the stroke, 10 x displacement noise), so sensor
  noise and small controller wobble never create cycles. Each reversal is then
  placed on the extreme of the smoothed displacement around it, refined to the
  raw extreme within a few samples (window / 8).
- Holds (dwells): spans where the smoothed speed stays under 10 % of the typical
  crosshead speed for longer than the smoothing window. A hold at a turning point,
  at the start (preload dwell) or at the end is left out of the half-cycles.
- Half-cycles: loading = displacement increasing (compression positive), unloading
  = decreasing. Consecutive half-cycles share their turning-point sample (the
  curve is continuous there). Cycle k is the k-th loading and the unloading that
  follows it; an unloading before the first loading (a run that starts at the
  top) is cycle 0 and is not in ``cycles``.
- Contact loss (the paper's recovery region, section 3.1): after the first
  contact, the force sits on the load cell's unloaded reading. That reading is
  the level of the lowest forces of the run when they are near zero and flat
  (independent of the displacement); it is often a little off zero: -0.23 N on
  the bundled Bluehill file. The threshold is 5 x the noise of those samples
  above it. A run that keeps its preload has no flat floor and no contact loss.
- First-cycle linear elastic region: the longest stretch from the first contact
  in the first loading whose force is a straight line in displacement, i.e. whose
  least-squares line leaves residuals within max(1.5 x force noise, 0.5 % of
  the force range of the stretch) RMS (0.5 % of the range is R^2 >= ~0.9997 on
  noise-free data). It starts where the plate is in contact and has begun to
  move (a preload start settles the force for a few samples first).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import NamedTuple, Protocol

import numpy as np
from scipy import signal

from foamlab import FoamlabError

LOADING = "loading"
UNLOADING = "unloading"

#: A reversal smaller than this fraction of the stroke is not a turning point.
HYSTERESIS_FRACTION_OF_STROKE = 0.05
#: ...nor one smaller than this many times the displacement noise.
HYSTERESIS_NOISE_MULTIPLE = 10.0
#: Speeds under this fraction of the typical crosshead speed are a hold.
HOLD_SPEED_FRACTION = 0.10
#: Linear region: allowed RMS deviation from a line, as a multiple of the force noise...
LINEAR_NOISE_MULTIPLE = 1.5
#: ...or as a fraction of the force range (for noise-free data), whichever is larger.
LINEAR_RELATIVE_RMS = 0.005
#: Contact threshold above the unloaded reading, in multiples of its noise.
CONTACT_NOISE_MULTIPLE = 5.0


class Samples(Protocol):
    """What segment() reads: a foamlab.rundata.RunData, or anything with these arrays.

    Structural, so that this module needs nothing of RunData's (RunData.segments()
    calls segment(); the dependency points from rundata to here only).
    """

    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_N: np.ndarray


@dataclass(frozen=True)
class HalfCycle:
    """Samples ``start`` .. ``stop - 1`` of a run (a Python slice), one direction."""

    start: int
    stop: int
    direction: str  # LOADING or UNLOADING
    cycle: int      # 1-based; 0 for an unloading before the first loading

    @property
    def is_loading(self) -> bool:
        return self.direction == LOADING

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)

    def __len__(self) -> int:
        return self.stop - self.start

    @property
    def label(self) -> str:
        return f"cycle {self.cycle} {self.direction}"


@dataclass(frozen=True)
class Cycle:
    number: int
    loading: HalfCycle
    unloading: HalfCycle | None  # None when the run ends during the loading

    @property
    def start(self) -> int:
        return self.loading.start

    @property
    def stop(self) -> int:
        return (self.unloading or self.loading).stop


class HalfCycleData(NamedTuple):
    time_s: np.ndarray
    displacement_mm: np.ndarray
    force_N: np.ndarray


@dataclass
class Segmentation:
    run: Samples = field(repr=False)
    turning_points: np.ndarray          # sample index of each reversal, in time order
    cycles: list[Cycle]
    contact_lost: np.ndarray            # bool per sample
    first_cycle_linear_region: tuple[int, int] | None  # (start, stop) slice of samples
    holds: list[tuple[int, int]]        # (start, stop) spans left out of half-cycles
    leading_unloading: HalfCycle | None = None
    stroke_mm: float = 0.0
    hysteresis_mm: float = 0.0
    contact_zero_N: float = 0.0         # unloaded load-cell reading
    contact_threshold_N: float = 0.0    # force at or below this = no contact
    first_contact: int | None = None    # first sample in contact, None if never
    notes: tuple[str, ...] = ()         # where the engine's labels and the displacement disagree
    labelled: bool = False              # the half-cycles are the engine's labels

    @property
    def n_cycles(self) -> int:
        return len(self.cycles)

    @property
    def half_cycles(self) -> list[HalfCycle]:
        """All half-cycles in time order."""
        halves = [self.leading_unloading] if self.leading_unloading else []
        for cycle in self.cycles:
            halves.append(cycle.loading)
            if cycle.unloading is not None:
                halves.append(cycle.unloading)
        return halves

    def arrays(self, half: HalfCycle, *, in_contact_only: bool = False) -> HalfCycleData:
        """Time, displacement and force of one half-cycle (copies).

        ``in_contact_only`` drops the contact-loss samples (the paper's recovery
        region), as the paper's identification does.
        """
        sl = half.slice
        keep = np.ones(len(half), dtype=bool)
        if in_contact_only:
            keep = ~self.contact_lost[sl]
        return HalfCycleData(
            self.run.time_s[sl][keep].copy(),
            self.run.displacement_mm[sl][keep].copy(),
            self.run.force_N[sl][keep].copy(),
        )

    @property
    def contact_lost_spans(self) -> list[tuple[int, int]]:
        """(start, stop) sample spans where the plate is off the specimen."""
        return _true_spans(self.contact_lost)

    def cycle_of(self, index: int) -> int:
        """Cycle number of a sample (0 outside cycles)."""
        for cycle in self.cycles:
            if cycle.start <= index < cycle.stop:
                return cycle.number
        return 0


def segment(run: Samples) -> Segmentation:
    """Turning points, cycles, contact loss and first-cycle linear region of a run.

    The half-cycles are the engine's labels where the run has them (``run.step`` and
    ``run.cycle``, a run foamlab acquired), found in the displacement otherwise (a vendor
    file). Where both exist and disagree the labels are kept and ``notes`` says so."""
    # absurd magnitudes (1e300) overflow in squares; the result is still defined
    with np.errstate(over="ignore", invalid="ignore"):
        x, f = _checked(run)
        scale = _scale(x)
        step, cycle = getattr(run, "step", None), getattr(run, "cycle", None)
        if step is None or cycle is None:
            halves, turning, holds = _found_halves(x, scale)
            notes: tuple[str, ...] = ()
        else:
            halves, turning, holds = _labelled_halves(x, np.asarray(step), np.asarray(cycle), scale)
            notes = _disagreement(x, scale, halves)
        return _assemble(run, x, f, scale, halves, turning, holds, notes)


def _checked(run: Samples) -> tuple[np.ndarray, np.ndarray]:
    x = np.asarray(run.displacement_mm, dtype=float)
    f = np.asarray(run.force_N, dtype=float)
    n = len(x)
    if n < 3:
        raise FoamlabError(f"run has {n} samples: too few to find a half-cycle")
    if not (np.all(np.isfinite(x)) and np.all(np.isfinite(f))):
        raise FoamlabError("run has NaN or infinite displacement/force values")
    return x, f


class _Scale(NamedTuple):
    """What the displacement says about itself: its noise and stroke, the reversal that counts
    (hysteresis), the smoothing window, the smoothed displacement and the holds."""

    noise: float
    stroke: float
    hysteresis: float
    step: int                            # decimation of the first pass
    coarse_pivots: list[tuple[int, bool]]
    window: int
    smooth: np.ndarray
    holds: list[tuple[int, int]]


def _scale(x: np.ndarray) -> _Scale:
    n = len(x)
    noise_x = _noise_sigma(x)
    lo, hi = np.percentile(x, [0.1, 99.9]) if n >= 1000 else (x.min(), x.max())
    stroke = float(hi - lo)
    if stroke <= max(HYSTERESIS_NOISE_MULTIPLE * 2 * noise_x, 1e-9 * max(1.0, abs(hi))):
        raise FoamlabError(
            f"no motion: the displacement spans {stroke:.4g} mm, within its noise "
            f"({noise_x:.2g} mm); no half-cycle to analyse")
    hysteresis = max(HYSTERESIS_FRACTION_OF_STROKE * stroke, HYSTERESIS_NOISE_MULTIPLE * noise_x)
    # First pass on a decimated copy (bounded cost on long runs), to learn how long
    # a half-cycle is and so choose the smoothing window from the data.
    step = max(1, n // 20000)
    coarse_pivots = _zigzag(x[::step], hysteresis)
    edges = np.concatenate(([0], np.asarray([p for p, _ in coarse_pivots], dtype=int) * step, [n - 1]))
    shortest_half = int(np.min(np.diff(edges))) if len(edges) > 1 else n
    window = _odd(np.clip(shortest_half // 50, 5, 401), n)
    xs = _smooth(x, window)
    speed = np.abs(_smooth(x, window, deriv=1))
    is_hold = speed < HOLD_SPEED_FRACTION * float(np.percentile(speed, 95))
    holds = [(a, b) for a, b in _true_spans(is_hold) if b - a >= window]
    return _Scale(noise_x, stroke, float(hysteresis), step, coarse_pivots, window, xs, holds)


def _found_halves(x: np.ndarray, sc: _Scale) -> tuple[list[HalfCycle], np.ndarray, list[tuple[int, int]]]:
    """Half-cycles found in the displacement alone (a run without the engine's labels)."""
    n, window, holds = len(x), sc.window, sc.holds
    turning: list[int] = []
    # Place each reversal on the extreme of the smoothed displacement nearby, then
    # on the raw extreme within a few samples of it: smoothing rounds a sharp
    # reversal off by a sample or so, and the peak force belongs to the loading.
    radius = max(2, window // 8)
    for p, is_max in sc.coarse_pivots:
        centre = p * sc.step
        a, b = max(0, centre - 2 * sc.step - window), min(n, centre + 2 * sc.step + window + 1)
        pick = np.argmax if is_max else np.argmin
        smooth_at = a + int(pick(sc.smooth[a:b]))
        a, b = max(0, smooth_at - radius), min(n, smooth_at + radius + 1)
        turning.append(a + int(pick(x[a:b])))
    turning_arr = np.asarray(sorted(set(turning)), dtype=int)

    # Half-cycle boundaries, with holds at the boundaries taken out.
    first, last = 0, n  # last exclusive
    for a, b in holds:
        if a == 0:
            first = b - 1       # motion starts at the end of the initial hold
        if b == n:
            last = a + 1        # motion ends where the final hold starts
    bounds: list[tuple[int, int]] = []  # (start, stop exclusive) of each half
    prev_start = first
    for tp in turning_arr:
        end, next_start = tp, tp
        for a, b in holds:
            if a - window <= tp < b + window and 0 < a and b < n:
                end, next_start = a, b - 1
                break
        bounds.append((prev_start, end + 1))
        prev_start = next_start
    bounds.append((prev_start, last))
    bounds = [(a, b) for a, b in bounds if b - a >= 2]
    if not bounds:
        raise FoamlabError("no half-cycle: the displacement never moves monotonically")
    halves: list[HalfCycle] = []
    cycle_no = 0
    for a, b in bounds:
        direction = LOADING if sc.smooth[b - 1] > sc.smooth[a] else UNLOADING
        cycle_no += direction == LOADING
        halves.append(HalfCycle(int(a), int(b), direction, cycle_no))
    return halves, turning_arr, list(holds)


@dataclass(frozen=True)
class LabelSettings:
    """How the engine's labels become half-cycles, and when the displacement's own
    segmentation is said to disagree with them."""

    #: A labelled step that moves the plate less than this fraction of the stroke (or than the
    #: reversal noise allows, HYSTERESIS_NOISE_MULTIPLE) is a hold: a dwell, whose position
    #: stands still to the encoder's resolution.
    hold_fraction_of_stroke: float = 0.01
    #: Disagreement: another number of cycles, or a cycle boundary further apart than this
    #: many samples or this many smoothing windows (which moves found boundaries at a hold by
    #: about half of itself). On the engine's runs both agree to a sample (3-20 cycles, 16 Hz).
    tolerance_samples: int = 5
    tolerance_windows: float = 1.0


LABELS = LabelSettings()


def _labelled_halves(x: np.ndarray, step: np.ndarray, cycle: np.ndarray, sc: _Scale,
                     settings: LabelSettings = LABELS,
                     ) -> tuple[list[HalfCycle], np.ndarray, list[tuple[int, int]]]:
    """Half-cycles from the engine's labels: each run of one step is a loading, an unloading
    or a hold by how far the plate moved in it (a step's own samples say which, no method
    needed). Consecutive half-cycles share their turning sample, as found ones do: the last
    sample of a step starts the next half-cycle (the last sample of a hold, across one)."""
    still = max(HYSTERESIS_NOISE_MULTIPLE * sc.noise, settings.hold_fraction_of_stroke * sc.stroke)
    changes = np.flatnonzero(np.diff(step) != 0) + 1
    starts = np.concatenate(([0], changes))
    stops = np.concatenate((changes, [len(x)]))
    halves: list[HalfCycle] = []
    holds: list[tuple[int, int]] = []
    for a, b in zip(starts.tolist(), stops.tolist()):
        begin = max(a - 1, 0)
        moved = x[b - 1] - x[begin]
        if step[a] < 0 or abs(moved) <= still:
            holds.append((a, b))
            continue
        direction = LOADING if moved > 0 else UNLOADING
        if halves and halves[-1].direction == direction:     # two steps one way (a hold between)
            halves[-1] = HalfCycle(halves[-1].start, b, direction, halves[-1].cycle)
            continue
        halves.append(HalfCycle(begin, b, direction, int(cycle[a])))
    if not halves:
        raise FoamlabError("no half-cycle: the labelled steps never move the plate")
    turning = np.asarray([h.stop - 1 for h in halves[:-1]], dtype=int)    # a step ends at its target
    return halves, turning, holds


def _disagreement(x: np.ndarray, sc: _Scale, labelled: list[HalfCycle],
                  check: LabelSettings = LABELS) -> tuple[str, ...]:
    """One note when segmenting the displacement would give other cycles than the labels."""
    try:
        found, _, _ = _found_halves(x, sc)
    except FoamlabError as exc:
        return (f"the engine's cycle labels are kept; the displacement alone finds none ({exc})",)
    mine, theirs = _cycles(labelled)[0], _cycles(found)[0]
    if len(mine) != len(theirs):
        return (f"the engine's labels are kept: {len(mine)} cycles; segmenting the displacement "
                f"would find {len(theirs)}",)
    tolerance = max(check.tolerance_samples, int(check.tolerance_windows * sc.window))
    offsets = [abs(a - b) for m, t in zip(mine, theirs)
               for a, b in ((m.start, t.start), (m.loading.stop, t.loading.stop), (m.stop, t.stop))]
    worst = max(offsets, default=0)
    if worst > tolerance:
        return (f"the engine's labels are kept: segmenting the displacement would move a cycle "
                f"boundary by {worst} samples (more than {tolerance})",)
    return ()


def _cycles(halves: list[HalfCycle]) -> tuple[list[Cycle], HalfCycle | None]:
    """Cycle k: the k-th loading and the unloading after it; an unloading before any loading
    is the leading one."""
    cycles: list[Cycle] = []
    leading = None
    for i, half in enumerate(halves):
        if half.direction == UNLOADING and not cycles and i == 0:
            leading = half
        elif half.direction == LOADING:
            nxt = halves[i + 1] if i + 1 < len(halves) else None
            unloading = nxt if nxt is not None and nxt.direction == UNLOADING else None
            cycles.append(Cycle(half.cycle, half, unloading))
    return cycles, leading


def _assemble(run: Samples, x: np.ndarray, f: np.ndarray, sc: _Scale, halves: list[HalfCycle],
              turning: np.ndarray, holds: list[tuple[int, int]], notes: tuple[str, ...]) -> Segmentation:
    cycles, leading_unloading = _cycles(halves)
    if not cycles and leading_unloading is None:
        raise FoamlabError("no half-cycle found in the displacement")
    in_stroke = np.zeros(len(x), dtype=bool)
    in_stroke[halves[0].start:halves[-1].stop] = True
    contact = _contact(x, f, sc.window, in_stroke)
    linear = None
    if cycles:
        linear = _linear_region(x, f, cycles[0].loading, contact, sc.window,
                                motion_tolerance=max(5 * sc.noise, 1e-3 * sc.stroke))
    return Segmentation(
        run=run,
        turning_points=turning,
        cycles=cycles,
        contact_lost=contact.lost,
        first_cycle_linear_region=linear,
        holds=holds,
        leading_unloading=leading_unloading,
        stroke_mm=sc.stroke,
        hysteresis_mm=sc.hysteresis,
        contact_zero_N=contact.zero,
        contact_threshold_N=contact.threshold,
        first_contact=contact.first,
        notes=notes,
        labelled=getattr(run, "step", None) is not None,
    )


# --------------------------------------------------------------------------- helpers


def _noise_sigma(a: np.ndarray) -> float:
    """White-noise sigma from second differences (insensitive to ramps), MAD-based."""
    if len(a) < 4:
        return 0.0
    d2 = np.diff(a, 2)
    return float(np.median(np.abs(d2 - np.median(d2))) / 0.6745 / np.sqrt(6.0))


def _odd(w: int, n: int) -> int:
    w = int(min(w, n if n % 2 else n - 1))
    w = w if w % 2 else w - 1
    return max(w, 3) if n >= 3 else 1


def _smooth(a: np.ndarray, window: int, deriv: int = 0) -> np.ndarray:
    if window < 3 or len(a) < window:
        return np.gradient(a) if deriv else a.copy()
    return signal.savgol_filter(a, window, 2, deriv=deriv, mode="interp")


def _zigzag(x: np.ndarray, h: float) -> list[tuple[int, bool]]:
    """(index, is_maximum) of reversals larger than ``h`` (hysteresis turning points).

    Hand-written because scipy.signal.find_peaks neither alternates maxima and
    minima nor knows about the run's ends; this is one pass over plain floats.
    """
    values = x.tolist()
    pivots: list[tuple[int, bool]] = []
    direction = 0
    hi_i = lo_i = 0
    hi = lo = values[0]
    for i, v in enumerate(values):
        if direction >= 0:
            if v > hi:
                hi, hi_i = v, i
            if direction == 1 and v < hi - h:
                pivots.append((hi_i, True))
                direction, lo, lo_i = -1, v, i
                continue
        if direction <= 0:
            if v < lo:
                lo, lo_i = v, i
            if direction == -1 and v > lo + h:
                pivots.append((lo_i, False))
                direction, hi, hi_i = 1, v, i
                continue
        if direction == 0:
            if v - lo > h:
                direction, hi, hi_i = 1, v, i
            elif hi - v > h:
                direction, lo, lo_i = -1, v, i
    return pivots


def _drop_short(mask: np.ndarray, min_len: int, value: bool) -> np.ndarray:
    """Flip interior runs of ``value`` shorter than ``min_len`` samples."""
    out = mask.copy()
    runs = _true_spans(mask if value else ~mask)
    for a, b in runs:
        interior = a > 0 and b < len(mask)
        if b - a < min_len and (interior or value):
            out[a:b] = not value
    return out


def _true_spans(mask: np.ndarray) -> list[tuple[int, int]]:
    if not len(mask):
        return []
    padded = np.concatenate(([False], mask.astype(bool), [False]))
    changes = np.flatnonzero(padded[1:] != padded[:-1])
    return [(int(a), int(b)) for a, b in zip(changes[0::2], changes[1::2])]


class _Contact(NamedTuple):
    lost: np.ndarray
    zero: float
    threshold: float
    first: int | None


def _contact(x: np.ndarray, f: np.ndarray, window: int, in_stroke: np.ndarray) -> _Contact:
    fs = _smooth(f, window)
    lowest = np.percentile(fs, 2.0)
    top = np.percentile(fs, 99.5)
    span = max(top - lowest, 1e-12)
    band = 0.01 * span
    at_floor = fs <= lowest + band
    floor_samples = f[at_floor]
    floor = float(np.median(floor_samples))
    floor_noise = float(1.4826 * np.median(np.abs(floor_samples - floor)))
    noise = max(floor_noise, _noise_sigma(f), 2e-4 * span)
    # The lowest forces are the unloaded load-cell reading only if they are near
    # zero AND flat: off the specimen the force does not follow the plate. At the
    # bottom of a run that keeps its preload the force still follows the
    # specimen's stiffness, and there is no contact loss at all.
    x_floor = x[at_floor]
    change = 0.0
    if np.ptp(x_floor) > 0:
        dx = x_floor - x_floor.mean()
        with np.errstate(all="ignore"):
            slope = float(np.dot(dx, floor_samples - floor_samples.mean()) / np.dot(dx, dx))
        change = abs(slope) * float(np.ptp(x_floor)) if np.isfinite(slope) else np.inf
    flat = change <= 0.5 * band
    near_zero = abs(floor) <= max(CONTACT_NOISE_MULTIPLE * noise, 0.02 * span)
    if near_zero and flat:
        zero = floor
    else:
        # no unloaded reading in this run: the floor's spread is the specimen, not noise
        zero, noise = 0.0, max(_noise_sigma(f), 2e-4 * span)
    threshold = zero + CONTACT_NOISE_MULTIPLE * noise
    in_contact = fs > threshold
    first = int(np.argmax(in_contact)) if in_contact.any() else None
    lost = (fs <= threshold) & in_stroke
    if first is not None:
        lost[:first] = False  # not in contact yet: approach, not a loss of contact
    else:
        lost[:] = False
    # Drop flicker at the edges of a span: gaps and spans shorter than half the
    # smoothing window are noise crossing the threshold, not contact changes.
    lost = _drop_short(lost, window // 2, value=False)
    lost = _drop_short(lost, window // 2, value=True)
    return _Contact(lost, float(zero), float(threshold), first)


def _linear_region(x: np.ndarray, f: np.ndarray, loading: HalfCycle,
                   contact: _Contact, window: int,
                   motion_tolerance: float) -> tuple[int, int] | None:
    sl = loading.slice
    # Start where the plate is in contact AND has begun to move: a preload start
    # settles the force for a few samples while the plate stands still.
    moved = np.abs(x[sl] - x[loading.start]) > motion_tolerance
    in_contact = ~contact.lost[sl] & (f[sl] > contact.threshold)
    usable = moved & in_contact
    if not usable.any():
        return None
    start = loading.start + max(0, int(np.argmax(usable)) - 1)
    stop = loading.stop
    m = stop - start
    if m < 10:
        return None
    xx = x[start:stop] - x[start]
    ff = f[start:stop] - f[start]
    # Force noise as seen by a line fit: what a local quadratic (smoothing window)
    # cannot follow. Second differences underestimate it when the noise is
    # correlated over a few samples, as load-cell noise often is.
    noise = float(np.sqrt(np.mean((ff - _smooth(ff, _odd(window, m))) ** 2)))
    # Prefix sums give the least-squares line of every prefix in one pass.
    k = np.arange(1, m + 1, dtype=float)
    sx, sf = np.cumsum(xx), np.cumsum(ff)
    sxx, sff, sxf = np.cumsum(xx * xx), np.cumsum(ff * ff), np.cumsum(xx * ff)
    with np.errstate(invalid="ignore", divide="ignore"):
        vxx = sxx - sx * sx / k
        vff = sff - sf * sf / k
        vxf = sxf - sx * sf / k
        sse = np.clip(vff - np.where(vxx > 0, vxf * vxf / vxx, 0.0), 0.0, None)
        rms = np.sqrt(sse / k)
    frange = np.maximum.accumulate(ff) - np.minimum.accumulate(ff)
    allowed = np.maximum(LINEAR_NOISE_MULTIPLE * noise, LINEAR_RELATIVE_RMS * frange)
    ok = rms <= allowed
    # Judge only stretches longer than the smoothing window: a few samples say
    # nothing about linearity.
    min_len = max(10, min(window, m // 4))
    ok[:min_len] = True
    bad = np.flatnonzero(~ok)
    end = int(bad[0]) if len(bad) else m
    return (start, start + end)
