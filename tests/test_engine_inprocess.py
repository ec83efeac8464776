"""The run engine's safety paths against the in-process simulated machine, in virtual time.

The engine and the machine share one ManualClock (simulator.inprocess): every wait of the run
moves virtual time on, so each run below - minutes of machine time - takes milliseconds and
cannot be made late by a busy computer. Each exit path must leave the crosshead at rest (the
simulated machine's own state says so), every sample on disk and the reason recorded; a
failing request is scripted on the machine's link.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from drivers.base import DeviceTimeout
from foamlab import pipeline
from foamlab.acquisition import Limits
from foamlab.acquisition.settings import DEFAULT
from foamlab.storage.runfile import read_run_file
from simulator.inprocess import InProcessMachine
from tests.hil_support import SPECIMEN, START_MM, finish, inprocess_engine, machine_at_start, short_method

pytestmark = pytest.mark.timeout(30)


def run(machine: InProcessMachine, method_path, tmp_path, *listeners, **kwargs):
    engine = inprocess_engine(machine, method_path, tmp_path, **kwargs)
    for listener in listeners:
        engine.add_listener(listener)
    return engine, finish(engine)


def assert_file_matches(result):
    """Every sample the engine took is in the file, unchanged, with the status and reason."""
    on_disk = read_run_file(result.path)
    assert on_disk.status == result.status and on_disk.abort_reason == result.reason
    assert len(on_disk) == result.n_samples == len(result.run)
    np.testing.assert_array_equal(on_disk.displacement_mm, result.run.displacement_mm)
    np.testing.assert_array_equal(on_disk.force_N, result.run.force_N)
    assert on_disk.metadata.get("safety", "") == result.safety
    return on_disk


def assert_at_rest(machine: InProcessMachine):
    state = machine.sim.crosshead_status()
    assert not state.moving, state
    return state


class At:
    """Listener: calls `action()` once, from the run's own thread, when the displacement passes `mm`."""

    def __init__(self, mm: float, action):
        self.mm, self.action, self.fired, self.samples = mm, action, False, 0

    def on_sample(self, sample):
        self.samples += 1
        if sample.displacement_mm >= self.mm and not self.fired:
            self.fired = True
            self.action()


def test_a_run_finishes_keeps_every_deadline_and_parks(tmp_path):
    machine = machine_at_start()
    progress = []
    engine, result = run(machine, short_method(tmp_path, strain=0.05, speed=100.0, cycles=2), tmp_path,
                         type("P", (), {"on_progress": lambda self, p: progress.append(p)})())
    assert result.status == "finished" and result.end == "finished", result.reason
    # progress on the run's clock: every 0.25 s of machine time through ~8.7 s, then 1
    fractions = [p.fraction for p in progress if p.state == "running"]
    assert 30 <= len(fractions) <= 40 and fractions == sorted(fractions) and progress[-1].fraction == 1.0
    assert result.park == f"parked at {START_MM:.3f} mm"
    assert machine.sim.position_mm() == pytest.approx(START_MM, abs=0.003)
    assert result.missed == 0 and result.safety == ""
    assert_at_rest(machine)
    on_disk = assert_file_matches(result)
    # 16 Hz of machine time: two cycles of 2 x 3.625 mm at 100 mm/min, ~8.7 s and ~140 samples
    assert np.diff(on_disk.time_s) == pytest.approx(1 / 16)
    assert on_disk.displacement_mm.max() == pytest.approx(0.05 * SPECIMEN.height_mm, abs=0.01)
    assert {v.cycle for v in pipeline.method_stage(pipeline.Analysis(result.run, result.path),
                                                   engine.method).method_results.values if v.cycle} == {1, 2}


def test_a_broken_listener_does_not_stop_the_run(tmp_path, caplog):
    class Broken:
        def on_sample(self, sample):
            raise RuntimeError("display bug")

    finished = []
    machine = machine_at_start()
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.02, speed=100.0, cycles=1), tmp_path)
    engine.add_listener(Broken())
    engine.add_listener(type("L", (), {"on_finished": lambda self, r: finished.append(r)})())
    result = finish(engine)
    assert result.status == "finished" and finished == [result]
    assert result.n_samples > 20
    assert sum("display bug" in str(r.exc_info) or "Broken" in r.getMessage() for r in caplog.records) == 1
    assert_at_rest(machine)
    assert_file_matches(result)


def test_operator_stop_keeps_the_data_and_parks(tmp_path):
    machine = machine_at_start()
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path)
    listener = At(5.0, lambda: engine.request_stop("stopped by the test"))
    engine.add_listener(listener)
    result = finish(engine)
    assert result.status == "aborted" and result.reason == "stopped by the test" and result.end == "stop"
    assert result.park == f"parked at {START_MM:.3f} mm"
    state = assert_at_rest(machine)
    assert not state.fault and not state.emergency_stop
    # the stop came with the first sample past 5 mm: 23.6 mm/min is 0.025 mm per sample
    assert 5.0 <= result.run.displacement_mm.max() < 5.03
    assert listener.samples == result.n_samples
    assert_file_matches(result)


def test_emergency_stop_latches_and_does_not_park(tmp_path):
    machine = machine_at_start()
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path)
    stops_before = []

    def estop():
        stops_before.append(machine.requests["stop"])       # the contact search's stop
        engine.emergency_stop()

    engine.add_listener(At(4.0, estop))
    result = finish(engine)
    assert result.status == "aborted" and result.end == "estop" and "emergency stop" in result.reason
    state = assert_at_rest(machine)
    assert state.emergency_stop and state.fault
    assert result.park.startswith("not parked after estop")
    assert machine.requests["stop"] == stops_before[0]     # an e-stop is never downgraded to a stop
    # an e-stop halts at once: the plate stands where the last sample saw it
    position = machine.sim.position_mm()
    assert position == pytest.approx(result.contact_position_mm + result.run.displacement_mm[-1], abs=0.03)
    assert_file_matches(result)


def test_force_limit_stops_at_once_keeps_the_crossing_sample_and_parks(tmp_path):
    machine = machine_at_start()
    limits = Limits(force_N=30.0, travel_upper_mm=-20.0, travel_lower_mm=70.0, max_speed_mm_min=500.0)
    _, result = run(machine, short_method(tmp_path, strain=0.5, speed=100.0, cycles=1), tmp_path, limits=limits)
    assert result.status == "aborted" and result.end == "limit"
    assert result.reason.startswith("force limit 30 N reached")
    assert result.run.force_N[-1] >= 30.0 > result.run.force_N[-2]
    assert result.park == f"parked at {START_MM:.3f} mm"      # a limit stop parks (the load is removed)
    assert_at_rest(machine)
    assert_file_matches(result)


def test_a_method_beyond_the_travel_limit_is_refused_at_contact(tmp_path):
    machine = machine_at_start()
    limits = Limits(force_N=450.0, travel_upper_mm=-20.0, travel_lower_mm=20.0, max_speed_mm_min=500.0)
    _, result = run(machine, short_method(tmp_path, strain=0.5, cycles=1), tmp_path, limits=limits)
    assert result.status == "aborted" and result.end == "limit"
    assert "beyond the lower travel limit 20 mm" in result.reason
    assert result.n_samples == 0 and result.path is None          # stopped at contact, before any step
    assert result.park == f"parked at {START_MM:.3f} mm"
    assert_at_rest(machine)


def test_the_drive_reaching_its_travel_limit_ends_the_run(tmp_path):
    """The drive's own soft limit, set inside the run's: its limit bit ends the run, the file says so."""
    machine = machine_at_start()
    # the engine sets the drive's limits to the run's before it moves; the operator (or a wrong
    # profile) narrows them once the run is under way: the drive stops AT its limit
    _, result = run(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path,
                    At(2.0, lambda: machine.sim.set_travel_limits(-20.0, START_MM + 3.0)))
    assert result.status == "aborted" and result.end == "limit"
    assert result.reason == "crosshead reached its lower travel limit"
    # the drive stopped at its limit: the last sample saw it there (the park then took it back)
    assert result.contact_position_mm + result.run.displacement_mm[-1] == pytest.approx(START_MM + 3.0, abs=0.03)
    assert result.park == f"parked at {START_MM:.3f} mm"
    assert_at_rest(machine)
    assert_file_matches(result)


def test_load_cell_overload_stops_without_parking(tmp_path):
    machine = machine_at_start(faults=["overload@12"])
    _, result = run(machine, short_method(tmp_path, strain=0.3, cycles=1), tmp_path)
    assert result.status == "aborted" and result.end == "overload"
    assert result.reason.startswith("load cell overload (over-range)")
    assert result.park.startswith("not parked after overload")
    assert result.n_samples > 50
    assert_at_rest(machine)
    assert_file_matches(result)


def test_a_stalled_crosshead_is_a_fault_named_by_the_drive(tmp_path):
    machine = machine_at_start(faults=["stall@12"])
    _, result = run(machine, short_method(tmp_path, strain=0.3, cycles=1), tmp_path)
    assert result.status == "aborted" and result.end == "fault"
    assert "stall" in result.reason, result.reason
    assert result.park.startswith("not parked after fault")
    assert result.n_samples > 50
    assert_at_rest(machine)
    assert_file_matches(result)


def test_one_lost_reading_is_a_missed_deadline_and_the_run_goes_on(tmp_path):
    machine = machine_at_start()
    missed = At(1.0, lambda: machine.fail("read", DeviceTimeout("no reply to a reading")))
    _, result = run(machine, short_method(tmp_path, strain=0.05, speed=100.0, cycles=1), tmp_path, missed)
    assert result.status == "finished", result.reason
    assert result.missed == 1 and result.timing.failed_reads == 1
    assert result.timing.missed_waiting_device == 1       # the device's loss, not the engine's
    assert_file_matches(result)


def test_replies_lost_while_preparing_are_asked_again_and_the_run_goes_on(tmp_path):
    # CI stop 55: one status reply lost to a loaded computer before the first sample (2 x 40 ms
    # over Modbus TCP) ended a run that every later request would have survived
    machine = machine_at_start()
    machine.fail("status", DeviceTimeout("no reply to status"))
    machine.fail("position", DeviceTimeout("no reply to position"))
    _, result = run(machine, short_method(tmp_path, strain=0.05, speed=100.0, cycles=1), tmp_path)
    assert result.status == "finished", result.reason
    assert "1 crosshead status poll(s) failed" not in result.safety     # prepare's read was asked again
    assert_at_rest(machine)
    assert_file_matches(result)


def test_readings_lost_in_a_row_end_the_run(tmp_path):
    machine = machine_at_start()
    lost = At(1.0, lambda: machine.fail("read", DeviceTimeout("no reply to a reading"), DEFAULT.max_failed_reads + 1))
    _, result = run(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path, lost)
    assert result.status == "aborted" and result.end == "fault"
    assert result.reason == "device not answering: no reply to a reading"
    assert result.park.startswith("not parked after fault")
    assert_at_rest(machine)
    assert_file_matches(result)


def test_status_polls_failing_in_a_row_end_the_run_and_are_said(tmp_path):
    machine = machine_at_start()
    lost = At(1.0, lambda: machine.fail("status", DeviceTimeout("no reply to status"), DEFAULT.max_failed_status_polls))
    _, result = run(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path, lost)
    assert result.status == "aborted" and result.end == "fault"
    assert result.reason.startswith(f"crosshead status unreadable ({DEFAULT.max_failed_status_polls} polls in a row)")
    assert result.safety.startswith(f"{DEFAULT.max_failed_status_polls} crosshead status poll(s) failed")
    assert_at_rest(machine)
    assert_file_matches(result)


def test_a_stop_that_is_not_acknowledged_falls_back_to_the_emergency_stop(tmp_path):
    machine = machine_at_start()
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path)

    def stop_unanswered():
        machine.fail("stop", DeviceTimeout("no reply to stop"), times=100)
        engine.request_stop("stopped by the test")

    engine.add_listener(At(3.0, stop_unanswered))
    result = finish(engine)
    assert result.status == "aborted" and result.end == "stop"
    assert result.safety.startswith("emergency stopped after 1 failed attempt(s): no reply to stop")
    state = assert_at_rest(machine)
    assert state.emergency_stop                          # the e-stop did what the stop could not
    assert result.park.startswith("park failed") or result.park.startswith("park stopped")
    assert_file_matches(result)


def test_a_crosshead_not_confirmed_at_rest_is_emergency_stopped_and_said(tmp_path):
    machine = machine_at_start()
    engine = inprocess_engine(machine, short_method(tmp_path, strain=0.2, cycles=1), tmp_path)

    def stop_unanswered_then_status_lost():
        machine.fail("status", DeviceTimeout("no reply to status"), times=10_000)
        engine.request_stop("stopped by the test")

    # the status polls fail from here: the run ends on them or on the stop, whichever comes first;
    # either way the stop cannot be confirmed, so the e-stop is sent and the note says why
    engine.add_listener(At(3.0, stop_unanswered_then_status_lost))
    result = finish(engine)
    assert result.status == "aborted"
    assert "crosshead not confirmed at rest" in result.safety and "status unreadable: no reply to status" in result.safety
    assert "emergency stop sent" in result.safety
    assert_at_rest(machine)
    assert machine.sim.crosshead_status().emergency_stop
    assert_file_matches(result)


def test_the_in_process_machine_answers_as_a_driver():
    machine = machine_at_start(noise_sigma_N=0.0)
    machine.crosshead.move_to(START_MM + 1.0, 60.0)
    machine.clock.advance(0.5)
    sample = machine.read_sample()                  # force and position at one instant of the machine
    assert sample.position_mm == machine.sim.snapshot().position_mm and sample.time == machine.clock.now()
    assert machine.crosshead.status().moving
    machine.fail("status", DeviceTimeout("no reply to status"))
    with pytest.raises(DeviceTimeout, match="no reply to status"):
        machine.crosshead.status()
    assert machine.crosshead.status().moving        # the scripted failure was used up
    with pytest.raises(ValueError, match="unknown request 'bogus'"):
        machine.fail("bogus", DeviceTimeout("x"))
    machine.crosshead.emergency_stop()
    status = machine.crosshead.status()
    assert status.emergency_stopped and status.fault and machine.crosshead.fault_reason() == "emergency"
    machine.crosshead.move_to(START_MM, 60.0)       # refused while latched, as a drive ignores it
    assert not machine.crosshead.status().moving
    assert machine.requests["status"] == 5 and machine.requests["move"] == 2


def test_closing_a_session_stops_a_moving_crosshead_whose_status_reply_was_lost():
    """safety.bring_to_rest (a session's close): a status that cannot be read is taken as moving -
    the stop is sent all the same (before: one lost reply left a jogging crosshead moving, a warning
    logged) - and the crosshead is confirmed at rest."""
    from foamlab.acquisition.safety import bring_to_rest

    machine = InProcessMachine(speedup=50.0, noise_sigma_N=0.02)
    try:
        machine.crosshead.jog(-1, 100.0)          # up, away from the specimen
        assert machine.sim.crosshead_status().moving
        machine.fail("status", DeviceTimeout("no reply to status"))
        assert bring_to_rest(machine, replace(DEFAULT, stop_confirm_s=5.0)) == ""
        assert machine.requests["stop"] == 1 and machine.requests["estop"] == 0
        assert_at_rest(machine)
    finally:
        machine.sim.close()
