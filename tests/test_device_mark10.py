"""The Mark-10 ESM303 + Series 5 as their manuals document them, byte for byte.

The transcripts below are written from the manuals (docs/devices/notes-mark10.md §5; the
device file configs/devices/mark10-esm303.toml cites each entry) and run twice: (a) against
the driver, a recorded peer playing the device on a pty, and (b) against the simulator's
server on its pty. Where the manuals are silent the device file's assumption is the
transcript (no terminator on stand commands, `n` as force line then travel line, `p` as
space-separated codes); those entries are `confirmed = false` there.
"""

from __future__ import annotations

import os
import re
import select
import time
import tty
from contextlib import contextmanager

import pytest

from drivers.ascii import DeviceErrorReply
from drivers.base import CrossheadStatus, DeviceProtocolError, DeviceRefused
from drivers.mark10_device import CommandSet
from drivers.profile import load_profile, open_machine
from recorded_peer import RecordedPeer
from simulator.clock import ManualClock
from simulator.launch import start_simulator
from simulator.machine import SimulatedMachine

pytestmark = pytest.mark.timeout(30)

# ---------------------------------------------------------------- transcripts from the manuals
#: speed mm/min -> `eXXXX.X` (S1 §6.2 format rule; example e0200.3 in S1/S2)
SPEEDS = [(200.3, b"e0200.3"), (23.6, b"e0023.6"), (1100.0, b"e1100.0"), (0.5, b"e0000.5")]
#: lower limit mm -> `g-XXX.XX` (S1 §6.2 examples g-007.52, g010.70: g is the LOWER limit)
LOWER_LIMITS = [(-7.52, b"g-007.52"), (10.7, b"g010.70")]
#: upper limit mm -> `h-XXX.XX` (the same rule, S1 §6.2)
UPPER_LIMITS = [(-7.52, b"h-007.52"), (10.7, b"h010.70")]
#: inch formats (S1 §6.2: eXX.XX, g-XX.XXX; examples e02.85, g-00.550, g01.258 in S1/S2)
INCH = [("speed", 2.85, b"e02.85"), ("lower", -0.55, b"g-00.550"), ("lower", 1.258, b"g01.258")]
#: gauge reading through the pass-through (S1 §6.2.1: / ... \; S9: `4.285 N` CR LF, compression +)
GAUGE_READ = [(b"/", b""), (b"?C\r", b"4.285 N\r\n"), (b"\\", b"")]
#: the gauge's error codes (S5 p.19)
ERRORS = [(b"*10", "illegal command"), (b"*11", "not applicable"), (b"*12", "invalid specifier"),
          (b"*22", "value too large")]


def line(text: str) -> bytes:
    return text.encode("ascii") + b"\r\n"


def gauge(command: bytes, reply: bytes = b"") -> list:
    """One gauge command through the stand: `/`, the command and CR, its reply, `\\`."""
    return [(b"/", b""), (command + b"\r", reply), (b"\\", b"")]


# ================================================================= (a) the driver, recorded peer

@contextmanager
def driver(exchanges, *, connect=False, timeout_s=0.3, retries=1, setter_window_s=0.05, **profile_changes):
    profile = load_profile("sim-serial")
    for section, values in profile_changes.items():
        profile[section] = {**profile[section], **values}
    with RecordedPeer(exchanges, transport="pty") as peer:
        machine = open_machine(profile, connect=False, port_url=peer.url, timeout_s=timeout_s, retries=retries)
        machine.commands = machine.link.commands = _quick(machine.commands, setter_window_s)
        if connect:
            machine.connect()
        else:
            machine.line.connect()
        try:
            yield machine
        finally:
            machine.close()
        peer.verify()


def _quick(commands: CommandSet, setter_window_s: float) -> CommandSet:
    """The device file with the pass-through pause and setter window shortened (tests only)."""
    from dataclasses import replace
    return replace(commands, passthrough_pause_s=0.0, setter_window_s=setter_window_s)


CONNECT = [(b"i", b""), *gauge(b"N"), *gauge(b"FULL"), (b"h-020.00", b""), (b"g070.00", b""), (b"l", b"")]


def test_connect_sets_units_and_the_safety_limits_in_limit_mode():
    with driver(CONNECT, connect=True) as machine:
        machine.connect()            # idempotent: nothing more is sent


@pytest.mark.parametrize("speed, sent", SPEEDS)
def test_speed_is_sent_in_the_vendors_fixed_width(speed, sent):
    with driver([(sent, b""), (b"g070.00", b""), (b"l", b""), (b"d", b"")]) as machine:
        machine.crosshead.jog(+1, speed)


@pytest.mark.parametrize("mm, sent", LOWER_LIMITS)
def test_a_move_down_sets_the_lower_limit_g_then_limit_mode_then_d(mm, sent):
    exchanges = [(b"x", line("-20.00 mm")), (b"e0100.0", b""), (sent, b""), (b"l", b""), (b"d", b""),
                 (b"p", line("D L")), (b"p", line("S L DL"))]
    with driver(exchanges) as machine:
        machine.crosshead.move_to(mm, 100.0)
        assert machine.crosshead.status() == CrossheadStatus(moving=True)
        # stopped at the limit move_to set: arrived, not a travel-limit event
        assert machine.crosshead.status() == CrossheadStatus(in_position=True)


@pytest.mark.parametrize("mm, sent", UPPER_LIMITS)
def test_a_move_up_sets_the_upper_limit_h_then_u(mm, sent):
    exchanges = [(b"x", line("50.00 mm")), (b"e0023.6", b""), (sent, b""), (b"l", b""), (b"u", b""),
                 (b"p", line("U L")), (b"p", line("S L UL"))]
    with driver(exchanges) as machine:
        machine.crosshead.move_to(mm, 23.6)
        assert machine.crosshead.status().moving
        assert machine.crosshead.status() == CrossheadStatus(in_position=True)


def test_stopping_at_the_safety_limit_is_a_limit_event():
    exchanges = [*CONNECT, (b"e0050.0", b""), (b"g070.00", b""), (b"l", b""), (b"d", b""),
                 (b"p", line("S L DL")), (b"p", line("DL"))]      # C1's single-code form too
    with driver(exchanges, connect=True) as machine:
        machine.crosshead.jog(+1, 50.0)
        assert machine.crosshead.status() == CrossheadStatus(lower_limit=True)
        assert machine.crosshead.status() == CrossheadStatus(lower_limit=True)


@pytest.mark.parametrize("what, value, sent", INCH)
def test_inch_formats_when_the_profile_is_in_inches(what, value, sent):
    mm = value * 25.4
    if what == "speed":
        exchanges, act = [(sent, b""), (b"g02.756", b""), (b"l", b""), (b"d", b"")], \
            lambda m: m.crosshead.jog(+1, mm)
    else:
        exchanges, act = [(b"h-00.787", b""), (sent, b""), (b"l", b"")], \
            lambda m: m.crosshead.set_travel_limits(-20.0, mm)
    with driver(exchanges, crosshead={"travel_unit": "in"}) as machine:
        act(machine)


def test_connect_in_inches_sends_b():
    exchanges = [(b"b", b""), *gauge(b"N"), *gauge(b"FULL"), (b"h-00.787", b""), (b"g02.756", b""), (b"l", b"")]
    with driver(exchanges, connect=True, crosshead={"travel_unit": "in"}) as machine:
        assert machine.crosshead.unit.reply == "in"


def test_travel_sign_minus_one_turns_the_stands_travel_into_mm_down():
    exchanges = [(b"x", line("12.35 mm")), (b"x", line("12.35 mm")), (b"e0010.0", b""), (b"h015.00", b""), (b"l", b""), (b"u", b""),
                 (b"n", line("4.285 N") + line("-3.00 mm"))]
    with driver(exchanges, crosshead={"travel_sign": -1}) as machine:
        assert machine.crosshead.read_position() == -12.35
        machine.crosshead.move_to(-15.0, 10.0)          # up: the upper limit, in the stand's sign
        sample = machine.read_sample()
    assert (sample.force_N, sample.position_mm) == (4.285, 3.0)


def test_gauge_reading_through_the_pass_through():
    with driver(GAUGE_READ) as machine:
        reading = machine.load_cell.read()
    assert reading.force_N == 4.285 and not reading.status.over_range


def test_zero_and_tare_are_the_gauges_one_zero():
    with driver([*gauge(b"Z"), *gauge(b"Z"), (b"z", b"")]) as machine:
        machine.load_cell.zero()
        machine.load_cell.tare()
        machine.crosshead.set_zero()


def test_a_sample_is_one_n_two_lines_force_first():
    with driver([(b"n", line("4.285 N") + line("12.35 mm")), (b"n", line("-0.012 N") + line("-0.50 mm"))]) as machine:
        first, second = machine.read_sample(), machine.read_sample()
    assert (first.force_N, first.position_mm) == (4.285, 12.35)
    assert (second.force_N, second.position_mm) == (-0.012, -0.5)


@pytest.mark.parametrize("code, meaning", ERRORS)
def test_error_codes_are_refusals_named_as_the_vendor_names_them(code, meaning):
    with driver(gauge(b"?C", code + b"\r\n")) as machine:          # one exchange: never retried
        with pytest.raises(DeviceErrorReply) as info:
            machine.load_cell.read()
    assert str(info.value).endswith(f"device refused '?C': {code.decode()} {meaning}")
    assert isinstance(info.value, DeviceRefused) and "\n" not in str(info.value)
    assert (info.value.code, info.value.meaning) == (code.decode(), meaning)


def test_a_gauge_setter_refused_is_an_error_reply():
    # a window long enough for a busy host: the refusal ends the wait as soon as it arrives
    with driver(gauge(b"Z", b"*10\r\n"), setter_window_s=5.0) as machine:
        with pytest.raises(DeviceErrorReply, match=r"'Z': \*10 illegal command"):
            machine.load_cell.zero()


@pytest.mark.parametrize("exchange, message", [
    (gauge(b"?C", b"0.963 lbF\r\n"), "gauge answers '?C' in lbF, the profile expects N"),
    ([(b"x", line("0.486 in"))], "stand answers 'x' in in, the profile expects mm"),
    ([(b"n", line("4.285 kgF") + line("1.00 mm"))], "gauge answers 'n' in kgF, the profile expects N"),
])
def test_a_unit_other_than_the_profiles_is_one_line_naming_both(exchange, message):
    with driver(exchange) as machine:                       # not repeated: it would not help
        with pytest.raises(DeviceProtocolError, match=re.escape(message)) as info:
            machine.load_cell.read() if exchange[0][0] == b"/" else (
                machine.crosshead.read_position() if exchange[0][0] == b"x" else machine.read_sample())
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("reply, expected", [
    (b"12.35\r\n", 12.35),                 # no unit token (C3 parses a bare number)
    (b"12.35 mm\n", 12.35),                # LF only
    (b"\r\n12.35 mm\r\n", 12.35),          # an undocumented acknowledge line before it
    (b"12.35mm\r\n", 12.35),
])
def test_the_driver_is_tolerant_where_the_manual_is_silent(reply, expected):
    with driver([(b"x", reply)]) as machine:
        assert machine.crosshead.read_position() == expected


def test_the_driver_never_sends_an_invented_command():
    """No `w` as status, `r` as reset, `!` as e-stop: status is `p`, the e-stop is `s`, a reset is nothing."""
    exchanges = [(b"s", b""), (b"p", line("S L")), (b"s", b""), (b"p", line("S L"))]
    with driver(exchanges) as machine:
        machine.crosshead.emergency_stop()
        assert machine.crosshead.status() == CrossheadStatus()
        assert "no fault latch" in machine.crosshead.reset_fault()     # sends nothing
        machine.crosshead.stop()
        assert not machine.crosshead.status().emergency_stopped


def test_a_whole_session_sends_only_documented_commands(monkeypatch):
    """Every byte a run's calls send, split as the stand reads them, is a device-file command."""
    sent = bytearray()
    machine, clock = sim_machine()
    with start_simulator("serial", machine=machine) as sim:
        driver_machine = open_machine(load_profile("sim-serial"), connect=False, timeout_s=1.0,
                                      **sim.profile_overrides)
        original = driver_machine.line.write
        monkeypatch.setattr(driver_machine.line, "write", lambda data: (sent.extend(data), original(data)))
        with driver_machine as m:
            m.read_sample(), m.load_cell.read(), m.crosshead.status(), m.crosshead.read_position()
            m.crosshead.move_to(10.0, 100.0)
            m.crosshead.jog(-1, 50.0)
            m.crosshead.stop(), m.crosshead.emergency_stop(), m.crosshead.reset_fault()
            m.crosshead.set_zero(), m.load_cell.zero(), m.load_cell.tare()
            m.identify(), m.crosshead.read_travel_limits(), m.crosshead.read_speed()
    commands = CommandSet.from_toml(load_profile("sim-serial")["wire"])
    stand, gauge_lines = split_stream(bytes(sent), commands)
    documented = {c.prefix for c in commands.stand.values()} | {u.command for u in commands.stand_units.values()}
    assert {s[:1] for s in stand} <= documented
    assert not {"!", "r", "c", "f", "t"} & {s[:1] for s in stand}
    assert stand.count("w") == 1                                 # read_travel_limits' only
    gauge_sent = {c.send for c in commands.gauge.values()} | {u.command for u in commands.gauge_units.values()}
    assert set(gauge_lines) <= gauge_sent


def split_stream(data: bytes, commands: CommandSet) -> tuple[list[str], list[str]]:
    """Stand commands (letter + fixed-width argument) and gauge lines, as the stand reads the bytes."""
    stand, gauge_lines, i, text = [], [], 0, data.decode("ascii")
    mm = commands.stand_units["mm"]
    while i < len(text):
        c = text[i]
        if c == "/":
            end = text.index("\\", i)
            gauge_lines += [g for g in text[i + 1:end].split("\r") if g]
            i = end + 1
            continue
        width = {"e": 7, "g": 7, "h": 7}.get(c, 1) + (c in "gh" and text[i + 1] == "-")
        assert width == 1 or mm.speed.integer_digits == 4
        stand.append(text[i:i + width])
        i += width
    return stand, gauge_lines


# ================================================================= (b) the simulator on its pty

def sim_machine(**settings):
    clock = ManualClock()
    machine = SimulatedMachine(load_profile("sim-serial"), clock=clock, noise_sigma_N=0.0,
                               load_cell_offset_N=4.285, resolution_N=0.001, **settings)
    return machine, clock


class Wire:
    """Raw bytes to and from the simulator's pty, as a terminal program would send them."""

    def __init__(self, path: str):
        self.fd = os.open(path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        tty.setraw(self.fd)

    def ask(self, data: bytes, lines: int = 1, timeout: float = 2.0) -> bytes:
        """Send; return the reply once `lines` lines arrived (0: confirm silence with a following `x`)."""
        os.write(self.fd, data)
        if lines == 0:
            return self.ask(b"x")
        reply, deadline = b"", time.monotonic() + timeout
        while reply.count(b"\n") < lines and time.monotonic() < deadline:
            if select.select([self.fd], [], [], 0.05)[0]:
                reply += os.read(self.fd, 256)
        return reply

    def close(self):
        os.close(self.fd)


@contextmanager
def simulated(**settings):
    machine, clock = sim_machine(**settings)
    with start_simulator("serial", machine=machine) as sim:
        wire = Wire(sim.server.client_url)
        try:
            yield wire, machine, clock
        finally:
            wire.close()


def test_sim_answers_the_documented_requests_in_the_assumed_formats():
    with simulated() as (w, _, _):
        assert w.ask(b"x") == b"0.00 mm\r\n"
        assert w.ask(b"p") == b"S M\r\n"                       # powers up in manual mode
        assert w.ask(b"n", 2) == b"4.285 N\r\n0.00 mm\r\n"     # force line first, then travel
        assert w.ask(b"v") == b"-20.00 mm\r\n" and w.ask(b"w") == b"70.00 mm\r\n"
        assert w.ask(b"a") == b"50.0 mm/min\r\n"
        assert w.ask(b"x\r\nx", 2) == b"0.00 mm\r\n0.00 mm\r\n"  # a terminator a host sends is ignored


def test_sim_gauge_reading_through_the_pass_through():
    with simulated() as (w, _, _):
        assert w.ask(b"".join(request for request, _ in GAUGE_READ)) == GAUGE_READ[1][1]
        assert w.ask(b"/?\r\\") == b"4.285 N\r\n"                # the displayed reading: the same here
        assert w.ask(b"/?C\r\n\\") == b"4.285 N\r\n"             # CR LF: the LF is ignored (S5b)
        assert w.ask(b"/LB\r?C\r\\") == b"0.963 lbF\r\n"         # in the unit it was set to
        assert w.ask(b"/N\rZ\r?C\r\\") == b"0.000 N\r\n"         # Z: the gauge's one zero


#: what makes the simulated gauge give each code (the simulator's choice: docs in simulator/mark10_stand.py)
SIM_ERRORS = [(request_, code) for request_, (code, _) in zip((b"XYZ", b"?A", b"AOFFx", b"AOFF31"), ERRORS)]


@pytest.mark.parametrize("request_, code", SIM_ERRORS, ids=[code.decode() for _, code in SIM_ERRORS])
def test_sim_gauge_error_codes(request_, code):
    with simulated() as (w, _, _):
        assert w.ask(b"/" + request_ + b"\r\\") == code + b"\r\n"
        assert w.ask(b"x") == b"0.00 mm\r\n"                  # back on the stand after `\\`


@pytest.mark.parametrize("speed, sent", SPEEDS)
def test_sim_takes_the_speed_format_and_reports_it(speed, sent):
    with simulated() as (w, _, _):
        assert w.ask(sent + b"a") == f"{speed:.1f} mm/min\r\n".encode()


@pytest.mark.parametrize("mm, sent", LOWER_LIMITS)
def test_sim_lower_limit_is_g_and_w_reads_it(mm, sent):
    with simulated() as (w, _, _):
        assert w.ask(sent + b"w") == f"{mm:.2f} mm\r\n".encode()
        assert w.ask(b"v") == b"-20.00 mm\r\n"                # the upper one is untouched


@pytest.mark.parametrize("mm, sent", UPPER_LIMITS)
def test_sim_upper_limit_is_h_and_v_reads_it(mm, sent):
    with simulated() as (w, _, _):
        assert w.ask(sent + b"v") == f"{mm:.2f} mm\r\n".encode()


def test_sim_ignores_an_argument_out_of_format():
    with simulated() as (w, _, _):
        assert w.ask(b"e200.30a") == b"50.0 mm/min\r\n"        # 'e200.30' is not eXXXX.X: ignored


def test_sim_limit_mode_move_stops_at_the_lower_limit_and_back_up():
    with simulated() as (w, _, clock):
        assert w.ask(b"e0500.0g010.70ld", 0) == b"0.00 mm\r\n"   # silent commands: only x answers
        assert w.ask(b"p") == b"D L\r\n"
        clock.advance(5.0)
        assert w.ask(b"x") == b"10.70 mm\r\n" and w.ask(b"p") == b"S L DL\r\n"
        assert w.ask(b"d", 0) == b"10.70 mm\r\n"                # at the limit: stays stopped
        assert w.ask(b"p") == b"S L DL\r\n"
        assert w.ask(b"h005.00u", 0) == b"10.70 mm\r\n" and w.ask(b"p") == b"U L\r\n"
        clock.advance(5.0)
        assert w.ask(b"x") == b"5.00 mm\r\n" and w.ask(b"p") == b"S L UL\r\n"


def test_sim_ignores_invented_and_unsimulated_stand_commands():
    with simulated() as (w, machine, clock):
        assert w.ask(b"e0100.0d", 0) == b"0.00 mm\r\n"
        clock.advance(0.5)
        assert w.ask(b"!r", 0).endswith(b" mm\r\n")            # no e-stop, no reset: ignored
        status = machine.crosshead_status()
        assert status.moving and not status.emergency_stop
        assert w.ask(b"w") == b"70.00 mm\r\n"                   # `w` is the lower limit, not a status
        assert w.ask(b"s", 0).endswith(b" mm\r\n")
        clock.advance(1.0)
        assert w.ask(b"p") == b"S M\r\n"


def test_sim_inch_units():
    with simulated() as (w, _, _):
        assert w.ask(b"b" + INCH[0][2] + b"a") == b"2.85 in/min\r\n"
        assert w.ask(INCH[1][2] + b"w") == b"-0.550 in\r\n"
        assert w.ask(b"x") == b"0.000 in\r\n"
        assert w.ask(b"ix") == b"0.00 mm\r\n"


def test_driver_and_simulator_agree_end_to_end():
    """The real driver on the simulated device: connect, read, move in limit mode, zero."""
    machine, clock = sim_machine()
    with start_simulator("serial", machine=machine) as sim:
        with open_machine(load_profile("sim-serial"), timeout_s=1.0, **sim.profile_overrides) as m:
            assert m.read_sample().force_N == 4.285
            m.crosshead.move_to(12.345, 300.0)
            assert m.crosshead.status().moving      # a reply: the stand has read every byte before it
            clock.advance(10.0)
            status = m.crosshead.status()
            assert status.in_position and not status.lower_limit
            assert m.crosshead.read_position() == pytest.approx(12.34, abs=0.011)   # g012.35 or g012.34
            assert m.crosshead.read_travel_limits() == (-20.0, m.crosshead.read_position())
            m.load_cell.tare()
            assert m.load_cell.read().force_N == 0.0


# ================================================================= commissioning (foamlab probe)

def test_every_unconfirmed_entry_says_its_assumption_and_what_settles_it():
    commands = CommandSet.from_toml(load_profile("sim-serial")["wire"])
    open_items = {e.name: e for e in commands.unconfirmed()}
    for name in ("[stand.framing]", "[stand.reply_framing]", "[stand.acknowledge]", "[stand.commands.read_sample]",
                 "[stand.commands.status]", "[stand.commands.read_travel]", "[gauge.commands.zero]"):
        assert open_items[name].assumption and open_items[name].settle, name
    assert "[stand.commands.set_speed]" not in open_items and "[gauge.errors_source]" not in open_items
    assert any("e-stop" in a for a in commands.absent) and any("watchdog" in a for a in commands.absent)


def test_self_checks_confirm_the_simulated_device_and_identify_it():
    machine, _ = sim_machine()
    with start_simulator("serial", machine=machine) as sim:
        with open_machine(load_profile("sim-serial"), timeout_s=1.0, **sim.profile_overrides) as m:
            checks = m.self_checks()
            identity = m.identify()
    assert [ok for _, ok, _ in checks] == [True] * 8, checks
    assert all("as the device file assumes" in detail for _, _, detail in checks[:7])
    assert identity == "foamlab simulated Series 5 / M5-100 (simulated) / 1.00 / SIM00001"


def test_self_checks_say_which_reply_differs_from_the_assumption():
    exchanges = [(b"x", b"12.35\r\n"),                                  # bare number: read, but differs
                 (b"n", line("4.285 N") + line("12.35 mm")), (b"p", b"S;L\r\n"),   # unreadable
                 (b"a", line("50.0 mm/min")), (b"v", line("-20.00 mm")), (b"w", line("70.00 mm")),
                 *gauge(b"?C", line("4.285 N")), *gauge(b"LIST", line("V1.00;LBF;CUR;FULL;B0"))]
    with driver(exchanges) as machine:
        checks = {name.split(" (")[0]: (ok, detail) for name, ok, detail in machine.self_checks()}
    assert checks["travel reply"][0] and "differs from the device file's assumption" in checks["travel reply"][1]
    assert checks["status reply"] == (False, "b'S;L\\r\\n': the driver cannot read it (serial %s: unexpected "
                                      "reply to 'p': 'S;L')" % machine.line.url)
    assert checks["sample reply"] == (True, "b'4.285 N\\r\\n12.35 mm\\r\\n': as the device file assumes")
    assert checks["gauge settings"][0] is False and "lacks N" in checks["gauge settings"][1]
