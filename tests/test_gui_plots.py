"""The live plots on their own (offscreen): segmentation into per-cycle curves,
incremental updates, buffer growth, export."""

from __future__ import annotations

import os

os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")

import numpy as np
import pytest

from foamlab.gui.plots import LOADING, UNLOADING, LivePlots, PhaseTracker, SampleBuffer, cycle_pen

pytestmark = [pytest.mark.gui, pytest.mark.timeout(60)]


def triangular(n_cycles=3, per_half=200, stroke=10.0, noise=0.0, seed=0):
    up = np.linspace(0, stroke, per_half, endpoint=False)
    down = np.linspace(stroke, 0, per_half, endpoint=False)
    x = np.concatenate([np.concatenate([up, down]) for _ in range(n_cycles)])
    x = x + np.random.default_rng(seed).normal(0, noise, len(x))
    t = np.arange(len(x)) / 16.0
    f = 3 * x + x**2 / 10
    return t, x, f


@pytest.fixture
def plots(qtbot):
    widget = LivePlots()
    qtbot.addWidget(widget)
    widget.resize(900, 400)
    widget.show()
    return widget


def test_unlabelled_samples_become_one_curve_per_half_cycle(plots):
    t, x, f = triangular(noise=0.01)
    plots.clear(expected_samples=len(t))
    for i in range(0, len(t), 37):            # arrive in frames, like the engine's samples
        plots.add_samples(t[i:i + 37], x[i:i + 37], f[i:i + 37])
        plots.refresh()
    labels = [(s.cycle, s.phase) for s in plots.segments]
    assert labels == [(c, p) for c in (1, 2, 3) for p in (LOADING, UNLOADING)]
    assert plots.sample_count == len(t)
    assert plots.plotted_points() == len(t)
    ft_x, ft_y = plots.ft_curve.getData()
    np.testing.assert_array_equal(ft_x, t)
    np.testing.assert_array_equal(ft_y, f)
    # Consecutive curves share their joint sample: the drawn line has no gap.
    for a, b in zip(plots.segments, plots.segments[1:]):
        xa, _ = a.curve.getData()
        xb, _ = b.curve.getData()
        assert xa[-1] == xb[0]


def test_a_frame_touches_only_the_growing_curve_and_force_time(plots):
    t, x, f = triangular()
    plots.add_samples(t[:700], x[:700], f[:700])
    plots.refresh()
    plots.add_samples(t[700:720], x[700:720], f[700:720])
    assert plots.refresh() == 2                # growing half-cycle + force-time, nothing else
    assert plots.refresh() == 0                # nothing new, nothing redrawn


def test_labels_given_by_the_engine_are_used_as_is(plots):
    t, x, f = triangular(n_cycles=1)
    n = len(t)
    cycles = [4] * n
    phases = [LOADING] * (n // 2) + ["dwell"] * 10 + [UNLOADING] * (n - n // 2 - 10)
    plots.add_samples(t, x, f, cycles, phases)
    plots.refresh()
    assert [(s.cycle, s.phase) for s in plots.segments] == [(4, LOADING), (4, "dwell"), (4, UNLOADING)]


def test_buffer_grows_past_its_capacity_without_losing_samples():
    buffer = SampleBuffer(capacity=8)
    data = np.arange(100, dtype=float)
    for i in range(0, 100, 7):
        buffer.extend(data[i:i + 7], -data[i:i + 7], 2 * data[i:i + 7])
    assert buffer.n == 100 and buffer.capacity >= 100
    np.testing.assert_array_equal(buffer.time_s[:100], data)
    np.testing.assert_array_equal(buffer.force_N[:100], 2 * data)


def test_phase_tracker_ignores_noise_smaller_than_its_deadband():
    tracker = PhaseTracker(deadband_mm=0.05)
    wiggle = [0.0, 0.02, 0.01, 0.03, 0.02, 1.0, 0.99, 0.97, 0.5, 0.52, 0.51, 0.8]
    labels = [tracker.update(v) for v in wiggle]
    assert labels[:8] == [(1, LOADING)] * 8
    assert labels[8:11] == [(1, UNLOADING)] * 3
    assert labels[11] == (2, LOADING)


def test_pens_distinguish_cycles_and_unloading():
    assert cycle_pen(1, LOADING).color() != cycle_pen(2, LOADING).color()
    assert cycle_pen(1, LOADING).style() != cycle_pen(1, UNLOADING).style()


def test_export_png_and_fit_overlay(plots, tmp_path):
    t, x, f = triangular()
    plots.show_run(t, x, f)
    plots.show_fit(t, x, f * 1.01)
    assert plots.fit_fd is not None and plots.fit_ft is not None
    out = tmp_path / "plot.png"
    plots.export_png(str(out), width=800)
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    plots.clear()
    assert plots.fit_fd is None and plots.sample_count == 0 and not plots.segments
