"""Runs with a known hidden effect, for tests, the detection benchmark and the docs.

The paper's protocol (triangular cycles), or any test method's nominal history
(foamlab.methods.Method.history), through the model, an effect chain of
foamlab.model.effects (batch form: the simulator's arithmetic), white load-cell noise
and, optionally, a disturbance outside the catalogue (a periodic force).
"""

from __future__ import annotations

from typing import Mapping

import numpy as np

from foamlab.methods import Method
from foamlab.model import ModelParameters, label_history, triangular_history
from foamlab.model.effects import EffectChain, make_effects
from foamlab.rundata import RunData, Specimen

#: Load-cell noise of the synthetic runs (N, 1 sigma): ~0.1 % of the default specimen's peak force.
NOISE_N = 0.2


def hidden_effect_run(effects: Mapping[str, float] | EffectChain | None = None, *,
                      params: ModelParameters | None = None, amplitude_mm: float | None = None,
                      speed_mm_min: float = 23.6, cycles: int = 3, sampling_hz: float | None = None,
                      noise_N: float = NOISE_N, seed: int = 0,
                      periodic_N: float = 0.0, period_s: float = 30.0,
                      method: Method | None = None, height_mm: float | None = None) -> RunData:
    """A run with `effects` hidden: the paper's triangular cycles (amplitude, speed, cycles;
    16 Hz by default) or, given a method, its nominal history for a specimen of height_mm
    (at the method's sampling rate by default). height_mm is the run's specimen height."""
    params = params or ModelParameters.default()
    if method is not None:
        if not height_mm:
            raise ValueError("a run of a method needs the specimen height")
        t, x = method.history(height_mm, sampling_hz)
    else:
        amplitude = params.x_scale_mm if amplitude_mm is None else amplitude_mm
        t, x = triangular_history(amplitude, speed_mm_min / 60.0, cycles, sampling_hz or 16.0)
    chain = make_effects(effects)
    force = chain.measured_force(params, t, x, labels=label_history(x))
    rng = np.random.default_rng(seed)
    force = force + rng.normal(0.0, noise_N, len(t))
    if periodic_N:
        force = force + periodic_N * np.sin(2 * np.pi * t / period_s + rng.uniform(0, 2 * np.pi))
    return RunData(t, x, force, specimen=Specimen(height_mm=height_mm),
                   method=method.name if method is not None else "",
                   source=f"synthetic {dict(effects or {})} seed {seed}",
                   metadata={"hidden_effects": {e.name: e.values for e in chain.effects},
                             "noise_N": noise_N, "periodic_N": periodic_N})
