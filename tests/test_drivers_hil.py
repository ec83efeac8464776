"""Hardware in the loop: the real drivers against the simulated machine over real wire protocols.

Modbus TCP, Modbus RTU over socket:// and over a pty, and the ESM303 stand + gauge over a pty,
each with the profile's own timeouts (40 ms, one retry). The simulator's machine is
the truth the readings are checked against; its wire faults must come out as the
right DeviceError subclass.
"""

from __future__ import annotations

import time
from contextlib import contextmanager

import pytest

from drivers.ascii import DeviceErrorReply
from drivers.base import CrossheadStatus, DeviceConnectionLost, DeviceProtocolError, DeviceTimeout, Machine
from drivers.cs2rs import EmergencyStopLatched
from drivers.profile import load_profile, open_machine
from simulator import launch

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]

TRANSPORTS = ["modbus-tcp", "modbus-rtu", "modbus-rtu-pty", "serial"]
# Moderate: at 5x a poll's round trip on a busy CI machine is a small part of a move.
SPEEDUP = 5.0
# Functional tests allow a slow scheduler; the fault and timing tests keep the profile's 40 ms.
PATIENT = {"timeout_s": 0.25}


@contextmanager
def simulated(transport: str, **sim_options):
    with launch.start_simulator(transport, speedup=sim_options.pop("speedup", SPEEDUP), **sim_options) as sim:
        yield sim


@contextmanager
def machine_for(sim, *, connect=True, **overrides):
    machine = open_machine(load_profile(sim.profile_name), connect=connect, **{**sim.profile_overrides, **overrides})
    try:
        yield machine
    finally:
        machine.close()


def wait_for(condition, what: str, timeout_s: float = 5.0, poll_s: float = 0.01):
    """Poll a device condition until true; fail with `what` at the deadline."""
    deadline = time.monotonic() + timeout_s
    while True:
        value = condition()
        if value:
            return value
        if time.monotonic() > deadline:
            pytest.fail(f"timed out after {timeout_s} s waiting for {what}")
        time.sleep(poll_s)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_read_move_jog_stop_estop_reset(transport):
    with simulated(transport) as sim, machine_for(sim, **PATIENT) as machine:
        truth = sim.machine
        near = 6e-3 if transport == "serial" else 1e-3        # the ESM303 reads travel to 0.01 mm
        sample = machine.read_sample()
        assert sample.position_mm == pytest.approx(truth.position_mm(), abs=near)
        assert abs(sample.force_N) < 1.0                       # no contact at the start

        crosshead = machine.crosshead
        crosshead.move_to(5.0, 300.0)
        wait_for(lambda: crosshead.status().in_position, "in position at 5 mm")
        assert crosshead.read_position() == pytest.approx(5.0, abs=2e-3)
        assert truth.position_mm() == pytest.approx(5.0, abs=2e-3)
        assert not crosshead.status().moving

        crosshead.move_to(2.0, 300.0)                          # and back up
        wait_for(lambda: crosshead.status().in_position, "in position at 2 mm")
        assert crosshead.read_position() == pytest.approx(2.0, abs=2e-3)

        crosshead.jog(-1, 120.0)
        wait_for(lambda: crosshead.read_position() < 1.9, "jogging up")
        crosshead.stop()
        wait_for(lambda: not crosshead.status().moving, "the stop")
        stopped_at = crosshead.read_position()
        assert -20.0 < stopped_at < 1.9
        assert crosshead.read_position() == stopped_at          # at rest

        crosshead.jog(+1, 120.0)
        wait_for(lambda: crosshead.status().moving, "jogging down")
        crosshead.emergency_stop()
        if transport == "serial":
            # the ESM303 has no e-stop command: `s`, a stop; nothing latches, nothing to reset
            wait_for(lambda: not crosshead.status().moving, "the stop")
            assert crosshead.status() == CrossheadStatus()
        else:
            status = crosshead.status()
            assert status.emergency_stopped and status.fault and not status.moving
        frozen = crosshead.read_position()
        assert truth.position_mm() == pytest.approx(frozen, abs=near)
        crosshead.reset_fault()
        status = crosshead.status()
        assert not status.emergency_stopped and not status.fault

        crosshead.set_zero()
        assert crosshead.read_position() == pytest.approx(0.0, abs=near)
        machine.load_cell.tare()
        assert abs(machine.load_cell.read().force_N) < 0.5


@pytest.mark.parametrize("transport", [t for t in TRANSPORTS if t != "serial"])
def test_emergency_stop_latches_until_reset(transport):
    with simulated(transport) as sim, machine_for(sim, **PATIENT) as machine:
        machine.crosshead.emergency_stop()
        with pytest.raises(EmergencyStopLatched):          # the CS2RS latches nothing: the driver holds it
            machine.crosshead.jog(+1, 50.0)
        assert not machine.crosshead.status().moving
        assert machine.crosshead.status().emergency_stopped
        machine.crosshead.reset_fault()
        machine.crosshead.jog(+1, 50.0)
        wait_for(lambda: machine.crosshead.status().moving, "motion after reset")
        machine.crosshead.stop()


def test_the_esm303_stop_is_its_emergency_stop_and_latches_nothing():
    """No e-stop command on the ESM303 (S1 §6.2): `s` stops it, the next move just moves."""
    with simulated("serial") as sim, machine_for(sim, **PATIENT) as machine:
        machine.crosshead.jog(+1, 50.0)
        wait_for(lambda: machine.crosshead.status().moving, "motion")
        machine.crosshead.emergency_stop()
        wait_for(lambda: not machine.crosshead.status().moving, "the stop")
        assert not sim.machine.crosshead_status().emergency_stop    # the stand never e-stops the machine
        assert "no reset command" in machine.crosshead.reset_fault()
        machine.crosshead.jog(+1, 50.0)
        wait_for(lambda: machine.crosshead.status().moving, "motion after the stop")
        machine.crosshead.stop()


def test_modbus_rtu_by_pty_device_path():
    with simulated("modbus-rtu-pty") as sim, machine_for(sim, port_url=sim.server.pty.device_path, **PATIENT) as machine:
        assert sim.server.pty.device_path.startswith("/dev/")
        assert machine.read_sample().position_mm == pytest.approx(sim.machine.position_mm(), abs=1e-3)


def test_ascii_by_pty_device_path():
    with simulated("serial") as sim, machine_for(sim, port_url=sim.server.pty.device_path, **PATIENT) as machine:
        assert machine.read_sample().position_mm == pytest.approx(sim.machine.position_mm(), abs=1e-3)


FAULTS = [
    ("timeout:p=1", DeviceTimeout, r"no reply"),
    ("crc:p=1", DeviceProtocolError, r"(bad CRC|bad framing|garbage|unexpected)"),
    ("exception:p=1", DeviceProtocolError, r"(Modbus exception 0x04|\*10)"),
]


@pytest.mark.parametrize("transport", TRANSPORTS)
@pytest.mark.parametrize("fault,error,message", FAULTS, ids=[f[0] for f in FAULTS])
def test_wire_faults_become_the_right_device_error(transport, fault, error, message):
    with simulated(transport, faults=fault) as sim, machine_for(sim, connect=False, timeout_s=0.1) as machine:
        machine_connect(machine)
        # the stand has no error reply (it ignores a garbled command): `*10` comes from the gauge
        read = machine.load_cell.read if transport == "serial" and "exception" in fault else machine.read_sample
        started = time.monotonic()
        with pytest.raises(error, match=message) as info:
            read()
        elapsed = time.monotonic() - started
    assert "\n" not in str(info.value)
    if error is DeviceTimeout:
        assert elapsed < 0.6                # two attempts of 100 ms, not pymodbus' 3 s default
    if error is DeviceProtocolError and "crc" in fault:
        assert not isinstance(info.value, DeviceErrorReply)


def try_connect(machine: Machine) -> bool:
    # A pty hung up by the simulator is replaced behind the same path; in between,
    # opening it fails (as with a USB adapter re-enumerating).
    try:
        machine.connect()
    except DeviceConnectionLost:
        return False
    return True


def machine_connect(machine: Machine) -> None:
    """Open the link only: configuring the drive would already meet the fault."""
    (machine.link if hasattr(machine, "link") else machine.line).connect()


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_dropped_link_is_connection_lost_and_a_reconnect_works(transport):
    with simulated(transport, faults="drop@0") as sim, machine_for(sim, connect=False) as machine:
        machine_connect(machine)
        with pytest.raises(DeviceConnectionLost):
            machine.read_sample()
        machine.close()
        wait_for(lambda: try_connect(machine), "the line to come back")   # the fault fired once
        assert machine.read_sample().position_mm == pytest.approx(sim.machine.position_mm(), abs=1e-3)


@pytest.mark.parametrize("transport", TRANSPORTS)
def test_sampling_at_16_hz_fits_the_period(transport):
    """One sample (force + position) costs far less than the 62.5 ms period on every transport."""
    with simulated(transport) as sim, machine_for(sim) as machine:
        durations = []
        for _ in range(40):
            started = time.perf_counter()
            machine.read_sample()
            durations.append(time.perf_counter() - started)
    durations.sort()
    assert durations[len(durations) // 2] < 0.020, f"median sample {durations[20] * 1000:.1f} ms"
