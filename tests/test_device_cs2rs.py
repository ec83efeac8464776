"""Leadshine CS2RS transcripts, written from its manuals (S1 CS2RS Modbus manual §5.5.4 p.43: PR0 at
0x6200..0x6207 and the 0x6002 trigger; S3/S4 §4.3-4.4: 0x1003, 0x1801, 0x2203, exceptions; S5 §4.3.1:
pulses/rev at 0x0001) and the profile's screw: lead 4 mm, gear 10, 10 000 pulses/rev, so 1 mm =
25 000 pulses and 23.6 mm/min = 59 rpm; 50 mm/s^2 = 133 ms per 1000 rpm.

Unit 2 on the RTU line; CRCs computed here and checked by two routines (rtu_transcript.frame) -
except the two frames quoted from the manual, whose printed CRCs are right (the notes list the
ones that are not). Each transcript runs against the driver and against the simulator.
"""

from __future__ import annotations

import struct

import pytest

from drivers.base import Crosshead, CrossheadStatus, DeviceRefused
from drivers.cs2rs import DeviceMismatch, EmergencyStopLatched
from drivers.profile import load_profile, open_machine
from recorded_peer import rtu
from rtu_transcript import driver_on, frame, rtu_profile, simulated

pytestmark = pytest.mark.timeout(30)

READ_PPR = "02 03 00 01 00 01 D5 F9"                   # Pr0.00 pulses/rev (0x0001)
PPR_10000 = "02 03 02 27 10 E6 78"
# move_to(10 mm, 23.6 mm/min): PR0 = mode 0x0001 absolute, position 250 000 = 0x0003:0xD090 (high
# word first), 59 rpm = 0x003B, accel = decel = 133 = 0x0085 ms/1000 rpm; one FC16 of 6 registers.
MOVE_10MM = "02 10 62 00 00 06 0C 00 01 00 03 D0 90 00 3B 00 85 00 85 7F 3B"
PR0_WRITTEN = "02 10 62 00 00 06 5F 80"
START_PR0 = "02 06 60 02 00 10 37 F5"                  # 0x6002 = 0x0010: start path 0
QUICK_STOP = "02 06 60 02 00 40 37 C9"                 # 0x6002 = 0x0040
SET_ZERO = "02 06 60 02 00 21 F6 21"                   # 0x6002 = 0x0021: present position := 0
RESET_ALARM = "02 06 18 01 11 11 12 C5"                # 0x1801 = 0x1111
READ_STATUS = "02 03 10 03 00 01 70 F9"
READ_POSITION = "02 03 60 2C 00 02 1B F1"              # motor position 0x602C/0x602D
READ_ALARM = "02 03 22 03 00 01 7E 41"


# ----------------------------------------------------------------------------- (a) the driver

def test_connect_reads_pulses_per_rev_and_refuses_another_value():
    with driver_on([(READ_PPR, PPR_10000)], connect=True):
        pass
    with pytest.raises(DeviceMismatch, match=r"pulses_per_rev \(0x0001\) reads 4000 pulse/rev, the profile "
                                             r"says 10000") as info:
        with driver_on([(READ_PPR, "02 03 02 0F A0 F9 CC")], connect=True):
            pass
    assert "\n" not in str(info.value)


def test_move_to_writes_pr0_then_triggers_path_0():
    with driver_on([(MOVE_10MM, PR0_WRITTEN), (START_PR0, START_PR0)]) as machine:
        machine.crosshead.move_to(10.0, 23.6)


def test_jog_is_a_bounded_absolute_move_to_the_travel_limit():
    # down: to the lower limit 70 mm = 1 750 000 = 0x001A:0xB3F0; up: to -20 mm = -500 000 = 0xFFF8:0x5EE0;
    # 50 mm/min = 125 rpm = 0x007D
    # (first the position: a jog from beyond its limit would move the other way, and is refused)
    exchanges = [(READ_POSITION, "02 03 04 00 03 D0 90 64 9F"),                       # at 10 mm
                 ("02 10 62 00 00 06 0C 00 01 00 1A B3 F0 00 7D 00 85 00 85 77 5F", PR0_WRITTEN),
                 (START_PR0, START_PR0),
                 (READ_POSITION, "02 03 04 00 03 D0 90 64 9F"),
                 ("02 10 62 00 00 06 0C 00 01 FF F8 5E E0 00 7D 00 85 00 85 4C 18", PR0_WRITTEN),
                 (START_PR0, START_PR0),
                 (READ_POSITION, "02 03 04 00 1A B3 F0 9D 80")]                       # at 70 mm: the limit
    with driver_on(exchanges) as machine:
        machine.crosshead.jog(+1, 50.0)
        machine.crosshead.jog(-1, 50.0)
        with pytest.raises(ValueError, match=r"jog down refused: the crosshead is at 70.000 mm, at or beyond "
                                             r"the travel limit 70 mm"):
            machine.crosshead.jog(+1, 50.0)


def test_stop_estop_reset_and_zero_write_their_documented_values():
    exchanges = [(QUICK_STOP, QUICK_STOP), (QUICK_STOP, QUICK_STOP), (RESET_ALARM, RESET_ALARM),
                 (SET_ZERO, SET_ZERO)]
    with driver_on(exchanges) as machine:
        crosshead = machine.crosshead
        crosshead.stop()
        crosshead.emergency_stop()
        with pytest.raises(EmergencyStopLatched):        # the driver holds it: nothing is sent
            crosshead.move_to(5.0, 50.0)
        crosshead.reset_fault()
        crosshead.set_zero()


def test_status_position_and_alarm_decode():
    exchanges = [(READ_STATUS, "02 03 02 00 06 7C 46"),                 # enabled + running
                 (READ_STATUS, "02 03 02 00 32 7D 91"),                 # enabled + command done + path done
                 (READ_POSITION, "02 03 04 00 03 D0 90 64 9F"),         # 250 000 pulses
                 (READ_STATUS, "02 03 02 00 01 3D 84"),                 # fault
                 (READ_ALARM, "02 03 02 01 80 FC 74")]                  # 0x0180
    with driver_on(exchanges) as machine:
        crosshead = machine.crosshead
        assert crosshead.status() == CrossheadStatus(moving=True)
        assert crosshead.status() == CrossheadStatus(in_position=True)
        assert crosshead.read_position() == pytest.approx(10.0, abs=1e-12)
        assert crosshead.status() == CrossheadStatus(fault=True)
        assert crosshead.fault_reason().startswith("alarm 0x0180: position following error")


def test_an_exception_reply_is_device_refused_naming_the_register_in_the_drives_words():
    with driver_on([(MOVE_10MM, PR0_WRITTEN), (START_PR0, "02 86 03 F2 61")]) as machine:
        with pytest.raises(DeviceRefused, match=r"unit 2 refused write of trigger \(0x6002\) = 0x0010 \(start_path0\): "
                                                r"Modbus exception 0x03 \(wrong data") as info:
            machine.crosshead.move_to(10.0, 23.6)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("target, speed, message", [
    (10.0, 0.5, r"0.5 mm/min is 1.250 rpm at the motor; the drive takes whole rpm \(pr0_speed \(0x6203\)\): "
                r"1 rpm = 0.4 mm/min, 20.0 % off"),
    (10.0, 23.5, r"23.5 mm/min is 58.750 rpm .* 59 rpm = 23.6 mm/min, 0.4 % off"),    # within 1 %: taken
    (10.0, 600.0, r"600 mm/min outside \(0, 500\]"),
    (70.5, 50.0, r"target 70.5 mm outside the travel limits \[-20, 70\] mm"),
])
def test_speeds_the_drive_cannot_hold_and_targets_beyond_the_limits_are_refused_before_sending(target, speed, message):
    machine = open_machine(load_profile("sim-modbus-rtu"), connect=False)
    if "0.4 % off" in message:
        assert machine.crosshead.rpm(speed) == 59
        return
    with pytest.raises(ValueError, match=message):
        machine.crosshead.move_to(target, speed)


class _Wire:
    """An in-memory link: every write recorded, reads answer zeros."""

    where = "memory"

    def __init__(self):
        import threading
        self.lock = threading.RLock()
        self.writes: list[tuple[int, list[int]]] = []

    def read_words(self, unit, address, count, label, meanings=None):
        return [0x2710] if address == 0x0001 else [0] * count

    def write_words(self, unit, address, words, label, meanings=None, single=True, repeatable=False):
        self.writes.append((address, list(words)))


def test_0x0021_to_0x6002_is_written_by_set_zero_and_nothing_else():
    """On a real CS2RS, 0x21 at 0x6002 sets the present position to zero (the invented map used it as a jog)."""
    from drivers.cs2rs import Cs2rsCrosshead
    from drivers.modbus import device_map

    profile = load_profile("sim-modbus-rtu")
    wire = _Wire()
    device = device_map(profile, "crosshead")
    crosshead = Cs2rsCrosshead(wire, device, profile["crosshead"], profile["limits"])
    calls = {"move_to": (5.0, 50.0), "jog": (1, 50.0), "set_travel_limits": (-10.0, 60.0), "check_device": (device,)}
    public = {name for name in dir(crosshead) if not name.startswith("_") and callable(getattr(crosshead, name))}
    assert set(Crosshead.__abstractmethods__) <= public
    for name in sorted(public - {"set_zero"}):
        method = getattr(crosshead, name)
        args = calls.get(name, (50.0,) if name in ("rpm", "pulses") else ())
        try:
            method(*args)
        except TypeError:
            pytest.fail(f"add {name}'s arguments to this test")
        crosshead._estop_latched = False
    crosshead.jog(-1, 50.0)
    assert (0x6002, [0x0021]) not in wire.writes, wire.writes
    crosshead.set_zero()
    assert wire.writes[-1] == (0x6002, [0x0021])


# ----------------------------------------------------------------------------- (b) the simulator

def test_the_simulator_moves_as_written_and_reports_it():
    with simulated() as (machine, clock, wire):
        assert wire.ask(frame(READ_PPR), 7) == frame(PPR_10000)
        assert wire.ask(frame(MOVE_10MM), 8) == frame(PR0_WRITTEN)
        assert not machine.crosshead_status().moving                        # nothing before the trigger
        assert wire.ask(frame(START_PR0), 8) == frame(START_PR0)
        assert wire.ask(frame(READ_STATUS), 7) == frame("02 03 02 00 06 7C 46")   # enabled + running
        assert machine.speed_mm_min() == pytest.approx(0.0)               # starting: the ramp begins
        clock.advance(1.0)
        assert machine.speed_mm_min() == pytest.approx(23.6)              # 59 rpm x 0.4 mm/min
        clock.advance(30.0)
        assert wire.ask(frame(READ_STATUS), 7) == frame("02 03 02 00 32 7D 91")   # command + path done
        assert wire.ask(frame(READ_POSITION), 9) == frame("02 03 04 00 03 D0 90 64 9F")
        assert wire.ask(frame(SET_ZERO), 8) == frame(SET_ZERO)
        assert wire.ask(frame(READ_POSITION), 9) == frame("02 03 04 00 00 00 00 C9 33")
        assert machine.position_mm() == 0.0


def test_the_simulator_quick_stops_and_an_alarm_is_reset():
    with simulated(faults=["stall@2"]) as (machine, clock, wire):
        wire.ask(frame(MOVE_10MM), 8)
        wire.ask(frame(START_PR0), 8)
        clock.advance(1.0)
        assert wire.ask(frame(QUICK_STOP), 8) == frame(QUICK_STOP)
        assert not machine.crosshead_status().moving
        assert wire.ask(frame(READ_STATUS), 7) == frame("02 03 02 00 12 7C 49")   # enabled + command done
        wire.ask(frame(START_PR0), 8)                                       # not latched: the path runs again
        clock.advance(3.0)                                                  # the stall at 2 s: following error
        assert wire.ask(frame(READ_STATUS), 7) == frame("02 03 02 00 11 3C 48")   # fault + command done
        assert wire.ask(frame(READ_ALARM), 7) == frame("02 03 02 01 80 FC 74")
        assert wire.ask(frame(RESET_ALARM), 8) == frame(RESET_ALARM)
        assert wire.ask(frame(READ_ALARM), 7) == frame("02 03 02 00 00 FC 44")


@pytest.mark.parametrize("units, request_hex, reply_hex", [
    # S1 §5.5.4 p.43 verbatim: PR0 at unit 7 in one FC16 of 8 words ending in the 0x6207 trigger
    # (velocity 0 as printed: the path goes nowhere) -> the printed reply
    ({"crosshead": 7}, "07 10 62 00 00 08 10 00 01 00 00 27 10 00 00 27 10 27 10 00 00 00 10 8D 50",
     "07 10 62 00 00 08 DE 11"),
    # S3/S4 §4.4.1 verbatim: function 02 is not supported -> exception 0x01
    ({"crosshead": 1, "load_cell": 3}, "01 02 00 01 00 01 E8 0A", "01 82 01 81 60"),
    # the invented map's "watchdog" at 0x6020 is not a register -> exception 0x02
    ({}, "02 03 60 20 00 01 9B F3", "02 83 02 30 F1"),
    # 0x20 homing: documented, not simulated (no home switch) -> 0x03
    ({}, "02 06 60 02 00 20 37 E1", "02 86 03 F2 61"),
])
def test_the_simulator_answers_the_manuals_frames(units, request_hex, reply_hex):
    with simulated(rtu_profile(**units)) as (machine, clock, wire):
        assert wire.ask(frame(request_hex), len(frame(reply_hex))) == frame(reply_hex)
        assert not machine.crosshead_status().moving


# ----------------------------------------------------------------------------- foamlab probe's reads

def _read(address: int, count: int, *words: int) -> tuple[str, str]:
    request = rtu(2, struct.pack(">BHH", 3, address, count))
    return request.hex(" "), rtu(2, bytes([3, 2 * len(words)]) + struct.pack(f">{len(words)}H", *words)).hex(" ")


def test_the_probe_reads_catch_a_motor_position_in_encoder_counts():
    """0x602C's unit is open (pulses or encoder counts, notes §7.2): at rest it must agree with 0x602A."""
    exchanges = [_read(0x0001, 1, 10000), _read(0x1003, 1, 0x0032), _read(0x2203, 1, 0),
                 _read(0x602A, 2, 0x0003, 0xD090), _read(0x602C, 2, 0x0000, 0x9C40)]   # 250 000 vs 40 000
    with driver_on(exchanges) as machine:
        checks = {name: ok for name, ok, _ in machine.crosshead.self_checks()}
    assert checks == {"CS2RS pulses per revolution": True, "CS2RS status bits": True, "CS2RS alarm": True,
                      "CS2RS position units": False}


def test_the_probe_reads_pass_on_the_simulated_drive():
    with simulated() as (sim_machine, clock, wire):
        machine = open_machine(rtu_profile(), port_url=wire.url, timeout_s=0.5)
        try:
            machine.crosshead.move_to(3.0, 300.0)
            clock.advance(5.0)
            assert all(ok for _, ok, _ in machine.crosshead.self_checks()), machine.crosshead.self_checks()
        finally:
            machine.close()
