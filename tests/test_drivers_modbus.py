"""Modbus drivers, byte for byte: the real pymodbus client against recorded exchanges.

Frames are built here by hand (struct + a reference CRC in recorded_peer), with the
register addresses written out literally, so these tests also pin the register map.
TCP uses the MBAP header; RTU runs over pyserial's socket:// URL to the same peer.
"""

from __future__ import annotations

import struct
import threading
from contextlib import contextmanager

import pytest

from drivers.base import (
    CrossheadStatus,
    DeviceConnectionLost,
    DeviceProtocolError,
    DeviceTimeout,
    LoadCellStatus,
)
from drivers.profile import load_profile, open_machine
from recorded_peer import CLOSE, RecordedPeer, crc16_modbus, mbap, rtu

pytestmark = pytest.mark.timeout(30)

LOAD_CELL, CROSSHEAD = 1, 2      # unit ids in the sim profiles


# ----------------------------------------------------------------------------- frames

def words_of(fmt: str, value, word_order: str) -> list[int]:
    """32-bit value -> two 16-bit registers in the given word order."""
    raw = struct.pack(">" + fmt, value)
    high, low = struct.unpack(">HH", raw)
    return [high, low] if word_order == "big" else [low, high]


def regs(*words: int) -> bytes:
    return struct.pack(f">{len(words)}H", *words)


def read_request(address: int, count: int) -> bytes:
    return struct.pack(">BHH", 0x03, address, count)


def read_reply(*words: int) -> bytes:
    return bytes([0x03, 2 * len(words)]) + regs(*words)


def write_single(address: int, value: int) -> bytes:
    return struct.pack(">BHH", 0x06, address, value)      # the reply echoes the request


def write_multiple(address: int, words: list[int]) -> tuple[bytes, bytes]:
    request = struct.pack(">BHHB", 0x10, address, len(words), 2 * len(words)) + regs(*words)
    return request, struct.pack(">BHH", 0x10, address, len(words))


class Frames:
    """Builds request/reply frames for one transport, counting MBAP transaction ids."""

    def __init__(self, transport: str):
        self.transport = transport
        self.tid = 0

    def __call__(self, unit: int, request_pdu: bytes, reply_pdu: bytes | None = None, *, retry: bool = False):
        if not retry:
            self.tid += 1
        if self.transport.startswith("rtu"):
            request = rtu(unit, request_pdu)
            return request, (rtu(unit, reply_pdu) if reply_pdu is not None else b"")
        return mbap(self.tid, unit, request_pdu), (mbap(self.tid, unit, reply_pdu) if reply_pdu is not None else b"")


def peer_for(transport: str, exchanges, **options) -> RecordedPeer:
    """RTU runs over a pty (like a USB adapter); `rtu-socket` over pyserial's socket:// URL."""
    return RecordedPeer(exchanges, transport="pty" if transport == "rtu" else "socket", **options)


@contextmanager
def machine_on(peer: RecordedPeer, transport: str, word_order: str = "big", *, timeout_s=0.5, retries=1):
    """A Modbus machine from the sim profile, pointed at the peer, link connected (no configure)."""
    name = "sim-modbus-tcp" if transport == "tcp" else "sim-modbus-rtu"
    where = {"port": peer.port} if transport == "tcp" else {"port_url": peer.url}
    machine = open_machine(load_profile(name), connect=False, word_order=word_order,
                           timeout_s=timeout_s, retries=retries, **where)
    machine.link.connect()
    try:
        yield machine
    finally:
        machine.close()
    peer.verify()   # not reached when the body failed: its own error is the one to see


TRANSPORT_ORDERS = [("tcp", "big"), ("tcp", "little"), ("rtu", "big"), ("rtu", "little"), ("rtu-socket", "big")]


def test_reference_crc_matches_the_modbus_specification_example():
    # Modbus over serial line guide (V1.02), 6.2.2: read 2 registers from 0x6B, unit 2? The
    # classic worked example: 01 03 00 00 00 0A -> CRC C5 CD.
    assert crc16_modbus(bytes.fromhex("01 03 00 00 00 0A")) == bytes.fromhex("C5 CD")


# ----------------------------------------------------------------------------- load cell

@pytest.mark.parametrize("transport,word_order", TRANSPORT_ORDERS)
def test_load_cell_read_is_one_block_read_giving_net_force_and_status(transport, word_order):
    frame = Frames(transport)
    status_word = 0b1100       # no_motion (bit 2) + tare_set (bit 3)
    block = [*words_of("f", 4.5, word_order), *words_of("f", 4.285, word_order), status_word]
    with peer_for(transport, [frame(LOAD_CELL, read_request(0x3500, 5), read_reply(*block))]) as peer:
        with machine_on(peer, transport, word_order) as machine:
            reading = machine.load_cell.read()
    assert reading.force_N == pytest.approx(4.285, rel=1e-6)
    assert reading.status == LoadCellStatus(under_range=False, over_range=False, stable=True, tare_set=True)


def test_load_cell_overload_bit_and_negative_force():
    frame = Frames("tcp")
    block = [*words_of("f", -1.0, "big"), *words_of("f", -512.25, "big"), 0b0010]
    with peer_for("tcp", [frame(LOAD_CELL, read_request(0x3500, 5), read_reply(*block))]) as peer:
        with machine_on(peer, "tcp") as machine:
            reading = machine.load_cell.read()
    assert reading.force_N == -512.25
    assert reading.status.over_range and not reading.status.stable


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_zero_and_tare_write_the_command_register(transport):
    frame = Frames(transport)
    exchanges = [frame(LOAD_CELL, write_single(0x2061, 1), write_single(0x2061, 1)),
                 frame(LOAD_CELL, write_single(0x2061, 2), write_single(0x2061, 2))]
    with peer_for(transport, exchanges) as peer:
        with machine_on(peer, transport) as machine:
            machine.load_cell.zero()
            machine.load_cell.tare()


# ----------------------------------------------------------------------------- crosshead

@pytest.mark.parametrize("transport,word_order", TRANSPORT_ORDERS)
def test_move_to_writes_target_speed_then_trigger(transport, word_order):
    frame = Frames(transport)
    target = write_multiple(0x6201, words_of("i", 12345, word_order))     # 12.345 mm in um
    speed = write_multiple(0x6203, words_of("i", 2360, word_order))       # 23.6 mm/min in 0.01 mm/min
    exchanges = [frame(CROSSHEAD, *target), frame(CROSSHEAD, *speed),
                 frame(CROSSHEAD, write_single(0x6002, 0x0010), write_single(0x6002, 0x0010))]
    with peer_for(transport, exchanges) as peer:
        with machine_on(peer, transport, word_order) as machine:
            machine.crosshead.move_to(12.345, 23.6)


def test_move_to_negative_target_is_twos_complement():
    frame = Frames("rtu")
    exchanges = [frame(CROSSHEAD, *write_multiple(0x6201, [0xFFFF, 0xEC78])),      # -5000 um, big
                 frame(CROSSHEAD, *write_multiple(0x6203, [0x0000, 0xC350])),      # 500 mm/min
                 frame(CROSSHEAD, write_single(0x6002, 0x0010), write_single(0x6002, 0x0010))]
    with peer_for("rtu", exchanges) as peer:
        with machine_on(peer, "rtu", "big") as machine:
            machine.crosshead.move_to(-5.0, 500.0)


def test_jog_stop_estop_reset_zero_write_their_triggers():
    frame = Frames("tcp")
    trigger = lambda code: frame(CROSSHEAD, write_single(0x6002, code), write_single(0x6002, code))
    exchanges = [frame(CROSSHEAD, *write_multiple(0x6203, [0, 10000])), trigger(0x0022),   # jog up 100 mm/min
                 frame(CROSSHEAD, *write_multiple(0x6203, [0, 2360])), trigger(0x0021),    # jog down
                 trigger(0x0040), trigger(0x0050), trigger(0x0060), trigger(0x0030)]
    with peer_for("tcp", exchanges) as peer:
        with machine_on(peer, "tcp") as machine:
            machine.crosshead.jog(-1, 100.0)
            machine.crosshead.jog(+1, 23.6)
            machine.crosshead.stop()
            machine.crosshead.emergency_stop()
            machine.crosshead.reset_fault()
            machine.crosshead.set_zero()


def test_speed_beyond_the_drive_maximum_is_refused_before_anything_is_sent():
    with peer_for("tcp", []) as peer:
        with machine_on(peer, "tcp") as machine:
            with pytest.raises(ValueError, match="500"):
                machine.crosshead.move_to(10.0, 600.0)
            with pytest.raises(ValueError):
                machine.crosshead.jog(0, 10.0)


@pytest.mark.parametrize("transport,word_order", [("tcp", "big"), ("rtu", "little")])
def test_position_and_status_decode(transport, word_order):
    frame = Frames(transport)
    status_word = (1 << 1) | (1 << 2) | (1 << 5)     # enabled, moving, lower limit
    exchanges = [frame(CROSSHEAD, read_request(0x602A, 2), read_reply(*words_of("i", -20123, word_order))),
                 frame(CROSSHEAD, read_request(0x1003, 1), read_reply(status_word)),
                 frame(CROSSHEAD, read_request(0x1003, 1), read_reply((1 << 0) | (1 << 6) | (1 << 3))),
                 frame(CROSSHEAD, read_request(0x2203, 1), read_reply(2))]
    with peer_for(transport, exchanges) as peer:
        with machine_on(peer, transport, word_order) as machine:
            assert machine.crosshead.read_position() == pytest.approx(-20.123)
            assert machine.crosshead.status() == CrossheadStatus(moving=True, lower_limit=True)
            assert machine.crosshead.status() == CrossheadStatus(fault=True, emergency_stopped=True, in_position=True)
            assert machine.crosshead.fault_reason() == "watchdog"


def test_read_sample_brackets_the_force_with_two_position_readings():
    frame = Frames("tcp")
    exchanges = [frame(CROSSHEAD, read_request(0x602A, 2), read_reply(*words_of("i", 7250, "big"))),
                 frame(LOAD_CELL, read_request(0x3500, 5),
                       read_reply(*words_of("f", 1.0, "big"), *words_of("f", 2.5, "big"), 0)),
                 frame(CROSSHEAD, read_request(0x602A, 2), read_reply(*words_of("i", 7250, "big")))]
    with peer_for("tcp", exchanges) as peer:
        with machine_on(peer, "tcp") as machine:
            sample = machine.read_sample()
    assert (sample.force_N, sample.position_mm) == (2.5, 7.25)


def test_connect_configures_acceleration_watchdog_and_travel_limits():
    frame = Frames("tcp")
    exchanges = [frame(CROSSHEAD, *write_multiple(0x6205, [0, 50000])),          # 50 mm/s^2 in um/s^2
                 frame(CROSSHEAD, write_single(0x6020, 2000), write_single(0x6020, 2000)),
                 frame(CROSSHEAD, *write_multiple(0x6010, words_of("i", -20000, "big") + words_of("i", 70000, "big")))]
    with RecordedPeer(exchanges) as peer:
        machine = open_machine(load_profile("sim-modbus-tcp"), port=peer.port, timeout_s=0.5)
        machine.connect()            # idempotent: nothing more is sent
        machine.close()
        peer.verify()


# ----------------------------------------------------------------------------- errors

def test_bad_crc_on_every_attempt_is_a_protocol_error_naming_register_and_unit():
    good = rtu(LOAD_CELL, read_reply(0, 0, 0, 0, 0))
    corrupted = good[:-1] + bytes([good[-1] ^ 0xFF])
    request = rtu(LOAD_CELL, read_request(0x3500, 5))
    with peer_for("rtu", [(request, corrupted), (request, corrupted)]) as peer:
        with machine_on(peer, "rtu", timeout_s=0.1, retries=1) as machine:
            with pytest.raises(DeviceProtocolError, match=r"0x3500.*unit 1") as info:
                machine.load_cell.read()
    assert "CRC" in str(info.value) and "\n" not in str(info.value)


def test_bad_crc_then_good_reply_recovers_on_the_retry():
    reply = rtu(LOAD_CELL, read_reply(*words_of("f", 0.0, "little"), *words_of("f", 3.25, "little"), 0))
    corrupted = reply[:9] + bytes([reply[9] ^ 0x01]) + reply[10:]    # one bit of the net force flipped
    request = rtu(LOAD_CELL, read_request(0x3500, 5))
    with peer_for("rtu", [(request, corrupted), (request, reply)]) as peer:
        with machine_on(peer, "rtu", "little", timeout_s=0.1) as machine:
            assert machine.load_cell.read().force_N == 3.25


@pytest.mark.parametrize("transport", ["tcp", "rtu"])
def test_modbus_exception_reply_is_a_protocol_error(transport):
    frame = Frames(transport)
    with peer_for(transport, [frame(CROSSHEAD, read_request(0x602A, 2), bytes([0x83, 0x02]))]) as peer:
        with machine_on(peer, transport) as machine:
            with pytest.raises(DeviceProtocolError,
                               match=r"unit 2 refused read of actual_position \(0x602A\).*0x02 \(illegal data address\)"):
                machine.crosshead.read_position()


def test_write_exception_reply_is_a_protocol_error():
    frame = Frames("rtu")
    with peer_for("rtu", [frame(CROSSHEAD, write_single(0x6002, 0x0010), bytes([0x86, 0x04]))]) as peer:
        with machine_on(peer, "rtu") as machine:
            with pytest.raises(DeviceProtocolError, match=r"trigger \(0x6002\).*server device failure"):
                machine.crosshead._trigger("move_absolute")


@pytest.mark.parametrize("transport", ["tcp", "rtu", "rtu-socket"])
def test_silence_is_a_timeout_after_one_retry(transport):
    frame = Frames(transport)
    first = frame(LOAD_CELL, read_request(0x3500, 5))
    again = frame(LOAD_CELL, read_request(0x3500, 5), retry=True)
    with peer_for(transport, [first, again]) as peer:
        with machine_on(peer, transport, timeout_s=0.05, retries=1) as machine:
            with pytest.raises(DeviceTimeout, match=r"no reply to read of block \(0x3500.*unit 1 \(2 attempts of 50 ms\)"):
                machine.load_cell.read()


@pytest.mark.parametrize("transport", ["tcp", "rtu", "rtu-socket"])
def test_dropped_link_is_connection_lost(transport):
    frame = Frames(transport)
    with peer_for(transport, [(frame(CROSSHEAD, read_request(0x1003, 1))[0], CLOSE)]) as peer:
        with machine_on(peer, transport) as machine:
            with pytest.raises(DeviceConnectionLost, match="unit 2"):
                machine.crosshead.status()


def test_nothing_listening_is_connection_lost():
    with RecordedPeer([]) as peer:
        port = peer.port
    machine = open_machine(load_profile("sim-modbus-tcp"), connect=False, port=port)
    with pytest.raises(DeviceConnectionLost, match="cannot connect"):
        machine.connect()
    machine.close()


def test_rtu_device_path_that_does_not_exist_is_connection_lost():
    machine = open_machine(load_profile("sim-modbus-rtu"), connect=False, port_url="/dev/does-not-exist-foamlab")
    with pytest.raises(DeviceConnectionLost, match="/dev/does-not-exist-foamlab"):
        machine.connect()


def test_requests_from_two_threads_never_interleave():
    frame = Frames("tcp")
    n = 20
    block = read_reply(*words_of("f", 0.0, "big"), *words_of("f", 1.5, "big"), 0)
    exchanges = [frame(LOAD_CELL, read_request(0x3500, 5), block) for _ in range(2 * n)]
    results: list[float] = []
    with peer_for("tcp", exchanges) as peer:
        with machine_on(peer, "tcp") as machine:
            def worker():
                for _ in range(n):
                    results.append(machine.load_cell.read().force_N)
            threads = [threading.Thread(target=worker) for _ in range(2)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(timeout=10)
    assert results == [1.5] * (2 * n)


def test_a_late_answer_to_an_earlier_request_is_called_stale_not_corrupt():
    # The device answers request 2 with the reply it owed request 1 (which had timed out):
    # a well-formed frame whose MBAP transaction id is not the request's.
    frame = Frames("tcp")
    block = read_reply(*words_of("f", 0.0, "big"), *words_of("f", 1.5, "big"), 0)
    request, _ = frame(LOAD_CELL, read_request(0x3500, 5), block)
    late = mbap(frame.tid - 1, LOAD_CELL, block)
    with peer_for("tcp", [(request, late)]) as peer:
        with machine_on(peer, "tcp") as machine:
            with pytest.raises(DeviceProtocolError, match=r"stale reply to read of block.*transaction 0 answers "
                                                          r"an earlier request, not 1") as info:
                machine.load_cell.read()
    assert "\n" not in str(info.value)


def test_a_tcp_reply_whose_header_does_not_add_up_is_bad_framing():
    frame = Frames("tcp")
    block = read_reply(*words_of("f", 0.0, "big"), *words_of("f", 1.5, "big"), 0)
    request, reply = frame(LOAD_CELL, read_request(0x3500, 5), block)
    broken = reply[:2] + b"\x00\x07" + reply[4:]          # protocol id 7: not Modbus
    with peer_for("tcp", [(request, broken), (request, broken)]) as peer:
        with machine_on(peer, "tcp") as machine:
            with pytest.raises(DeviceProtocolError, match=r"invalid reply \(bad framing\) to read of block"):
                machine.load_cell.read()
