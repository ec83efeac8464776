"""The simulated machine's wire protocols, seen from the wire (not through the drivers).

A pymodbus client and raw socket / pty I/O talk to the servers of simulator/launch.py.
Most tests use a SimulatedMachine on a ManualClock with a noise-free load cell, so the
machine's state does not move between a wire read and the reference read: values are
compared exactly (to the register resolution).
"""

from __future__ import annotations

import os
import re
import select
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
import tty
from pathlib import Path

import pytest
from pymodbus.client import ModbusSerialClient, ModbusTcpClient
from pymodbus.framer import FramerRTU, FramerType

from drivers.modbus import device_map
from drivers.profile import load_profile
from foamlab.cli import main as foamlab_main
from simulator.clock import ManualClock
from simulator.launch import start_simulator
from simulator.machine import SimulatedMachine
from simulator.faults import FaultPlan

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]

ROOT = Path(__file__).resolve().parent.parent
MODBUS_TRANSPORTS = ("modbus-tcp", "modbus-rtu", "modbus-rtu-pty")
PROFILE_OF = {"modbus-tcp": "sim-modbus-tcp", "modbus-rtu": "sim-modbus-rtu",
              "modbus-rtu-pty": "sim-modbus-rtu", "serial": "sim-serial"}
# The devices as their device files describe them (a Flintec DAD 141.1, a Leadshine CS2RS);
# the byte-exact transcripts of each are in tests/test_device_*.py.
LC = device_map(load_profile("sim-modbus-tcp"), "load_cell")
CH = device_map(load_profile("sim-modbus-tcp"), "crosshead")
A = {**{k: r.address for k, r in LC.registers.items()}, "block": LC.blocks["result"].address,
     **{f"ch_{k}": r.address for k, r in CH.registers.items()}}
TRIG = CH.values["trigger"]
LC_UNIT, CH_UNIT = 1, 2
#: The profiles' screw: lead 4 mm, gear 10, 10 000 pulses/rev -> pulses per mm, mm/min per rpm.
PULSES_PER_MM, MM_MIN_PER_RPM = 25000, 0.4


# ----------------------------------------------------------------------------- helpers

def manual_machine(transport: str, faults=(), **settings):
    clock = ManualClock()
    profile = load_profile(PROFILE_OF[transport])
    machine = SimulatedMachine(profile, clock=clock, noise_sigma_N=0.0,
                               faults=FaultPlan(list(faults)), **settings)
    return machine, clock


def pymodbus_client(sim):
    if sim.transport == "modbus-tcp":
        client = ModbusTcpClient(sim.server.host, port=sim.server.port, timeout=3, retries=0)
    else:
        client = ModbusSerialClient(sim.server.client_url, framer=FramerType.RTU, baudrate=115200,
                                    timeout=3, retries=0)
    assert client.connect()
    return client


def f32(regs):
    """Two registers, high word first (both devices' order) -> float32."""
    return struct.unpack(">f", struct.pack(">HH", *regs))[0]


def i32(regs):
    return struct.unpack(">i", struct.pack(">HH", *regs))[0]


def to_i32(value):
    return list(struct.unpack(">HH", struct.pack(">i", int(value))))


class RawLink:
    """Bytes in, bytes out: a TCP socket or a pty opened by path (as a serial client would)."""

    def __init__(self, sim):
        self.sock = self.fd = None
        if sim.transport in ("modbus-rtu-pty", "serial"):
            self.fd = os.open(sim.server.client_url, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            tty.setraw(self.fd)
        else:
            self.sock = socket.create_connection((sim.server.host, sim.server.port), timeout=2)

    def fileno(self):
        return self.fd if self.fd is not None else self.sock.fileno()

    def send(self, data: bytes) -> None:
        if self.sock:
            self.sock.sendall(data)
        else:
            os.write(self.fd, data)

    def recv(self, timeout: float, *, n: int | None = None, until: bytes | None = None) -> bytes:
        """Read until n bytes / the `until` marker / EOF / timeout; EOF on a pty reads as b""
        too (EIO: the line was hung up). Returns what arrived."""
        data = b""
        deadline = time.monotonic() + timeout
        while (n is None or len(data) < n) and (until is None or until not in data):
            left = deadline - time.monotonic()
            if left <= 0 or not select.select([self.fileno()], [], [], left)[0]:
                break
            try:
                chunk = self.sock.recv(4096) if self.sock else os.read(self.fd, 4096)
            except OSError:  # EIO from a hung-up pty
                chunk = b""
            if not chunk:
                raise EOFError(data)
            data += chunk
        return data

    def close(self):
        if self.sock:
            self.sock.close()
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None


def wait_for(predicate, timeout: float = 2.0) -> bool:
    """Poll a condition another thread makes true, with a deadline."""
    deadline = time.monotonic() + timeout
    while not predicate():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.005)
    return True


def rtu_frame(unit: int, pdu: bytes) -> bytes:
    body = bytes([unit]) + pdu
    return body + FramerRTU.compute_CRC(body).to_bytes(2, "big")


def rtu_crc_ok(frame: bytes) -> bool:
    return len(frame) >= 4 and FramerRTU.compute_CRC(frame[:-2]) == int.from_bytes(frame[-2:], "big")


def read_request(transport: str, unit: int, address: int, count: int, tid: int = 1) -> bytes:
    pdu = struct.pack(">BHH", 3, address, count)
    if transport == "modbus-tcp":
        return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu
    return rtu_frame(unit, pdu)


def reply_length(transport: str, pdu_len: int) -> int:
    return 7 + pdu_len if transport == "modbus-tcp" else 3 + pdu_len


def split_reply(transport: str, frame: bytes) -> tuple[int, bytes]:
    """(unit, pdu) of a well-formed reply; AssertionError otherwise."""
    if transport == "modbus-tcp":
        tid, pid, length, unit = struct.unpack(">HHHB", frame[:7])
        assert pid == 0 and length == len(frame) - 6, frame.hex()
        return unit, frame[7:]
    assert rtu_crc_ok(frame), frame.hex()
    return frame[0], frame[1:-2]


# ----------------------------------------------------------------------------- registers

@pytest.mark.parametrize("transport", MODBUS_TRANSPORTS)
def test_registers_decode_to_the_machine_state(transport):
    machine, clock = manual_machine(transport)
    machine.move_to(25.0, 300.0)
    clock.advance(3.0)   # moving down, 15+ mm into the foam (its top is 5 mm below zero)
    with start_simulator(transport, machine=machine) as sim:
        client = pymodbus_client(sim)
        try:
            block = client.read_holding_registers(A["block"], count=5, device_id=LC_UNIT).registers
            gross = client.read_holding_registers(A["gross"], count=2, device_id=LC_UNIT).registers
            net_int = client.read_holding_registers(A["net_int"], count=2, device_id=LC_UNIT).registers
            peak = client.read_holding_registers(A["peak"], count=2, device_id=LC_UNIT).registers
            qualifier = client.read_holding_registers(A["qualifier"], count=1, device_id=LC_UNIT).registers[0]
            positions = client.read_holding_registers(A["ch_command_position"], count=4, device_id=CH_UNIT).registers
            ch_status = client.read_holding_registers(A["ch_status"], count=1, device_id=CH_UNIT).registers[0]
            alarm = client.read_holding_registers(A["ch_alarm"], count=1, device_id=CH_UNIT).registers[0]
            ppr = client.read_holding_registers(A["ch_pulses_per_rev"], count=1, device_id=CH_UNIT).registers[0]
        finally:
            client.close()
        ref = machine.read_load_cell()   # same virtual time: identical without noise
        state = machine.crosshead_status()
        assert ref.net_N > 5.0, "the plate should be in the foam"
        assert f32(block[0:2]) == pytest.approx(ref.gross_N, rel=1e-6)      # gross, net, qualifier (S1 p.10)
        assert f32(block[2:4]) == pytest.approx(ref.net_N, rel=1e-6)
        assert f32(gross) == pytest.approx(ref.gross_N, rel=1e-6)
        assert i32(net_int) == round(ref.net_N * 100)                        # increments of 0.01 N
        assert f32(peak) == pytest.approx(ref.peak_N, rel=1e-6)
        bits = LC.bits["qualifier"]
        assert block[4] == qualifier == sum(1 << bits[k] for k in bits if getattr(ref, k))
        assert i32(positions[0:2]) == i32(positions[2:4]) == round(machine.position_mm() * PULSES_PER_MM)
        assert machine.speed_mm_min() == pytest.approx(300.0)
        assert ch_status == 0x0006 and state.moving                          # enabled + running
        assert alarm == 0 and ppr == 10000


def test_32_bit_values_are_high_word_first():
    """Both devices document high word first: 500.0 (float32 0x43FA0000) and -2 pulses."""
    machine, _ = manual_machine("modbus-tcp", load_cell_offset_N=500.0, capacity_N=1000.0)
    with start_simulator("modbus-tcp", machine=machine) as sim:
        client = pymodbus_client(sim)
        try:
            assert client.read_holding_registers(A["gross"], count=2, device_id=LC_UNIT).registers == [0x43FA, 0x0000]
            client.write_registers(A["ch_pr0_position"], to_i32(-2), device_id=CH_UNIT)
            raw = client.read_holding_registers(A["ch_pr0_position"], count=2, device_id=CH_UNIT).registers
            assert raw == [0xFFFF, 0xFFFE]
        finally:
            client.close()


# ----------------------------------------------------------------------------- writes act

def pr0(client, position_mm: float, speed_mm_min: float, ramp_ms: int = 133, mode: int = 0x0001) -> None:
    """Write the PR0 block (mode, position in pulses, rpm, ramps) in one function-16 request."""
    words = [mode, *to_i32(round(position_mm * PULSES_PER_MM)), round(speed_mm_min / MM_MIN_PER_RPM), ramp_ms, ramp_ms]
    assert not client.write_registers(A["ch_pr0_mode"], words, device_id=CH_UNIT).isError()


def test_crosshead_writes_act_on_the_physics():
    machine, clock = manual_machine("modbus-tcp")
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            def trigger(name):
                assert not c.write_register(A["ch_trigger"], TRIG[name], device_id=CH_UNIT).isError()

            def status():
                return c.read_holding_registers(A["ch_status"], count=1, device_id=CH_UNIT).registers[0]

            pr0(c, 12.345, 300.0)
            trigger("start_path0")
            assert machine.crosshead_status().moving
            clock.advance(10.0)
            assert machine.position_mm() == pytest.approx(12.345, abs=1e-9)
            assert status() == 0x0032                                        # enabled, command done, path done

            trigger("set_zero")
            assert machine.position_mm() == 0.0
            pr0(c, -3.0, 300.0, mode=CH.values["pr0_mode"]["relative"])     # 3 mm up from here
            trigger("start_path0")
            clock.advance(0.5)
            assert machine.speed_mm_min() == pytest.approx(-300.0)
            trigger("quick_stop")                                            # immediate in the simulation
            assert not machine.crosshead_status().moving and -3.0 < machine.position_mm() < 0.0
            assert status() == 0x0012                                        # no alarm: a stop is not a fault
            assert machine.crosshead_status().emergency_stop                 # what the machine records

            # the ramp: 1 mm/s^2 is 6667 ms per 1000 rpm; a 1 mm move at 5 mm/s is a triangle, 0.5 mm after 1 s
            start = machine.position_mm()
            pr0(c, start + 1.0, 300.0, ramp_ms=6667)
            trigger("start_path0")                                           # runs: the quick stop latched nothing
            clock.advance(1.0)
            assert machine.position_mm() - start == pytest.approx(0.5, abs=1e-3)
            clock.advance(2.0)

            # no soft limits on the drive: the machine's travel (its limit switches) stops a move
            pr0(c, 75.0, 500.0)                                              # beyond the profile's 70 mm
            trigger("start_path0")
            clock.advance(20.0)
            assert machine.position_mm() == pytest.approx(70.0, abs=1e-6)

            assert not c.write_register(A["ch_control_word"], CH.values["control_word"]["reset_alarm"],
                                        device_id=CH_UNIT).isError()
            assert not machine.crosshead_status().emergency_stop
        finally:
            c.close()


def test_the_drive_has_no_watchdog_a_triggered_move_runs_to_its_end():
    """No host watchdog is documented for the CS2RS: a silent host does not stop a move."""
    machine, clock = manual_machine("modbus-tcp")
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            pr0(c, 60.0, 100.0)
            assert not c.write_register(A["ch_trigger"], TRIG["start_path0"], device_id=CH_UNIT).isError()
            clock.advance(40.0)                                              # silent for 40 s
            assert machine.position_mm() == pytest.approx(60.0, abs=1e-9)
            assert machine.crosshead_status().fault_code == 0
        finally:
            c.close()


def test_load_cell_commands():
    machine, clock = manual_machine("modbus-tcp")
    machine.move_to(20.0, 500.0)
    clock.advance(15.0)          # at rest in the foam long enough for the reading to settle
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            def command(name):
                value = LC.values["bit_commands"][name]
                assert not c.write_register(A["bit_commands"], value, device_id=LC_UNIT).isError()

            assert machine.read_load_cell().net_N > 5.0 and machine.read_load_cell().no_motion
            command("set_tare")
            r = machine.read_load_cell()
            assert r.tare_set and abs(r.net_N) <= 0.01 and r.gross_N > 5.0
            command("reset_tare")
            assert not machine.read_load_cell().tare_set
            command("set_zero")          # refused: far beyond 2 % of the capacity from the calibration zero
            assert machine.read_load_cell().gross_N > 5.0
            clock.advance(1.0)
            command("reset_max")
            r = machine.read_load_cell()
            assert r.peak_N == pytest.approx(r.net_N, abs=0.011)
        finally:
            c.close()


def test_bad_addresses_and_values_answer_modbus_exceptions():
    machine, _ = manual_machine("modbus-tcp")
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            def code(resp):
                assert resp.isError(), resp
                return resp.exception_code

            assert code(c.read_holding_registers(0x0000, count=1, device_id=LC_UNIT)) == 0x02
            assert code(c.read_holding_registers(A["gross"], count=2, device_id=CH_UNIT)) == 0x02
            assert code(c.read_holding_registers(A["block"] + 3, count=5, device_id=LC_UNIT)) == 0x02
            assert code(c.read_holding_registers(0x2004, count=2, device_id=LC_UNIT)) == 0x02     # no peak there
            assert code(c.read_holding_registers(0x6010, count=1, device_id=CH_UNIT)) == 0x02     # homing: not served
            assert code(c.write_register(A["gross"], 1, device_id=LC_UNIT)) == 0x02              # read-only
            assert code(c.write_register(A["ch_motor_position"], 1, device_id=CH_UNIT)) == 0x02
            assert code(c.write_register(A["ch_trigger"], 0x99, device_id=CH_UNIT)) == 0x03      # no such trigger
            assert code(c.write_register(A["bit_commands"], 0x0003, device_id=LC_UNIT)) == 0x03  # two bits at once
            assert code(c.write_register(A["ch_pulses_per_rev"], 100, device_id=CH_UNIT)) == 0x03  # below 200
            assert code(c.read_input_registers(A["ch_status"], count=1, device_id=CH_UNIT)) == 0x01  # not FC 04
            # a refused write leaves the stored value as it was
            assert c.read_holding_registers(A["ch_pulses_per_rev"], count=1, device_id=CH_UNIT).registers == [10000]
            pr0(c, 10.0, 600.0)                                                                   # 1500 rpm > 1250
            assert code(c.write_register(A["ch_trigger"], TRIG["start_path0"], device_id=CH_UNIT)) == 0x03
            assert code(c.read_holding_registers(A["block"], count=5, device_id=7)) == 0x0B  # no such unit
            assert not machine.crosshead_status().moving
        finally:
            c.close()


def test_rtu_unit_not_on_the_line_gets_no_reply():
    machine, _ = manual_machine("modbus-rtu")
    with start_simulator("modbus-rtu", machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(read_request("modbus-rtu", 9, A["block"], 5))
            assert link.recv(0.3, n=1) == b""
            link.send(read_request("modbus-rtu", LC_UNIT, A["block"], 5))
            unit, pdu = split_reply("modbus-rtu", link.recv(2.0, n=15))
            assert unit == LC_UNIT and pdu[:2] == b"\x03\x0a"
        finally:
            link.close()


# ----------------------------------------------------------------------------- wire faults

@pytest.mark.parametrize("transport", MODBUS_TRANSPORTS)
@pytest.mark.parametrize("fault", ["drop", "timeout", "exception", "crc", "garbage"])
def test_modbus_wire_fault_is_seen_on_the_wire_once(transport, fault):
    machine, _ = manual_machine(transport, faults=[f"{fault}@0"])
    request = read_request(transport, LC_UNIT, A["block"], 5)
    good_len = reply_length(transport, 2 + 10)
    with start_simulator(transport, machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(request)
            if fault == "drop":
                with pytest.raises(EOFError):
                    link.recv(2.0, n=good_len)
                link.close()
                if transport == "modbus-rtu-pty":
                    assert wait_for(lambda: sim.server.pty.generation == 2), "a fresh pty replaces the hung-up one"
                link = RawLink(sim)   # reconnect: same address / same path
                link.send(request)
            elif fault == "timeout":
                assert link.recv(0.3, n=1) == b""
                link.send(request)
            elif fault == "exception":
                unit, pdu = split_reply(transport, link.recv(2.0, n=reply_length(transport, 2)))
                assert pdu == bytes([0x83, 0x04])
                link.send(request)
            else:  # crc / garbage: a reply of the right size that a careful client rejects
                bad = link.recv(2.0, n=good_len)
                assert len(bad) == good_len
                with pytest.raises(AssertionError):
                    split_reply(transport, bad)
                link.send(request)
            unit, pdu = split_reply(transport, link.recv(2.0, n=good_len))
            assert unit == LC_UNIT and pdu[:2] == b"\x03\x0a", "the next request is answered normally"
            assert [name for _, name in machine.faults.fired] == [fault]
        finally:
            link.close()


@pytest.mark.parametrize("fault, done", [("timeout", False), ("exception", False), ("crc", True),
                                         ("garbage", True)])
def test_a_faulted_write_is_done_only_when_the_reply_was_hit(fault, done):
    machine, _ = manual_machine("modbus-rtu", faults=[f"{fault}@0"])
    with start_simulator("modbus-rtu", machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(rtu_frame(LC_UNIT, struct.pack(">BHH", 6, A["bit_commands"], LC.values["bit_commands"]["set_tare"])))
            link.recv(0.3, n=8)
            assert machine.read_load_cell().tare_set is done
        finally:
            link.close()


# ----------------------------------------------------------------------------- ASCII (ESM303 + Series 5)
# What the simulated ESM303 answers to each documented command: tests/test_device_mark10.py.

def test_esm303_overload_is_a_full_scale_reading_not_an_error():
    # the vendor's `*22` is "value too large" (a parameter error), not an overload: the gauge
    # keeps answering, at its full scale; the driver flags over range from the capacity
    machine, clock = manual_machine("serial", faults=["overload@1+2"])
    with start_simulator("serial", machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(b"/?C\r\\")
            assert link.recv(2.0, until=b"\r\n") == b"0.000 N\r\n"
            clock.advance(1.5)
            full_scale = machine.settings.capacity_N * machine.settings.full_scale_ratio
            link.send(b"n")
            assert link.recv(2.0, n=len(f"{full_scale:.3f} N\r\n0.00 mm\r\n")) == \
                f"{full_scale:.3f} N\r\n0.00 mm\r\n".encode()
        finally:
            link.close()


@pytest.mark.parametrize("fault", ["drop", "timeout", "exception", "crc", "garbage"])
@pytest.mark.parametrize("channel, asked, normal", [("stand", b"x", b"0.00 mm\r\n"),
                                                      ("gauge", b"/?C\r\\", b"0.000 N\r\n")])
def test_esm303_wire_fault_is_seen_on_the_wire_once(fault, channel, asked, normal):
    machine, _ = manual_machine("serial", faults=[f"{fault}@0"])
    with start_simulator("serial", machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(asked)
            if fault == "drop":
                with pytest.raises(EOFError):
                    link.recv(2.0, until=b"\r\n")
                link.close()
                assert wait_for(lambda: sim.server.pty.generation == 2), "a fresh pty replaces the hung-up one"
                link = RawLink(sim)
            elif fault == "timeout" or (fault == "exception" and channel == "stand"):
                assert link.recv(0.3, n=1) == b""     # not done; the stand ignores a garbled command
            else:
                got = link.recv(2.0, until=b"\r\n")
                assert got.endswith(b"\r\n") and got != normal
                if fault == "exception":
                    assert got == b"*10\r\n"          # the gauge: illegal command
                else:   # crc / garbage: not a valid reply
                    assert any(b >= 0x80 for b in got) or not re.fullmatch(rb"-?\d+\.\d+ (mm|N)\r\n", got)
            link.send(asked)
            assert link.recv(2.0, until=b"\r\n") == normal
            assert [name for _, name in machine.faults.fired] == [fault]
        finally:
            link.close()


# ----------------------------------------------------------------------------- lifecycle

def _open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


@pytest.mark.parametrize("transport", MODBUS_TRANSPORTS + ("serial",))
def test_stop_leaves_no_threads_or_fds(transport):
    threads_before = set(threading.enumerate())
    fds_before = _open_fds()
    sim = start_simulator(transport, speedup=10.0)   # owns its machine (physics ticker thread)
    pty_dir = Path(sim.server.client_url).parent if transport in ("modbus-rtu-pty", "serial") else None
    link = RawLink(sim)   # a client still connected when the server stops
    link_fd = str(link.fileno())
    if transport == "serial":
        link.send(b"x")
        assert link.recv(2.0, until=b"\r\n").endswith(b" mm\r\n")
    else:
        link.send(read_request(transport, LC_UNIT, A["block"], 5))
        assert len(link.recv(2.0, n=reply_length(transport, 12))) == reply_length(transport, 12)
    assert len(set(threading.enumerate()) - threads_before) >= 2   # server loop + physics ticker
    sim.stop()
    sim.stop()   # idempotent
    assert not sim.running
    assert set(threading.enumerate()) - threads_before == set()
    link.close()
    assert _open_fds() - fds_before - {link_fd} == set()
    if pty_dir is not None:
        assert not pty_dir.exists()


def test_port_in_use_is_an_error_and_leaves_nothing_running():
    with start_simulator("modbus-tcp", speedup=10.0) as sim:
        threads = set(threading.enumerate())
        with pytest.raises(OSError):
            start_simulator("modbus-tcp", port=sim.server.port, speedup=10.0)
        assert set(threading.enumerate()) - threads == set()


# ----------------------------------------------------------------------------- foamlab sim

@pytest.mark.parametrize("argv, message", [
    (["--transport", "modbus-tcp", "--effect", "nope"], "NAME=MAGNITUDE"),
    (["--transport", "modbus-tcp", "--port", "0", "--fault", "explode@1"], "unknown fault"),
    (["--transport", "modbus-tcp", "--port", "70000"], "--port"),
    (["--transport", "modbus-tcp", "--speedup", "-1"], "--speedup"),
    (["--transport", "serial", "--port", "5020"], "pty"),
    (["--device", "mark10-esm303", "--port", "5020"], "pty"),
    (["--device", "nope"], "unknown device 'nope'"),
    (["--device", "mark10-esm303", "--transport", "modbus-tcp"], "--device or --transport"),
    ([], "--device or --transport"),
    (["--transport", "modbus-tcp", "--pty"], "--pty"),
    (["--transport", "modbus-tcp", "--port", "0", "--specimen", "/nonexistent/fit.json"], "fit.json"),
    (["--transport", "modbus-tcp", "--port", "x"], "invalid int"),
    (["--transport", "smoke-signals"], "invalid choice"),
])
def test_sim_command_bad_arguments_one_line_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(foamlab_main(["sim", *argv]))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err


def _start_cli(*args) -> tuple[subprocess.Popen, list[str]]:
    proc = subprocess.Popen([sys.executable, "-m", "foamlab.cli", "sim", *args], cwd=ROOT,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: list[str] = []
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line.rstrip("\n"))
        if "Ctrl-C" in line:
            return proc, lines
    proc.kill()
    raise AssertionError(f"foamlab sim did not start: {lines} {proc.stderr.read()}")


def test_sim_command_serves_until_sigterm():
    proc, lines = _start_cli("--transport", "modbus-tcp", "--port", "0", "--speedup", "10")
    try:
        m = re.search(r"serving at 127\.0\.0\.1:(\d+)", lines[0])
        assert m and "profile: sim-modbus-tcp" in "\n".join(lines), lines
        client = ModbusTcpClient("127.0.0.1", port=int(m[1]), timeout=2, retries=0)
        assert client.connect()
        ppr = client.read_holding_registers(A["ch_pulses_per_rev"], count=1, device_id=CH_UNIT)
        client.close()
        assert ppr.registers == [10000]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped" in out and "Traceback" not in err


@pytest.mark.parametrize("argv", [("--device", "mark10-esm303"), ("--transport", "serial")])
def test_sim_command_esm303_prints_a_pty_path_that_answers_until_ctrl_c(argv):
    proc, lines = _start_cli(*argv, "--speedup", "10")
    try:
        m = re.search(r"serving at (\S+) \(pty (/dev/pts/\d+)\)", lines[0])
        assert m, lines
        fd = os.open(m[1], os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(fd)
            os.write(fd, b"x")
            reply = b""
            deadline = time.monotonic() + 5
            while not reply.endswith(b"\r\n") and time.monotonic() < deadline:
                if select.select([fd], [], [], 0.2)[0]:
                    reply += os.read(fd, 100)
            assert reply == b"0.00 mm\r\n"
            assert "device mark10-esm303" in "\n".join(lines)
        finally:
            os.close(fd)
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=15)
        assert proc.returncode == 0, err
        assert "stopped" in out and "Traceback" not in err
        assert not Path(m[1]).exists()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


@pytest.mark.timeout(60)
def test_simulator_process_stops_when_its_parent_is_killed():
    """A `foamlab run` killed outright (SIGKILL: no cleanup) must not leave its simulated
    machine serving forever (a CI run found one 23 min later, holding its port)."""
    repo = Path(__file__).resolve().parent.parent
    code = ("import sys, time; sys.path.insert(0, sys.argv[1]); "
            "from simulator.process import start_simulator_process; "
            "sim = start_simulator_process('modbus-tcp', speedup=1); print(sim.process.pid, flush=True); "
            "time.sleep(60)")
    parent = subprocess.Popen([sys.executable, "-c", code, str(repo)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(parent.stdout.readline())
    finally:
        parent.kill()
        parent.wait()
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        try:
            os.kill(child, 0)
        except ProcessLookupError:
            return
        time.sleep(0.1)
    os.kill(child, signal.SIGKILL)
    pytest.fail("the simulator process outlived its killed parent by 20 s")
