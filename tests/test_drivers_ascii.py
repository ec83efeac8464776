"""ASCII stand + gauge driver, byte for byte, over pyserial's socket:// URL to a recorded peer."""

from __future__ import annotations

from contextlib import contextmanager

import pytest

from drivers.ascii import DeviceErrorReply
from drivers.base import (
    CrossheadStatus,
    DeviceConnectionLost,
    DeviceProtocolError,
    DeviceTimeout,
    MachineSample,
)
from drivers.profile import load_profile, open_machine
from recorded_peer import CLOSE, RecordedPeer

pytestmark = pytest.mark.timeout(30)

ACK = b"\r\n"


def cmd(text: str) -> bytes:
    return text.encode("ascii") + b"\r"


def line(text: str) -> bytes:
    return text.encode("ascii") + b"\r\n"


def stand(exchanges, transport="pty") -> RecordedPeer:
    """The stand on a pty (like a USB serial adapter), or behind pyserial's socket:// URL."""
    return RecordedPeer(exchanges, transport=transport)


@contextmanager
def machine_on(peer: RecordedPeer, *, timeout_s=0.5, retries=1, configure=False):
    machine = open_machine(load_profile("sim-serial"), connect=False, port_url=peer.url,
                           timeout_s=timeout_s, retries=retries)
    if configure:
        machine.connect()
    else:
        machine.line.connect()
    try:
        yield machine
    finally:
        machine.close()
    peer.verify()   # not reached when the body failed: its own error is the one to see


def test_connect_sets_the_safety_travel_limits():
    with stand([(cmd("g-20.000"), ACK), (cmd("h70.000"), ACK)]) as peer:
        with machine_on(peer, configure=True) as machine:
            machine.connect()            # idempotent: nothing more is sent


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_read_sample_is_one_n_request(transport):
    with stand([(cmd("n"), line("12.345,4.285")), (cmd("n"), line("-0.500,-0.012"))], transport) as peer:
        with machine_on(peer) as machine:
            first = machine.read_sample()
            second = machine.read_sample()
    assert (first.position_mm, first.force_N) == (12.345, 4.285)
    assert isinstance(first, MachineSample) and not first.load_cell_status.over_range
    assert (second.position_mm, second.force_N) == (-0.5, -0.012)


def test_gauge_read_travel_read_and_zeroes():
    exchanges = [(cmd("?"), line("4.285 N")), (cmd("x"), line("12.345")),
                 (cmd("Z"), ACK), (cmd("Z"), ACK), (cmd("z"), ACK)]
    with stand(exchanges) as peer:
        with machine_on(peer) as machine:
            reading = machine.load_cell.read()
            assert reading.force_N == 4.285 and not reading.status.over_range
            assert machine.crosshead.read_position() == 12.345
            machine.load_cell.zero()
            machine.load_cell.tare()
            machine.crosshead.set_zero()


def test_gauge_reading_at_capacity_is_flagged_over_range():
    with stand([(cmd("?"), line("500.000 N"))]) as peer:
        with machine_on(peer) as machine:
            assert machine.load_cell.read().status.over_range


def test_move_to_down_sets_the_lower_limit_to_the_target_then_moves_down():
    exchanges = [(cmd("x"), line("10.000")), (cmd("e23.6"), ACK), (cmd("h12.345"), ACK), (cmd("d"), ACK),
                 (cmd("w"), line("M1 U0 L0 F0 E0 O0")),
                 (cmd("w"), line("M0 U0 L1 F0 E0 O0"))]
    with stand(exchanges) as peer:
        with machine_on(peer, configure=False) as machine:
            machine.crosshead.safety_upper_mm, machine.crosshead.safety_lower_mm = -20.0, 70.0
            machine.crosshead.move_to(12.345, 23.6)
            assert machine.crosshead.status() == CrossheadStatus(moving=True)
            # Stopped at the limit move_to set: arrived, not a travel-limit event.
            assert machine.crosshead.status() == CrossheadStatus(in_position=True)


def test_move_to_up_sets_the_upper_limit_then_moves_up():
    exchanges = [(cmd("x"), line("20.000")), (cmd("e100.0"), ACK), (cmd("g5.000"), ACK), (cmd("u"), ACK)]
    with stand(exchanges) as peer:
        with machine_on(peer) as machine:
            machine.crosshead.move_to(5.0, 100.0)


def test_move_to_where_it_already_is_sends_no_motion():
    with stand([(cmd("x"), line("5.000"))]) as peer:
        with machine_on(peer) as machine:
            machine.crosshead.move_to(5.0, 100.0)


def test_move_to_outside_the_travel_limits_sends_nothing():
    with stand([]) as peer:
        with machine_on(peer) as machine:
            with pytest.raises(ValueError, match="travel limits"):
                machine.crosshead.move_to(80.0, 10.0)
            with pytest.raises(ValueError, match="speed"):
                machine.crosshead.jog(+1, 2000.0)


def test_jog_restores_the_safety_limit_and_stopping_there_is_a_limit_event():
    exchanges = [(cmd("g-20.000"), ACK), (cmd("h70.000"), ACK),                 # connect
                 (cmd("x"), line("0.000")), (cmd("e50.0"), ACK), (cmd("h30.000"), ACK), (cmd("d"), ACK),
                 (cmd("e50.0"), ACK), (cmd("h70.000"), ACK), (cmd("d"), ACK),  # jog down
                 (cmd("w"), line("M0 U0 L1 F0 E0 O0"))]
    with stand(exchanges) as peer:
        with machine_on(peer, configure=True) as machine:
            machine.crosshead.move_to(30.0, 50.0)
            machine.crosshead.jog(+1, 50.0)
            assert machine.crosshead.status() == CrossheadStatus(lower_limit=True)


def test_stop_emergency_stop_reset_and_status_flags():
    exchanges = [(cmd("s"), ACK), (cmd("!"), ACK), (cmd("w"), line("M0 U0 L0 F1 E1 O1")),
                 (cmd("w"), line("M0 U0 L0 F1 E1 O1")), (cmd("r"), ACK), (cmd("w"), line("M0 U0 L0 F0 E0 O1")),
                 (cmd("u"), ACK)]
    with stand(exchanges) as peer:
        with machine_on(peer) as machine:
            machine.crosshead.stop()
            machine.crosshead.emergency_stop()
            assert machine.crosshead.status() == CrossheadStatus(fault=True, emergency_stopped=True)
            assert machine.crosshead.fault_reason() == "emergency"
            machine.crosshead.reset_fault()
            assert machine.crosshead.fault_reason() == "overload"
            machine.line.query("move_up")


def test_error_reply_is_named_and_not_retried():
    with stand([(cmd("d"), line("*10"))]) as peer:
        with machine_on(peer) as machine:
            with pytest.raises(DeviceErrorReply, match=r"'d': \*10 unknown command") as info:
                machine.line.query("move_down")
    assert (info.value.code, info.value.name) == ("*10", "unknown_command")
    assert isinstance(info.value, DeviceProtocolError)


def test_overload_error_on_a_sample():
    with stand([(cmd("n"), line("*22"))]) as peer:
        with machine_on(peer) as machine:
            with pytest.raises(DeviceErrorReply, match="overload"):
                machine.read_sample()


@pytest.mark.parametrize("garbage", [b"12.3\xff5,4.2\r\n", b"12.345;4.285\r\n", b"12.345,4.285 N\r\n",
                                     b"\r\n", b"12.34"])
def test_garbage_or_partial_reply_is_a_protocol_error_after_the_retry(garbage):
    with stand([(cmd("n"), garbage), (cmd("n"), garbage)]) as peer:
        with machine_on(peer, timeout_s=0.1) as machine:
            with pytest.raises(DeviceProtocolError, match="'n'") as info:
                machine.read_sample()
    assert not isinstance(info.value, DeviceErrorReply)


def test_garbage_then_good_reply_recovers_on_the_retry():
    with stand([(cmd("x"), b"#~\r\n"), (cmd("x"), line("1.250"))]) as peer:
        with machine_on(peer) as machine:
            assert machine.crosshead.read_position() == 1.25


def test_unexpected_text_for_an_acknowledge_is_a_protocol_error():
    with stand([(cmd("s"), line("12.000")), (cmd("s"), line("12.000"))]) as peer:
        with machine_on(peer) as machine:
            with pytest.raises(DeviceProtocolError, match="expected an empty acknowledge"):
                machine.crosshead.stop()


def test_silence_is_a_timeout_after_one_retry():
    with stand([(cmd("n"), b""), (cmd("n"), b"")]) as peer:
        with machine_on(peer, timeout_s=0.05) as machine:
            with pytest.raises(DeviceTimeout, match=r"no reply to 'n' \(2 x 50 ms\)"):
                machine.read_sample()


def test_a_stale_extra_line_is_flushed_before_the_next_command():
    # The device sends one line too many (e.g. a late reply); it must not shift later replies.
    with stand([(cmd("x"), line("1.000") + line("99.000")), (cmd("n"), line("2.000,3.000"))]) as peer:
        with machine_on(peer) as machine:
            assert machine.crosshead.read_position() == 1.0
            assert machine.read_sample() == MachineSample(3.0, 2.0, machine.load_cell.status_for(3.0))


def test_a_late_reply_arriving_after_the_flush_is_skipped_without_resending():
    # the reply to an earlier, timed-out `n` arrives just after this command was sent:
    # it is a well-formed reply to another command, so the driver reads on for its own
    with stand([(cmd("w"), line("12.302,48.080") + line("M1 U0 L0 F0 E0 O0"))]) as peer:
        with machine_on(peer) as machine:
            assert machine.crosshead.status().moving


@pytest.mark.parametrize("transport", ["pty", "socket"])
def test_dropped_line_is_connection_lost(transport):
    with stand([(cmd("w"), CLOSE)], transport) as peer:
        with machine_on(peer) as machine:
            with pytest.raises(DeviceConnectionLost):
                machine.crosshead.status()


def test_missing_device_path_is_connection_lost():
    machine = open_machine(load_profile("sim-serial"), connect=False, port_url="/dev/does-not-exist-foamlab")
    with pytest.raises(DeviceConnectionLost, match="cannot open"):
        machine.connect()
