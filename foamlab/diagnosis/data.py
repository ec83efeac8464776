"""Measured runs as diagnosis sees them (the model's path and labels, velocity, speed)."""

from __future__ import annotations

import numpy as np

from foamlab.diagnosis.design import Series
from foamlab.diagnosis.noise import noise_sigma
from foamlab.identification.data import PathNodes, exact_history, prepare
from foamlab.model.effects import estimate_velocity, loading_rate
from foamlab.rundata import RunData

#: Samples within this many sample steps before / after a corner of the crosshead's path
#: (a turning point, or where it arrived at or left one) are judged only where the force is
#: steady: where it changes from a neighbouring sample by at most this many noise sigmas.
CORNER_STEPS_BEFORE, CORNER_STEPS_AFTER = 1.5, 2.5
STEADY_NOISE_MULTIPLE = 4.0


def path_determined(t: np.ndarray, x: np.ndarray, force: np.ndarray, nodes: PathNodes,
                    noise_N: float) -> np.ndarray:
    """The samples whose model force the measured displacement determines.

    The crosshead stops, waits and reverses between two samples; where exactly, and how
    (it decelerates and accelerates), the samples do not say. Near a turning point the
    model's force changes by several newtons within a sample step (the damping stops, the
    residual's near-derivative memory starts), so there it depends on instants the data
    cannot resolve: measured on 16 Hz runs with the simulator's crosshead (acceleration
    ramps, random dwells), the true model driven by the estimated path misses the sample at
    the extreme by 5-9 N rms, the next two by 0.5-3 N and 0.1-0.3 N, and every other sample
    by less than the load cell's noise. Those samples are predicted but not used as evidence
    (fits, statistics, held-out checks). Where the force is steady near a corner (the plate
    off the specimen at the end of an unloading) the instant does not matter: kept. An
    exact (synthetic) history has its corners at its samples: every sample is evidence.
    """
    t = np.asarray(t, float)
    y = np.asarray(force, float)
    n = len(t)
    used = np.ones(n, dtype=bool)
    if n < 3 or exact_history(x):
        return used
    h = float(np.median(np.diff(t)))
    near = np.zeros(n, dtype=bool)
    for tc in nodes.t[nodes.corners]:
        near |= (t >= tc - CORNER_STEPS_BEFORE * h) & (t <= tc + CORNER_STEPS_AFTER * h)
    step = np.abs(np.diff(y))
    change = np.maximum(np.concatenate([[0.0], step]), np.concatenate([step, [0.0]]))
    used[near & (change > STEADY_NOISE_MULTIPLE * noise_N)] = False
    return used


def series_from_run(run: RunData, name: str = "") -> Series:
    """The run with identification's path, labels and corner nodes (the base model is identification's)."""
    t = np.asarray(run.time_s, float)
    y = np.asarray(run.force_N, float)
    # the model as identification drives it: the displacement path (the measured one without
    # its noise, with the corners the crosshead turns at between samples) and the turning
    # points where the model switches (the last sample at each extreme, dwells included)
    fd = prepare(run)
    labels, x = fd.labels, fd.nodes.at_samples
    velocity = estimate_velocity(t, x, labels)
    moving = np.abs(velocity) > 0.5 * np.percentile(np.abs(velocity), 95)
    speed = float(np.median(np.abs(velocity[moving]))) * 60.0 if np.any(moving) else 0.0
    return Series(name=name or run.source or "run", t=t, x=x, y=y, labels=labels, nodes=fd.nodes,
                  x_measured=np.asarray(run.displacement_mm, float),
                  evidence=path_determined(t, run.displacement_mm, y, fd.nodes, noise_sigma(y)),
                  no_contact=np.asarray(fd.seg.contact_lost, bool),
                  velocity=velocity, rate=loading_rate(t, x, labels.starts), speed_mm_min=speed)
