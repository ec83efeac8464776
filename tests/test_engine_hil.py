"""Run engine exit paths against the simulated machine (Modbus TCP, real drivers): operator
stop, emergency stop, force and travel limits, a broken listener. Every path must leave the
crosshead at rest, the samples on disk and the reason recorded."""

from __future__ import annotations

import threading

import numpy as np
import pytest

from foamlab import pipeline
from foamlab.acquisition import Limits
from foamlab.storage.runfile import read_run_file
from tests.hil_support import approach, machine_for, make_engine, short_method, simulated, wait_at_rest

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]

SPEEDUP = 10.0


def _assert_file_matches(result):
    """Every sample the engine took is in the file, unchanged, with the status and reason."""
    on_disk = read_run_file(result.path)
    assert on_disk.status == result.status
    assert on_disk.abort_reason == result.reason
    assert len(on_disk) == result.n_samples == len(result.run)
    np.testing.assert_allclose(on_disk.time_s, result.run.time_s, atol=1e-9)
    np.testing.assert_allclose(on_disk.displacement_mm, result.run.displacement_mm, atol=1e-9)
    np.testing.assert_allclose(on_disk.force_N, result.run.force_N, atol=1e-9)
    return on_disk


class StopAfter:
    """Listener that calls `action` once the displacement passes `mm` (from the worker thread)."""

    def __init__(self, mm, action):
        self.mm, self.action, self.fired = mm, action, threading.Event()
        self.samples = 0

    def on_sample(self, sample):
        self.samples += 1
        if sample.displacement_mm >= self.mm and not self.fired.is_set():
            self.fired.set()
            threading.Thread(target=self.action).start()   # as the GUI does, from another thread


def test_operator_stop_keeps_the_data_and_parks(tmp_path):
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, short_method(tmp_path, strain=0.2, cycles=1), tmp_path, speedup=SPEEDUP)
        listener = StopAfter(5.0, lambda: engine.request_stop("stopped by the test"))
        engine.add_listener(listener)
        result = engine.run()
        status = wait_at_rest(sim)
    assert result.status == "aborted" and result.reason == "stopped by the test" and result.end == "stop"
    assert result.park.startswith("parked at")
    assert status["fault"] is False and status["emergency_stop"] is False
    assert 5.0 <= result.run.displacement_mm.max() < 6.0    # stopped right after the request
    assert listener.samples == result.n_samples
    _assert_file_matches(result)
    assert pipeline.method_stage(pipeline.Analysis(result.run, result.path), engine.method).method_results is not None


def test_emergency_stop_latches_and_does_not_park(tmp_path):
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, short_method(tmp_path, strain=0.2, cycles=1), tmp_path, speedup=SPEEDUP)
        engine.add_listener(StopAfter(4.0, engine.emergency_stop))
        result = engine.run()
        status = wait_at_rest(sim)
        position = sim.snapshot()["position_mm"]
    assert result.status == "aborted" and result.end == "estop"
    assert "emergency stop" in result.reason
    assert status["emergency_stop"] is True and status["fault"] is True
    assert result.park.startswith("not parked")
    assert position == pytest.approx(result.contact_position_mm + result.run.displacement_mm[-1], abs=0.1)
    _assert_file_matches(result)


def test_force_limit_stops_at_once_and_marks_the_run(tmp_path):
    limits = Limits(force_N=30.0, travel_upper_mm=-20.0, travel_lower_mm=70.0, max_speed_mm_min=500.0)
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, short_method(tmp_path, strain=0.5, speed=100.0, cycles=1), tmp_path,
                             speedup=SPEEDUP, limits=limits)
        result = engine.run()
        wait_at_rest(sim)
    assert result.status == "aborted" and result.end == "limit"
    assert result.reason.startswith("force limit 30 N reached")
    assert result.run.force_N[-1] >= 30.0 > result.run.force_N[-2]   # the sample that crossed it is kept
    assert result.park.startswith("parked at")                      # a limit stop parks (load removed)
    _assert_file_matches(result)


def test_travel_limit_refuses_a_method_that_would_cross_it(tmp_path):
    limits = Limits(force_N=450.0, travel_upper_mm=-20.0, travel_lower_mm=20.0, max_speed_mm_min=500.0)
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, short_method(tmp_path, strain=0.5, cycles=1), tmp_path, speedup=SPEEDUP,
                             limits=limits)
        result = engine.run()
        wait_at_rest(sim)
    assert result.status == "aborted" and result.end == "limit"
    assert "beyond the lower travel limit 20 mm" in result.reason
    assert result.n_samples == 0 and result.path is None         # stopped at contact, before any step


def test_a_broken_listener_does_not_stop_the_run(tmp_path, caplog):
    class Broken:
        def on_sample(self, sample):
            raise RuntimeError("display bug")

    finished = []
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        engine = make_engine(sim, short_method(tmp_path, strain=0.02, speed=100.0, cycles=1), tmp_path,
                             speedup=SPEEDUP)
        engine.add_listener(Broken())
        engine.add_listener(type("L", (), {"on_finished": lambda self, r: finished.append(r)})())
        result = engine.run()
        wait_at_rest(sim)
    assert result.status == "finished" and finished == [result]
    assert sum("display bug" in str(r.exc_info) or "Broken" in r.getMessage() for r in caplog.records) == 1
    _assert_file_matches(result)


def test_a_run_made_with_a_method_file_finds_its_method_again(tmp_path):
    """A method file that is not built in: the run file records it, so the method's results
    are computed after the run from the file alone (the window, `foamlab report`, a series)."""
    methods = tmp_path / "methods"
    methods.mkdir()
    method_file = short_method(methods, strain=0.05, speed=100.0, cycles=2, name="lab-own")
    with simulated(speedup=SPEEDUP) as sim:
        approach(machine_for(sim))
        result = make_engine(sim, method_file, tmp_path, speedup=SPEEDUP).run()
        wait_at_rest(sim)
    assert result.status == "finished", result.reason
    on_disk = _assert_file_matches(result)
    assert on_disk.method == "lab-own" and on_disk.metadata["method_file"] == str(method_file.resolve())
    analysis = pipeline.method_stage(pipeline.Analysis(on_disk, result.path))
    assert analysis.method_error == "" and analysis.method_results is not None
    assert {v.cycle for v in analysis.method_results.values if v.cycle} == {1, 2}
    method_file.rename(methods / "elsewhere.toml")
    gone = pipeline.method_stage(pipeline.Analysis(on_disk, result.path))
    assert gone.method_results is None
    assert "unknown method 'lab-own'" in gone.method_error and str(method_file.resolve()) in gone.method_error
    assert "\n" not in gone.method_error
