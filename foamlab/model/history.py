"""Half-cycle labels of a displacement history: which samples load, which unload,
which cycle they belong to. The model's components switch on these labels
(damping while loading, the residual of cycle k from its first unloading on)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class HistoryLabels:
    direction: np.ndarray      # +1 loading, -1 unloading, 0 before the first loading
    cycle: np.ndarray          # 1-based cycle number (0 before the first loading)
    starts: list[int]          # index where cycle k's loading starts (its minimum)
    peaks: list[int]           # index of cycle k's maximum (last loading sample)


def label_history(x: np.ndarray, deadband_mm: float = 1e-9) -> HistoryLabels:
    """Turning points are extremes that x leaves by more than deadband_mm.

    The default deadband suits exact (simulated) histories; for measured
    displacement pass the segmentation's turning points to labels_from_extrema.
    """
    x = np.asarray(x, dtype=float)
    minima: list[int] = []
    maxima: list[int] = []
    state = 0               # 0 unknown, +1 rising, -1 falling
    ext_i = 0
    for i in range(1, len(x)):
        if state == 0:
            if x[i] > x[ext_i] + deadband_mm:
                minima.append(ext_i)
                state, ext_i = 1, i
            elif x[i] < x[ext_i] - deadband_mm:
                state, ext_i = -1, i
            elif x[i] < x[ext_i]:
                ext_i = i
        elif state == 1:
            if x[i] >= x[ext_i]:
                ext_i = i
            elif x[i] < x[ext_i] - deadband_mm:
                maxima.append(ext_i)
                state, ext_i = -1, i
        else:
            if x[i] <= x[ext_i]:
                ext_i = i
            elif x[i] > x[ext_i] + deadband_mm:
                minima.append(ext_i)
                state, ext_i = 1, i
    return labels_from_extrema(len(x), minima, maxima)


def labels_from_extrema(n: int, minima: list[int], maxima: list[int]) -> HistoryLabels:
    """Labels from alternating extrema: minima[k] starts cycle k+1, maxima[k] ends its loading."""
    direction = np.zeros(n, dtype=int)
    cycle = np.zeros(n, dtype=int)
    starts, peaks = [], []
    for k, s in enumerate(minima):
        following = [m for m in maxima if m > s]
        p = following[0] if following else n - 1
        nxt = minima[k + 1] if k + 1 < len(minima) else n
        p = min(p, nxt)
        starts.append(int(s))
        peaks.append(int(p))
        direction[s:p + 1] = 1
        direction[p + 1:nxt] = -1
        cycle[s:nxt] = k + 1
    return HistoryLabels(direction, cycle, starts, peaks)
