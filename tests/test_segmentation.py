"""Segmentation into cycles/half-cycles, contact loss and the first-cycle linear region."""

from __future__ import annotations

from pathlib import Path

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


@pytest.mark.parametrize("preload_mm", [1.0, 0.1])
def test_no_contact_loss_when_preload_is_kept(preload_mm):
    # 0.1 mm keeps 0.5 N, under 2 % of the peak force: low, but it follows the plate
    run, _ = triangle_run(residual_mm=0.0, preload_mm=preload_mm, zero_offset_N=0.0)
    seg = segment(run)
    assert not seg.contact_lost.any()
    assert seg.contact_zero_N == 0.0


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


# --------------------------------------------------------------------------- the real file
# tests/data/real/Specimen_RawData_6.csv (Instron Bluehill, CC0; see PROVENANCE.md).
# Reference values read from the file itself: the crosshead reverses at samples
# 3004 / 6005 / 9006 / 12008 / 15009 (extremes of -Extension: 60.04 s, 120.04 s,
# 180.04 s, 240.06 s, 300.06 s); the controller's Segment ID column switches
# 0.25-0.4 s later (60.40, 120.38, 180.40, 240.42, 300.30 s). After each unloading
# the load sits at -0.24 +- 0.03 N (load-cell zero) from ~113 s to ~124.7 s,
# ~229.5 s to ~247.4 s and ~347.4 s to the end.

REAL = Path(__file__).parent / "data" / "real" / "Specimen_RawData_6.csv"


@pytest.fixture(scope="module")
def real():
    from foamlab.importers import load_run

    run = load_run(REAL)
    return run, segment(run)


def test_real_file_turning_points(real):
    run, seg = real
    assert seg.n_cycles == 3
    assert len(seg.turning_points) == 5
    assert list(seg.turning_points) == [3004, 6005, 9006, 12008, 15009]
    assert np.allclose(run.time_s[seg.turning_points], [60.04, 120.04, 180.04, 240.06, 300.06],
                       atol=1e-4)
    # reversals at the file's displacement extremes: 10.0 mm (top) and 0.0 mm (bottom)
    assert np.allclose(run.displacement_mm[seg.turning_points], [10.0, 0.0, 10.0, 0.0, 10.0],
                       atol=0.01)
    assert [h.label for h in seg.half_cycles] == [
        f"cycle {c} {d}" for c in (1, 2, 3) for d in (LOADING, UNLOADING)]
    assert seg.holds == []


def test_real_file_first_loading_and_linear_region(real):
    run, seg = real
    first = seg.cycles[0].loading
    assert first.start == 0 and run.time_s[first.stop - 1] == pytest.approx(60.04, abs=0.1)
    a, b = seg.first_cycle_linear_region
    # starts once the plate moves (preload start: the force settles for 3 samples)
    assert run.time_s[a] == pytest.approx(0.1, abs=0.05)
    # ends where the first loading bends away from its initial line: 1.1-1.6 mm
    # (the paper: where later cycles regain contact, here 0.77 and 1.23 mm)
    assert 1.1 <= run.displacement_mm[b - 1] <= 1.6
    slope = np.polyfit(run.displacement_mm[a:b], run.force_N[a:b], 1)[0]
    assert slope == pytest.approx(5.0, abs=0.3)


def test_real_file_contact_loss_at_start_of_cycles_2_and_3(real):
    run, seg = real
    assert seg.contact_zero_N == pytest.approx(-0.235, abs=0.03)
    assert -0.2 < seg.contact_threshold_N < 0.1
    spans = seg.contact_lost_spans
    assert len(spans) == 3
    times = [(run.time_s[a], run.time_s[b - 1]) for a, b in spans]
    assert times[0] == pytest.approx((113.0, 124.7), abs=0.6)
    assert times[1] == pytest.approx((229.5, 247.4), abs=0.6)
    assert times[2][0] == pytest.approx(347.4, abs=0.6) and spans[2][1] == len(run)
    # spans 1 and 2 run from the end of an unloading into the start of the next loading
    for (a, b), cycle in zip(spans[:2], seg.cycles[1:]):
        assert a < cycle.loading.start < b
        assert seg.cycle_of(b - 1) == cycle.number
    # the plate regains contact at 0.77 mm (cycle 2) and 1.23 mm (cycle 3)
    assert run.displacement_mm[spans[0][1] - 1] == pytest.approx(0.77, abs=0.1)
    assert run.displacement_mm[spans[1][1] - 1] == pytest.approx(1.23, abs=0.1)
    assert not seg.contact_lost[: spans[0][0]].any()
