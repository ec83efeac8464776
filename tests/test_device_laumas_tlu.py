"""Laumas TLU transcripts, written from its manual: the fourth device (configs/devices/laumas-tlu.toml).

L1 = Laumas "Installation and User Manual, TLU - TLUANA" v1.04 p.30: registers 40001-40019 in
Modicon numbering (PDU address = number - 40001), 32-bit weights high word first (H at the lower
register), functions 03 and 16 only, exceptions 01/02/03 as `address, function + 0x80, code, CRC`,
no reply to a request with a bad CRC. L3 p.3 (the LCB's protocol page): weights are the displayed
value without its decimal point, their sign in the status register (bits 7-9), bit 11 stability,
bit 10 net mode. The manuals print no frames: the CRCs were computed here and are checked by two
CRC routines (rtu_transcript.frame). Unit 1 on the RTU line of sim-modbus-rtu-tlu (decimals 2, N).
Each transcript runs against the driver (a recorded peer) and, separately, against the simulator.
"""

from __future__ import annotations

import copy
import struct
import tomllib

import pytest

from drivers.base import DeviceRefused, LoadCellStatus
from drivers.profile import DEVICES_DIR, ProfileError, load_profile, open_machine, validate_profile
from drivers.registers import DeviceMap
from drivers.tlu import UnconfirmedCommand
from recorded_peer import rtu
from rtu_transcript import driver_on, frame, rtu_profile, simulated

pytestmark = pytest.mark.timeout(30)

PROFILE = "sim-modbus-rtu-tlu"
# 40007-40013 (0x0006, 7 registers): status, gross H/L, net H/L, peak H/L (L1 p.30)
READ_SAMPLE = "01 03 00 06 00 07 E4 09"
# status 0x0800 (bit 11 stable), gross 12345, net 12345, peak 12400: 123.45 N at 2 decimals
SAMPLE_STABLE = "01 03 0E 08 00 00 00 30 39 00 00 30 39 00 00 30 70 54 62"
# status 0x0D80: gross negative (7), net negative (8), net mode (10), stable (11); gross 250, net 2550
SAMPLE_NEGATIVE = "01 03 0E 0D 80 00 00 00 FA 00 00 09 F6 00 00 00 00 AE 31"
ILLEGAL_ADDRESS = "01 83 02 C0 F1"
SAVE_EEPROM = "01 10 00 05 00 01 02 00 63 E6 2C"          # command 99 in 40006, function 16 (L1 p.30)
SAVE_EEPROM_ECHO = "01 10 00 05 00 01 11 C8"              # FC 16 reply: start address and count


@pytest.fixture(scope="module")
def tlu() -> DeviceMap:
    with (DEVICES_DIR / "laumas-tlu.toml").open("rb") as f:
        return DeviceMap.from_toml(tomllib.load(f), "laumas-tlu.toml")


# ----------------------------------------------------------------------------- the device file

def test_the_documented_registers_at_their_pdu_addresses(tlu):
    # 40006 command, 40007 status, 40008/40010/40012 gross/net/peak high words (L1 p.30)
    assert {n: r.address for n, r in tlu.registers.items() if n in ("command", "status", "gross", "net", "peak")} \
        == {"command": 0x0005, "status": 0x0006, "gross": 0x0007, "net": 0x0009, "peak": 0x000B}
    assert tlu.functions == {3, 16} and tlu.word_order == "big"
    assert all(r.type != "float32" for r in tlu.registers.values())            # no floats documented
    assert tlu.blocks["sample"].count == 7 and not tlu.blocks["sample"].is_copy
    assert tlu.exceptions == {1: "illegal function", 2: "illegal data address", 3: "illegal data value"}


def test_what_only_third_party_code_says_is_unconfirmed(tlu):
    assert tlu.value("command", "save_eeprom") == 99 and tlu.provenance["[values.command] save_eeprom"].confirmed
    for name in ("semi_auto_zero", "tare"):
        where = tlu.provenance[f"[values.command] {name}"]
        assert not where.confirmed and where.source.startswith("T1") and "L1 p.31+" in where.settle
    assert all(not tlu.provenance[f"[bits.status] {name}"].confirmed for name in tlu.bits["status"])
    assert all(p.source for p in tlu.provenance.values())


def test_a_profile_without_the_displays_decimals_is_refused():
    profile = copy.deepcopy(load_profile(PROFILE))
    del profile["load_cell"]["decimals"]
    with pytest.raises(ProfileError, match=r"\[load_cell\] `decimals` must be 0..4: the decimals the TLU's "
                                           r"display shows .* got None") as info:
        validate_profile(profile)
    assert "\n" not in str(info.value)


# ----------------------------------------------------------------------------- (a) the driver

def test_a_sample_is_one_read_of_status_gross_net_peak():
    with driver_on([(READ_SAMPLE, SAMPLE_STABLE)], profile=PROFILE) as machine:
        reading = machine.load_cell.read()
    assert reading.force_N == pytest.approx(123.45)            # net 12345 at 2 decimals, in N
    assert reading.status == LoadCellStatus(stable=True)


def test_the_sign_is_the_status_bit_and_a_twos_complement_weight_reads_the_same():
    twos = "01 03 0E 0D 80 FF FF FF 06 FF FF F6 0A 00 00 00 00 AA D4"    # -250, -2550 as int32
    with driver_on([(READ_SAMPLE, SAMPLE_NEGATIVE), (READ_SAMPLE, twos)], profile=PROFILE) as machine:
        magnitude, complement = machine.load_cell.read(), machine.load_cell.read()
    assert magnitude.force_N == complement.force_N == pytest.approx(-25.5)
    assert magnitude.status == LoadCellStatus(stable=True, tare_set=True)


def test_over_110_percent_is_an_overload():
    over = "01 03 0E 00 08 00 00 EA 60 00 00 EA 60 00 00 EA 60 A5 A3"    # bit 3, 600.00 N
    with driver_on([(READ_SAMPLE, over)], profile=PROFILE) as machine:
        reading = machine.load_cell.read()
    assert reading.status.over_range and not reading.status.stable and reading.force_N == pytest.approx(600.0)


def test_a_load_cell_error_bit_fails_the_read_in_one_line():
    error = "01 03 0E 00 01 00 00 00 00 00 00 00 00 00 00 00 00 ED 94"   # bit 0 load cell error
    with driver_on([(READ_SAMPLE, error)], profile=PROFILE) as machine:
        with pytest.raises(DeviceRefused, match=r"unit 1 \(Laumas TLU\): status 0x0001 reports load_cell_error: "
                                                r"no weight to read") as info:
            machine.load_cell.read()
    assert "\n" not in str(info.value)


def test_an_exception_reply_is_device_refused_naming_the_block():
    with driver_on([(READ_SAMPLE, ILLEGAL_ADDRESS)], profile=PROFILE) as machine:
        with pytest.raises(DeviceRefused, match=r"unit 1 refused read of sample \(0x0006, 7 registers\): "
                                                r"Modbus exception 0x02 \(illegal data address\)"):
            machine.load_cell.read()


def test_zero_and_tare_are_refused_and_nothing_is_sent():
    with driver_on([], profile=PROFILE) as machine:                  # the peer fails on any byte sent
        with pytest.raises(UnconfirmedCommand, match=r"zero refused, nothing sent: its command value 8 is from "
                                                     r"T1 \(W100 code\), not a TLU manual; would settle it: "
                                                     r".*command list \(L1 p.31\+\)") as info:
            machine.load_cell.zero()
        with pytest.raises(UnconfirmedCommand, match=r"tare refused, nothing sent: its command value 130"):
            machine.load_cell.tare()
    assert "\n" not in str(info.value)


def test_identify_reads_the_instrument_type_and_firmware():
    exchanges = [("01 03 00 01 00 01 D5 CA", "01 03 02 00 05 78 47"),        # 40002 instrument type
                 ("01 03 00 00 00 01 84 0A", "01 03 02 01 04 B8 17")]        # 40001 firmware
    with driver_on(exchanges, profile=PROFILE) as machine:
        assert machine.load_cell.identify() == "Laumas TLU: instrument type 5, firmware 0x0104 " \
                                               "(encodings not documented)"


def test_the_probe_catches_gross_and_net_apart_without_net_mode():
    # status 0x0800 (no net mode), gross 12345, net 57: the LCB's bit map would not be the TLU's
    apart = rtu(bytes.fromhex("01 03 0E 08 00 00 00 30 39 00 00 00 39 00 00 30 70")).hex(" ")
    with driver_on([(READ_SAMPLE, apart)], profile=PROFILE) as machine:
        checks = {name: ok for name, ok, _ in machine.load_cell.self_checks()}
    assert checks == {"Laumas TLU status bits": False, "Laumas TLU decimals": True}


# ----------------------------------------------------------------------------- (b) the simulator

@pytest.fixture
def tlu_sim():
    with simulated(rtu_profile(PROFILE)) as parts:
        yield parts


def test_the_simulator_answers_the_sample_block(tlu_sim):
    machine, clock, wire = tlu_sim
    machine.move_to(20.0, 500.0)
    clock.advance(5.0)                                      # 15 mm into the foam, at rest
    reply = wire.ask(frame(READ_SAMPLE), 19)
    truth = machine.read_load_cell()                        # the same instant: no noise, manual clock
    assert truth.gross_N > 5.0 and truth.no_motion and not truth.tare_set
    counts = round(truth.net_N * 100)
    body = bytes.fromhex("01 03 0E") + struct.pack(">HiiI", 1 << 11, counts, counts, round(truth.peak_N * 100))
    assert reply == rtu(body)


def test_the_simulator_sends_the_magnitude_with_the_sign_bits(tlu_sim):
    machine, clock, wire = tlu_sim
    machine.move_to(20.0, 500.0)
    clock.advance(5.0)
    machine.tare()                                           # net 0 under the load ...
    machine.move_to(0.0, 500.0)
    clock.advance(10.0)                                      # ... then off it: net negative
    reply = wire.ask(frame(READ_SAMPLE), 19)
    truth = machine.read_load_cell()
    status, gross, net, _peak = struct.unpack(">HiiI", reply[3:17])
    assert truth.net_N < -5.0 and net == round(-truth.net_N * 100) > 0
    assert status & (1 << 8) and status & (1 << 10) and not status & (1 << 7)


@pytest.mark.parametrize("request_hex, reply_hex", [
    (SAVE_EEPROM, SAVE_EEPROM_ECHO),                                          # command 99 (L1 p.30)
    ("01 10 00 10 00 02 04 FF FF FA 24 B0 3C", "01 10 00 10 00 02 40 0D"),    # setpoint 1 = -1500
    ("01 06 00 05 00 63 D9 E2", "01 86 01 83 A0"),                            # function 06: not the TLU's
    ("01 04 00 06 00 07 51 C9", "01 84 01 82 C0"),                            # function 04 neither
    ("01 03 00 13 00 01 75 CF", ILLEGAL_ADDRESS),                             # beyond L1 p.30's list read
    ("01 10 00 07 00 02 04 00 00 00 01 73 89", "01 90 02 CD C1"),             # the gross weight is read-only
    ("01 10 00 05 00 01 02 00 08 A7 C3", "01 90 03 0C 01"),                   # 8: third-party zero, not simulated
    ("01 10 00 05 00 01 02 00 82 26 64", "01 90 03 0C 01"),                   # 130: third-party tare, neither
])
def test_the_simulator_answers_writes_and_undocumented_requests(tlu_sim, request_hex, reply_hex):
    machine, clock, wire = tlu_sim
    assert wire.ask(frame(request_hex), len(bytes.fromhex(reply_hex))) == frame(reply_hex)


def test_the_simulator_keeps_a_setpoint_and_reads_it_back(tlu_sim):
    machine, clock, wire = tlu_sim
    wire.ask(frame("01 10 00 10 00 02 04 FF FF FA 24 B0 3C"), 8)
    assert wire.ask(frame("01 03 00 10 00 02 C5 CE"), 9) == frame("01 03 04 FF FF FA 24 B8 AC")


def test_a_request_with_a_bad_crc_gets_no_reply(tlu_sim):
    machine, clock, wire = tlu_sim
    bad = bytearray(frame(READ_SAMPLE))
    bad[-1] ^= 0xFF
    assert wire.ask(bytes(bad), 1, timeout=0.3) == b""
    # still listening: the next good request gets its reply, and nothing came for the bad one
    assert wire.ask(frame("01 03 00 01 00 01 D5 CA"), 7) == frame("01 03 02 00 00 B8 44")


def test_the_driver_reads_the_simulated_tlu(tlu_sim):
    sim_machine, clock, wire = tlu_sim
    sim_machine.move_to(20.0, 500.0)
    clock.advance(5.0)
    machine = open_machine(rtu_profile(PROFILE), port_url=wire.url, timeout_s=0.5)
    try:
        reading = machine.load_cell.read()
        assert reading.force_N == pytest.approx(sim_machine.read_load_cell().net_N, abs=0.005)
        assert reading.status.stable and not reading.status.over_range
        assert all(ok for _, ok, _ in machine.load_cell.self_checks())
        with pytest.raises(UnconfirmedCommand):
            machine.load_cell.tare()
    finally:
        machine.close()
