"""The run file is the run's record: what the engine knew (each sample's step and cycle, the
method itself, the machine profile, the schedule's statistics, how the run ended) is written by
the recorder, read back by load_run, and the cycles of a run come from its labels - a run whose
displacement alone would be cut into other cycles keeps the engine's and says so once.

The samples are written here, as numbers, not made by foamlab's model or simulator."""

from __future__ import annotations

import numpy as np
import pytest

from foamlab.analysis.prepared import prepare
from foamlab.importers import load_run
from foamlab.methods import METHOD_KEY, cycle_spans, load_method, method_of_run, method_record
from foamlab.reporting.content import schedule_summary
from foamlab.rundata import RunData, Specimen
from foamlab.runformat import END_KEY, PROFILE_KEY, SCHEDULE_KEY, is_run_file_path
from foamlab.storage.recorder import Recorder
from foamlab.storage.runfile import write_run_file
from tests.hil_support import finish, inprocess_engine, machine_at_start, short_method

METHOD_TOML = """\
name = "record-test"
title = "three cycles, the second a shallow one"
sampling_hz = 10.0

[contact]
preload_N = 0.5
search_speed_mm_min = 20.0
max_search_mm = 30.0

[[sequence]]
label = "cycle"
steps = [
  { action = "compress", strain = 0.20, speed_mm_min = 24.0 },
  { action = "return", speed_mm_min = 24.0 },
  { action = "compress", strain = 0.10, speed_mm_min = 24.0 },
  { action = "dwell", duration_s = 2.0 },
  { action = "return", speed_mm_min = 24.0 },
  { action = "compress", strain = 0.20, speed_mm_min = 24.0 },
  { action = "return", speed_mm_min = 24.0 },
]
"""

SCHEDULE = {"samples": 0, "missed": 3, "missed_waiting_device": 1, "lateness_p99_ms": 1.25,
            "lateness_max_ms": 4.5}


def ramp(start: float, stop: float, n: int) -> list[float]:
    """n samples moving from `start` (excluded) to `stop` (included): one step's displacement."""
    return list(start + (stop - start) * np.arange(1, n + 1) / n)


def labelled_run(second_return_to_mm: float = 0.0) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(displacement, force, step, cycle) of a 20 mm specimen: cycle 1 to 4 mm and back, cycle
    2 to 2 mm, a 20-sample dwell, back to `second_return_to_mm`, then cycle 3 to 4 mm and back."""
    spans = [(0, 1, 0.0, 4.0, 40), (1, 1, 4.0, 0.0, 40), (2, 2, 0.0, 2.0, 20), (3, 2, 2.0, 2.0, 20),
             (4, 2, 2.0, second_return_to_mm, 20), (5, 3, second_return_to_mm, 4.0, 40),
             (6, 3, 4.0, 0.0, 40)]
    x, steps, cycles = [0.0], [0], [1]
    for step, cycle, a, b, n in spans:
        x += ramp(a, b, n)
        steps += [step] * n
        cycles += [cycle] * n
    x = np.asarray(x)
    loading = np.concatenate(([True], np.diff(x) > 0))
    force = 12.0 * x + 0.8 * x ** 2 + np.where(loading, 2.0, 0.0) * (x > 0)   # stiffer going in
    return x, force, np.asarray(steps), np.asarray(cycles)


def record(tmp_path, x, force, steps, cycles, *, toml: bool = True) -> tuple[Recorder, object]:
    """A run recorded as the engine records it (header and trailer facts), its method file gone."""
    method_file = tmp_path / "record-test.toml"
    method_file.write_text(METHOD_TOML)
    method = load_method(method_file)
    method_file.unlink()                    # the method file moved: the run must not need it
    header = {"method": method.name, "specimen": Specimen("R1", 20.0, 50.0, 50.0), "machine": "bench",
              "sampling_hz": 10.0, "method_file": str(method_file), METHOD_KEY: method_record(method),
              PROFILE_KEY: "sim-modbus-tcp"}
    recorder = Recorder(tmp_path / "runs", run_name="record")
    recorder.open(header)
    for i, (xi, fi, si, ci) in enumerate(zip(x, force, steps, cycles)):
        recorder.record(i / 10.0, float(xi), float(fi), 0.5, int(si), int(ci))
    recorder.finish("aborted", "stopped by the operator",
                    facts={SCHEDULE_KEY: {**SCHEDULE, "samples": len(x)}, END_KEY: "stop"})
    return recorder, method


def test_a_recorded_run_round_trips_its_labels_method_profile_schedule_and_end(tmp_path):
    x, force, steps, cycles = labelled_run()
    recorder, method = record(tmp_path, x, force, steps, cycles)
    run = load_run(recorder.path)
    assert is_run_file_path(recorder.path)
    np.testing.assert_array_equal(run.step, steps)
    np.testing.assert_array_equal(run.cycle, cycles)
    assert method_of_run(run) == method                   # from the file: its TOML is gone
    assert run.metadata[PROFILE_KEY] == "sim-modbus-tcp"
    assert run.metadata[SCHEDULE_KEY] == {**SCHEDULE, "samples": len(x)}
    assert (run.status, run.abort_reason, run.metadata[END_KEY]) == ("aborted", "stopped by the operator", "stop")
    summary = schedule_summary(run, method)
    assert (summary.missed, summary.missed_source) == (3, "recorded in the run file")
    # the run the analysis gets straight after acquisition is the one read back next year
    now = recorder.run_data()
    for name in ("time_s", "displacement_mm", "force_N", "step", "cycle"):
        np.testing.assert_array_equal(getattr(now, name), getattr(run, name))
    assert (now.specimen, now.method, now.machine, now.started_at, now.finished_at, now.status,
            now.abort_reason) == (run.specimen, run.method, run.machine, run.started_at, run.finished_at,
                                  run.status, run.abort_reason)
    assert {k: v for k, v in run.metadata.items() if k != "encoding"} == now.metadata


@pytest.mark.timeout(30)
def test_the_engine_hands_over_the_run_its_file_holds(tmp_path):
    """The in-process machine in virtual time: the run the window analyses at once is the file's."""
    method_file = short_method(tmp_path, strain=0.05, cycles=2, dwell_s=1.0)
    engine = inprocess_engine(machine_at_start(), method_file, tmp_path / "runs")
    result = finish(engine)
    method_file.unlink()
    on_disk = load_run(result.path)
    assert result.status == "finished" and on_disk.has_labels and result.run.has_labels
    for name in ("time_s", "displacement_mm", "force_N", "step", "cycle"):
        np.testing.assert_array_equal(getattr(result.run, name), getattr(on_disk, name))
    assert {k: v for k, v in on_disk.metadata.items() if k != "encoding"} == result.run.metadata
    assert (result.run.specimen, result.run.status, result.run.abort_reason) == \
        (on_disk.specimen, on_disk.status, on_disk.abort_reason)
    assert method_of_run(on_disk) == engine.method                  # its file is gone
    assert on_disk.metadata[PROFILE_KEY] == engine.machine.profile["name"]
    assert on_disk.metadata[SCHEDULE_KEY]["missed"] == result.missed
    assert on_disk.metadata[SCHEDULE_KEY]["samples"] == result.timing.samples
    assert on_disk.metadata[END_KEY] == result.end == "finished"
    assert sorted(set(on_disk.cycle.tolist())) == [1, 2]
    seg = on_disk.segments()
    assert seg.labelled and seg.notes == () and [c.number for c in seg.cycles] == [1, 2]


def test_labels_survive_a_slice_and_a_rewrite(tmp_path):
    x, force, steps, cycles = labelled_run()
    run = RunData(np.arange(len(x)) / 10.0, x, force, step=steps, cycle=cycles)
    part = run.slice(30, 130)
    np.testing.assert_array_equal(part.cycle, cycles[30:130])
    np.testing.assert_array_equal(run.take(x > 1.0).step, steps[x > 1.0])
    again = load_run(write_run_file(tmp_path / "copy.csv", run))
    np.testing.assert_array_equal(again.step, steps)
    np.testing.assert_array_equal(again.cycle, cycles)


def test_the_cycles_are_the_engines_labels():
    x, force, steps, cycles = labelled_run()
    run = RunData(np.arange(len(x)) / 10.0, x, force, step=steps, cycle=cycles)
    seg = run.segments()
    assert seg.labelled and seg.notes == ()
    # loading 0-40 and unloading 40-80 share their turning sample; the dwell (101-120) is a hold
    bounds = [(c.number, c.loading.start, c.loading.stop, c.unloading.start, c.unloading.stop)
              for c in seg.cycles]
    assert bounds == [(1, 0, 41, 40, 81), (2, 80, 101, 120, 141), (3, 140, 181, 180, 221)]
    assert seg.holds == [(101, 121)]


def test_a_run_whose_displacement_would_be_cut_otherwise_keeps_the_labels_and_says_so(tmp_path):
    # cycle 2 comes back only 0.1 mm (2.5 % of the 4 mm stroke): under the 5 % a reversal
    # needs in the displacement alone, which would merge cycles 2 and 3
    x, force, steps, cycles = labelled_run(second_return_to_mm=1.9)
    found = RunData(np.arange(len(x)) / 10.0, x, force).segments()
    assert found.n_cycles == 2 and not found.labelled and found.notes == ()
    recorder, _ = record(tmp_path, x, force, steps, cycles)
    run = load_run(recorder.path)
    seg = run.segments()
    assert [c.number for c in seg.cycles] == [1, 2, 3]
    assert seg.cycles[1].unloading.stop == 141 and seg.cycles[2].loading.start == 140
    assert len(seg.notes) == 1 and "3 cycles" in seg.notes[0] and "would find 2" in seg.notes[0]
    assert prepare(run).warnings.count(seg.notes[0]) == 1     # said once, in the analysis' notes


def test_a_run_file_without_labels_still_loads_and_is_segmented(tmp_path):
    x, force, _, _ = labelled_run()
    lines = ["# foamlab run file v1", "# method: record-test", "# specimen_height_mm: 20",
             "time_s,displacement_mm,force_N,rtt_ms"]
    lines += [f"{i / 10:.1f},{xi:.6f},{fi:.6f},0.5" for i, (xi, fi) in enumerate(zip(x, force))]
    lines += ["# status: finished"]
    path = tmp_path / "old.csv"
    path.write_text("\n".join(lines) + "\n")
    run = load_run(path)
    assert run.step is None and run.cycle is None and not run.has_labels
    seg = run.segments()
    assert not seg.labelled and seg.notes == () and seg.n_cycles == 3
    assert [c.loading.start for c in seg.cycles][1:] == pytest.approx([80, 140], abs=2)


def test_method_results_take_the_cycles_from_the_labels(tmp_path):
    x, force, steps, cycles = labelled_run()
    recorder, method = record(tmp_path, x, force, steps, cycles)
    run = load_run(recorder.path)
    unlabelled = RunData(run.time_s, run.displacement_mm, run.force_N, specimen=run.specimen)
    by_labels, by_plan = cycle_spans(method, run), cycle_spans(method, unlabelled)
    assert [(s.cycle, s.hold, s.unloading, s.peak_mm, s.complete) for s in by_labels] == [
        (1, (41, 41), (40, 81), 4.0, True), (2, (101, 121), (100, 141), 2.0, True),
        (3, (181, 181), (180, 221), 4.0, True)]
    # the plan's own search agrees (it starts cycle 3 one sample later, on its first move)
    assert [(s.cycle, s.hold, s.unloading, s.peak_mm) for s in by_plan] == \
        [(s.cycle, s.hold, s.unloading, s.peak_mm) for s in by_labels]
    assert [s.loading for s in by_labels] == [(0, 41), (80, 101), (140, 181)]
