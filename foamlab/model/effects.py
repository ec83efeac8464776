"""What the base model leaves out: the diagnosis catalogue's effects, defined once.

Each effect is a small class with a parameter vector (names, units, bounds), a
docstring on its physics, and two forms that agree (tests/test_effects.py):

- batch:  ``EffectChain([...]).measured_force(model, t, x)`` (or ``effect.measured_force``)
  maps a displacement history to the force a load cell would read, vectorised and
  smooth in the effect's parameters, so diagnosis can fit an extended model with
  scipy.optimize.least_squares;
- online: ``EffectChain([...]).online()`` gives the stepper the simulator uses inside
  SimulatedMachine, one physics step at a time.

Where an effect acts (the order of the chain):
  1. input     machine_compliance      the specimen sees the crosshead minus the frame's deflection
  2. specimen  memory_lag (the damping and residual components through a response in time),
               cycle_softening, damping_cycle_change, rate_dependence (scale model components),
               direction_friction (adds a force while in contact)
  3. contact   the plate cannot pull: max(total, 0), and 0 where the specimen is not compressed
  4. sensor    channel_lag (force channel late), force_zero_drift (load-cell zero drifts)

Conventions: x is the crosshead compression in mm (positive into the specimen), t in
s, velocity in mm/s (positive while compressing), forces in N (compression positive).
``EFFECTS`` maps each catalogue name to its class; ``make_effects({"name": magnitude})``
builds a chain from the simulator's ``--effect NAME=MAG`` options.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Any, Callable, ClassVar, Iterable, Mapping

import numpy as np
from scipy.optimize import brentq
from scipy.signal import lfilter, savgol_filter

from foamlab.model.history import HistoryLabels
from foamlab.model.params import ModelParameters
from foamlab.model.response import ModelResponse, evaluate
from foamlab.model.turns import JUST_AFTER, REFINE, on_grid

ModelFn = Callable[[np.ndarray, np.ndarray, "HistoryLabels | None"], ModelResponse]


@dataclass(frozen=True)
class EffectParameter:
    name: str
    unit: str
    typical: float        # a clearly visible value on the paper's protocol (default magnitude)
    lower: float          # bounds for fitting
    upper: float
    fitted: bool = True   # False: a fixed setting (reference speed, smoothing width)
    doc: str = ""


@dataclass
class Components:
    """Model components plus what the effects need; arrays (batch) or floats (online)."""

    elastic: Any
    damping: Any
    residual: Any
    extra: Any            # forces added by effects (friction, ...)
    cycle: Any            # 1-based cycle of the model's labels (0 before the first loading)
    velocity: Any         # crosshead velocity, mm/s, positive compressing
    rate: Any = None      # mean crosshead speed since the current cycle started, mm/s
                          # (None: |velocity|; see loading_rate)

    @property
    def total(self):
        return self.elastic + self.damping + self.residual + self.extra


# ----------------------------------------------------------------------------- base class

class Effect:
    """One hidden effect. Construct with the magnitude (first parameter) and/or named values."""

    name: ClassVar[str]
    meaning: ClassVar[str] = ""             # what it is, physically (one line)
    signature: ClassVar[str] = ""           # how it shows in the residuals of the paper's model
    stage: ClassVar[str]                    # "input" | "specimen" | "sensor"
    parameters: ClassVar[tuple[EffectParameter, ...]]

    def __init__(self, magnitude: float | None = None, **values: float) -> None:
        known = {p.name for p in self.parameters}
        unknown = set(values) - known
        if unknown:
            raise ValueError(f"{self.name}: unknown parameter(s) {', '.join(sorted(unknown))} "
                             f"(known: {', '.join(sorted(known))})")
        v = {p.name: float(p.typical) for p in self.parameters}
        if magnitude is not None:
            v[self.parameters[0].name] = float(magnitude)
        for k, val in values.items():
            v[k] = float(val)
        for k, val in v.items():
            if not math.isfinite(val):
                raise ValueError(f"{self.name}: parameter {k} must be a finite number, got {val}")
        self.values: dict[str, float] = v

    def __repr__(self) -> str:
        inner = ", ".join(f"{k}={v:g}" for k, v in self.values.items())
        return f"{type(self).__name__}({inner})"

    @property
    def magnitude(self) -> float:
        return self.values[self.parameters[0].name]

    # fitting interface: only the fitted parameters form the vector
    @classmethod
    def fitted_parameters(cls) -> tuple[EffectParameter, ...]:
        return tuple(p for p in cls.parameters if p.fitted)

    def vector(self) -> np.ndarray:
        return np.array([self.values[p.name] for p in self.fitted_parameters()])

    def with_vector(self, v) -> "Effect":
        new = type(self)(**self.values)
        for p, val in zip(self.fitted_parameters(), np.atleast_1d(v)):
            new.values[p.name] = float(val)
        return new

    @classmethod
    def bounds(cls) -> tuple[np.ndarray, np.ndarray]:
        ps = cls.fitted_parameters()
        return np.array([p.lower for p in ps]), np.array([p.upper for p in ps])

    # stage hooks (identity by default); the same code serves arrays and floats
    def modify(self, c: Components) -> Components:
        return c

    def sensor_batch(self, t: np.ndarray, force: np.ndarray) -> np.ndarray:
        return force

    def sensor_online(self) -> "SensorStepper | None":
        return None

    def memory_batch(self, t: np.ndarray, damping: np.ndarray, residual: np.ndarray):
        """Specimen stage, before ``modify``: the model's memory components (damping,
        residual) through a response in time; arrays (n,) or (n, k), time along axis 0."""
        return damping, residual

    def memory_online(self) -> "MemoryStepper | None":
        return None

    # convenience
    def measured_force(self, model, t, x, **kw) -> np.ndarray:
        return EffectChain([self]).measured_force(model, t, x, **kw)


class MemoryStepper:
    """Online form of an effect on the memory components (memory_batch)."""

    def step(self, t: float, damping: float, residual: float) -> tuple[float, float]:  # pragma: no cover
        raise NotImplementedError


class SensorStepper:
    """Online form of a sensor-stage effect."""

    def step(self, t: float, force: float) -> float:  # pragma: no cover - interface
        raise NotImplementedError


# ----------------------------------------------------------------------------- the catalogue

class CycleSoftening(Effect):
    """Elastic skeleton softens from cycle to cycle (Mullins-like damage of cell struts).

    E_c(x) = E(x) (1 - s)^(c - c0 + 1) for cycle c >= c0 (the setting from_cycle, 2 by
    default): the cycles before c0 are the base model, each later cycle loses the fraction
    s of the previous cycle's elastic force. The base model's elastic part is
    cycle-independent (paper, assumption c), so this shows up as later cycles lying below
    the model on loading and unloading alike, growing with x. A later onset (from_cycle 3)
    is a specimen damaged during the test: what the live prediction must catch.
    """

    name = "cycle_softening"
    meaning = ("the elastic force softens from cycle to cycle (Mullins-type stress softening): "
               "the model's assumption (c) of one elastic curve for every cycle does not hold")
    signature = "later cycles lie below the model on loading and unloading, more at large displacement"
    stage = "specimen"
    parameters = (EffectParameter("s", "1/cycle", 0.05, -0.5, 0.9,
                                  doc="fraction of the elastic force lost per cycle"),
                  EffectParameter("from_cycle", "cycle", 2.0, 2.0, 1e6, fitted=False,
                                  doc="the first cycle that is softer"))

    def modify(self, c: Components) -> Components:
        n = np.maximum(c.cycle - self.values["from_cycle"] + 1, 0)
        return replace(c, elastic=c.elastic * (1.0 - self.values["s"]) ** n)


class DampingCycleChange(Effect):
    """Damping force changes with the cycle (air paths open or clog as cells break).

    V_D,c = V_D (1 + d (c - 1)): the paper assumes one damping force for every
    loading half-cycle (assumption b); d != 0 makes later loadings differ from the
    first by a rate-dependent (loading-only) amount.
    """

    name = "damping_cycle_change"
    meaning = ("the damping force differs between loading half-cycles: the model's assumption (b) "
               "of one damping force for every loading does not hold")
    signature = "later loadings differ from the model by a loading-only, rate-like amount"
    stage = "specimen"
    parameters = (EffectParameter("d", "1/cycle", 0.2, -0.45, 2.0,
                                  doc="relative change of the damping force per cycle"),)

    def modify(self, c: Components) -> Components:
        n = np.maximum(c.cycle, 1) - 1
        return replace(c, damping=c.damping * (1.0 + self.values["d"] * n))


class RateDependence(Effect):
    """Damping depends on the crosshead rate beyond what the model's kernel gives.

    V_D -> V_D (v / v_ref)^m, v = the loading rate: the mean crosshead speed since the
    cycle started, (x - x_start) / (t - t_start) (a pause lowers it slowly instead of
    switching the damping off). At the reference speed v_ref (the speed the base model
    was identified at) the factor is 1, so one run at v_ref cannot show it, and one run
    at any single speed cannot tell m from the damping amplitudes a_i: m needs runs at
    two or more speeds (their damping forces differ by (v1/v2)^m beyond the base
    model's own rate dependence).
    """

    name = "rate_dependence"
    meaning = ("the damping depends on the crosshead rate beyond the model's kernel: a model "
               "identified at one speed mispredicts another")
    signature = "the runs at other speeds miss the model by a loading-only amount that grows with the speed ratio"
    stage = "specimen"
    parameters = (
        EffectParameter("m", "-", 0.5, -1.0, 2.0, doc="exponent of the extra rate dependence"),
        EffectParameter("v_ref_mm_min", "mm/min", 23.6, 1e-3, 1e4, fitted=False,
                        doc="speed at which the base model holds (its identification run)"),
    )

    def modify(self, c: Components) -> Components:
        v_ref = self.values["v_ref_mm_min"] / 60.0
        # floor |v| smoothly so a pause does not send the factor to 0 or infinity
        rate = np.abs(c.velocity) if c.rate is None else c.rate
        speed = np.sqrt(np.square(rate) + (1e-3 * v_ref) ** 2)
        return replace(c, damping=c.damping * (speed / v_ref) ** self.values["m"])


class DirectionFriction(Effect):
    """A force that opposes the motion, the same size both ways (platen/guide friction).

    F += f tanh(v / v_s) while the plate is in contact: it raises the loading branch
    and lowers the unloading branch by f each, i.e. extra hysteresis of constant width
    2f, independent of x and of the rate (unlike damping). tanh with a small v_s keeps
    it smooth through the turning points.
    """

    name = "direction_friction"
    meaning = "a constant force opposes the motion (platen or guide friction)"
    signature = "loading above and unloading below the model by the same force, independent of x"
    stage = "specimen"
    parameters = (
        EffectParameter("f_N", "N", 2.0, -50.0, 50.0, doc="friction force"),
        EffectParameter("v_smooth_mm_s", "mm/s", 0.01, 1e-6, 10.0, fitted=False,
                        doc="speed over which the friction reverses (tanh width)"),
    )

    def modify(self, c: Components) -> Components:
        f = self.values["f_N"] * np.tanh(c.velocity / self.values["v_smooth_mm_s"])
        return replace(c, extra=c.extra + f)


class MachineCompliance(Effect):
    """The frame and load cell deflect under load: the specimen sees less than the crosshead.

    x_specimen = x_crosshead - C G, G = the force seen by the frame. Stiff foam regions
    (densification) then look softer than the model and the loading peak is rounded. Within
    each crosshead half-cycle the specimen displacement is kept monotone: the frame springing
    back when the model's damping vanishes at a turning point does not re-load the foam.

    tau_frame_s = 0: a frame that answers at once, G the force at the same instant - a real
    frame, and what diagnosis fits (causes.MachineCompliance; docs/analysis.md, "The frame at
    once"). Its loop is implicit (the force depends on x_specimen, which depends on the force):
    the batch form from the model alone solves it (_loop_fixed_point), the simulator per step on
    copies of its state (SimSpecimen; ~20 x the cost of a step). Just after a turn it has no
    solution (the force drops as the specimen turns, which un-turns it): there the two keep
    different values for a few samples (<= 2 % of the force at the upper C; tests/test_effects.py).
    tau_frame_s > 0 (the simulator's 0.2 s by default, from --effect): G is the previous
    sample's force through a first-order response of that time constant. The model's
    fractional residual reacts to a one-step change of x like a dashpot (~100 N/mm at 50 ms
    steps, more at shorter ones); a loop closed on the previous force oscillates at the
    simulator's small steps, while through 0.2 s it settles within a few steps for C up to the
    upper bound (0.01 mm/N, a 100 N/mm frame: softer than any real one) at any step size.
    Batch forms: given the measured force, ``specimen_displacement`` (one pass, linear in F:
    what diagnosis fits; at once, with the measured force smoothed as the displacement's path
    is); from the model alone, the loop's fixed point. With tau_frame_s > 0 both are the
    simulator's arithmetic, sample for sample.
    """

    name = "machine_compliance"
    meaning = "the frame and load train deflect: part of the measured displacement is the machine's"
    signature = "the stiff (high-force) part of the curve is softer than the model and the peak is rounded"
    stage = "input"
    parameters = (
        EffectParameter("c_mm_per_N", "mm/N", 0.005, 0.0, 0.01, doc="frame + load-cell compliance"),
        EffectParameter("tau_frame_s", "s", 0.2, 0.0, 10.0, fitted=False,
                        doc="response time of the frame deflection to the force (0: at once)"),
    )


class ChannelLag(Effect):
    """The force channel is late relative to displacement (filters, sample skew).

    F_measured(t) = F(t - tau). On a hysteresis loop it looks like extra hysteresis
    that grows with the slope dF/dt, so it is largest where the foam is stiff, and
    it is the same on loading and unloading (unlike damping, loading only).
    Batch: linear interpolation (any tau, also negative = force early); online: a
    delay line (tau >= 0).
    """

    name = "channel_lag"
    meaning = "force and displacement are sampled out of step (the force channel is late or early)"
    signature = "extra hysteresis on loading and unloading alike, growing with the force's slope"
    stage = "sensor"
    parameters = (EffectParameter("tau_s", "s", 0.5, -5.0, 5.0, doc="delay of the force channel"),)

    def sensor_batch(self, t, force):
        return np.interp(np.asarray(t) - self.values["tau_s"], t, force)

    def sensor_online(self) -> SensorStepper:
        return _DelayLine(self.values["tau_s"])


class ForceZeroDrift(Effect):
    """The load cell's zero drifts linearly in time (temperature, creep of the bridge).

    F_measured = F + r (t - t_0), t_0 = the first sample (the cell is zeroed just
    before the run starts). Seen where the true force is zero: the no-contact
    regions read -r t or +r t instead of 0, and the curves of later cycles shift.
    """

    name = "force_zero_drift"
    meaning = "the load cell's zero drifts during the run (temperature, bridge creep)"
    signature = "an error growing linearly in time, seen also where the plate is off the specimen"
    stage = "sensor"
    parameters = (EffectParameter("rate_N_per_s", "N/s", 0.005, -1.0, 1.0, doc="zero drift rate"),)

    def sensor_batch(self, t, force):
        t = np.asarray(t, float)
        return force + self.values["rate_N_per_s"] * (t - t[0])

    def sensor_online(self) -> SensorStepper:
        return _Drift(self.values["rate_N_per_s"])


class _DelayLine(SensorStepper):
    """F(t - tau) by linear interpolation in the recorded history (same rule as np.interp)."""

    def __init__(self, tau: float):
        if tau < 0:
            raise ValueError("channel_lag: the simulator can only delay the force (tau_s >= 0)")
        self.tau = tau
        self._t: list[float] = []
        self._f: list[float] = []
        self._start = 0

    def step(self, t: float, force: float) -> float:
        self._t.append(t)
        self._f.append(force)
        target = t - self.tau
        ts, fs = self._t, self._f
        # drop history older than needed (keep one sample before the target)
        while self._start + 1 < len(ts) and ts[self._start + 1] <= target:
            self._start += 1
        if self._start > 4096:
            del ts[:self._start], fs[:self._start]
            self._start = 0
        i = self._start
        if target <= ts[i]:          # before the first sample: hold it (as np.interp)
            return fs[i]
        if i + 1 >= len(ts):
            return fs[-1]
        w = (target - ts[i]) / (ts[i + 1] - ts[i])
        return fs[i] + w * (fs[i + 1] - fs[i])


class _Drift(SensorStepper):
    def __init__(self, rate: float):
        self.rate = rate
        self._t0: float | None = None

    def step(self, t: float, force: float) -> float:
        if self._t0 is None:
            self._t0 = t
        return force + self.rate * (t - self._t0)


class MemoryLag(Effect):
    """The specimen's memory forces follow the loading history with a relaxation time.

    The paper's model switches at a turning point from the loading branch to the unloading
    branch at once: its damping (loading only, Eqs. 8-9) is switched off and the unloading's
    residual memory (Eqs. 10-11), whose value there is the fractional derivative of the whole
    loading, is switched on - a jump of several newtons in the model's force. A real specimen
    releases that force over a time (the air in the cells, the polymer's fastest relaxation):
    the damping and residual components D, R of the model act through a first-order
    response of time constant tau, D' = (D - D_lag) / tau (and R alike); the elastic force
    is instantaneous. On a smooth stretch that is a delay of the memory forces by ~tau
    (small: they change slowly); at a turning point it turns the model's jump into a release
    over a few tau. Unlike channel_lag (the whole measured force late, a sensor filter),
    the elastic force is not delayed.
    Batch: the exact response for a component linear between the samples and finer times after
    each turn (model.turns: the jump is not a line between samples); online: between physics steps.
    """

    name = "memory_lag"
    meaning = ("the specimen's memory forces (damping and residual) follow the loading history with "
               "a relaxation time: at a turning point, where the paper's model passes from the loading "
               "to the unloading branch at once, the specimen releases its force over that time")
    signature = ("after each reversal the measured force falls over a few tenths of a second where the "
                 "model drops at once; the elastic force is not delayed (unlike channel_lag)")
    stage = "specimen"
    parameters = (EffectParameter("tau_s", "s", 0.2, 0.0, 5.0,
                                  doc="relaxation time of the damping and residual forces"),)

    def memory_batch(self, t, damping, residual):
        tau = self.values["tau_s"]
        return first_order_response(t, damping, tau), first_order_response(t, residual, tau)

    def memory_online(self) -> MemoryStepper:
        return _MemoryLagStepper(self.values["tau_s"])


class _MemoryLagStepper(MemoryStepper):
    def __init__(self, tau: float):
        self.tau = tau
        self._prev: tuple[float, float, float, float, float] | None = None   # t, u_d, u_r, y_d, y_r

    def step(self, t: float, damping: float, residual: float) -> tuple[float, float]:
        if self._prev is None or self.tau <= 0:
            y = (damping, residual)
        else:
            t0, ud, ur, yd, yr = self._prev
            if t > t0:
                a, b = _first_order_weights(t - t0, self.tau)
                y = (a * yd + (1 - b) * damping + (b - a) * ud, a * yr + (1 - b) * residual + (b - a) * ur)
            else:
                y = (yd, yr)
        self._prev = (t, damping, residual, y[0], y[1])
        return y


def _first_order_weights(dt, tau):
    """y_i = a y_{i-1} + (1 - b) u_i + (b - a) u_{i-1}: the exact response of y' = (u - y)/tau
    over a step dt for an input linear across it (a = exp(-dt/tau), b = tau/dt (1 - a))."""
    a = np.exp(-np.asarray(dt, float) / tau)
    b = -np.expm1(-np.asarray(dt, float) / tau) * tau / np.asarray(dt, float)
    return a, b


#: Stretches of the exponential sums in first_order_response span at most this many tau.
_CHUNK_TAUS = 30.0


def first_order_response(t, u, tau: float) -> np.ndarray:
    """y' = (u - y) / tau from y = u at t[0], u linear between samples (exact; any sampling).

    u: (n,) or (n, k), time along axis 0. The recursion y_i = a_i y_{i-1} + g_i is summed as
    y_i = sum_j exp(-(t_i - t_j)/tau) g_j, in stretches of at most _CHUNK_TAUS tau (so the
    exponentials neither overflow nor lose precision), vectorised because a fit calls it
    hundreds of times (a plain loop's cost: docs/model.md#measured-costs-behind-implementation-choices).
    Every stretch is summed at once (_Stretches); only the value carried from one stretch into the
    next is a loop, one step per stretch. Where the steps come in few runs of one length (a
    sampling grid, a decimated one) the recursion itself is filtered instead (_filtered)."""
    u = np.asarray(u, float)
    t = np.asarray(t, float)
    if tau <= 0 or len(t) < 2:
        return u.copy()
    dt = np.diff(t)
    step = dt > 0
    safe = np.where(step, dt, 1.0)
    a, b = _first_order_weights(safe, tau)
    a, b = np.where(step, a, 1.0), np.where(step, b, 1.0)       # no time: state kept
    ex = (lambda v: v[:, None]) if u.ndim > 1 else (lambda v: v)
    g = ex(1 - b) * u[1:] + ex(b - a) * u[:-1]
    y = np.empty_like(u)
    y[0] = u[0]
    n = len(t)
    # where the step changes (beyond the rounding of time stamps like k / 10 s: a decay off by 1e-9 dt / tau)
    runs = np.flatnonzero(np.abs(np.diff(safe)) > _SAME_STEP * safe[1:]) + 1
    if len(runs) <= max(_FEW_RUNS, n // _FEW_RUNS):
        return _filtered(a, g, y, np.concatenate([[0], runs, [len(dt)]]))
    ends = np.searchsorted(t, t[:-1] + _CHUNK_TAUS * tau, side="right").tolist()   # of a stretch from each sample
    longer = np.flatnonzero(np.array(ends) > np.arange(2, n + 1)) + 1    # stretches from here span several steps
    segments, i = [], 1
    while i < n:
        j = ends[i - 1]
        if j <= i + 1:                                # steps each longer than a stretch, up to the next stretch
            at = int(np.searchsorted(longer, i))
            j = int(longer[at]) if at < len(longer) else n
            segments.append((False, i, j))
        else:
            j = min(j, n)
            segments.append((True, i, j))
        i = j
    stretches = _Stretches(t, g, tau, [(i, j) for summed, i, j in segments if summed])
    # the carried value in Python floats (the same IEEE arithmetic, without numpy's per-call cost)
    acc_last, decay_last = np.asarray(stretches.acc_last).tolist(), np.asarray(stretches.decay_last).tolist()
    carry = ((lambda acc, prev, d: [(x + p) * d for x, p in zip(acc, prev)]) if u.ndim > 1
             else (lambda acc, prev, d: (acc + prev) * d))
    start, c = [], 0
    prev = y[0].tolist()
    for summed, i, j in segments:
        if summed:
            start.append(prev)
            prev = carry(acc_last[c], prev, decay_last[c])
            c += 1
        else:
            y[i:j] = _single_steps(ex(a[i - 1:j - 1]), g[i - 1:j - 1], np.asarray(prev))
            prev = y[j - 1].tolist()
    stretches.fill(y, start)
    return y


#: At most this many runs of equal steps (or n / this), the recursion is filtered run by run.
_FEW_RUNS = 64
#: Steps within this share of each other are one length.
_SAME_STEP = 1e-9


def _filtered(a: np.ndarray, g: np.ndarray, y: np.ndarray, bounds: np.ndarray) -> np.ndarray:
    """first_order_response's recursion y_i = a_i y_{i-1} + g_i where its steps come in few runs of
    one length (a uniform or decimated grid): one IIR filter call a run, every column at once
    (scipy.signal.lfilter; 2-9 x faster than the stretches' sums, equal to 4e-15 relative)."""
    prev = y[0]
    for i, j in zip(bounds[:-1].tolist(), bounds[1:].tolist()):
        y[i + 1:j + 1], _ = lfilter([1.0], [1.0, -a[i]], g[i:j], axis=0, zi=np.asarray(a[i] * prev)[None, ...])
        prev = y[j]
    return y


class _Stretches:
    """The stretches of first_order_response summed at once: padded to the longest, each row
    y = (cumsum(g exp(rel)) + y_start) exp(-rel), rel = (t - t_start) / tau in (0, _CHUNK_TAUS];
    a row's cumsum adds its terms in order, as one stretch's own cumsum does."""

    def __init__(self, t, g, tau: float, spans: list[tuple[int, int]]):
        self.columns = g.ndim > 1          # g (n, k): a weight per row applies to every column
        if not spans:
            self.acc_last = self.decay_last = []
            return
        first, stop = np.array(spans).T
        width = int((stop - first).max())
        idx = first[:, None] + np.arange(width)[None, :]
        self.valid = idx < stop[:, None]
        self.idx = np.where(self.valid, idx, first[:, None])
        rel = (t[self.idx] - t[first - 1][:, None]) / tau
        terms = g[self.idx - 1] * self._per_row(np.exp(rel))
        terms[~self.valid] = 0.0
        self.acc = np.cumsum(terms, axis=1)
        self.decay = np.exp(-rel)
        last = stop - first - 1
        rows = np.arange(len(first))
        self.acc_last, self.decay_last = self.acc[rows, last], self.decay[rows, last]

    def _per_row(self, v):
        return v[:, :, None] if self.columns else v

    def fill(self, y: np.ndarray, start: list) -> None:
        if not start:
            return
        first = np.asarray(start)[:, None]
        values = (self.acc + first) * self._per_row(self.decay)
        y[self.idx[self.valid]] = values[self.valid]


def _single_steps(a: np.ndarray, g: np.ndarray, y0: np.ndarray) -> np.ndarray:
    """y_i = a_i y_{i-1} + g_i from y0, for steps each longer than _CHUNK_TAUS tau (a_i < e^-30).

    Solved as the fixed point of the whole stretch updated at once: once an update changes no
    bit, every y_i is a_i y_{i-1} + g_i rounded as the step-by-step loop rounds it (by induction
    from y0, the solution is unique), in two or three updates where that loop took one Python
    step per sample (12 ms a fit's column block at 16 Hz, tau < 2 ms)."""
    y = g.copy()
    for _ in range(len(g) + 1):                   # exact after len(g) updates in any case
        prev = np.concatenate([np.asarray(y0)[None], y[:-1]])
        new = a * prev + g
        if np.array_equal(new, y, equal_nan=True):
            break
        y = new
    return y


EFFECTS: dict[str, type[Effect]] = {
    cls.name: cls for cls in (CycleSoftening, DampingCycleChange, ChannelLag, ForceZeroDrift,
                              MachineCompliance, DirectionFriction, RateDependence, MemoryLag)
}


# ----------------------------------------------------------------------------- helpers

def motion_direction(x: np.ndarray) -> np.ndarray:
    """+1 / -1 from the last change of x (a pause keeps the previous direction; 0 before any)."""
    x = np.asarray(x, float)
    d = np.zeros(len(x), dtype=int)
    if len(x) > 1:
        d[1:] = np.sign(np.diff(x)).astype(int)
    idx = np.where(d != 0, np.arange(len(d)), 0)
    np.maximum.accumulate(idx, out=idx)
    return d[idx]


def estimate_velocity(t, x, labels: HistoryLabels | None = None, window_s: float = 1.0) -> np.ndarray:
    """Crosshead velocity (mm/s) from sampled displacement, one half-cycle at a time.

    The history is split at its turning points (the labels' starts and peaks when
    given, else where the direction of motion changes), so the estimate does not smear
    a reversal; inside each piece a local least-squares slope over ~window_s
    (Savitzky-Golay, order 1) is exact on a constant-speed ramp and averages out the
    1 um resolution of a crosshead encoder. Irregular sampling: central differences.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    n = len(t)
    if n < 2:
        return np.zeros(n)
    if labels is not None:
        cuts = sorted({int(i) for i in list(labels.starts) + [p + 1 for p in labels.peaks] if 0 < i < n})
    else:
        cuts = list(np.flatnonzero(np.diff(motion_direction(x)) != 0) + 1)
    v = np.empty(n)
    dt = np.diff(t)
    h = float(np.median(dt))
    uniform = h > 0 and bool(np.all(np.abs(dt - h) <= 0.05 * h))
    for a, b in zip([0] + cuts, cuts + [n]):
        seg_t, seg_x = t[a:b], x[a:b]
        m = b - a
        window = min(int(round(window_s / h)) | 1, m if m % 2 else m - 1) if uniform else 0
        if window >= 3:
            v[a:b] = savgol_filter(seg_x, window, 1, deriv=1, delta=h, mode="interp")
        elif m >= 2:
            v[a:b] = np.gradient(seg_x, seg_t)
        else:   # a single sample between two cuts: the motion that brought it there
            v[a:b] = (x[a] - x[a - 1]) / (t[a] - t[a - 1]) if a > 0 else 0.0
    return v


def loading_rate(t, x, starts) -> np.ndarray:
    """Mean crosshead speed since the start of the current cycle (|velocity| before the first);
    at a start sample itself 0 (the damping is zero there)."""
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    rate = np.zeros(len(t))
    bounds = list(starts) + [len(t)]
    for s, e in zip(bounds[:-1], bounds[1:]):
        dt = t[s + 1:e] - t[s]
        rate[s + 1:e] = np.abs(x[s + 1:e] - x[s]) / np.where(dt > 0, dt, np.inf)
    if bounds[0] > 1:
        rate[1:bounds[0]] = np.abs(np.diff(x[:bounds[0]]) / np.diff(t[:bounds[0]]))
    return rate


def _monotone_in_runs(x_s: np.ndarray, direction: np.ndarray, x0: float = 0.0) -> np.ndarray:
    """Keep x_s non-decreasing while the crosshead loads and non-increasing while it unloads,
    continuous across the runs (the same rule as the online stepper)."""
    out = np.empty_like(x_s)
    prev = x0
    n = len(x_s)
    if n == 0:
        return out
    change = np.flatnonzero(np.diff(direction)) + 1
    bounds = np.concatenate([[0], change, [n]])
    for a, b in zip(bounds[:-1], bounds[1:]):
        seg = x_s[a:b]
        d = direction[a]
        if d > 0:
            seg = np.maximum.accumulate(np.concatenate([[prev], seg]))[1:]
        elif d < 0:
            seg = np.minimum.accumulate(np.concatenate([[prev], seg]))[1:]
        out[a:b] = seg
        prev = seg[-1]
    return out


def frame_force(t, force, tau_s: float) -> np.ndarray:
    """Force the frame deflects under: at once (tau_s = 0) the force itself; else the previous
    sample's force through a first-order response of time constant tau_s (exact for a force
    held over each step), 0 at t[0]."""
    if tau_s <= 0:
        return np.array(force, dtype=float)
    tl, fl = np.asarray(t, float).tolist(), np.asarray(force, float).tolist()
    out = [0.0] * len(tl)
    g = 0.0
    for i in range(1, len(tl)):    # a plain loop: the simulator's arithmetic, bit for bit
        g += -math.expm1(-(tl[i] - tl[i - 1]) / tau_s) * (fl[i - 1] - g)
        out[i] = g
    return np.asarray(out)


def specimen_displacement(x, force, compliance_mm_per_N: float, t=None,
                          tau_frame_s: float | None = None, *, frame: np.ndarray | None = None) -> np.ndarray:
    """machine_compliance's input stage: the compression the specimen sees for crosshead x.

    x - C frame_force(t, force, tau_frame_s), kept monotone within each crosshead
    half-cycle (see MachineCompliance); force is the measured (or contact) force on the
    same samples t (required: the frame response is in time). ``frame``: that
    frame_force already computed (diagnosis reuses it for every trial compliance).
    """
    x = np.asarray(x, float)
    if len(x) == 0:
        return x.copy()
    if frame is None:
        if t is None:
            raise ValueError("specimen_displacement needs the sample times t (the frame responds in time)")
        tau = MachineCompliance.parameters[1].typical if tau_frame_s is None else tau_frame_s
        frame = frame_force(t, force, tau)
    g = np.asarray(frame, float)
    return _monotone_in_runs(x - compliance_mm_per_N * g, motion_direction(x), x0=min(x[0], 0.0))


def _as_model_fn(model) -> ModelFn:
    if isinstance(model, ModelParameters):
        return lambda t, x, labels=None: evaluate(model, t, x, labels)
    if callable(model):
        return model
    raise TypeError("model must be ModelParameters or a callable (t, x, labels) -> ModelResponse")


# ----------------------------------------------------------------------------- the chain

#: A frame at once: the compliance loop's damped iteration (the step toward the loop's own answer)
#: and the share of samples that may stay unsettled (where the force jumps across the loop).
LOOP_DAMPING, LOOP_UNSETTLED_MAX = 0.5, 0.01


def _loop_fixed_point(x: np.ndarray, step, max_iter: int, tol_mm: float, at_once: bool) -> np.ndarray:
    """The specimen displacement the compliance loop settles at: x_s = step(x_s), step the
    specimen displacement for the force at x_s.

    A frame through a response (not at once) deflects under earlier forces only: the plain
    iteration settles, and not settling is an error. A frame at once: a damped iteration first
    (half a step toward the loop's answer). It can have no fixed point at a few samples - where
    the force jumps (first touch, a turn) the loop jumps across the solution - and the iteration
    settles everywhere else; those samples keep its last value (at most LOOP_UNSETTLED_MAX of
    them). Where it does not settle (C times the specimen's one-step stiffness, ~100 N/mm and more
    from the fractional residual, above ~3), Newton-Krylov (scipy): 44-111 loop evaluations on
    tests/test_effects.py's two-cycle trace at the upper C."""
    from scipy.optimize import root

    damping = LOOP_DAMPING if at_once else 1.0
    x_s = x.copy()
    for _ in range(max_iter):
        r = step(x_s) - x_s
        if np.max(np.abs(r), initial=0.0) <= tol_mm:
            return x_s
        x_s = x_s + damping * r
    if at_once and np.mean(np.abs(step(x_s) - x_s) > tol_mm) <= LOOP_UNSETTLED_MAX:
        return x_s
    sol = root(lambda xs: xs - step(xs), step(x), method="krylov",
               options={"fatol": tol_mm, "maxiter": max_iter}) if at_once else None
    if sol is None or not sol.success:
        why = f"; {sol.message}" if sol is not None else ""
        raise RuntimeError(f"machine_compliance: the force loop did not converge in {max_iter} "
                           f"iterations{why} (compliance too large?)")
    return sol.x


@dataclass
class EffectResponse:
    force: np.ndarray           # what the load cell reads (before noise/quantisation)
    contact_force: np.ndarray   # force between plate and specimen (after specimen effects)
    x_specimen: np.ndarray      # compression the specimen actually sees
    base: ModelResponse         # the model evaluated on x_specimen


class EffectChain:
    """Several effects applied in the physical order (input, specimen, contact, sensor)."""

    def __init__(self, effects: Iterable[Effect] = ()) -> None:
        self.effects = list(effects)
        names = [e.name for e in self.effects]
        if len(set(names)) != len(names):
            raise ValueError("each effect can be applied once")
        inputs = [e for e in self.effects if e.stage == "input"]
        self.compliance = inputs[0].values["c_mm_per_N"] if inputs else 0.0
        self.frame_tau_s = inputs[0].values["tau_frame_s"] if inputs else 1.0
        self._specimen = [e for e in self.effects if e.stage == "specimen"]
        self._sensor = sorted((e for e in self.effects if e.stage == "sensor"),
                              key=lambda e: e.name != ChannelLag.name)   # lag, then drift

    def __bool__(self) -> bool:
        return bool(self.effects)

    @property
    def specimen_effects(self) -> list[Effect]:
        """Specimen-stage effects in the order they act (diagnosis pushes model components through them)."""
        return list(self._specimen)

    @property
    def sensor_effects(self) -> list[Effect]:
        """Sensor-stage effects in the order they act (lag before drift)."""
        return list(self._sensor)

    @property
    def has_memory(self) -> bool:
        """Some specimen effect responds in time to the memory components (memory_batch: memory_lag)."""
        return any(type(e).memory_batch is not Effect.memory_batch for e in self._specimen)

    def __repr__(self) -> str:
        return f"EffectChain({self.effects!r})"

    def memory_batch(self, t, damping, residual):
        """The specimen effects' responses in time on the memory components (memory_batch)."""
        for e in self._specimen:
            damping, residual = e.memory_batch(t, damping, residual)
        return damping, residual

    # ---- shared per-sample formulas (arrays or floats)
    def _contact_force(self, elastic, damping, residual, cycle, velocity, rate, x_s):
        c = Components(elastic, damping, residual, 0.0 * elastic, cycle, velocity, rate)
        for e in self._specimen:
            c = e.modify(c)
        # the plate pushes where the specimen's own force is positive: a force the effects add
        # (friction) acts only there, and the total cannot pull
        return np.where((x_s > 0) & (c.total - c.extra > 0), np.maximum(c.total, 0.0), 0.0)

    # ---- batch
    def measured_force(self, model, t, x, *, velocity=None, labels: HistoryLabels | None = None,
                       measured_force=None, max_iter: int = 200, tol_mm: float = 1e-9) -> np.ndarray:
        return self.response(model, t, x, velocity=velocity, labels=labels, measured_force=measured_force,
                             max_iter=max_iter, tol_mm=tol_mm).force

    def response(self, model, t, x, *, velocity=None, labels: HistoryLabels | None = None,
                 measured_force=None, max_iter: int = 200, tol_mm: float = 1e-9) -> EffectResponse:
        """The force a load cell reads for the crosshead history x(t), with these effects.

        model: ModelParameters or a callable (t, x, labels) -> ModelResponse.
        velocity: crosshead velocity in mm/s (default: estimate_velocity(t, x, labels)).
        labels: half-cycle labels of the measured data (default: from the specimen's history).
        measured_force: with machine_compliance, close the loop with this measured force
        (one pass, specimen_displacement) instead of iterating to the fixed point.
        """
        fn = _as_model_fn(model)
        t = np.asarray(t, float)
        x = np.asarray(x, float)
        v = estimate_velocity(t, x, labels) if velocity is None else np.broadcast_to(np.asarray(velocity, float), t.shape)

        def forward(x_s):
            base = fn(t, x_s, labels)
            rate = loading_rate(t, x, base.labels.starts)
            damping, residual = self._memory_stage(fn, t, x_s, base)
            contact = self._contact_force(base.elastic, damping, residual, base.cycle, v, rate, x_s)
            return base, contact

        if self.compliance == 0.0:
            x_s = x
            base, contact = forward(x_s)
        else:
            def specimen_x(force):
                return specimen_displacement(x, force, self.compliance, t, self.frame_tau_s)

            if measured_force is not None:
                x_s = specimen_x(np.asarray(measured_force, float))
                base, contact = forward(x_s)
            else:
                x_s = _loop_fixed_point(x, lambda xs: specimen_x(forward(xs)[1]), max_iter, tol_mm,
                                        at_once=self.frame_tau_s <= 0)
                base, contact = forward(x_s)
        force = contact
        for e in self._sensor:
            force = e.sensor_batch(t, force)
        return EffectResponse(force=force, contact_force=contact, x_specimen=x_s, base=base)

    def _memory_stage(self, fn: ModelFn, t: np.ndarray, x_s: np.ndarray, base: ModelResponse):
        """The specimen effects' responses in time on the memory components, computed along the path
        on a uniform grid REFINE times finer than the samples (each turn at the last grid time not
        after it) and read at the samples: from the samples alone the model's jump at a turn would
        be a line across a sampling step (model.turns). Just after each peak, the grid's next two
        values extrapolated back stand for the other side of the jump (the fit's ExtendedModel
        evaluates the model there: the two within 0.05 N at the samples, 4 Hz, tau 0.2 s)."""
        if not self.has_memory:
            return base.damping, base.residual
        if len(t) < 3:
            return self.memory_batch(t, base.damping, base.residual)
        step = float(np.median(np.diff(t))) / REFINE
        grid, x_grid, labels = on_grid(t, x_s, base.labels, step)
        fine = fn(grid, x_grid, labels)
        turns = np.array(sorted(p for p in labels.peaks if p + 2 < len(grid)), int)   # the jumps: at the peaks
        times = np.insert(grid, turns + 1, grid[turns] + JUST_AFTER * REFINE * step)
        far = lambda u: u[turns + 1] + (u[turns + 1] - u[turns + 2]) * (1 - JUST_AFTER * REFINE)
        back = lambda u: np.insert(u, turns + 1, far(u))
        damping, residual = self.memory_batch(times, back(fine.damping), back(fine.residual))
        keep = np.ones(len(times), bool)
        keep[turns + 1 + np.arange(len(turns))] = False
        return np.interp(t, grid, damping[keep]), np.interp(t, grid, residual[keep])

    # ---- online
    def online(self) -> "OnlineEffects":
        """The stepper SimulatedMachine uses."""
        return OnlineEffects(self)


class OnlineEffects:
    """The chain stepped one sample at a time (SimulatedMachine's physics step).

    Per step the machine calls, in this order:
      x_s = specimen_x(t, x_crosshead)       (compliance, through the frame response)
      comps = SpecimenState.step(t, x_s)
      F_contact = contact_force(t, x_crosshead, x_s, comps, velocity)
      F_sensor = sensor(t, F_contact)
    """

    def __init__(self, chain: EffectChain):
        self.chain = chain
        self._frame = 0.0                 # frame_force, online
        self._sensors = [s for s in (e.sensor_online() for e in chain._sensor) if s is not None]
        self._memory = [m for m in (e.memory_online() for e in chain._specimen) if m is not None]
        self._prev_force = 0.0
        self._prev_t: float | None = None
        self._prev_x: float | None = None
        self._prev_x_s = 0.0
        self._direction = 0
        self._cycle = 0
        self._start: tuple[float, float] = (0.0, 0.0)
        self._last: tuple[float, float] | None = None

    @property
    def frame_at_once(self) -> bool:
        """machine_compliance with tau_frame_s = 0: the caller solves the step's loop and passes
        the force at its solution to specimen_x (simulator.specimen.SimSpecimen)."""
        return bool(self.chain.compliance) and self.chain.frame_tau_s <= 0

    def specimen_x(self, t: float, x: float, force_now: float | None = None) -> float:
        """x_s for crosshead x: x - C G, G the frame's force (at once: force_now, the force at
        this step's x_s; else the previous force through the frame's response)."""
        first = self._prev_x is None
        if not first and x != self._prev_x:
            self._direction = 1 if x > self._prev_x else -1
        self._prev_x = x
        c = self.chain.compliance
        if c == 0.0:
            x_s = x
        else:
            prev = self._prev_x_s if not first else min(x, 0.0)
            if self.frame_at_once:
                if force_now is None:
                    raise ValueError("a frame at once needs the force at this step (force_now)")
                self._frame = force_now
            elif not first:
                self._frame += -math.expm1(-(t - self._prev_t) / self.chain.frame_tau_s) * (
                    self._prev_force - self._frame)
            x_s = x - c * self._frame
            if self._direction > 0:
                x_s = max(prev, x_s)
            elif self._direction < 0:
                x_s = min(prev, x_s)
        self._prev_t, self._prev_x_s = t, x_s
        return x_s

    def contact_force(self, t: float, x: float, x_s: float, comps, velocity: float) -> float:
        """comps: the SpecimenState step (elastic, damping, residual, direction, cycle); x: crosshead."""
        if comps.cycle != self._cycle:           # a cycle starts at the previous sample
            self._cycle = comps.cycle
            self._start = self._last if self._last is not None else (t, x)
        if self._cycle > 0:
            dt = t - self._start[0]
            rate = abs(x - self._start[1]) / dt if dt > 0 else 0.0
        else:
            last = self._last
            rate = abs(x - last[1]) / (t - last[0]) if last is not None and t > last[0] else 0.0
        self._last = (t, x)
        damping, residual = comps.damping, comps.residual
        for m in self._memory:
            damping, residual = m.step(t, damping, residual)
        f = float(self.chain._contact_force(comps.elastic, damping, residual, comps.cycle,
                                            velocity, rate, x_s))
        self._prev_force = f
        return f

    def sensor(self, t: float, force: float) -> float:
        for s in self._sensors:
            force = s.step(t, force)
        return force


def make_effects(spec: Mapping[str, float] | Iterable[Effect] | EffectChain | None) -> EffectChain:
    """An EffectChain from {"name": magnitude} (the simulator's --effect NAME=MAG) or effects."""
    if spec is None:
        return EffectChain()
    if isinstance(spec, EffectChain):
        return spec
    if isinstance(spec, Mapping):
        effects = []
        for name, magnitude in spec.items():
            if name not in EFFECTS:
                raise ValueError(f"unknown effect {name!r} (known: {', '.join(EFFECTS)})")
            p = EFFECTS[name].parameters[0]
            if not p.lower <= magnitude <= p.upper:   # the plausible range (also the fit bounds)
                raise ValueError(f"effect {name}={magnitude:g} is outside [{p.lower:g}, {p.upper:g}] {p.unit}")
            effects.append(EFFECTS[name](magnitude))
        return EffectChain(effects)
    return EffectChain(spec)


def parse_effect_option(text: str) -> tuple[str, float]:
    """'NAME=MAG' -> (name, magnitude); ValueError with one line otherwise."""
    name, sep, mag = text.partition("=")
    name = name.strip()
    if not sep or name not in EFFECTS:
        raise ValueError(f"effect {text!r}: expected NAME=MAGNITUDE with NAME one of {', '.join(EFFECTS)}")
    try:
        value = float(mag)
    except ValueError:
        raise ValueError(f"effect {text!r}: magnitude {mag.strip()!r} is not a number") from None
    if not math.isfinite(value):
        raise ValueError(f"effect {text!r}: magnitude must be finite")
    return name, value


# ----------------------------------------------------------------------------- size vs noise

def signature_rms(effect: Effect, model, t, x, **kw) -> float:
    """RMS change of the measured force that the effect causes on this history (N)."""
    plain = EffectChain().measured_force(model, t, x, **kw)
    with_effect = EffectChain([effect]).measured_force(model, t, x, **kw)
    return float(np.sqrt(np.mean(np.square(with_effect - plain))))


def relative_magnitude(effect: Effect, model, t, x, noise_sigma_N: float, **kw) -> float:
    """The effect's RMS signature in units of the load cell's noise (1 = as big as the noise)."""
    return signature_rms(effect, model, t, x, **kw) / noise_sigma_N


def magnitude_for_ratio(name: str, ratio: float, model, t, x, noise_sigma_N: float,
                        sign: float = 1.0, **kw) -> float:
    """The magnitude of effect `name` whose signature is `ratio` times the noise on this history.

    Searches between 0 and the parameter's bound on the side of `sign` (brentq).
    """
    cls = EFFECTS[name]
    p = cls.parameters[0]
    limit = p.upper if sign > 0 else p.lower
    if limit == 0:
        raise ValueError(f"{name}: magnitude cannot take that sign")

    def gap(m):
        return relative_magnitude(cls(m), model, t, x, noise_sigma_N, **kw) - ratio

    hi = float(np.clip(abs(p.typical) * np.sign(sign), p.lower, p.upper))
    while gap(hi) < 0:
        if hi == limit:
            raise ValueError(f"{name}: even the bound {limit} gives less than {ratio} x noise")
        hi = float(np.clip(2 * hi, p.lower, p.upper))
    return float(brentq(gap, 0.0, hi, xtol=1e-12 + 1e-9 * abs(hi)))
