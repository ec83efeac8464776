"""The simulated specimen: the model's force for the compression the crosshead imposes.

The specimen's top surface lies at `top_mm` (machine coordinates at start). The crosshead's
compression x = max(position - top, 0), through the hidden effects (foamlab.model.effects:
compliance, contact, the load cell's lag and drift), drives foamlab.model.SpecimenState - a
fitted specimen from where its elastic force is zero (surface_offset_mm). The plate cannot
pull: the effects' contact force is max(total, 0) while x > 0, else 0.
"""

from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
from scipy.optimize import brentq

from foamlab.model import ModelParameters, SpecimenState
from foamlab.model.effects import EffectChain

SPECIMEN_T_MAX_S = 1e6          # memory operators stay accurate over this much virtual time
FRAME_XTOL_MM = 1e-10           # a frame at once: the step's loop solved to this (mm)


def surface_offset_mm(params: ModelParameters) -> float:
    """Where the specimen's elastic force is zero, in its model's displacement (<= 0).

    A fitted specimen measures displacement from where the run's contact search reached
    its preload, so its elastic force at 0 is k0 ~ the preload: its top lies before 0.
    The plate touching the top is therefore at this displacement of the model (the largest
    root of the elastic polynomial below 0); 0 for a specimen whose force starts at zero
    (the default). Without it a fitted specimen would push back with k0 the instant it is
    touched, and every fit -> simulate -> fit would move the zero by the preload's travel.
    """
    k = np.asarray(params.elastic_k, float)
    if not k[0] > 0:
        return 0.0
    roots = np.roots(k[::-1]) * params.x_scale_mm          # in x / x_scale, highest power first
    real = roots[np.abs(roots.imag) <= 1e-9 * params.x_scale_mm].real
    below = real[(real < 0) & (real > -params.x_scale_mm)]
    return float(below.max()) if len(below) else 0.0


def load_specimen(specimen) -> ModelParameters:
    """ModelParameters, a fit/TOML path, or None (the default specimen)."""
    if specimen is None:
        return ModelParameters.default()
    if isinstance(specimen, ModelParameters):
        return specimen
    return ModelParameters.load(Path(specimen))


class SimSpecimen:
    """The specimen under the plate and the hidden effects between it and the load cell.

    step(t, position, velocity) brings it to t for the crosshead at `position` (physical mm)
    and returns the force the load cell senses; the intermediate quantities stay readable.
    """

    def __init__(self, params: ModelParameters, effects: EffectChain, top_mm: float):
        self.params, self.top_mm = params, float(top_mm)
        self._state = SpecimenState(params, t_max=SPECIMEN_T_MAX_S)
        self._surface_mm = surface_offset_mm(params)
        self._online = effects.online()
        self.x_crosshead_mm = 0.0     # compression the crosshead imposes (>= 0)
        self.x_specimen_mm = 0.0      # compression the specimen sees (after compliance)
        self.contact_force_N = 0.0    # plate <-> specimen
        self.sensor_force_N = 0.0     # what the load cell senses (after lag/drift)
        self.components = None        # the model's force components (cycle, direction)

    def step(self, t: float, position_mm: float, velocity_mm_s: float) -> float:
        x_cross = max(position_mm - self.top_mm, 0.0)
        if self._online.frame_at_once:
            x_s = self._online.specimen_x(t, x_cross, self._force_at_once(t, x_cross, velocity_mm_s))
        else:
            x_s = self._online.specimen_x(t, x_cross)
        comps = self._state.step(t, x_s + self._surface_mm)
        contact = self._online.contact_force(t, x_cross, x_s, comps, velocity_mm_s)
        sensor = self._online.sensor(t, contact)
        self.x_crosshead_mm, self.x_specimen_mm, self.contact_force_N = x_cross, x_s, contact
        self.sensor_force_N, self.components = sensor, comps
        return sensor

    def _force_at_once(self, t: float, x_cross: float, velocity_mm_s: float) -> float:
        """The contact force F at this step's solution of x_s = x - C F(x_s) (a frame at once).

        The step is tried on copies of the specimen's state (the loop is implicit: the force
        depends on the x_s it sets) and the root found by Brent's method between x - C F(x) and x
        (F grows with x_s); where the force does not (a turn's drop), the force at x. Costs ~10
        trial steps with their copies (~2.5 ms) per physics step: only this effect pays it."""
        c = self._online.chain.compliance

        def force(x_s: float) -> float:
            state, online = copy.deepcopy(self._state), copy.deepcopy(self._online)
            comps = state.step(t, x_s + self._surface_mm)
            return online.contact_force(t, x_cross, x_s, comps, velocity_mm_s)

        at_x = force(x_cross)
        low = x_cross - c * at_x
        gap = low - x_cross + c * force(low)
        if at_x <= 0.0 or gap >= 0.0:
            return at_x
        root = brentq(lambda z: z - x_cross + c * force(z), low, x_cross, xtol=FRAME_XTOL_MM)
        return force(root)

    @property
    def cycle(self) -> int:
        return self.components.cycle if self.components else 0

    @property
    def direction(self) -> int:
        return self.components.direction if self.components else 0
