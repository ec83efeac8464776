"""When the measurement leaves the prediction by more than the noise allows, and saying so.

The rule (DepartureWatch): r = measured - predicted at each sample; m = its mean over the
last WINDOW_S of machine time (w samples); the limit for m is

    K_SIGMA * sqrt(noise^2 / w + sigma_pred^2) + spread + RELATIVE_FLOOR * |predicted|

noise: the load cell's white noise (the fit's estimate); sigma_pred: the forecast's own 1-sigma
uncertainty (the fit's parameters by the delta method, and the residual terms of a cycle not yet
seen); spread: how far the model's neighbours forecast from it (foamlab.prediction.forecast).
A departure is m beyond the limit, on one side, for w samples in a row: reported once per
half-cycle, with where it began.

Why K_SIGMA = 5 and w samples in a row: with a correct forecast m is Gaussian around a bias
within the forecast's uncertainty, so its noise part must pass >= 4 of its own sigmas
(p = 6e-5 per window) and stay there for a second, independent window (p ~ 4e-9). A run has
~10^3 windows: < 1e-5 false alarms per run from the noise.
Why the spread on top, at face value: the delta method linearises one model form; the memory
carried across the unloaded gap between cycles is where the forecast errs, and there the
neighbours (equally good fits of the first cycles) disagree by about as much as the forecast
errs: on 45 clean simulated runs the error reached 32 x the delta-method sigma but at most 0.75
of the limit above; 0 of 50 clean runs flagged, 20 of 20 softened ones (docs/prediction.md).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from foamlab.prediction.forecast import StepForecast

K_SIGMA = 5.0
#: A forecast is not held to better than the force is measured: 1 % of the reading, a class 1
#: testing machine's load cell (ISO 7500-1); a softening of the specimen is ten times that.
RELATIVE_FLOOR = 0.01
#: Machine seconds the residual is averaged over (and must stay beyond the limit).
WINDOW_S = 1.0
#: Fewest samples in the window, whatever the sampling rate.
MIN_WINDOW = 4


def window_samples(sampling_hz: float) -> int:
    return max(MIN_WINDOW, int(round(WINDOW_S * sampling_hz)))


def departure_limit(predicted_N, sigma_N, spread_N, noise_N: float, window: int):
    """What the noise and the forecast's uncertainty allow the window's mean residual (N)."""
    sigma = np.asarray(sigma_N, float)
    return (K_SIGMA * np.sqrt(noise_N ** 2 / window + sigma ** 2) + np.asarray(spread_N, float)
            + RELATIVE_FLOOR * np.abs(np.asarray(predicted_N, float)))


def _size(value: float) -> str:
    value = abs(value)
    return f"{value:.1f}" if value >= 1 else f"{value:.2g}"


def _place(mm: float) -> str:
    return f"{mm:.0f}" if abs(mm) >= 10 else f"{mm:.1f}"


@dataclass(frozen=True)
class Departure:
    """The specimen left the prediction: where, by how much, which way."""

    cycle: int
    phase: str                # loading | unloading | dwell
    size_N: float             # mean of measured - predicted over the window (negative: below)
    limit_N: float            # what the noise and the forecast allowed there
    since_mm: float           # displacement where the departure began
    at_mm: float              # displacement when it was established
    time_s: float             # machine time when it was established
    from_cycles: int          # the forecast's fitted cycles

    @property
    def below(self) -> bool:
        return self.size_N < 0

    @property
    def message(self) -> str:
        """One line, in words: 'cycle 3 loading: 4.1 N below the prediction since 31 mm'."""
        side = "below" if self.below else "above"
        return f"cycle {self.cycle} {self.phase}: {_size(self.size_N)} N {side} the prediction since {_place(self.since_mm)} mm"


@dataclass(frozen=True)
class Compared:
    """Samples compared with the forecast (for the window's residual strip)."""

    cycle: np.ndarray
    step: np.ndarray
    displacement_mm: np.ndarray
    predicted_N: np.ndarray
    residual_N: np.ndarray    # measured - predicted
    mean_N: np.ndarray        # over the window (nan until it is full)
    limit_N: np.ndarray       # departure_limit at each sample


class DepartureWatch:
    """Compares samples with a forecast, step by step (see the module docstring). Vectorised:
    the predictor's thread shares the interpreter lock with the acquisition, and after a
    forecast arrives it compares hundreds of samples at once."""

    def __init__(self, noise_N: float, sampling_hz: float) -> None:
        if not (noise_N > 0 and math.isfinite(noise_N)):
            raise ValueError(f"the noise level must be a positive number, got {noise_N!r}")
        self.noise_N = float(noise_N)
        self.window = window_samples(sampling_hz)
        self._restart(None)
        self._reported: set[int] = set()   # steps whose departure was said

    def compare(self, forecast: StepForecast, from_cycles: int, x: np.ndarray, t_in_step: np.ndarray,
                force: np.ndarray, time_s: np.ndarray) -> tuple[Compared, list[Departure]]:
        """Samples of one step (in order) against its forecast; the departures they establish."""
        x = np.asarray(x, float)
        predicted, sigma, spread = forecast.at(x, t_in_step)
        if self._step != forecast.index:
            self._restart(forecast.index)
        n, w = len(x), self.window
        residual = np.asarray(force, float) - predicted
        limit = departure_limit(predicted, sigma, spread, self.noise_N, w)
        # the last w-1 samples of this step carried over, so windows span the calls
        r, lim, xs = (np.concatenate([old, new]) for old, new in
                      ((self._r, residual), (self._lim, limit), (self._x, x)))
        carried = len(self._r)
        self._r, self._lim, self._x = r[-(w - 1):], lim[-(w - 1):], xs[-(w - 1):]
        mean = np.full(n, np.nan)
        if len(r) < w:
            return self._compared(forecast, x, predicted, residual, mean, limit), []
        kernel = np.ones(w) / w
        m = np.convolve(r, kernel, "valid")               # window ending at combined index w-1+j
        allowed = np.convolve(lim, kernel, "valid")      # what its samples may err by, on average
        side = (m > allowed).astype(int) - (m < -allowed).astype(int)
        ends = np.arange(w - 1, len(r))
        mean[ends - carried] = m
        found = self._runs(side, m, allowed, ends, xs, forecast, from_cycles, x, time_s, carried)
        return self._compared(forecast, x, predicted, residual, mean, limit), found

    def _runs(self, side, m, allowed, ends, xs, forecast, from_cycles, x, time_s, carried) -> list[Departure]:
        """Runs of windows beyond the limit on one side; a departure when one reaches w windows."""
        w = self.window
        same = np.r_[side[0] == self._side, side[1:] == side[:-1]] & (side != 0)
        starts = np.maximum.accumulate(np.where(same, 0, np.arange(len(side))))
        run = np.arange(len(side)) - starts + 1 + np.where(starts == 0, self._beyond if same[0] else 0, 0)
        run[side == 0] = 0
        # where each run began: its first window's first sample (x kept from an earlier call)
        since = np.where(starts == 0, self._since if same[0] else xs[ends[0] - w + 1], xs[ends[starts] - w + 1])
        self._side, self._beyond, self._since = int(side[-1]), int(run[-1]), float(since[-1])
        hit = np.flatnonzero(run >= w)
        if not len(hit) or forecast.index in self._reported:
            return []
        i = hit[0]
        self._reported.add(forecast.index)
        k = ends[i] - carried
        return [Departure(forecast.cycle, forecast.phase, float(m[i]), float(allowed[i]), float(since[i]),
                          float(x[k]), float(time_s[k]), from_cycles)]

    @staticmethod
    def _compared(forecast, x, predicted, residual, mean, limit) -> Compared:
        n = len(x)
        return Compared(np.full(n, forecast.cycle), np.full(n, forecast.index), x, predicted, residual, mean, limit)

    def _restart(self, step: int | None) -> None:
        self._step = step
        self._r = self._lim = self._x = np.zeros(0)
        self._beyond, self._side, self._since = 0, 0, math.nan
