"""Measured runs as diagnosis sees them (model labels, velocity, speed)."""

from __future__ import annotations

import numpy as np

from foamlab import FoamlabError
from foamlab.diagnosis.design import Series
from foamlab.model.effects import estimate_velocity, loading_rate
from foamlab.identification.data import prepare
from foamlab.rundata import RunData


def series_from_run(run: RunData, name: str = "") -> Series:
    """Labels from the segmentation's turning points (the model switches on them)."""
    t = np.asarray(run.time_s, float)
    x = np.asarray(run.displacement_mm, float)
    y = np.asarray(run.force_N, float)
    # the turning points exactly as identification switches the model at them (the last
    # sample at each extreme, dwells included): the base model is identification's
    labels = prepare(run).labels
    velocity = estimate_velocity(t, x, labels)
    moving = np.abs(velocity) > 0.5 * np.percentile(np.abs(velocity), 95)
    speed = float(np.median(np.abs(velocity[moving]))) * 60.0 if np.any(moving) else 0.0
    return Series(name=name or run.source or "run", t=t, x=x, y=y, labels=labels,
                  velocity=velocity, rate=loading_rate(t, x, labels.starts), speed_mm_min=speed)
