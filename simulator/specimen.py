"""The simulated specimen: the model's force for the compression the crosshead imposes.

The specimen's top surface lies at `top_mm` (machine coordinates at start). The crosshead's
compression x = max(position - top, 0), through the hidden effects (foamlab.model.effects:
compliance, contact, the load cell's lag and drift), drives foamlab.model.SpecimenState - a
fitted specimen from where its elastic force is zero (surface_offset_mm). The plate cannot
pull: the effects' contact force is max(total, 0) while x > 0, else 0.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from foamlab.model import ModelParameters, SpecimenState
from foamlab.model.effects import EffectChain

SPECIMEN_T_MAX_S = 1e6          # memory operators stay accurate over this much virtual time


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
        x_s = self._online.specimen_x(t, x_cross)
        comps = self._state.step(t, x_s + self._surface_mm)
        contact = self._online.contact_force(t, x_cross, x_s, comps, velocity_mm_s)
        sensor = self._online.sensor(t, contact)
        self.x_crosshead_mm, self.x_specimen_mm, self.contact_force_N = x_cross, x_s, contact
        self.sensor_force_N, self.components = sensor, comps
        return sensor

    @property
    def cycle(self) -> int:
        return self.components.cycle if self.components else 0

    @property
    def direction(self) -> int:
        return self.components.direction if self.components else 0
