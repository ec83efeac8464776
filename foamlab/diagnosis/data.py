"""Measured runs as diagnosis sees them (the model's path and labels, velocity, speed)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from foamlab.diagnosis.design import Series
from foamlab.diagnosis.noise import noise_sigma
from foamlab.identification.data import PathNodes, exact_history, prepare
from foamlab.model.effects import estimate_velocity, loading_rate
from foamlab.rundata import RunData

#: Samples within this many sample steps before / after a corner of the crosshead's path
#: (a turning point, or where it arrived at or left one) are not evidence, unless the force
#: is steady over that whole window: no step larger than this many noise sigmas.
CORNER_STEPS_BEFORE, CORNER_STEPS_AFTER = 1.5, 2.5
STEADY_NOISE_MULTIPLE = 4.0
#: A sample taken this far (as a fraction of the sampling step) off its schedule is left out
#: (on_schedule) when at most this share of the samples are.
OFF_SCHEDULE, RARE_OFF_SCHEDULE = 0.5, 0.02


def path_determined(t: np.ndarray, x: np.ndarray, force: np.ndarray, nodes: PathNodes,
                    noise_N: float) -> np.ndarray:
    """The samples whose model force the measured run determines.

    The crosshead stops, waits and reverses between two samples; where exactly, and how
    (it decelerates and accelerates), the samples do not say. Near a turning point the
    model's force changes by several newtons within a sample step (the damping stops, the
    residual's near-derivative memory starts), so there it depends on instants the data
    cannot resolve: measured on 16 Hz runs with the simulator's crosshead (acceleration
    ramps, random dwells), the true model driven by the estimated path misses the sample at
    the extreme by 5-9 N rms, the next two by 0.5-3 N and 0.1-0.3 N, and every other sample
    by less than the load cell's noise. Where the force is steady around a corner (the plate
    off the specimen at the end of an unloading) the instant does not matter: kept.
    These samples are predicted but not used as evidence (fits, statistics, held-out
    checks). An exact (synthetic) history has its corners at its samples: all are evidence.
    """
    t = np.asarray(t, float)
    y = np.asarray(force, float)
    n = len(t)
    used = np.ones(n, dtype=bool)
    if n < 3 or exact_history(x):
        return used
    h = float(np.median(np.diff(t)))
    step = np.abs(np.diff(y))
    steady = STEADY_NOISE_MULTIPLE * noise_N
    for tc in nodes.t[nodes.corners]:
        near = np.flatnonzero((t >= tc - CORNER_STEPS_BEFORE * h) & (t <= tc + CORNER_STEPS_AFTER * h))
        if not len(near):
            continue
        steps = step[max(near[0] - 1, 0):min(near[-1] + 1, n - 1)]     # into, inside and out of it
        if not len(steps) or steps.max() > steady:
            used[near] = False
    return used


def on_schedule(run: RunData) -> tuple[RunData, int]:
    """The run without the samples taken off its sampling schedule, and how many there were.

    A request that stalls leaves a gap, then samples bunched; the instant of the samples
    around the stall is unsure by the stall (S x its wall time on a machine run at speedup
    S). Measured on a recording with one 0.17 s stall at speedup 3: the sample after it was
    stamped 0.17 s early (its position 0.34 mm off the crosshead's line), which bent the
    estimated displacement path for a second around it and a cause was named on a clean run.
    Samples whose interval to a neighbour is off the sampling step by more than OFF_SCHEDULE
    of it are left out - only when they are rare (a regular clock that stalled): a clock
    irregular by design (logging on change) is kept as it is.
    """
    t = np.asarray(run.time_s, float)
    if len(t) < 10:
        return run, 0
    dt = np.diff(t)
    h = float(np.median(dt))
    off = np.abs(dt - h) > OFF_SCHEDULE * h
    bad = np.zeros(len(t), dtype=bool)
    bad[1:] |= off
    bad[:-1] |= off
    if not bad.any() or bad.mean() > RARE_OFF_SCHEDULE:
        return run, 0
    keep = ~bad
    return replace(run, time_s=t[keep], displacement_mm=np.asarray(run.displacement_mm)[keep],
                   force_N=np.asarray(run.force_N)[keep]), int(bad.sum())


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
