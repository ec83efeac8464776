"""ESM303 + Series 5 driver: how it copes with a bad line, byte for byte, against a recorded peer.

What the device sends when all is well is tests/test_device_mark10.py's (transcripts from the
manuals); here: silence, garbage, partial and late lines, a lost port, over-range, and the
pass-through closed whatever happened inside it.
"""

from __future__ import annotations

from contextlib import contextmanager
from dataclasses import replace

import pytest

from drivers.ascii import DeviceErrorReply
from drivers.base import DeviceConnectionLost, DeviceProtocolError, DeviceTimeout, MachineSample
from drivers.profile import load_profile, open_machine
from recorded_peer import CLOSE, RecordedPeer

pytestmark = pytest.mark.timeout(30)


def line(text: str) -> bytes:
    return text.encode("ascii") + b"\r\n"


def gauge(command: bytes, reply: bytes = b"") -> list:
    return [(b"/", b""), (command + b"\r", reply), (b"\\", b"")]


@contextmanager
def machine_on(exchanges, *, transport="pty", timeout_s=0.5, retries=1):
    with RecordedPeer(exchanges, transport=transport) as peer:
        machine = open_machine(load_profile("sim-serial"), connect=False, port_url=peer.url,
                               timeout_s=timeout_s, retries=retries)
        machine.commands = machine.link.commands = replace(machine.commands, passthrough_pause_s=0.0)
        machine.line.connect()
        try:
            yield machine
        finally:
            machine.close()
        peer.verify()   # not reached when the body failed: its own error is the one to see


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_read_sample_is_one_n_request(transport):
    with machine_on([(b"n", line("4.285 N") + line("12.35 mm"))], transport=transport) as machine:
        sample = machine.read_sample()
    assert (sample.position_mm, sample.force_N) == (12.35, 4.285)
    assert isinstance(sample, MachineSample) and not sample.load_cell_status.over_range


def test_gauge_reading_at_capacity_is_flagged_over_range():
    # the gauge reports no status with a reading: over range follows from the profile's capacity
    with machine_on(gauge(b"?C", line("500.000 N"))) as machine:
        assert machine.load_cell.read().status.over_range


@pytest.mark.parametrize("garbage", [b"12.3\xff5 mm\r\n", b"12.35;4.285\r\n", b"mm 12.35\r\n", b"12.35 mm"])
def test_garbage_or_partial_reply_is_a_protocol_error_after_the_retry(garbage):
    with machine_on([(b"x", garbage), (b"x", garbage)], timeout_s=0.1) as machine:
        with pytest.raises(DeviceProtocolError, match="'x'") as info:
            machine.crosshead.read_position()
    assert not isinstance(info.value, DeviceErrorReply) and "\n" not in str(info.value)


def test_garbage_then_good_reply_recovers_on_the_retry():
    with machine_on([(b"x", b"#~\r\n"), (b"x", line("1.25 mm"))]) as machine:
        assert machine.crosshead.read_position() == 1.25


def test_silence_is_a_timeout_after_one_retry():
    with machine_on([(b"n", b""), (b"n", b"")], timeout_s=0.05) as machine:
        with pytest.raises(DeviceTimeout, match=r"no reply to 'n' \(2 x 50 ms\)"):
            machine.read_sample()


def test_half_a_sample_then_silence_is_a_timeout():
    with machine_on([(b"n", line("4.285 N")), (b"n", line("4.285 N"))], timeout_s=0.05) as machine:
        with pytest.raises(DeviceTimeout, match="'n'"):
            machine.read_sample()


def test_the_pass_through_is_closed_after_every_attempt():
    # silence inside the gauge channel: each attempt opens and closes it, so a repeat or the
    # next stand command never lands in the gauge
    exchanges = [*gauge(b"?C"), *gauge(b"?C", line("1.500 N")), (b"x", line("2.00 mm"))]
    with machine_on(exchanges, timeout_s=0.1) as machine:
        assert machine.load_cell.read().force_N == 1.5
        assert machine.crosshead.read_position() == 2.0


def test_an_error_reply_closes_the_pass_through_and_is_not_retried():
    with machine_on([*gauge(b"?C", line("*10")), (b"x", line("2.00 mm"))]) as machine:
        with pytest.raises(DeviceErrorReply, match=r"\*10 illegal command"):
            machine.load_cell.read()
        assert machine.crosshead.read_position() == 2.0


def test_a_late_reply_arriving_after_the_flush_is_skipped_without_resending():
    # the reply to an earlier, timed-out `x` arrives just after `p` was sent: it is a
    # well-formed reply to another command, so the driver reads on for its own
    with machine_on([(b"p", line("12.30 mm") + line("D L"))]) as machine:
        assert machine.crosshead.status().moving


def test_a_late_travel_line_before_a_sample_is_skipped():
    with machine_on([(b"n", line("12.30 mm") + line("4.285 N") + line("12.35 mm"))]) as machine:
        assert machine.read_sample().position_mm == 12.35


def test_unknown_status_code_is_a_protocol_error():
    with machine_on([(b"p", line("S Q")), (b"p", line("S Q"))]) as machine:
        with pytest.raises(DeviceProtocolError, match=r"unexpected reply to 'p': 'S Q'"):
            machine.crosshead.status()


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_dropped_line_is_connection_lost(transport):
    with machine_on([(b"p", CLOSE)], transport=transport) as machine:
        with pytest.raises(DeviceConnectionLost):
            machine.crosshead.status()


def test_motion_outside_the_limits_or_the_speed_range_sends_nothing():
    with machine_on([]) as machine:
        with pytest.raises(ValueError, match="travel limits"):
            machine.crosshead.move_to(80.0, 10.0)
        with pytest.raises(ValueError, match="speed"):
            machine.crosshead.jog(+1, 2000.0)
        with pytest.raises(ValueError, match="speed"):
            machine.crosshead.jog(+1, 0.04)         # rounds to e0000.0


def test_missing_device_path_is_connection_lost():
    machine = open_machine(load_profile("sim-serial"), connect=False, port_url="/dev/does-not-exist-foamlab")
    with pytest.raises(DeviceConnectionLost, match="cannot open"):
        machine.connect()
