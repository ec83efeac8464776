"""Total force of the combined model (Eq. 20a-f) for any displacement history.

`evaluate` is the time-domain model used everywhere (identification's joint refinement,
diagnosis, the simulator through SpecimenState); its residual is the causal Eq. 10 or, for
``residual_form = 'paper'``, each cycle's Eq. 11 in x (docs/model.md). `closed_form`
is the same model on the ideal triangular history evaluated with the paper's
closed forms (Eqs. 9, 11, 12 and the exact piecewise-linear RL derivative); the
two agree within the tolerance stated in docs/model.md (tests/test_model.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from foamlab.model.components import (
    damping_closed_form,
    elastic_force,
    residual_static,
    rl_derivative_piecewise_linear,
)
from foamlab.model.history import HistoryLabels, label_history, labels_from_extrema
from foamlab.model.operators import FractionalOperator, HereditaryOperator, fractional_sum, is_uniform
from foamlab.model.params import ModelParameters


@dataclass
class ModelResponse:
    t: np.ndarray
    x: np.ndarray
    elastic: np.ndarray
    damping: np.ndarray
    residual: np.ndarray
    labels: HistoryLabels

    @property
    def force(self) -> np.ndarray:
        """Model force, unclipped (negative = the plate would have to pull: no contact)."""
        return self.elastic + self.damping + self.residual

    @property
    def measured_force(self) -> np.ndarray:
        """What a load cell reads: the plate cannot pull the foam."""
        return np.maximum(self.force, 0.0)

    @property
    def contact(self) -> np.ndarray:
        return self.force > 0.0

    @property
    def direction(self) -> np.ndarray:
        return self.labels.direction

    @property
    def cycle(self) -> np.ndarray:
        return self.labels.cycle


def evaluate(
    params: ModelParameters,
    t,
    x,
    labels: HistoryLabels | None = None,
) -> ModelResponse:
    """Causal model force for the history x(t) (mm of compression, s).

    labels: the half-cycle labels (from the segmentation of measured data); if
    omitted they are taken from x with label_history (exact histories).
    Cost is O(len(t)) per cycle (no history sums). A clock with jitter under 10 % of
    its step is used as is (step = median); a really irregular one is evaluated on a
    uniform grid of the median step and interpolated back.
    """
    t = np.asarray(t, float)
    x = np.asarray(x, float)
    if labels is None:
        labels = label_history(x)
    n = len(t)
    uniform = is_uniform(t)
    h = float(np.median(np.diff(t))) if n > 1 else 1.0
    t_span = max(float(t[-1] - t[0]), h) if n > 1 else 1.0
    damping = np.zeros(n)
    residual = np.zeros(n)
    shared_from = params.n_residual_cycles - 1 if uniform and params.residual_form != "paper" else None
    for k, (s, p) in enumerate(zip(labels.starts, labels.peaks)):
        # the memory operators are continuous in time; on an irregular clock they run
        # on a uniform grid from the cycle's start and are interpolated back, and the
        # switching (damping while loading, residual after the peak) is applied on the
        # original samples so no switch is smeared.
        if uniform:
            tk, xk = t[s:], x[s:] - x[s]
        else:
            tk = t[s] + h * np.arange(int(np.ceil((t[-1] - t[s]) / h)) + 1)
            xk = np.interp(tk, t, x) - x[s]

        def on_samples(values, lo, hi):
            return values[lo - s:hi - s] if uniform else np.interp(t[lo:hi], tk[:len(values)], values)

        hered = HereditaryOperator(params.damping_a, params.damping_alpha)
        n_load = int(np.searchsorted(tk, t[p], side="right")) + 1 if not uniform else p + 1 - s
        damping[s:p + 1] = on_samples(hered.batch(h, xk[:min(n_load, len(xk))]), s, p + 1)
        if p + 1 >= n or params.residual_form == "paper" or (shared_from is not None and k >= shared_from):
            continue
        residual[p + 1:] += on_samples(_memory(params, k + 1, h, t_span, xk), p + 1, n)
    if shared_from is not None and len(labels.starts) > shared_from:
        residual += _shared_memories(params, h, t_span, x, labels, shared_from)
    if params.residual_form == "paper":
        residual = paper_residual(params, t, x, labels)
    return ModelResponse(t, x, elastic_force(params, x), damping, residual, labels)


def _memory(params: ModelParameters, cycle: int, h: float, t_span: float, u: np.ndarray) -> np.ndarray:
    """The residual memory of a 1-based cycle (Eq. 10) for the input u on a uniform step h."""
    r, beta = params.residual_terms(cycle)
    return fractional_sum([(r_i, FractionalOperator(b_i, h_min=h, t_max=t_span)) for r_i, b_i in zip(r, beta)],
                          h, np.asarray(u, float))


def _shared_memories(params: ModelParameters, h: float, t_span: float, x: np.ndarray,
                     labels: HistoryLabels, first: int) -> np.ndarray:
    """The memories of the cycles from index ``first`` on, which share the last identified
    cycle's terms, on a uniform clock, in time linear in the run: the operator is linear and
    causal, so the sum of the memories, each switched on after its cycle's peak, is the
    operator on the summed inputs (x - x(t_k) from each start t_k) less each memory over its
    own loading. One memory per cycle run to the end grew with cycles x samples."""
    n = len(x)
    starts = np.asarray(labels.starts[first:], int)
    peaks = np.asarray(labels.peaks[first:], int)
    s0 = int(starts[0])
    begun = np.zeros(n - s0)
    offset = np.zeros(n - s0)
    np.add.at(begun, starts - s0, 1.0)
    np.add.at(offset, starts - s0, x[starts])
    summed = np.cumsum(begun) * x[s0:] - np.cumsum(offset)
    out = np.zeros(n)
    out[s0:] = _memory(params, first + 1, h, t_span, summed)
    for s, p in zip(starts, peaks):
        out[s:p + 1] -= _memory(params, first + 1, h, t_span, x[s:p + 1] - x[s])
    return out


def paper_residual(params: ModelParameters, t, x, labels: HistoryLabels) -> np.ndarray:
    """The paper form's residual force: each cycle's Eq. 11 in x after its peak. Exact on
    any samples (no memory): its strokes and periods are those of the labels' turning points."""
    t, x = np.asarray(t, float), np.asarray(x, float)
    residual = np.zeros(len(t))
    for k, (s, p) in enumerate(zip(labels.starts, labels.peaks)):
        r, beta = params.residual_terms(k + 1)
        residual[p + 1:] += static_residual(r, beta, x[p + 1:] - x[s], x[p] - x[s], t[p] - t[s])
    return residual


def static_residual(r, beta, x_rel, stroke_mm: float, loading_s: float) -> np.ndarray:
    """The paper form's residual of one cycle (Eq. 11 in x) at displacements x_rel from the
    cycle's start: its stroke and its period, twice its loading time (Eq. 7's triangle)."""
    values, _ = residual_static(x_rel, stroke_mm, 2.0 * loading_s, beta)
    return values @ np.asarray(r, float)


def triangular_history(amplitude_mm: float, rate_mm_s: float, n_cycles: int = 3,
                       sampling_hz: float = 16.0) -> tuple[np.ndarray, np.ndarray]:
    """The paper's ideal protocol (Eq. 7): x = v t up to A, back to 0, repeated."""
    period = 2 * amplitude_mm / rate_mm_s
    t = np.arange(0.0, n_cycles * period + 0.5 / sampling_hz, 1.0 / sampling_hz)
    phase = np.mod(t, period)
    x = np.where(phase <= period / 2, rate_mm_s * phase, rate_mm_s * (period - phase))
    return t, x


def closed_form(params: ModelParameters, t, amplitude_mm: float, rate_mm_s: float,
                n_cycles: int = 3) -> ModelResponse:
    """The model on the ideal triangular history by the closed forms (no time stepping)."""
    t = np.asarray(t, float)
    A, v = amplitude_mm, rate_mm_s
    T = 2 * A / v
    phase = np.mod(t, T)
    x = np.where(phase <= T / 2, v * phase, v * (T - phase))
    x = np.where(t >= n_cycles * T, 0.0, x)
    starts = [int(np.argmin(np.abs(t - k * T))) for k in range(n_cycles)]
    peaks = [int(np.argmin(np.abs(t - (k + 0.5) * T))) for k in range(n_cycles)]
    labels = labels_from_extrema(len(t), starts, peaks)
    loading = labels.direction == 1
    damping = np.where(loading, damping_closed_form(params, np.where(loading, x, 0.0), v), 0.0)
    residual = np.zeros_like(t)
    for k in range(n_cycles):
        tk = k * T
        corners = [tk] + [tk + j * T / 2 for j in range(1, 2 * (n_cycles - k) + 1)]
        slopes = [v] + [(-2 * v if j % 2 else 2 * v) for j in range(1, 2 * (n_cycles - k))] + [v]
        active = (t > tk + T / 2) & (np.arange(len(t)) > peaks[k])
        r, beta = params.residual_terms(k + 1)
        if params.residual_form == "paper":       # Eq. 11 itself, in every later half-cycle
            residual += np.where(active, static_residual(r, beta, x, A, T / 2), 0.0)
            continue
        for r_i, b_i in zip(r, beta):
            residual += np.where(active, r_i * rl_derivative_piecewise_linear(t, tk, corners, slopes, b_i), 0.0)
    return ModelResponse(t, x, elastic_force(params, x), damping, residual, labels)
