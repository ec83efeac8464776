"""The simulated load cell: an indicator reading the force the specimen's effects deliver.

Capacity, ADC range (full_scale_ratio x capacity), Gaussian noise (seeded), quantisation to
resolution_N, zero / tare / peak, over- and under-range flags, the no-motion flag (noise-free
signal within motion_band_N over motion_window_s). The fault `overload` forces the reading to
the ADC full scale (from T on, inside a window, or RANDOM_OVERLOAD_S per random event).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from simulator.faults import FaultPlan

if TYPE_CHECKING:
    from simulator.machine import MachineSettings

RANDOM_OVERLOAD_S = 1.0         # duration of one random overload event (virtual s)


@dataclass(frozen=True)
class LoadCellReading:
    gross_N: float
    net_N: float
    peak_N: float
    under_range: bool
    over_range: bool
    no_motion: bool
    tare_set: bool


class SimLoadCell:
    """The indicator's state at the machine's physics time `t` (see the module docstring).

    step() follows the physics; the commands act at the last step's instant (the machine
    brings the physics to now first).
    """

    def __init__(self, settings: "MachineSettings", faults: FaultPlan, seed: int = 0):
        self.settings, self.faults = settings, faults
        self._rng = np.random.default_rng(seed)
        self.t = -math.inf
        self.sensor_N = 0.0            # the force sensed at t, before offset, zero and noise
        self._overload_until = -math.inf
        self._zero_counts = 0.0
        self._tare = 0.0
        self._tare_set = False
        self._peak = -math.inf
        self._history: collections.deque[tuple[float, float]] = collections.deque()

    @property
    def _full_scale(self) -> float:
        return self.settings.capacity_N * self.settings.full_scale_ratio

    def quantize(self, value: float) -> float:
        r = self.settings.resolution_N
        return round(round(value / r) * r, 9)

    def raw(self) -> float:
        """The noise-free raw signal (ADC range, offset, overload) at t."""
        full = self._full_scale
        if self.faults.active("overload", self.t) or self.t < self._overload_until:
            return full
        return min(max(self.sensor_N + self.settings.load_cell_offset_N, -full), full)

    def _net_noise_free(self) -> float:
        return self.quantize(self.raw() - self._zero_counts) - self._tare

    def step(self, t_prev: float, t: float, sensor_N: float, first: bool = False) -> None:
        """The physics reached t with `sensor_N` sensed: overload events, no-motion window, peak."""
        self.t, self.sensor_N = t, sensor_N
        if not first and self.faults.fires_during("overload", t_prev, t, windows=False):
            if any(s.name == "overload" and s.is_random for s in self.faults.specs):
                self._overload_until = t + RANDOM_OVERLOAD_S
        self._history.append((t, self.raw()))
        while self._history and self._history[0][0] < t - self.settings.motion_window_s:
            self._history.popleft()
        self._peak = max(self._peak, self._net_noise_free())

    def read(self) -> LoadCellReading:
        st = self.settings
        full = self._full_scale
        noisy = self.raw() + (self._rng.normal(0.0, st.noise_sigma_N) if st.noise_sigma_N > 0 else 0.0)
        counts = self.quantize(min(max(noisy, -full), full))
        gross = round(counts - self._zero_counts, 9)
        net = round(gross - self._tare, 9)
        self._peak = max(self._peak, net)
        values = [f for _, f in self._history]
        return LoadCellReading(
            gross_N=gross, net_N=net, peak_N=self._peak,
            under_range=counts < -st.capacity_N, over_range=counts > st.capacity_N,
            no_motion=bool(values) and max(values) - min(values) <= st.motion_band_N,
            tare_set=self._tare_set,
        )

    def zero(self) -> None:
        """Gross := 0 at the present load (the indicator averages, i.e. noise-free)."""
        self._zero_counts = self.quantize(self.raw())
        self._peak = self._net_noise_free()

    def reset_zero(self) -> None:
        """Gross zero back to the calibration zero (an indicator's "reset zero")."""
        self._zero_counts = 0.0

    def tare(self) -> None:
        self._tare = self.quantize(self.raw() - self._zero_counts)
        self._tare_set = True
        self._peak = 0.0

    def clear_tare(self) -> None:
        self._tare = 0.0
        self._tare_set = False

    def reset_peak(self) -> None:
        self._peak = self._net_noise_free()
