"""The model's memory components after each turning point, on times finer than the samples.

At a turning point the paper's model switches at once - the damping off, the unloading's residual
memory on, a jump of several newtons - and every memory has a cusp, (t - t_turn)^nu, after each
corner of the path. A response in time of those components (memory_lag: first order) computed from
the samples alone takes them linear between two samples, which spreads the jump over a whole
sampling step: against an independent generator's 300 ms lag that misfit 0.14 N rms on A causal
1000, 2-4 N on the samples after each turn (docs/analysis.md, "A memory lag across the turn's
jump"). With the components also at finer times after each turn (times_after), the response sees
the jump where it happens and the cusps as curves. Both batch forms use it: EffectChain.response
and the fit's ExtendedModel (its columns there from a second basis, Series.turn_basis).
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Sequence

import numpy as np

from foamlab.model.history import HistoryLabels, labels_from_extrema

#: Times per sampling step, and steps after each turn, where the components are evaluated too,
#: and one time JUST_AFTER a step after the turn: the jump itself within a thousandth of a step.
#: Misfit to the generator's lag (A causal 1000 300 ms, B causal 1004 100 ms, B paper 1002 300 ms):
#: 0.015, 0.022, 0.018 N at REFINE 8 alone; 0.010, 0.013, 0.010 N with JUST_AFTER (the response
#: along the path on model_response's grid 8 x finer: 0.009-0.010 N); the samples alone 0.14-0.20 N.
REFINE = 8
STEPS = 3
JUST_AFTER = 1e-3


def turn_instants(t: np.ndarray, labels: HistoryLabels) -> np.ndarray:
    """Each turning point's time (a loading's peak, a later cycle's start): not the run's start."""
    idx = list(labels.starts[1:]) + list(labels.peaks)
    return np.sort(np.asarray(t, float)[np.asarray(idx, int)]) if idx else np.zeros(0)


def times_after(turns: np.ndarray, step_s: float, t_first: float, t_last: float) -> np.ndarray:
    """The turn instants, one time JUST_AFTER a step after each and REFINE times per step over
    STEPS steps after each, within [t_first, t_last], sorted and unique."""
    offsets = np.concatenate([[0.0, JUST_AFTER * step_s], step_s / REFINE * np.arange(1, REFINE * STEPS + 1)])
    out = (np.asarray(turns, float)[:, None] + offsets[None, :]).ravel()
    return np.unique(out[(out >= t_first) & (out <= t_last)])


class TimedPath(NamedTuple):
    """A path with extra times as nodes (with_times): its times, x there, the half-cycles' labels,
    the corners' indices, and each extra time's index."""

    t: np.ndarray
    x: np.ndarray
    labels: HistoryLabels
    corners: np.ndarray
    extra_rows: np.ndarray


def with_times(t: np.ndarray, x: np.ndarray, labels: HistoryLabels, extra: np.ndarray,
               corners: Sequence[int] = ()) -> TimedPath:
    """The path (t, x: piecewise linear through its nodes) with the extra times as nodes."""
    t_all = np.union1d(t, extra)
    x_all = np.interp(t_all, t, x)
    at = lambda idx: [int(i) for i in np.searchsorted(t_all, np.asarray(t, float)[np.asarray(idx, int)])]
    labels_all = labels_from_extrema(len(t_all), at(labels.starts), at(labels.peaks))
    return TimedPath(t_all, x_all, labels_all, np.asarray(at(corners), int), np.searchsorted(t_all, extra))


def respond_with(t: np.ndarray, values: Sequence[np.ndarray], t_extra: np.ndarray,
                 extra: Sequence[np.ndarray], response: Callable) -> tuple[np.ndarray, ...]:
    """response(times, *arrays) (a memory_batch) on the samples' rows and the extra times' rows
    merged in time, read back at the samples. At a time in both, the sample's row comes first
    (equal values: a step of no time keeps the response's state)."""
    if not len(t_extra):
        return tuple(response(t, *values))
    t_all = np.concatenate([t, t_extra])
    order = np.argsort(t_all, kind="stable")
    merged = [np.concatenate([v, e])[order] for v, e in zip(values, extra)]
    out = response(t_all[order], *merged)
    rank = np.empty(len(order), int)
    rank[order] = np.arange(len(order))
    return tuple(o[rank[:len(t)]] for o in out)


def on_grid(t: np.ndarray, x: np.ndarray, labels: HistoryLabels, step_s: float
            ) -> tuple[np.ndarray, np.ndarray, HistoryLabels]:
    """A uniform grid of step_s from t[0] through t[-1] along the path (t, x: piecewise linear
    through its nodes): (times, x there, the labels with each turning point at the last grid time
    not after it - there x is at the extreme)."""
    grid = t[0] + step_s * np.arange(int(np.ceil((t[-1] - t[0]) / step_s)) + 1)
    at = lambda idx: [int(np.searchsorted(grid, t[i] + 1e-9 * step_s, side="right")) - 1 for i in idx]
    return grid, np.interp(grid, t, x), labels_from_extrema(len(grid), at(labels.starts), at(labels.peaks))
