"""Measured runs as diagnosis sees them (segmentation -> model labels, velocity, speed)."""

from __future__ import annotations

import numpy as np

from foamlab import FoamlabError
from foamlab.diagnosis.design import Series
from foamlab.model.effects import estimate_velocity, loading_rate
from foamlab.model.history import labels_from_extrema
from foamlab.rundata import RunData
from foamlab.segmentation import segment


def series_from_run(run: RunData, name: str = "") -> Series:
    """Labels from the segmentation's turning points (the model switches on them)."""
    seg = segment(run)
    if not seg.cycles:
        raise FoamlabError("diagnosis needs at least one loading half-cycle; the run has none")
    t = np.asarray(run.time_s, float)
    x = np.asarray(run.displacement_mm, float)
    y = np.asarray(run.force_N, float)
    starts = [c.loading.start for c in seg.cycles]
    peaks = [c.loading.stop - 1 for c in seg.cycles]
    labels = labels_from_extrema(len(t), starts, peaks)
    velocity = estimate_velocity(t, x, labels)
    moving = np.abs(velocity) > 0.5 * np.percentile(np.abs(velocity), 95)
    speed = float(np.median(np.abs(velocity[moving]))) * 60.0 if np.any(moving) else 0.0
    return Series(name=name or run.source or "run", t=t, x=x, y=y, labels=labels,
                  velocity=velocity, rate=loading_rate(t, x, labels.starts), speed_mm_min=speed)
