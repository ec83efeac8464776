"""The diagnosis catalogue's eight causes, hidden in runs of tests/independent_model.py.

Why a second module: the hidden-effect tests and benchmarks/bench_detection_independent.py
must not hide an effect with the code that diagnosis fits (foamlab.model.effects). Each cause
is written here again from its physical definition, in this module's own arithmetic, on the
generator's closed-form components (elastic, damping, residual; either residual form, any
regime). Like the generator, it imports no foamlab model, analysis or diagnosis code
(tests/test_independent_model.py checks both modules); foamlab.rundata only hands a run over.

Sizes are physical, in the units of ``UNITS``:

* machine_compliance   frame stiffness k (N/mm): the specimen follows the triangle and the
                       crosshead (the measured displacement) travels the frame's deflection
                       F / k on top, F the specimen's force; no frame dynamics.
* direction_friction   f (N): +f while compressing, -f while releasing, where the plate is in
                       contact with the specimen; 0 before and after the motion.
* channel_lag          delay (ms): the force channel reads the force of `delay` earlier (the
                       force evaluated at t - delay, not interpolated between samples).
* memory_lag           relaxation time (ms): the damping and the residual force each pass
                       through a first-order response tau y' = u - y (scipy.signal.lsim on a
                       grid 16x finer than the samples); the elastic force is instantaneous.
* force_zero_drift     rate (N/min): the load cell's zero moves linearly from the first sample.
* cycle_softening      s (%/cycle): the elastic force of cycle c (1-based) is (1 - s)^(c - 1) of
                       the first cycle's.
* damping_cycle_change d (%/cycle): the damping force of cycle c is (1 + d (c - 1)) of the first's.
* rate_dependence      m (-): the damping force of a run at speed v is (v / v_ref)^m of the
                       model's; v_ref is the reference run's speed (one run cannot show it:
                       ``rate_pair`` gives the reference run and one at twice the speed).

Order (where each acts): the specimen's forces (softening, damping change, rate, memory lag),
friction while in contact, the plate cannot pull (max(F, 0)), the frame deflects under that
force, then the sensor (lag, zero drift), the zero offset and the generator's noise sequence:
with no cause a run is exactly ``independent_model.generate``'s (same seed, same noise).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy.signal import lsim

import independent_model as im

#: The catalogue's names (foamlab/diagnosis/causes.py) and the unit each size is given in here.
UNITS = {
    "machine_compliance": "N/mm frame",
    "direction_friction": "N",
    "channel_lag": "ms",
    "memory_lag": "ms",
    "force_zero_drift": "N/min",
    "cycle_softening": "%/cycle",
    "damping_cycle_change": "%/cycle",
    "rate_dependence": "-",
}
CAUSES = tuple(UNITS)
#: Fine grid of the memory lag's response: this many points per sample step.
OVERSAMPLE = 16


@dataclass(frozen=True)
class Hidden:
    """Causes and their sizes (UNITS) hidden in one run."""

    sizes: tuple[tuple[str, float], ...] = ()

    @classmethod
    def of(cls, causes: Mapping[str, float] | None) -> Hidden:
        unknown = set(causes or {}) - set(UNITS)
        if unknown:
            raise ValueError(f"not a catalogue cause: {', '.join(sorted(unknown))}")
        return cls(tuple((k, float(v)) for k, v in (causes or {}).items() if v))

    def get(self, name: str) -> float:
        return dict(self.sizes).get(name, 0.0)


def specimen_force(reg: im.Regime, times: np.ndarray, start_s: float, hidden: Hidden,
                   v_ref_mm_min: float) -> tuple[np.ndarray, np.ndarray]:
    """The force the specimen pushes with at `times` (clipped at 0), and the specimen's x."""
    comp = im.components(reg, times, start_s=start_s)
    h = comp.hist
    cycles_before = np.maximum(h.cycle, 0)                      # c - 1 for the 1-based cycle c
    elastic = comp.elastic * (1.0 - hidden.get("cycle_softening") / 100.0) ** cycles_before
    damping = comp.damping * (1.0 + hidden.get("damping_cycle_change") / 100.0 * cycles_before)
    damping = damping * (reg.speed_mm_min / v_ref_mm_min) ** hidden.get("rate_dependence")
    residual = comp.residual
    tau = hidden.get("memory_lag") / 1000.0
    if tau:
        system = ([1.0], [tau, 1.0])                           # 1 / (tau s + 1)
        damping = lsim(system, damping, times - times[0])[1]
        residual = lsim(system, residual, times - times[0])[1]
    total = elastic + damping + residual
    friction = hidden.get("direction_friction")
    if friction:
        moving = (times >= start_s - im.EPS_S) & (times <= h.end_s + im.EPS_S)
        direction = np.where(moving, np.where(h.loading, 1.0, -1.0), 0.0)
        total = np.where(total > 0, total + friction * direction, total)
    return np.maximum(total, 0.0), h.x


def independent_run(regime: str | im.Regime, seed: int, causes: Mapping[str, float] | None = None, *,
                    form: str | None = None, hz: float | None = None, speed_mm_min: float | None = None,
                    v_ref_mm_min: float | None = None, cycles: int | None = None):
    """One run of the regime (a name of independent_model.REGIMES or a Regime) with the causes
    {name: size in UNITS} hidden. form: the residual form ('causal' or 'paper'; the regime's
    unless given); hz: sampling rate; speed_mm_min: the run's speed (v_ref_mm_min: the reference
    speed of rate_dependence, the regime's own speed by default). Returns a RunData."""
    from foamlab.rundata import RunData, Specimen  # hand-over only, not model code

    reg = im.BY_NAME[regime] if isinstance(regime, str) else regime
    v_ref = v_ref_mm_min or reg.speed_mm_min
    changes = {k: v for k, v in (("form", form), ("sampling_hz", hz), ("speed_mm_min", speed_mm_min),
                                 ("cycles", cycles)) if v is not None}
    reg = reg.with_(**changes) if changes else reg
    hidden = Hidden.of(causes)
    clean = im.generate(reg, seed)                 # the samples, the motion's start, the noise
    t = clean.time_s
    noise = clean.force_N - clean.true_force_N
    fine_step = 1.0 / (reg.sampling_hz * OVERSAMPLE)
    fine = t[0] + fine_step * np.arange((len(t) - 1) * OVERSAMPLE + 1)
    delay = hidden.get("channel_lag") / 1000.0
    force, _ = specimen_force(reg, fine - delay, clean.start_s, hidden, v_ref)
    force = force[::OVERSAMPLE]
    x = clean.displacement_mm
    stiffness = hidden.get("machine_compliance")
    if stiffness:
        frame_force = force if not delay else specimen_force(reg, fine, clean.start_s, hidden, v_ref)[0][::OVERSAMPLE]
        x = clean.model.hist.x + frame_force / stiffness
        x = np.round(x / reg.quantum_mm) * reg.quantum_mm
    force = force + hidden.get("force_zero_drift") / 60.0 * (t - t[0])
    measured = force + reg.zero_offset_N + noise
    spec = Specimen(label=f"independent-{reg.name}-{seed}", height_mm=reg.height_mm,
                    width_mm=reg.width_mm, depth_mm=reg.depth_mm)
    return RunData(t.copy(), x.copy(), measured, specimen=spec, method="independent triangular",
                   source=f"independent_effects regime {reg.name} ({reg.form}) seed {seed} {dict(hidden.sizes)}",
                   metadata={"hidden": dict(hidden.sizes), "form": reg.form, "regime": reg.name})


def rate_pair(regime: str, seed: int, m: float, *, form: str | None = None, hz: float | None = None,
              ratio: float = 2.0) -> list:
    """rate_dependence's two runs (seeds seed, seed + 1): the regime's speed (the reference) and
    `ratio` times it, the damping of each scaled by (v / v_ref)^m."""
    v = im.BY_NAME[regime].speed_mm_min
    return [independent_run(regime, seed + i, {"rate_dependence": m}, form=form, hz=hz,
                            speed_mm_min=v * s, v_ref_mm_min=v) for i, s in enumerate((1.0, ratio))]
