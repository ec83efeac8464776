"""Run engine units: the deadline schedule (deterministic clock), safety limits, construction checks."""

from __future__ import annotations

import threading

import pytest

from drivers.profile import load_profile, open_machine
from foamlab import FoamlabError
from foamlab.acquisition import Limits, RunEngine, SampleSchedule, ScheduleStats
from foamlab.methods import load_method
from foamlab.rundata import Specimen


class FakeClock:
    """A monotonic clock the test moves; waiting on the schedule's event advances it."""

    def __init__(self):
        self.t = 100.0

    def __call__(self):
        return self.t


class ClockEvent(threading.Event):
    """wait(dt) advances the fake clock by dt instead of sleeping (never set by anyone)."""

    def __init__(self, clock: FakeClock, oversleep: float = 0.0):
        super().__init__()
        self.clock, self.oversleep = clock, oversleep

    def wait(self, timeout=None):
        self.clock.t += timeout + self.oversleep
        return False


def test_schedule_samples_on_the_deadlines():
    clock = FakeClock()
    schedule = SampleSchedule(0.0625, clock=clock, wake=ClockEvent(clock, oversleep=0.0003))
    slots = [schedule.next() for _ in range(5)]
    assert [k for k, _ in slots] == [0, 1, 2, 3, 4]
    assert slots[0][1] == 0.0                      # the first deadline is t0 itself
    assert all(late == pytest.approx(0.0003) for _, late in slots[1:])
    assert clock.t == pytest.approx(100.0 + 4 * 0.0625 + 0.0003)   # no drift: deadlines, not sleeps
    assert schedule.missed == 0


def test_a_slow_request_costs_the_deadlines_it_overran_and_they_are_counted():
    clock = FakeClock()
    schedule = SampleSchedule(0.0625, clock=clock, wake=ClockEvent(clock))
    assert schedule.next()[0] == 0
    clock.t += 0.0625 * 2.5                        # the request of sample 0 took 2.5 periods
    k, late = schedule.next()
    assert k == 2 and late == pytest.approx(0.5 * 0.0625)   # taken late in its own period
    assert schedule.missed == 1                    # deadline 1 passed entirely: missed
    clock.t += 0.01                                # a short request: no miss
    assert schedule.next()[0] == 3 and schedule.missed == 1
    schedule.miss()                                # a failed read is a miss too
    assert schedule.missed == 2


def test_each_miss_is_attributed_to_the_device_or_to_the_engine():
    clock = FakeClock()
    schedule = SampleSchedule(0.0625, clock=clock, wake=ClockEvent(clock))
    schedule.next()
    schedule.waited_for_device(0.0625 * 2.2)       # a stalled reply: 2.2 periods out
    clock.t += 0.0625 * 2.3                        # plus 0.1 period of the engine's own work
    assert schedule.next()[0] == 2                 # deadline 1 passed while the reply was out
    assert schedule.missed == 1 and schedule.missed_waiting_device == 1
    assert schedule.work_s == [pytest.approx(0.1 * 0.0625)]   # the engine's own time, waits excluded
    schedule.waited_for_device(0.001)              # a quick reply...
    clock.t += 0.0625 * 2.5                        # ...but the engine dawdled: now 4.8 periods
    assert schedule.next()[0] == 4                 # deadline 3 is the engine's loss
    assert schedule.missed == 2 and schedule.missed_waiting_device == 1
    schedule.miss()                                # a failed read: the device's
    assert schedule.missed == 3 and schedule.missed_waiting_device == 2
    stats = ScheduleStats.from_arrays(0.0625, [0.1], [1.0], schedule.missed, 1, schedule.missed_waiting_device)
    assert stats.missed_by_engine == 1


def test_schedule_wakes_early_for_a_stop_request():
    wake = threading.Event()
    schedule = SampleSchedule(10.0, wake=wake)     # the next deadline is 10 s away
    schedule.next()
    wake.set()
    assert schedule.next() is None                 # returns at once: the caller checks its flags
    assert schedule.missed == 0


def test_schedule_stats():
    stats = ScheduleStats.from_arrays(0.0625, [0.1, 0.2, 0.3, 5.0], [1.0, 1.0, 2.0, 3.0], missed=2, failed=1)
    assert stats.samples == 4 and stats.missed == 2 and stats.failed_reads == 1
    assert stats.lateness_p50_ms == pytest.approx(0.25) and stats.lateness_max_ms == 5.0
    assert stats.rtt_max_ms == 3.0
    empty = ScheduleStats.from_arrays(0.0625, [], [], 0, 0)
    assert empty.samples == 0


def test_limits_from_the_profile():
    profile = load_profile("sim-modbus-tcp")
    limits = Limits.from_profile(profile)
    assert limits == Limits(450.0, -20.0, 70.0, 500.0)
    del profile["limits"]["force_N"]               # default: 90 % of the load-cell capacity
    assert Limits.from_profile(profile).force_N == pytest.approx(0.9 * 500.0)
    with pytest.raises(FoamlabError, match="exceed the machine profile"):
        Limits(600.0, -20.0, 70.0, 500.0).within(limits)
    Limits(100.0, -10.0, 60.0, 100.0).within(limits)   # tighter is fine


def _machine():
    return open_machine(load_profile("sim-modbus-tcp"), connect=False)


def test_engine_refuses_what_it_cannot_run_safely(tmp_path):
    method = load_method("paper-3cycle")
    with pytest.raises(FoamlabError, match="specimen height"):
        RunEngine(_machine(), method, Specimen("x"), tmp_path)
    with pytest.raises(FoamlabError, match="above the speed limit"):
        RunEngine(_machine(), method, Specimen("x", 50.0), tmp_path, limits=Limits(450, -20, 70, 10.0))
    with pytest.raises(FoamlabError, match="exceed the machine profile"):
        RunEngine(_machine(), method, Specimen("x", 50.0), tmp_path, limits=Limits(490, -20, 70, 500))
    with pytest.raises(FoamlabError, match="speedup"):
        RunEngine(_machine(), method, Specimen("x", 50.0), tmp_path, speedup=0)
    engine = RunEngine(_machine(), method, Specimen("x", 72.5), tmp_path, speedup=50)
    assert engine.period_s == pytest.approx(1 / (16 * 50))
    assert engine.nominal_s == pytest.approx(6 * 58 / 23.6 * 60)
    assert engine.state == "idle"


def test_a_run_that_cannot_connect_ends_aborted_with_the_reason(tmp_path):
    # port 1 on loopback: connection refused at once; nothing was ever sent, nothing to stop
    machine = open_machine(load_profile("sim-modbus-tcp"), connect=False, port=1)
    states = []

    class Listener:
        def on_state(self, state):
            states.append(state)

    engine = RunEngine(machine, load_method("paper-3cycle"), Specimen("x", 72.5), tmp_path)
    engine.add_listener(Listener())
    engine.start()
    result = engine.wait(10)
    assert result is not None and result.status == "aborted"
    assert result.end == "link" and "cannot connect" in result.reason
    assert result.path is None and result.n_samples == 0
    assert states[0] == "connecting" and states[-1] == "aborted"
    assert not list(tmp_path.iterdir())           # no empty run file left behind
    with pytest.raises(FoamlabError, match="already been started"):
        engine.start()
