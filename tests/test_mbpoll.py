"""An independent Modbus client nobody here wrote - mbpoll (Debian package `mbpoll`) -
reads the simulated net force (the DAD 141.1's float32 at 0x2002, unit 1) and the
crosshead's motor position (the CS2RS's int32 pulses at 0x602C, unit 2) over Modbus TCP and
over Modbus RTU on the pty, and the values match the simulator's state.

The crosshead is moving into the foam while mbpoll runs (real-time virtual clock), so
each value must lie between the machine's noise-free state just before and just
after the mbpoll call: the tolerance is exactly the time that passed, plus one
count of the load cell / one pulse.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time

import pytest

from drivers.modbus import device_map
from drivers.profile import load_profile
from simulator.launch import TRANSPORTS, start_simulator
from simulator.machine import SimulatedMachine

pytestmark = [pytest.mark.hil, pytest.mark.timeout(60)]

MBPOLL = shutil.which("mbpoll")
if MBPOLL is None:
    if os.environ.get("CI"):
        pytest.fail("mbpoll is not installed (apt-get install -y mbpoll); CI must install it", pytrace=False)
    pytest.skip("mbpoll is not installed (apt-get install -y mbpoll)", allow_module_level=True)

SPEEDUP = 10.0
MOVE_SPEED_MM_MIN = 100.0


def mbpoll_read(sim, unit: int, address: int, kind: str) -> float:
    """One value read by mbpoll: PDU (0-based) addressing, high word first (both devices' order)."""
    profile = sim.profile
    # -B: high word first (mbpoll's default is low word first)
    common = ["-a", str(unit), "-r", str(address), "-0", "-t", f"4:{kind}", "-B", "-c", "1", "-1", "-o", "2"]
    if sim.transport == "modbus-tcp":
        argv = [MBPOLL, "-m", "tcp", "-p", str(sim.server.port), *common, sim.server.host]
    else:
        c = profile["connection"]
        parity = {"N": "none", "E": "even", "O": "odd"}[c.get("parity", "N")]
        argv = [MBPOLL, "-m", "rtu", "-b", str(c["baudrate"]), "-P", parity, "-s", str(c.get("stopbits", 1)),
                *common, sim.server.client_url]
    done = subprocess.run(argv, capture_output=True, text=True, timeout=15)
    assert done.returncode == 0, (argv, done.stdout, done.stderr)
    values = re.findall(r"^\[(\d+)\]:\s+(\S+)\s*$", done.stdout, re.M)
    assert len(values) == 1 and int(values[0][0]) == address, done.stdout
    return float(values[0][1])


@pytest.mark.parametrize("transport", ["modbus-tcp", "modbus-rtu-pty"])
def test_mbpoll_reads_force_and_position(transport):
    profile = load_profile(TRANSPORTS[transport].profile)
    net_force = device_map(profile, "load_cell").registers["net"].address
    motor_position = device_map(profile, "crosshead").registers["motor_position"].address
    c = profile["crosshead"]
    pulses_per_mm = c["pulses_per_rev"] * c["gear_ratio"] / c["lead_mm"]
    resolution = 0.01
    machine = SimulatedMachine(profile, speedup=SPEEDUP, noise_sigma_N=0.0, resolution_N=resolution)
    with start_simulator(transport, machine=machine) as sim:
        machine.move_to(45.0, MOVE_SPEED_MM_MIN)
        deadline = time.monotonic() + 20
        while machine.snapshot().x_crosshead_mm < 3.0:   # wait until the plate is 3 mm into the foam
            assert time.monotonic() < deadline, "the crosshead did not reach the foam"
            time.sleep(0.01)

        before = machine.snapshot()
        force = mbpoll_read(sim, profile["load_cell"]["unit_id"], net_force, "float")
        after = machine.snapshot()
        assert after.velocity_mm_s > 0, "still moving: the check must see time passing"
        low, high = sorted((before.sensor_force_N, after.sensor_force_N))
        assert low - resolution <= force <= high + resolution, (before, force, after)
        assert force > 1.0

        before = machine.snapshot()
        pulses = mbpoll_read(sim, profile["crosshead"]["unit_id"], motor_position, "int")
        after = machine.snapshot()
        assert before.position_mm * pulses_per_mm - 1 <= pulses <= after.position_mm * pulses_per_mm + 1, \
            (before.position_mm, pulses, after.position_mm)
        assert pulses > 8 * pulses_per_mm
