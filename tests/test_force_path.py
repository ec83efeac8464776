"""The force a frame deflects under at once, as the fits see it (path.force_path): the measured
force smoothed exactly as the displacement's path is, so the path less C times it is the path
of the displacement less the frame's deflection - whichever of the two the machine recorded."""

import numpy as np

from foamlab.analysis.path import displacement_path, force_path


def _triangle(n_half=160, hz=16.0, stroke=40.0):
    t = np.arange(4 * n_half + 1) / hz
    phase = (np.arange(len(t)) % (2 * n_half)) / n_half
    x = stroke * np.where(phase <= 1.0, phase, 2.0 - phase)
    corners = np.arange(0, len(t), n_half)
    return t, x, corners


def test_the_path_less_c_times_the_force_path_is_the_path_of_x_less_c_f():
    t, x, corners = _triangle()
    rng = np.random.default_rng(7)
    force = 200.0 * (x / x.max()) ** 3 + rng.normal(0.0, 0.15, len(t))
    c = 0.004                                              # 250 N/mm
    # a machine that records the specimen's travel plus the frame's, on a 1 um encoder
    measured = np.round((x + c * force) * 1000.0) / 1000.0
    specimen = displacement_path(t, measured, corners) - c * force_path(t, measured, force, corners)
    assert np.allclose(specimen, displacement_path(t, measured - c * force, corners), atol=1e-12)
    inside = np.ones(len(t), bool)
    inside[np.clip(np.concatenate([corners - 1, corners, corners + 1]), 0, len(t) - 1)] = False
    assert np.sqrt(np.mean((specimen - x)[inside] ** 2)) < 1e-3      # the triangle, to the encoder
    # the crosshead's path alone keeps the frame's deflection (C F: up to 0.8 mm here)
    assert np.abs(displacement_path(t, measured, corners) - x).max() > 0.5


def test_an_exact_history_keeps_its_force():
    t, x, corners = _triangle()
    force = 3.0 * x + np.sin(t)
    assert np.array_equal(force_path(t, x, force, corners), force)
