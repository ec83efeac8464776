"""A process started in the idle scheduling class (scripts/test.sh's phase 1) takes no real-time
priority: the engine's thread and the simulator's answering thread would otherwise escape the
class and take the CPU from the schedule tests beside it."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(not hasattr(os, "SCHED_IDLE"), reason="Linux scheduling classes only")

CHILD = """
import os
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
from foamlab.acquisition.schedule import raise_thread_priority
said = raise_thread_priority()
print(said, '|', os.sched_getscheduler(0) == os.SCHED_IDLE)
"""


def test_the_engine_thread_stays_in_the_idle_class():
    out = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    said, still_idle = out.stdout.strip().split(" | ")
    assert said.startswith("idle class") and still_idle == "True"


def test_a_simulator_started_in_the_idle_class_still_answers_in_device_time():
    """The simulator stands in for a device, which answers from its own processor whatever the
    host is doing: its answering thread takes its real-time priority even in the idle class
    (with it idle too, a phase-1 window test waited over 2 x 40 ms for a reply: ci13)."""
    child = """
import os
os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))
from simulator.process import start_simulator_process
with start_simulator_process("modbus-tcp") as sim:
    pid = sim.process.pid
    policies = [os.sched_getscheduler(int(t)) for t in os.listdir(f"/proc/{pid}/task")]
    print(policies.count(os.SCHED_FIFO), len(policies))
"""
    own = os.sched_getscheduler(0)
    try:        # SCHED_FIFO needs a privilege; without it the simulator answers at normal priority
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
    except PermissionError:
        pytest.skip("no permission for real-time priority here")
    finally:
        os.sched_setscheduler(0, own, os.sched_param(0))
    out = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=90)
    assert out.returncode == 0, out.stderr
    fifo, threads = (int(v) for v in out.stdout.split())
    assert fifo == 1 and threads >= 2
