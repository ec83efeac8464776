"""Flintec DAD 141.1 transcripts, written from its Modbus manual (S1 = E223-1 Rev. 2.2/2.3).

Unit 1 on the RTU line. Addresses and values are S1's (p.3 floats at 0x2000/0x2002, p.4
qualifier 0x2060 and bit commands 0x2061, p.10 block 0x3500); the CRCs were computed here
(the manual prints no frames) and are checked by two CRC routines in rtu_transcript.frame.
Each transcript runs against the driver (a recorded peer) and against the simulator.
"""

from __future__ import annotations

import struct

import pytest

from drivers.base import DeviceRefused, LoadCellStatus
from drivers.profile import open_machine
from recorded_peer import rtu
from rtu_transcript import driver_on, frame, rtu_profile, simulated

pytestmark = pytest.mark.timeout(30)

# 0x3500, 5 registers: gross 4.5 (40 90 00 00), net 4.25 (40 88 00 00), qualifier 0x0030
# (no motion 0x10 + tare set 0x20, S1 p.4). Floats high word first.
READ_BLOCK = "01 03 35 00 00 05 8A 05"
BLOCK_REPLY = "01 03 0A 40 90 00 00 40 88 00 00 00 30 64 AF"
SET_ZERO = "01 06 20 61 00 02 52 15"              # bit command 0x0002 "set zero" (S1 p.4)
SET_TARE = "01 06 20 61 00 08 D2 12"              # bit command 0x0008 "set tare" (S1 p.4)
READ_QUALIFIER = "01 03 20 60 00 01 8F D4"
ILLEGAL_ADDRESS = "01 83 02 C0 F1"


# ----------------------------------------------------------------------------- (a) the driver

def test_a_sample_is_one_block_read_gross_net_qualifier():
    with driver_on([(READ_BLOCK, BLOCK_REPLY)]) as machine:
        reading = machine.load_cell.read()
    assert reading.force_N == 4.25          # the net float (the block's second, S1 p.10)
    assert reading.status == LoadCellStatus(stable=True, tare_set=True)


def test_over_range_bit_is_an_overload_and_the_force_sign_is_kept():
    # gross -1.0 (BF 80 00 00), net -512.25 (C4 00 10 00), qualifier 0x0002 over range
    with driver_on([(READ_BLOCK, "01 03 0A BF 80 00 00 C4 00 10 00 00 02 E7 D2")]) as machine:
        reading = machine.load_cell.read()
    assert reading.force_N == -512.25
    assert reading.status.over_range and not reading.status.stable and not reading.status.under_range


def test_zero_writes_set_zero_and_tare_writes_set_tare_then_reads_the_tare_bit():
    exchanges = [(SET_ZERO, SET_ZERO),                                   # FC 06 replies echo the request
                 (SET_TARE, SET_TARE), (READ_QUALIFIER, "01 03 02 00 30 B8 50")]
    with driver_on(exchanges) as machine:
        machine.load_cell.zero()
        machine.load_cell.tare()


def test_a_tare_the_indicator_did_not_take_is_refused_in_one_line():
    exchanges = [(SET_TARE, SET_TARE), (READ_QUALIFIER, "01 03 02 00 10 B9 88")]   # no motion, no tare bit
    with driver_on(exchanges) as machine:
        with pytest.raises(DeviceRefused, match=r"unit 1 did not take set_tare \(bit_commands \(0x2061\) = "
                                                r"0x0008\): qualifier \(0x2060\) reads 0x0010") as info:
            machine.load_cell.tare()
    assert "\n" not in str(info.value)


def test_an_exception_reply_is_device_refused_naming_the_register():
    with driver_on([(READ_BLOCK, ILLEGAL_ADDRESS)]) as machine:
        with pytest.raises(DeviceRefused, match=r"unit 1 refused read of result \(0x3500, 5 registers\): "
                                                r"Modbus exception 0x02 \(illegal data address\)") as info:
            machine.load_cell.read()
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- (b) the simulator

def f32(value: float) -> bytes:
    return struct.pack(">f", value)


def test_the_simulator_answers_the_block_with_gross_net_and_qualifier():
    with simulated() as (machine, clock, wire):
        machine.move_to(20.0, 500.0)
        clock.advance(5.0)                                  # 15 mm into the foam
        wire.ask(frame(SET_TARE), 8)
        reply = wire.ask(frame(READ_BLOCK), 15)
        truth = machine.read_load_cell()                    # the same instant: no noise, manual clock
    assert truth.gross_N > 5.0 and truth.tare_set
    expected = bytes.fromhex("01 03 0A") + f32(truth.gross_N) + f32(truth.net_N) + bytes([0, 0x30])
    assert reply == expected + reply[-2:] and frame(reply.hex()) == reply


def test_the_simulator_echoes_set_zero_and_does_it():
    with simulated(load_cell_offset_N=3.0) as (machine, clock, wire):
        assert machine.read_load_cell().gross_N == pytest.approx(3.0)
        assert wire.ask(frame(SET_ZERO), 8) == frame(SET_ZERO)
        assert machine.read_load_cell().gross_N == 0.0
        assert wire.ask(frame("01 06 20 61 00 01 12 14"), 8) == frame("01 06 20 61 00 01 12 14")   # reset zero
        assert machine.read_load_cell().gross_N == pytest.approx(3.0)


def test_the_simulator_takes_no_tare_while_the_load_moves():
    with simulated() as (machine, clock, wire):
        machine.move_to(20.0, 500.0)
        clock.advance(2.5)                                  # still compressing: not stable
        assert wire.ask(frame(SET_TARE), 8) == frame(SET_TARE)
        assert wire.ask(frame(READ_QUALIFIER), 7) == frame("01 03 02 00 00 B8 44")   # neither stable nor tared
        assert not machine.read_load_cell().tare_set


@pytest.mark.parametrize("request_hex, reply_hex", [
    ("01 03 20 04 00 02 8E 0A", ILLEGAL_ADDRESS),            # 0x2004: no peak there (peak is 0x2080, S1 p.6)
    ("01 03 20 10 00 02 CE 0E", ILLEGAL_ADDRESS),            # 0x2010: no capacity register
    ("01 06 20 00 00 01 43 CA", "01 86 02 C3 A1"),           # the gross float is read-only
    ("01 06 20 61 00 03 93 D5", "01 86 03 02 61"),           # two bits at once: not one documented value
    ("01 01 20 60 00 01 F6 14", "01 81 01 81 90"),           # coils: not among functions 03/04/06/16
])
def test_the_simulator_answers_undocumented_requests_with_exceptions(request_hex, reply_hex):
    with simulated() as (machine, clock, wire):
        assert wire.ask(frame(request_hex), 5) == frame(reply_hex)


def test_function_4_reads_the_same_block():
    with simulated() as (machine, clock, wire):
        holding = wire.ask(frame(READ_BLOCK), 15)
        inputs = wire.ask(frame("01 04 35 00 00 05 3F C5"), 15)
    assert inputs[1] == 0x04 and inputs[2:-2] == holding[2:-2]


# ----------------------------------------------------------------------------- foamlab probe's reads

def _read(address: int, count: int, *words: int) -> tuple[str, str]:
    request = rtu(1, struct.pack(">BHH", 3, address, count))
    return request.hex(" "), rtu(1, bytes([3, 2 * len(words)]) + struct.pack(f">{len(words)}H", *words)).hex(" ")


def test_the_probe_reads_settle_the_block_order_and_catch_a_swapped_one():
    """With a tare gross != net: 0x3500 must hold 0x2000's value first (S1 p.10), not GW's net first."""
    gross, net = struct.unpack(">HH", f32(12.5)), struct.unpack(">HH", f32(2.5))
    exchanges = [_read(0x202E, 2, 0x0000, 0x0601), _read(0x2000, 2, *gross), _read(0x2020, 2, 0x0000, 1250),
                 _read(0x2002, 2, *net), _read(0x3500, 5, *net, *gross, 0x0030)]      # swapped
    with driver_on(exchanges) as machine:
        checks = {name: (ok, detail) for name, ok, detail in machine.load_cell.self_checks()}
    assert checks["DAD 141.1 address base"][0] and checks["DAD 141.1 float word order"][0]
    assert checks["DAD 141.1 order of 0x3500"] == (False, "0x3500 holds 2.5, 12.5; 0x2000 gross 12.5, 0x2002 net 2.5")


def test_a_float_in_the_other_word_order_is_caught():
    swapped = struct.unpack(">HH", f32(12.5))[::-1]                      # low word first
    exchanges = [_read(0x202E, 2, 0x0000, 0x0601), _read(0x2000, 2, *swapped), _read(0x2020, 2, 0x0000, 1250),
                 _read(0x2002, 2, *swapped), _read(0x3500, 5, *swapped, *swapped, 0x0010)]
    with driver_on(exchanges) as machine:
        checks = {name: ok for name, ok, _ in machine.load_cell.self_checks()}
    assert checks == {"DAD 141.1 address base": True, "DAD 141.1 float word order": False,
                      "DAD 141.1 order of 0x3500": True}                # no tare: not settled, said so


def test_the_probe_reads_pass_on_the_simulated_unit():
    with simulated(load_cell_offset_N=30.0, noise_sigma_N=0.05) as (sim_machine, clock, wire):
        machine = open_machine(rtu_profile(), port_url=wire.url, timeout_s=0.5)
        try:
            machine.load_cell.tare()                                   # 30 N: settles the block order
            assert machine.identify().startswith("Flintec DAD 141.1: device id 1410, firmware 1.06")
            assert all(ok for _, ok, _ in machine.self_checks()), machine.self_checks()
        finally:
            machine.close()
