"""Synthetic compression runs with known truth, for segmentation and importer tests.

A triangular displacement history (optionally with dwells at the turning points,
a preload hold at the start and a hold at the end), a foam-like force that is
linear up to ``knee_mm`` then softens, loses contact below a residual
displacement after the first loading (the paper's recovery region), and rests
on a load-cell zero offset. Noise is Gaussian with a fixed seed.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from foamlab.rundata import RunData


@dataclass
class Truth:
    turning_times_s: list[float] = field(default_factory=list)
    half_spans_s: list[tuple[float, float]] = field(default_factory=list)  # motion only
    hold_spans_s: list[tuple[float, float]] = field(default_factory=list)


def foam_force(x: np.ndarray, knee_mm: float = 1.0, stiffness: float = 5.0) -> np.ndarray:
    """Linear to the knee, then a soft plateau that stiffens again (densification)."""
    over = np.clip(x - knee_mm, 0.0, None)
    return stiffness * np.minimum(x, knee_mm) + 0.8 * over + 0.25 * over ** 2


def triangle_run(*, cycles: int = 3, stroke_mm: float = 10.0, speed_mm_min: float = 10.0,
                 rate_hz: float = 50.0, dwell_top_s: float = 0.0, dwell_bottom_s: float = 0.0,
                 preload_hold_s: float = 0.0, end_hold_s: float = 0.0,
                 noise_mm: float = 0.0005, noise_N: float = 0.03, zero_offset_N: float = -0.2,
                 residual_mm: float = 1.0, knee_mm: float = 1.0, preload_mm: float = 0.0,
                  stop_after_halves: int | None = None,
                 start_at_top: bool = False, seed: int = 1) -> tuple[RunData, Truth]:
    rng = np.random.default_rng(seed)
    dt = 1.0 / rate_hz
    ramp_s = stroke_mm / (speed_mm_min / 60.0)
    pieces: list[tuple[str, float]] = []  # (kind, duration) kind in up/down/hold
    if preload_hold_s:
        pieces.append(("hold", preload_hold_s))
    halves = []
    for c in range(cycles):
        halves += ["up", "down"]
    if start_at_top:
        halves = ["down"] + halves
    if stop_after_halves is not None:
        halves = halves[:stop_after_halves]
    for i, kind in enumerate(halves):
        pieces.append((kind, ramp_s))
        last = i == len(halves) - 1
        if not last:
            dwell = dwell_top_s if kind == "up" else dwell_bottom_s
            if dwell:
                pieces.append(("hold", dwell))
    if end_hold_s:
        pieces.append(("hold", end_hold_s))

    truth = Truth()
    t_parts, x_parts = [], []
    t0, x0 = 0.0, stroke_mm if start_at_top else 0.0
    for kind, duration in pieces:
        m = int(round(duration / dt))
        t = t0 + dt * np.arange(m)
        slope = {"up": 1.0, "down": -1.0, "hold": 0.0}[kind] * speed_mm_min / 60.0
        t_parts.append(t)
        x_parts.append(x0 + slope * (t - t0))
        if kind == "hold":
            truth.hold_spans_s.append((t0, t0 + duration))
        else:
            truth.half_spans_s.append((t0, t0 + duration))
        t0, x0 = t0 + m * dt, x0 + slope * m * dt
    t = np.concatenate(t_parts + [np.array([t0])])
    x = np.concatenate(x_parts + [np.array([x0])])
    spans = truth.half_spans_s
    truth.turning_times_s = [b for (a, b) in spans[:-1]]

    # Force: first loading from x = 0; afterwards the specimen keeps a residual
    # compression, so the plate is off it below residual_mm.
    first_turn = spans[0][1] if not start_at_top else 0.0
    offset = np.where(t > first_turn, residual_mm, 0.0)
    compression = x + preload_mm - offset
    f = np.where(compression > 0, foam_force(np.clip(compression, 0.0, None), knee_mm), 0.0)
    x_meas = x + rng.normal(0.0, noise_mm, len(x))
    f_meas = f + zero_offset_N + rng.normal(0.0, noise_N, len(x))
    return RunData(t, x_meas, f_meas), truth
