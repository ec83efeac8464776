"""Segmentation into cycles/half-cycles, contact loss and the first-cycle linear region."""

from __future__ import annotations

import numpy as np
import pytest

from foamlab import FoamlabError
from foamlab.rundata import RunData
from foamlab.segmentation import LOADING, UNLOADING, segment
from tests.synthetic import triangle_run


def _time_of(run, index):
    return float(run.time_s[index])


def test_three_triangular_cycles_with_noise():
    run, truth = triangle_run(noise_mm=0.002, noise_N=0.05)
    seg = segment(run)
    assert seg.n_cycles == 3
    assert len(seg.turning_points) == 5
    found = run.time_s[seg.turning_points]
    assert np.allclose(found, truth.turning_times_s, atol=0.5), (found, truth.turning_times_s)
    halves = seg.half_cycles
    assert [h.direction for h in halves] == [LOADING, UNLOADING] * 3
    assert [h.cycle for h in halves] == [1, 1, 2, 2, 3, 3]
    # time order, contiguous, sharing the turning-point sample
    assert halves[0].start == 0 and halves[-1].stop == len(run)
    for a, b in zip(halves, halves[1:]):
        assert b.start == a.stop - 1
    for cycle in seg.cycles:
        t, x, f = seg.arrays(cycle.loading)
        assert np.all(np.diff(t) > 0)
        assert x[-1] - x[0] > 9.5
        t, x, f = seg.arrays(cycle.unloading)
        assert x[0] - x[-1] > 9.5
    assert seg.holds == []
    assert seg.stroke_mm == pytest.approx(10.0, abs=0.1)


def test_noise_larger_than_usual_does_not_create_cycles():
    # 0.1 mm displacement noise (1 % of the stroke) and 0.5 N force noise
    run, truth = triangle_run(noise_mm=0.1, noise_N=0.5, seed=7)
    seg = segment(run)
    assert seg.n_cycles == 3
    assert np.allclose(run.time_s[seg.turning_points], truth.turning_times_s, atol=3.0)


def test_dwells_preload_hold_and_end_hold_are_left_out():
    run, truth = triangle_run(dwell_top_s=5, dwell_bottom_s=3, preload_hold_s=4, end_hold_s=6)
    seg = segment(run)
    assert seg.n_cycles == 3
    assert len(seg.holds) == len(truth.hold_spans_s)
    for (a, b), (ta, tb) in zip(seg.holds, truth.hold_spans_s):
        assert _time_of(run, a) == pytest.approx(ta, abs=1.0)
        assert _time_of(run, b - 1) == pytest.approx(tb, abs=1.0)
    for half, (ta, tb) in zip(seg.half_cycles, truth.half_spans_s):
        assert _time_of(run, half.start) == pytest.approx(ta, abs=1.0)
        assert _time_of(run, half.stop - 1) == pytest.approx(tb, abs=1.0)
    # a half-cycle never contains a dwell: the plate moves all along
    for half in seg.half_cycles:
        t, x, _ = seg.arrays(half)
        assert abs(x[-1] - x[0]) > 9.0


def test_run_ending_during_second_loading():
    run, _ = triangle_run(stop_after_halves=3)
    seg = segment(run)
    assert seg.n_cycles == 2
    assert seg.cycles[1].unloading is None
    assert [h.label for h in seg.half_cycles] == [
        "cycle 1 loading", "cycle 1 unloading", "cycle 2 loading"]


def test_run_starting_at_the_top_has_a_leading_unloading():
    run, _ = triangle_run(start_at_top=True, cycles=2, residual_mm=0.0)
    seg = segment(run)
    assert seg.leading_unloading is not None and seg.leading_unloading.cycle == 0
    assert seg.half_cycles[0] is seg.leading_unloading
    assert seg.n_cycles == 2


def test_single_half_cycle_is_enough():
    run, _ = triangle_run(stop_after_halves=1)
    seg = segment(run)
    assert seg.n_cycles == 1 and seg.cycles[0].unloading is None
    assert len(seg.turning_points) == 0


def test_contact_loss_found_in_recovery_region():
    run, _ = triangle_run(residual_mm=1.0, zero_offset_N=-0.2, noise_N=0.03)
    seg = segment(run)
    assert seg.contact_zero_N == pytest.approx(-0.2, abs=0.05)
    spans = seg.contact_lost_spans
    # end of cycles 1 and 2 unloading + start of cycles 2 and 3 loading, and end of cycle 3
    assert len(spans) == 3
    for k, (a, b) in enumerate(spans[:2]):
        bottom = seg.turning_points[2 * k + 1]
        assert a < bottom < b
        # the plate is off the specimen below the residual compression (1 mm)
        assert run.displacement_mm[a] == pytest.approx(1.0, abs=0.15)
        assert run.displacement_mm[b - 1] == pytest.approx(1.0, abs=0.15)
    assert spans[2][1] == len(run)
    # nothing before the first loss: the first loading is in contact from the start
    assert not seg.contact_lost[: spans[0][0]].any()
    t, x, f = seg.arrays(seg.cycles[1].loading, in_contact_only=True)
    assert x.min() == pytest.approx(1.0, abs=0.15)


def test_no_contact_loss_when_preload_is_kept():
    run, _ = triangle_run(residual_mm=0.0, preload_mm=1.0, zero_offset_N=0.0)
    seg = segment(run)
    assert not seg.contact_lost.any()


def test_linear_region_ends_at_the_knee():
    for knee in (0.5, 1.0, 2.0):
        run, _ = triangle_run(knee_mm=knee, noise_N=0.03)
        seg = segment(run)
        a, b = seg.first_cycle_linear_region
        assert run.displacement_mm[a] < 0.1
        assert run.displacement_mm[b - 1] == pytest.approx(knee, rel=0.35), knee


def test_linear_region_without_noise():
    run, _ = triangle_run(knee_mm=1.5, noise_N=0.0, noise_mm=0.0)
    a, b = segment(run).first_cycle_linear_region
    assert run.displacement_mm[b - 1] == pytest.approx(1.5, rel=0.25)


def test_any_sampling_rate():
    for rate in (2.0, 1000.0):
        run, truth = triangle_run(rate_hz=rate, cycles=2)
        seg = segment(run)
        assert seg.n_cycles == 2
        assert np.allclose(run.time_s[seg.turning_points], truth.turning_times_s,
                           atol=max(2.0 / rate, 0.5))


def test_no_motion_is_a_clear_error():
    t = np.arange(500) * 0.02
    run = RunData(t, np.full(500, 3.0) + np.random.default_rng(0).normal(0, 1e-3, 500),
                  np.ones(500))
    with pytest.raises(FoamlabError, match="no motion"):
        segment(run)


def test_too_few_samples_and_nan_are_clear_errors():
    with pytest.raises(FoamlabError, match="too few"):
        segment(RunData([0, 1], [0, 1], [0, 1]))
    with pytest.raises(FoamlabError, match="NaN"):
        segment(RunData([0, 1, 2, 3], [0, 1, np.nan, 3], [0, 1, 2, 3]))


def test_rundata_segments_shortcut():
    run, _ = triangle_run(cycles=1)
    assert run.segments().n_cycles == 1
