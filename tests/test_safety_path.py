"""Errors in the safety path are never swallowed (issue 24, item 4): a failed status poll, a stop
that is not acknowledged and a crosshead not confirmed at rest each end in a one-line reason - in
the run's result, its file's trailer and on screen - and the motion is stopped.

A scripted crosshead stands in for the drive: each test says exactly which request fails."""

from __future__ import annotations

import threading

import pytest

from drivers.base import CrossheadStatus, DeviceRefused, DeviceTimeout
from foamlab.acquisition.engine import safety_note
from foamlab.acquisition.events import RunAborted
from foamlab.acquisition.safety import CrossheadWatch, Stopper
from foamlab.acquisition.settings import DEFAULT, AcquisitionSettings
from foamlab.storage.runfile import RunWriter, read_run_file


class ScriptedCrosshead:
    """status() and the stops follow a script: each call pops its next outcome (an exception is raised)."""

    def __init__(self, status=(), stop=(), estop=()):
        self.script = {"status": list(status), "stop": list(stop), "estop": list(estop)}
        self.calls: list[str] = []

    def _next(self, name, default):
        self.calls.append(name)
        outcome = self.script[name].pop(0) if self.script[name] else default
        if isinstance(outcome, Exception):
            raise outcome
        return outcome

    def status(self):
        return self._next("status", CrossheadStatus())

    def stop(self):
        self._next("stop", None)

    def emergency_stop(self):
        self._next("estop", None)


class Machine:
    def __init__(self, crosshead):
        self.crosshead = crosshead

    def connect(self):
        pass


MOVING = CrossheadStatus(moving=True)
#: The stop confirmed (or not) within 50 ms instead of the default's seconds.
QUICK_CONFIRM = AcquisitionSettings(stop_confirm_s=0.05)


def test_a_crosshead_still_moving_after_the_stop_is_said_and_emergency_stopped():
    crosshead = ScriptedCrosshead(status=[MOVING] * 1000)
    note = Stopper(Machine(crosshead), threading.Event(), settings=QUICK_CONFIRM).confirm_at_rest()
    assert note.startswith("crosshead not confirmed at rest") and "still reports motion" in note
    assert "emergency stop sent" in note and crosshead.calls[-1] == "estop"


def test_an_unreadable_status_after_the_stop_is_said_not_taken_for_rest():
    crosshead = ScriptedCrosshead(status=[DeviceTimeout("no reply to status")] * 1000,
                                  estop=[DeviceTimeout("no reply to e-stop")])
    note = Stopper(Machine(crosshead), threading.Event(), settings=QUICK_CONFIRM).confirm_at_rest()
    assert "status unreadable: no reply to status" in note and "emergency stop failed: no reply to e-stop" in note


def test_a_crosshead_at_rest_is_confirmed_without_a_note():
    crosshead = ScriptedCrosshead(status=[MOVING, CrossheadStatus()])
    assert Stopper(Machine(crosshead), threading.Event()).confirm_at_rest() == ""
    assert "estop" not in crosshead.calls


def test_a_stop_that_is_not_acknowledged_falls_back_to_the_emergency_stop_and_says_so():
    crosshead = ScriptedCrosshead(stop=[DeviceTimeout("no reply to stop")])
    note = Stopper(Machine(crosshead), threading.Event()).stop()
    assert note.startswith("emergency stopped after 1 failed attempt") and "no reply to stop" in note
    assert safety_note(note, "", "") == note       # the stop went unanswered: said, though the e-stop was
    assert safety_note("stopped", "", "") == ""
    failed = "stop and emergency stop failed (4 attempts): no reply"
    assert safety_note(failed, "", "") == failed   # never acknowledged: said


def test_the_device_refusing_a_status_poll_ends_the_run_at_once():
    watch = CrossheadWatch(Machine(ScriptedCrosshead(status=[DeviceRefused("unit 2 refused: exception 0x02")])))
    with pytest.raises(RunAborted, match="crosshead status refused: unit 2 refused") as info:
        watch.read()
    assert info.value.kind == "fault"


def test_failed_status_polls_are_counted_said_and_end_the_run_when_they_persist():
    failures = [DeviceTimeout(f"no reply {i}") for i in range(DEFAULT.max_failed_status_polls)]
    watch = CrossheadWatch(Machine(ScriptedCrosshead(status=[failures[0], CrossheadStatus(), *failures])))
    assert watch.read() is None                         # one failure: counted, the run goes on
    assert watch.read() == CrossheadStatus()
    for _ in range(DEFAULT.max_failed_status_polls - 1):
        assert watch.read() is None
    with pytest.raises(RunAborted, match=f"unreadable \\({DEFAULT.max_failed_status_polls} polls in a row\\)"):
        watch.read()
    polls = DEFAULT.max_failed_status_polls + 1
    assert watch.note().startswith(f"{polls} crosshead status poll(s) failed, first: no reply 0")


def test_the_safety_note_is_in_the_run_file_trailer(tmp_path):
    path = tmp_path / "run.csv"
    writer = RunWriter(path, {"specimen": "x"})
    writer.write_sample(0.0, 0.0, 0.1)
    writer.write_sample(0.0625, 0.01, 0.2)
    writer.finish("aborted", "device not answering", safety="crosshead not confirmed at rest within 2 s")
    run = read_run_file(path)
    assert run.status == "aborted" and run.metadata["safety"] == "crosshead not confirmed at rest within 2 s"


def test_the_watch_obeys_the_settings_it_is_given():
    # acquisition.settings passed explicitly: one failed poll ends the run when the settings say so
    strict = AcquisitionSettings(max_failed_status_polls=1)
    watch = CrossheadWatch(Machine(ScriptedCrosshead(status=[DeviceTimeout("no reply")])), settings=strict)
    with pytest.raises(RunAborted, match=r"unreadable \(1 polls in a row\)"):
        watch.read()
