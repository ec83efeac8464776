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
WIRE = load_profile("sim-modbus-tcp")["wire"]
LC, CH = WIRE["load_cell"], WIRE["crosshead"]
A = {**{k: v["address"] for k, v in LC.items() if isinstance(v, dict) and "address" in v},
     **{f"ch_{k}": v["address"] for k, v in CH.items() if isinstance(v, dict) and "address" in v}}
TRIG = CH["triggers"]
LC_UNIT, CH_UNIT = 1, 2


# ----------------------------------------------------------------------------- helpers

def manual_machine(transport: str, faults=(), **settings):
    clock = ManualClock()
    profile = load_profile(PROFILE_OF[transport])
    machine = SimulatedMachine(profile, clock=clock, noise_sigma_N=0.0,
                               faults=FaultPlan(list(faults)), **settings)
    return machine, clock


def word_order(transport: str) -> str:
    return load_profile(PROFILE_OF[transport])["word_order"]


def pymodbus_client(sim):
    if sim.transport == "modbus-tcp":
        client = ModbusTcpClient(sim.server.host, port=sim.server.port, timeout=3, retries=0)
    else:
        client = ModbusSerialClient(sim.server.client_url, framer=FramerType.RTU, baudrate=115200,
                                    timeout=3, retries=0)
    assert client.connect()
    return client


def f32(client, regs, order):
    return client.convert_from_registers(regs, client.DATATYPE.FLOAT32, word_order=order)


def i32(client, regs, order):
    return client.convert_from_registers(regs, client.DATATYPE.INT32, word_order=order)


def to_i32(client, value, order):
    return client.convert_to_registers(int(value), client.DATATYPE.INT32, word_order=order)


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
    order = word_order(transport)
    machine.move_to(25.0, 300.0)
    clock.advance(3.0)   # moving down, 15+ mm into the foam (its top is 5 mm below zero)
    with start_simulator(transport, machine=machine) as sim:
        client = pymodbus_client(sim)
        try:
            block = client.read_holding_registers(A["block"], count=5, device_id=LC_UNIT).registers
            gross = client.read_holding_registers(A["gross_force"], count=2, device_id=LC_UNIT).registers
            peak = client.read_holding_registers(A["peak_force"], count=2, device_id=LC_UNIT).registers
            capacity = client.read_holding_registers(A["capacity"], count=2, device_id=LC_UNIT).registers
            lc_status = client.read_holding_registers(A["status"], count=1, device_id=LC_UNIT).registers[0]
            pos_speed = client.read_holding_registers(A["ch_actual_position"], count=4, device_id=CH_UNIT).registers
            ch_status = client.read_holding_registers(A["ch_status"], count=1, device_id=CH_UNIT).registers[0]
            fault_code = client.read_holding_registers(A["ch_fault_code"], count=1, device_id=CH_UNIT).registers[0]
        finally:
            client.close()
        ref = machine.read_load_cell()   # same virtual time: identical without noise
        state = machine.crosshead_status()
        assert ref.net_N > 5.0, "the plate should be in the foam"
        assert f32(client, block[0:2], order) == pytest.approx(ref.gross_N, rel=1e-6)
        assert f32(client, block[2:4], order) == pytest.approx(ref.net_N, rel=1e-6)
        assert f32(client, gross, order) == pytest.approx(ref.gross_N, rel=1e-6)
        assert f32(client, peak, order) == pytest.approx(ref.peak_N, rel=1e-6)
        assert f32(client, capacity, order) == 500.0
        bits = LC["status_bits"]
        expected = sum(1 << bits[k] for k in bits if getattr(ref, k))
        assert block[4] == lc_status == expected
        assert i32(client, pos_speed[0:2], order) == round(machine.position_mm() * 1000)
        assert i32(client, pos_speed[2:4], order) == round(machine.speed_mm_min() * 100)
        assert machine.speed_mm_min() == pytest.approx(300.0)
        sbits = CH["status_bits"]
        assert ch_status == sum(1 << sbits[k] for k in sbits if getattr(state, k))
        assert ch_status & (1 << sbits["moving"]) and ch_status & (1 << sbits["enabled"])
        assert fault_code == state.fault_code == 0


@pytest.mark.parametrize("order, words", [("big", [0x43FA, 0x0000]), ("little", [0x0000, 0x43FA])])
def test_word_order_is_the_profile_setting(order, words):
    """500.0 N capacity is float32 0x43FA0000: high word first for "big", low word first for "little"."""
    profile = load_profile("sim-modbus-tcp")
    profile["word_order"] = order
    machine, _ = manual_machine("modbus-tcp")
    machine.move_to(0.5, 60.0)
    with start_simulator("modbus-tcp", machine=machine, profile=profile) as sim:
        client = pymodbus_client(sim)
        try:
            assert client.read_holding_registers(A["capacity"], count=2, device_id=LC_UNIT).registers == words
            target = client.read_holding_registers(A["ch_target_position"], count=2, device_id=CH_UNIT)
            assert target.registers == [0, 0]
            client.write_registers(A["ch_target_position"], to_i32(client, -2, order), device_id=CH_UNIT)
            raw = client.read_holding_registers(A["ch_target_position"], count=2, device_id=CH_UNIT).registers
            assert raw == ([0xFFFF, 0xFFFE] if order == "big" else [0xFFFE, 0xFFFF])
        finally:
            client.close()


# ----------------------------------------------------------------------------- writes act

def test_crosshead_writes_act_on_the_physics():
    machine, clock = manual_machine("modbus-tcp")
    order = word_order("modbus-tcp")
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            def trigger(name):
                assert not c.write_register(A["ch_trigger"], TRIG[name], device_id=CH_UNIT).isError()

            c.write_registers(A["ch_target_position"], to_i32(c, 12345, order), device_id=CH_UNIT)
            c.write_registers(A["ch_target_speed"], to_i32(c, 30000, order), device_id=CH_UNIT)  # 300 mm/min
            trigger("move_absolute")
            assert machine.crosshead_status().moving
            clock.advance(10.0)
            assert machine.position_mm() == pytest.approx(12.345, abs=1e-9)
            assert machine.crosshead_status().in_position

            trigger("set_zero")
            assert machine.position_mm() == 0.0
            trigger("jog_up")
            clock.advance(1.0)
            assert machine.speed_mm_min() == pytest.approx(-300.0)
            trigger("stop")
            clock.advance(1.0)
            assert not machine.crosshead_status().moving and machine.position_mm() < -3.0

            # acceleration 1 mm/s^2: a 1 mm move at 5 mm/s is a triangle, 0.5 mm after 1 s
            c.write_registers(A["ch_acceleration"], c.convert_to_registers(1000, c.DATATYPE.UINT32, word_order=order),
                              device_id=CH_UNIT)
            start = machine.position_mm()
            c.write_registers(A["ch_target_position"], to_i32(c, round((start + 1.0) * 1000), order), device_id=CH_UNIT)
            trigger("move_absolute")
            clock.advance(1.0)
            assert machine.position_mm() - start == pytest.approx(0.5, abs=1e-3)
            clock.advance(2.0)

            # travel limits in one write: a jog down stops at the new lower limit
            c.write_registers(A["ch_upper_limit"], to_i32(c, -10000, order) + to_i32(c, 2000, order),
                              device_id=CH_UNIT)
            c.write_registers(A["ch_acceleration"], c.convert_to_registers(50000, c.DATATYPE.UINT32, word_order=order),
                              device_id=CH_UNIT)
            trigger("jog_down")
            clock.advance(5.0)
            status = c.read_holding_registers(A["ch_status"], count=1, device_id=CH_UNIT).registers[0]
            assert machine.position_mm() == pytest.approx(2.0, abs=1e-6)
            assert status & (1 << CH["status_bits"]["lower_limit"])

            trigger("emergency")
            status = c.read_holding_registers(A["ch_status"], count=1, device_id=CH_UNIT).registers[0]
            code = c.read_holding_registers(A["ch_fault_code"], count=1, device_id=CH_UNIT).registers[0]
            assert status & (1 << CH["status_bits"]["emergency_stop"]) and status & (1 << CH["status_bits"]["fault"])
            assert code == CH["fault_codes"]["emergency"]
            trigger("reset_fault")
            assert machine.crosshead_status().fault_code == 0
        finally:
            c.close()


def test_watchdog_is_fed_by_requests_and_trips_when_the_host_is_silent():
    machine, clock = manual_machine("modbus-tcp")
    order = word_order("modbus-tcp")
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            c.write_register(A["ch_watchdog_ms"], 500, device_id=CH_UNIT)
            c.write_registers(A["ch_target_position"], to_i32(c, 60000, order), device_id=CH_UNIT)
            c.write_registers(A["ch_target_speed"], to_i32(c, 10000, order), device_id=CH_UNIT)
            c.write_register(A["ch_trigger"], TRIG["move_absolute"], device_id=CH_UNIT)
            for _ in range(10):   # a host polling every 0.3 s keeps the drive going
                clock.advance(0.3)
                c.read_holding_registers(A["ch_actual_position"], count=2, device_id=CH_UNIT)
            assert machine.crosshead_status().moving and machine.crosshead_status().fault_code == 0
            clock.advance(0.6)    # silent longer than 500 ms
            code = c.read_holding_registers(A["ch_fault_code"], count=1, device_id=CH_UNIT).registers[0]
            assert code == CH["fault_codes"]["watchdog"]
        finally:
            c.close()


def test_load_cell_commands():
    machine, clock = manual_machine("modbus-tcp")
    machine.move_to(20.0, 500.0)
    clock.advance(5.0)
    with start_simulator("modbus-tcp", machine=machine) as sim:
        c = pymodbus_client(sim)
        try:
            def command(name):
                assert not c.write_register(A["command"], LC["commands"][name], device_id=LC_UNIT).isError()

            assert machine.read_load_cell().net_N > 5.0
            command("tare")
            r = machine.read_load_cell()
            assert r.tare_set and abs(r.net_N) <= 0.01 and r.gross_N > 5.0
            command("clear_tare")
            assert not machine.read_load_cell().tare_set
            command("zero")
            assert abs(machine.read_load_cell().gross_N) <= 0.01
            clock.advance(1.0)
            command("reset_peak")
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
            assert code(c.read_holding_registers(A["gross_force"], count=2, device_id=CH_UNIT)) == 0x02
            assert code(c.read_holding_registers(A["block"] + 3, count=5, device_id=LC_UNIT)) == 0x02
            assert code(c.write_register(A["gross_force"], 1, device_id=LC_UNIT)) == 0x02        # read-only
            assert code(c.write_register(A["ch_actual_position"], 1, device_id=CH_UNIT)) == 0x02
            assert code(c.write_register(A["ch_trigger"], 0x99, device_id=CH_UNIT)) == 0x03      # no such trigger
            assert code(c.write_register(A["command"], 99, device_id=LC_UNIT)) == 0x03
            assert code(c.write_register(A["ch_trigger"], TRIG["jog_down"], device_id=CH_UNIT)) == 0x03  # speed 0
            assert code(c.write_registers(A["ch_upper_limit"], [0, 5000, 0, 1000], device_id=CH_UNIT)) == 0x03
            # a refused write leaves the stored value as it was
            limits = c.read_holding_registers(A["ch_upper_limit"], count=4, device_id=CH_UNIT).registers
            assert i32(c, limits[2:4], "big") == 70000
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
            link.send(rtu_frame(LC_UNIT, struct.pack(">BHH", 6, A["command"], LC["commands"]["tare"])))
            link.recv(0.3, n=8)
            assert machine.read_load_cell().tare_set is done
        finally:
            link.close()


# ----------------------------------------------------------------------------- ASCII

class Ascii:
    def __init__(self, sim):
        self.link = RawLink(sim)

    def ask(self, command: str, timeout: float = 2.0) -> str:
        self.link.send(command.encode("ascii") + b"\r")
        reply = self.link.recv(timeout, until=b"\r\n")
        assert reply.endswith(b"\r\n"), (command, reply)
        return reply[:-2].decode("ascii")

    def close(self):
        self.link.close()


def test_ascii_commands_and_errors():
    machine, clock = manual_machine("serial")
    machine.move_to(20.0, 500.0)
    clock.advance(5.0)
    with start_simulator("serial", machine=machine) as sim:
        a = Ascii(sim)
        try:
            r = machine.read_load_cell()
            assert a.ask("n") == f"{machine.position_mm():.3f},{r.net_N:.3f}"
            assert a.ask("x") == "20.000"
            assert a.ask("?") == f"{r.net_N:.3f} N"
            assert a.ask("w") == "M0 U0 L0 F0 E0 O0"
            assert a.ask("e") == "50.0"
            assert a.ask("e123.4") == ""
            assert a.ask("e") == "123.4"
            assert a.ask("e0") == a.ask("e99999") == a.ask("ex") == "*11"
            assert a.ask("q") == a.ask("dd") == "*10"
            assert a.ask("u") == ""
            clock.advance(0.5)
            assert machine.speed_mm_min() == pytest.approx(-123.4)
            assert a.ask("w").startswith("M1 ")
            assert a.ask("s") == ""
            clock.advance(1.0)
            assert a.ask("!") == ""
            assert a.ask("d") == "*30" and a.ask("w") == "M0 U0 L0 F1 E1 O0"
            assert a.ask("r") == "" and a.ask("w") == "M0 U0 L0 F0 E0 O0"
            assert a.ask("z") == "" and a.ask("x") == "0.000"
            assert a.ask("Z") == "" and a.ask("?") == "0.000 N"
            assert a.ask("g-5") == "" and a.ask("g") == "-5.000"
            assert a.ask("h-10") == "*11"
            assert a.ask("h1.5") == "" and a.ask("d") == ""
            clock.advance(5.0)
            assert machine.position_mm() == pytest.approx(1.5)
            assert a.ask("w") == "M0 U0 L1 F0 E0 O0"
            assert a.ask("d") == "*21"
        finally:
            a.close()


def test_ascii_overload():
    machine, clock = manual_machine("serial", faults=["overload@1+2"])
    with start_simulator("serial", machine=machine) as sim:
        a = Ascii(sim)
        try:
            assert a.ask("?") == "0.000 N"
            clock.advance(1.5)
            assert a.ask("?") == a.ask("n") == a.ask("d") == "*22"
            assert a.ask("w").endswith("O1")
            clock.advance(2.0)
            assert a.ask("?") == "0.000 N"
        finally:
            a.close()


@pytest.mark.parametrize("fault", ["drop", "timeout", "exception", "crc", "garbage"])
def test_ascii_wire_fault_is_seen_on_the_wire_once(fault):
    machine, _ = manual_machine("serial", faults=[f"{fault}@0"])
    with start_simulator("serial", machine=machine) as sim:
        link = RawLink(sim)
        try:
            link.send(b"x\r")
            if fault == "drop":
                with pytest.raises(EOFError):
                    link.recv(2.0, until=b"\r\n")
                link.close()
                assert wait_for(lambda: sim.server.pty.generation == 2), "a fresh pty replaces the hung-up one"
                link = RawLink(sim)
            elif fault == "timeout":
                assert link.recv(0.3, n=1) == b""
            else:
                line = link.recv(2.0, until=b"\r\n")
                assert line.endswith(b"\r\n") and line != b"0.000\r\n"
                if fault == "exception":
                    assert line == b"*10\r\n"
                else:   # crc / garbage: not a valid ASCII reply
                    assert any(b >= 0x80 for b in line) or not re.fullmatch(rb"-?\d+\.\d{3}\r\n", line)
            link.send(b"x\r")
            assert link.recv(2.0, until=b"\r\n") == b"0.000\r\n"
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
        link.send(b"x\r")
        assert link.recv(2.0, until=b"\r\n").endswith(b"\r\n")
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
        capacity = client.read_holding_registers(A["capacity"], count=2, device_id=LC_UNIT)
        client.close()
        assert f32(client, capacity.registers, "big") == 500.0
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=15)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "stopped" in out and "Traceback" not in err


def test_sim_command_serial_prints_a_pty_path_that_answers_until_ctrl_c():
    proc, lines = _start_cli("--transport", "serial", "--speedup", "10")
    try:
        m = re.search(r"serving at (\S+) \(pty (/dev/pts/\d+)\)", lines[0])
        assert m, lines
        fd = os.open(m[1], os.O_RDWR | os.O_NOCTTY)
        try:
            tty.setraw(fd)
            os.write(fd, b"x\r")
            reply = b""
            deadline = time.monotonic() + 5
            while not reply.endswith(b"\r\n") and time.monotonic() < deadline:
                if select.select([fd], [], [], 0.2)[0]:
                    reply += os.read(fd, 100)
            assert reply == b"0.000\r\n"
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
