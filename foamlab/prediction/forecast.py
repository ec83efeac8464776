"""The forecast of the rest of a run from its first cycles, and how good it was.

    forecast = make_forecast(prefix, plan, after_cycle=2, sampling_hz=16, n_cycles=3)
    forecast.at(step_index, x_mm, t_in_step_s) -> (force_N, sigma_N)
    score = score_cycle(previous.params, previous.contact_zero_N, noise, run_to_end_of_k, rows, ...)
    scores = forecast_scores(run)            # offline: each cycle predicted from the ones before it

make_forecast identifies the model (foamlab.identification.fit_prepared) on the cycles measured so
far and evaluates it (foamlab.model.evaluate, causal) on the measured history followed by the
method's planned displacement for the rest of the run. With the force comes its uncertainty:
sigma (1 sigma, without the load cell's noise) - the fit's parameter uncertainty carried to the
future (delta method on the fit's own Jacobian) and the residual terms of a cycle the data have
not yet shown (its own terms, which the model starts at that cycle's first unloading) - and the
spread: how far the model's neighbours (other orders, equally good fits of the same cycles)
forecast from it, plus one sample's change of the force. Everything here is pure computation:
foamlab.prediction.live runs it off the acquisition thread (docs/prediction.md).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

from foamlab import FoamlabError
from foamlab.analysis.prepared import PreparedRun, prepare
from foamlab.identification import FitReport
from foamlab.identification.fit import fit_prepared
from foamlab.methods import PlannedStep
from foamlab.model import HistoryLabels, ModelParameters, evaluate, label_history
from foamlab.model.layout import OWN_RESIDUAL_CYCLES
from foamlab.rundata import RunData

#: Cycles measured before the first forecast. The paper's steps isolate the damping and the
#: residual by differences between cycles; a one-cycle fit predicts the next loading but the
#: uncertainty of its memory terms is tens of N (measured: 13-90 N on the default specimen).
MIN_CYCLES = 2
#: Turning points of the measured displacement: reversals by more than this (encoder and
#: float32 register noise are ~1 um; the plan's own turns are exact).
TURN_DEADBAND_MM = 0.01
#: The uncertainty is computed on at most this many points of the history (every k-th
#: sample; interpolated back): the Jacobian costs one model evaluation per parameter.
BAND_POINTS = 800
#: Singular values of the (column-scaled) Jacobian below this fraction of the largest are
#: directions the data do not determine: left out (their spread is not an estimate).
RCOND = 1e-10
#: Relative finite-difference step of the Jacobian.
FD_STEP = 1e-6
#: The model's neighbours (orders N,M,P with one damping mode or residual term fewer): each fits
#: the first cycles within the noise as well as the paper's orders, but carries the memory across
#: the unloaded gap differently - their spread is the forecast's model-form uncertainty, which the
#: delta method (one model form, linearised) cannot see. Measured on a clean simulated run: the
#: paper's orders missed cycle 3's loading by -4.2 N; the neighbours by +1.0, +0.7, -3.0 N.
NEIGHBOURS = ("2,3,7", "3,2,7", "2,2,7")
#: No forecast from a fit whose residuals' spread (robust: 1.4826 x their MAD, so that a few
#: samples a stalled reply spoiled do not count) is above this many times the noise: a model that
#: misses the cycles it was identified on extrapolates nowhere near them (measured: a specimen
#: softening from cycle 2 on, 4.2 x the noise, was forecast 150 N above itself in cycle 3; clean
#: simulated runs fit at 0.9-1.1 x; the real Bluehill file 6.7 x).
FIT_GATE = 2.0

LOADING, UNLOADING, DWELL = "loading", "unloading", "dwell"
PHASE_OF_ACTION = {"compress": LOADING, "return": UNLOADING, "dwell": DWELL}


@dataclass(frozen=True)
class StepForecast:
    """The predicted force over one planned step of the method."""

    index: int                    # PlannedStep.index
    cycle: int
    phase: str                    # loading | unloading | dwell
    time_s: np.ndarray            # planned machine time
    displacement_mm: np.ndarray
    force_N: np.ndarray           # what the load cell should read (the fit's unloaded reading off contact)
    sigma_N: np.ndarray           # 1 sigma of the prediction itself (the noise comes on top)
    spread_N: np.ndarray          # largest difference to the model's neighbours (NEIGHBOURS) + one sample's change

    def at(self, x_mm: np.ndarray, t_in_step_s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Prediction, its sigma and spread at measured samples: by displacement while the plate
        moves (a late or early sample is at the same place of the curve), by the time
        into the step during a dwell."""
        if self.phase == DWELL or len(self.time_s) < 2:
            key, grid = np.asarray(t_in_step_s, float), self.time_s - self.time_s[0]
        else:
            key, grid = np.asarray(x_mm, float), self.displacement_mm
        columns = (self.force_N, self.sigma_N, self.spread_N)
        if grid[-1] < grid[0]:          # unloading: np.interp needs a rising grid
            grid, columns = grid[::-1], [c[::-1] for c in columns]
        force, sigma, spread = (np.interp(key, grid, c) for c in columns)
        return force, sigma, spread


@dataclass(frozen=True)
class Forecast:
    """The rest of the run as predicted from its first `from_cycles` cycles."""

    from_cycles: int
    params: ModelParameters
    contact_zero_N: float
    noise_N: float                # the load cell's noise, estimated by the fit
    fit_rmse_N: float             # the fit on the cycles it saw
    elapsed_s: float              # identification + forecast, wall seconds
    sampling_hz: float
    steps: dict[int, StepForecast] = field(default_factory=dict)   # by PlannedStep.index

    def step(self, index: int) -> StepForecast | None:
        return self.steps.get(index)

    def cycle(self, number: int) -> list[StepForecast]:
        return [s for s in self.steps.values() if s.cycle == number]

    def describe(self) -> str:
        done = "cycle 1" if self.from_cycles == 1 else f"cycles 1-{self.from_cycles}"
        cycles = sorted({s.cycle for s in self.steps.values()})
        what = "" if not cycles else (f"cycle {cycles[0]} " if len(cycles) == 1 else f"cycles {cycles[0]}-{cycles[-1]} ")
        return (f"{what}predicted from {done} (fit RMSE {self.fit_rmse_N:.3g} N, noise {self.noise_N:.3g} N; "
                f"made in {self.elapsed_s:.1f} s)")


@dataclass(frozen=True)
class CycleScore:
    """How well a cycle was predicted from the cycles before it (an honest forecast score)."""

    cycle: int
    from_cycles: int              # the forecast was identified on cycles 1..from_cycles
    rmse_N: float                 # measured - predicted over the cycle's samples
    bias_N: float                 # their mean (negative: the specimen below the prediction)
    noise_N: float
    n_samples: int

    @property
    def ratio(self) -> float:
        """RMSE over the noise: 1 = the forecast was as good as the load cell allows."""
        return self.rmse_N / self.noise_N if self.noise_N > 0 else math.nan

    def describe(self) -> str:
        return (f"cycle {self.cycle} from cycles 1-{self.from_cycles}: RMSE {self.rmse_N:.3g} N "
                f"= {self.ratio:.2g} x noise (mean {self.bias_N:+.3g} N, {self.n_samples} samples)")


def history_labels(x: np.ndarray) -> HistoryLabels:
    return label_history(np.asarray(x, float), TURN_DEADBAND_MM)


def planned_future(plan: list[PlannedStep], after_cycle: int, t0: float, sampling_hz: float
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(t, x, step index) of the plan's steps after cycle `after_cycle`, from machine time t0."""
    dt = 1.0 / sampling_hz
    ts, xs, idx = [], [], []
    t = t0
    for p in plan:
        if p.step.cycle <= after_cycle:
            continue
        n = max(1, int(round(p.duration_s * sampling_hz)))
        frac = np.arange(1, n + 1) / n
        ts.append(t + dt * np.arange(1, n + 1))
        xs.append(p.start_mm + (p.end_mm - p.start_mm) * frac)
        idx.append(np.full(n, p.index))
        t += n * dt
    if not ts:
        return np.zeros(0), np.zeros(0), np.zeros(0, int)
    return np.concatenate(ts), np.concatenate(xs), np.concatenate(idx)


def make_forecast(prefix: RunData, plan: list[PlannedStep], after_cycle: int, sampling_hz: float,
                  n_cycles: int) -> Forecast:
    """Identify the model on `prefix` (the run's cycles 1..after_cycle) and predict the rest
    of the plan. Raises FoamlabError (one line) when the prefix cannot be identified."""
    started = time.perf_counter()
    fd, fit = _identified(prefix, after_cycle)
    t_f, x_f, steps_f = planned_future(plan, after_cycle, float(prefix.time_s[-1]), sampling_hz)
    t = np.concatenate([prefix.time_s, t_f])
    x = np.concatenate([prefix.displacement_mm, x_f])
    labels = history_labels(x)
    force = np.maximum(evaluate(fit.params, t, x, labels).force, fit.contact_zero_N)
    sigma = prediction_sigma(fit, t, x, len(prefix), n_cycles)
    # where a sample falls relative to a turn is known to a sample period: right after one the
    # force changes by up to tens of N per sample (the damping stops, the new memory starts)
    change = np.abs(np.diff(force, prepend=force[0]))
    spread = neighbours_spread(fd, fit, force, t, x, labels) + np.maximum(change, np.roll(change, -1))
    n = len(prefix)
    by_step = {}
    for p in plan:
        rows = n + np.flatnonzero(steps_f == p.index)
        if len(rows):
            by_step[p.index] = StepForecast(p.index, p.step.cycle, PHASE_OF_ACTION.get(p.step.action, LOADING),
                                            t[rows], x[rows], force[rows], sigma[rows], spread[rows])
    return Forecast(after_cycle, fit.params, fit.contact_zero_N, float(fit.noise_N), float(fit.rmse),
                    time.perf_counter() - started, float(sampling_hz), by_step)


def neighbours_spread(fd: PreparedRun, main: FitReport, force: np.ndarray, t: np.ndarray, x: np.ndarray,
                      labels: HistoryLabels) -> np.ndarray:
    """Largest |difference| between `force` (the `main` fit's) and the NEIGHBOURS' forecasts, of
    those that fit the prepared prefix `fd` within FIT_GATE x the noise (the others describe
    nothing). The neighbours keep the residual form the main fit chose: choosing it again for
    each doubled the forecast's time (4.1 s on a recorded 2-cycle prefix, the worker 8-13 s)."""
    spread = np.zeros(len(t))
    for orders in NEIGHBOURS:
        try:
            fit = fit_prepared(fd, orders=orders, form=main.params.residual_form, hold=False)
            check_fit(fit, 0)
        except FoamlabError:
            continue
        other = np.maximum(evaluate(fit.params, t, x, labels).force, fit.contact_zero_N)
        spread = np.maximum(spread, np.abs(other - force))
    return spread


def check_fit(fit: FitReport, after_cycle: int) -> None:
    """Refuse (one line, why) to forecast from a fit that does not describe its own cycles."""
    r = fit.residual_N[fit.observed]
    spread = 1.4826 * float(np.median(np.abs(r - np.median(r)))) if len(r) else math.inf
    ratio = spread / fit.noise_N if fit.noise_N > 0 else math.inf
    if not ratio <= FIT_GATE:
        cycles = "cycle 1" if after_cycle == 1 else f"cycles 1-{after_cycle}"
        raise FoamlabError(f"the model misses {cycles} by {ratio:.2g} x the noise (RMSE {fit.rmse:.3g} N): the "
                           "specimen is not what the model describes (it changed already, or the model lacks "
                           "something: see the diagnosis after the run)")


def prediction_sigma(fit: FitReport, t: np.ndarray, x: np.ndarray, n_data: int, n_cycles: int) -> np.ndarray:
    """1-sigma uncertainty of the fitted model's force along the history (t, x), whose first
    `n_data` samples are the fitted data: the parameter part and the unseen cycles' part."""
    step = max(1, int(math.ceil(len(t) / BAND_POINTS)))
    rows = np.arange(0, len(t), step)
    td, xd = t[rows], x[rows]
    labels = history_labels(xd)
    params = fit.params
    base = evaluate(params, td, xd, labels).force
    jac = _jacobian(fit, td, xd, labels, base)
    data = (rows < n_data) & (base > fit.contact_zero_N)
    parameter = _delta_method(jac, data, fit.noise_N, step)
    unseen = np.abs(evaluate(_unseen_cycles_zeroed(params, n_cycles), td, xd, labels).force - base)
    # kept where the model force is below the unloaded reading too: within a sigma or two of
    # it the plate may still touch (the point where contact ends is uncertain as well)
    return np.interp(t, td, np.hypot(parameter, unseen))


def _jacobian(fit: FitReport, t, x, labels, base) -> np.ndarray:
    """d force / d parameter (flat ModelParameters order) by forward differences; zero for the
    parameters the fit held fixed."""
    params = fit.params
    v = params.to_vector()
    varied = fit.varied if fit.varied is not None else np.ones(len(v), bool)
    jac = np.zeros((len(t), len(v)))
    for j in np.flatnonzero(varied):
        h = FD_STEP * max(abs(v[j]), 1e-3)
        moved = v.copy()
        moved[j] += h
        try:
            jac[:, j] = (evaluate(params.with_vector(moved), t, x, labels).force - base) / h
        except (FoamlabError, ValueError):   # a step across a bound (beta -> 1): no column
            continue
    return jac


def _delta_method(jac: np.ndarray, data: np.ndarray, noise_N: float, step: int) -> np.ndarray:
    """sigma of J theta at every row, for theta estimated by least squares on the `data` rows
    (each standing for `step` samples) with white noise of `noise_N`: noise * |J V S^-1| row-wise,
    from the SVD of the data rows (stable where the normal matrix is not)."""
    jd = jac[data]
    if not len(jd) or not np.isfinite(noise_N):
        return np.zeros(len(jac))
    scale = np.linalg.norm(jd, axis=0)
    scale[scale == 0] = 1.0
    _, s, vt = np.linalg.svd(jd / scale, full_matrices=False)
    keep = s > RCOND * s[0] if len(s) and s[0] > 0 else np.zeros(len(s), bool)
    a = (jac / scale) @ vt[keep].T / s[keep]
    return noise_N * np.sqrt(np.sum(a ** 2, axis=1) / step)


def _unseen_cycles_zeroed(params: ModelParameters, n_cycles: int) -> ModelParameters:
    """The parameters with zero residual terms for the cycles that will have terms of their own
    (up to OWN_RESIDUAL_CYCLES) but were not in the fit: the fit reuses its last cycle's terms
    for them, a guess worth +-100 % (the default specimen's cycle 3 has half its cycle 2's)."""
    have = params.n_residual_cycles
    own = min(OWN_RESIDUAL_CYCLES, max(n_cycles, have))
    if own <= have:
        return params
    extra = own - have
    return ModelParameters(params.x_scale_mm, params.elastic_k, params.damping_a, params.damping_alpha,
                           np.vstack([params.residual_r, np.zeros((extra, params.order_M))]),
                           np.vstack([params.residual_beta, np.repeat(params.residual_beta[-1:], extra, 0)]))


def score_cycle(forecast: Forecast, history: RunData, rows: np.ndarray, cycle: int) -> CycleScore:
    """Score `forecast` (made before `cycle`) on the measured `history` up to the end of that
    cycle, whose samples are `rows`: the model evaluated causally on the measured displacement."""
    f = history.force_N
    predicted = np.maximum(evaluate(forecast.params, history.time_s, history.displacement_mm,
                                    history_labels(history.displacement_mm)).force, forecast.contact_zero_N)
    r = f[rows] - predicted[rows]
    return CycleScore(cycle, forecast.from_cycles, float(np.sqrt(np.mean(r ** 2))) if len(r) else math.nan,
                      float(np.mean(r)) if len(r) else math.nan, forecast.noise_N, int(len(r)))


#: Offline scoring fits the run once per scored cycle: at most this many (the first predicted).
MAX_OFFLINE_SCORES = 5


@dataclass
class ForecastScores:
    """Each cycle's forecast from the cycles before it; `note` says what was left out."""

    scores: list[CycleScore] = field(default_factory=list)
    note: str = ""
    live: bool = False             # made during the run (else afterwards, from the run file)

    def __bool__(self) -> bool:
        return bool(self.scores)


def forecast_scores(run: RunData, method=None) -> ForecastScores:
    """Offline: each cycle after the first MIN_CYCLES predicted from the cycles before it
    (the run's cycles: RunData.segments), as the live prediction does during a run."""
    seg = run.segments()
    cycles = [c for c in seg.cycles if c.unloading is not None]
    out = ForecastScores(note="; ".join(seg.notes))
    if len(cycles) <= MIN_CYCLES:
        out.note = f"a forecast needs {MIN_CYCLES} cycles before the one it predicts; the run has {len(cycles)}"
        return out
    hz = run.sampling_hz
    notes = list(seg.notes)
    for cycle in cycles[MIN_CYCLES:MIN_CYCLES + MAX_OFFLINE_SCORES]:
        prefix = run.slice(0, cycle.start)
        try:
            forecast = _fit_only(prefix, cycle.number - 1, hz)
        except FoamlabError as exc:
            notes.append(f"cycle {cycle.number} not predicted: {exc}")
            continue
        out.scores.append(score_cycle(forecast, run.slice(0, cycle.stop), np.arange(cycle.start, cycle.stop),
                                      cycle.number))
    if len(cycles) > MIN_CYCLES + MAX_OFFLINE_SCORES:
        notes.append(f"cycles after {cycles[MIN_CYCLES + MAX_OFFLINE_SCORES - 1].number} not scored (one fit per cycle)")
    out.note = "; ".join(notes)
    return out


def _identified(prefix: RunData, after_cycle: int) -> tuple[PreparedRun, FitReport]:
    """The model identified on `prefix`, checked to describe its cycles, and the prepared run
    (once: a forecast's neighbours fit the same one)."""
    fd = prepare(prefix)
    fit = fit_prepared(fd, hold=False)       # the force is all a forecast needs
    check_fit(fit, after_cycle)
    return fd, fit


def _fit_only(prefix: RunData, after_cycle: int, sampling_hz: float) -> Forecast:
    started = time.perf_counter()
    _, fit = _identified(prefix, after_cycle)
    return Forecast(after_cycle, fit.params, fit.contact_zero_N, float(fit.noise_N), float(fit.rmse),
                    time.perf_counter() - started, float(sampling_hz))
