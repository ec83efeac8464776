"""The model stepped online, one sample at a time (the simulator's specimen)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from foamlab.model.components import elastic_force

from foamlab.model.operators import FractionalBank, FractionalOperator, HereditaryOperator
from foamlab.model.params import ModelParameters
from foamlab.model.response import static_residual


@dataclass(frozen=True)
class ComponentForces:
    elastic: float
    damping: float
    residual: float
    direction: int
    cycle: int

    @property
    def total(self) -> float:
        return self.elastic + self.damping + self.residual


class SpecimenState:
    """O(1) per step: the same operators, forms and switching as model.evaluate.

    Turning points are detected when x leaves its running extreme by more than
    deadband_mm (exact histories: the default); the extreme sample belongs to the
    half-cycle it ends, exactly as label_history does in batch.
    """

    def __init__(self, params: ModelParameters, h_min: float = 1e-3, t_max: float = 2e4,
                 deadband_mm: float = 1e-9):
        self.params = params
        self.h_min, self.t_max, self.deadband = h_min, t_max, deadband_mm
        self.reset()

    def reset(self) -> None:
        self._t = None
        self._x = 0.0
        self._state = 0           # 0 not started, +1 loading, -1 unloading
        self._ext_x = None
        self._cycle = 0
        self._x_ref = 0.0
        self._hered: HereditaryOperator | None = None
        self._damping = 0.0
        # one row per residual term of every cycle started, in one bank per order beta
        # (stepped together: see FractionalBank); per bank the rows' cycle, r_i and x_ref
        self._banks: dict[float, FractionalBank] = {}
        self._rows: dict[float, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
        self._active_cycles: set[int] = set()
        self._active_weights: dict[float, np.ndarray] = {}
        # the paper form: per unloaded cycle (r, beta, x at its start, stroke, loading time)
        self._static: list[tuple[np.ndarray, np.ndarray, float, float, float]] = []
        self._start_t = self._ext_t = 0.0

    def _start_cycle(self) -> None:
        self._cycle += 1
        self._x_ref, self._start_t = self._x, self._t
        self._hered = HereditaryOperator(self.params.damping_a, self.params.damping_alpha)
        if self.params.residual_form == "paper":
            return                         # no memory: the cycle's Eq. 11 is known at its peak
        r, beta = self.params.residual_terms(self._cycle)
        for r_i, b_i in zip(r, beta):
            b_i = float(b_i)
            if b_i not in self._banks:
                self._banks[b_i] = FractionalBank(FractionalOperator(b_i, self.h_min, self.t_max), rows=0)
                self._rows[b_i] = (np.zeros(0, int), np.zeros(0), np.zeros(0))
            self._banks[b_i].add_row()
            cycles, weights, x_refs = self._rows[b_i]
            self._rows[b_i] = (np.append(cycles, self._cycle), np.append(weights, float(r_i)),
                               np.append(x_refs, self._x_ref))
        self._update_active_weights()

    def _update_active_weights(self) -> None:
        # a cycle's residual force counts from its first unloading on (paper Eq. 10)
        active = np.array(sorted(self._active_cycles), dtype=int)
        self._active_weights = {b: np.where(np.isin(cycles, active), weights, 0.0)
                                for b, (cycles, weights, _) in self._rows.items()}

    def step(self, t: float, x: float) -> ComponentForces:
        if self._t is None:
            self._t, self._x, self._ext_x, self._ext_t = t, x, x, t
            return ComponentForces(float(elastic_force(self.params, x)), 0.0, 0.0, 0, 0)
        h = t - self._t
        # turning-point detection (same rule as history.label_history)
        if self._state in (0, -1) and x > self._ext_x + self.deadband:
            self._start_cycle()            # cycle starts at the previous sample (the minimum)
            self._state = 1
        elif self._state == 1 and x < self._ext_x - self.deadband:
            self._state = -1
            if self.params.residual_form == "paper":
                r, beta = self.params.residual_terms(self._cycle)
                self._static.append((r, beta, self._x_ref, self._ext_x - self._x_ref,
                                     self._ext_t - self._start_t))
            self._active_cycles.add(self._cycle)
            self._update_active_weights()
            self._damping = 0.0
        if (self._state == 1 and x >= self._ext_x) or (self._state != 1 and x <= self._ext_x):
            self._ext_x, self._ext_t = x, t
        elif self._state == 0 and x < self._ext_x:
            self._ext_x, self._ext_t = x, t
        if self._state == 1 and self._hered is not None:
            self._damping = self._hered.step(h, x - self._x_ref)
        residual = 0.0
        for b, bank in self._banks.items():
            values = bank.step(h, x - self._rows[b][2])
            residual += float(self._active_weights[b] @ values)
        for r, beta, x_ref, stroke, loading_s in self._static:
            residual += float(static_residual(r, beta, [x - x_ref], stroke, loading_s)[0])
        self._t, self._x = t, x
        damping = self._damping if self._state == 1 else 0.0
        return ComponentForces(float(elastic_force(self.params, x)), damping, residual,
                               self._state, self._cycle)


def stepped_force(params: ModelParameters, t: np.ndarray, x: np.ndarray, t_max: float = 2e4) -> np.ndarray:
    """The model's total force at each instant of a piecewise-linear path x(t), stepped one node
    at a time as the simulator steps its specimen (SpecimenState; its own step length each)."""
    state = SpecimenState(params, t_max=max(t_max, float(t[-1] - t[0]) if len(t) else 0.0))
    return np.array([state.step(float(ti), float(xi)).total for ti, xi in zip(t, x)])
