"""The simulated machine in its own process, like a real device on the wire.

    with start_simulator_process("modbus-tcp", speedup=50) as sim:
        machine = open_machine(sim.profile, connect=False, **sim.profile_overrides)
        ...
        sim.crosshead_status()      # the simulator's own view, for tests

Why a process and not simulator.launch's background thread: a Python client and a
Python server in one process share one interpreter lock. When the acquisition thread
wakes at its deadline it may wait for the simulator's threads to release the lock,
which on a busy computer means milliseconds of lateness that a real machine (its own
CPU) would never cause. In its own process the simulator costs the acquisition
nothing but the wire. The child runs simulator.launch.start_simulator unchanged.
"""

from __future__ import annotations

import gc
import multiprocessing as mp
import os
import sys
import threading
from dataclasses import asdict
from typing import Any

#: Seconds allowed for the child to import, start serving and answer.
START_TIMEOUT_S = 30.0
REPLY_TIMEOUT_S = 10.0


#: SCHED_FIFO priority for the child when asked (below the run engine's 10); else only
#: the thread answering requests gets it (SERVER_PRIORITY) and the rest a niceness
#: (negative = more CPU share). Both need privileges and are skipped without.
NICE = -15
REALTIME_PRIORITY = 5
SERVER_PRIORITY = 5
#: How often the child checks that its parent is alive (s).
PARENT_CHECK_S = 1.0
#: Interpreter-lock switch interval in the child (Python's default is 5 ms).
SWITCH_INTERVAL_S = 0.0005


def _child(conn, transport: str, kwargs: dict, realtime: bool) -> None:
    """Child process: serve the machine; answer requests on `conn` until told to stop."""
    # The parent's pid now, before "ready": read after it, a parent killed in between (a loaded
    # computer preempting the child right after its send) left the orphan watching its new parent.
    parent_pid = os.getppid()
    if realtime:
        # threads started below inherit the policy
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(REALTIME_PRIORITY))
        except (AttributeError, OSError):
            pass
    else:
        # a larger share of the CPU than the other (normal) processes, without real-time
        # starvation of the kernel's threads
        try:
            os.nice(NICE)
        except (AttributeError, OSError):
            pass
    # The server thread answers requests while the physics thread steps the specimen; with
    # the default 5 ms switch interval a reply could wait that long for the interpreter lock.
    sys.setswitchinterval(SWITCH_INTERVAL_S)
    try:
        from simulator.launch import start_simulator

        sim = start_simulator(transport, **kwargs)
    except BaseException as exc:   # report any start failure to the parent, then exit
        conn.send(("error", f"{type(exc).__name__}: {exc}"))
        return
    if not realtime:
        # A real device answers within its firmware's fixed time: the short-lived answering
        # thread may preempt other jobs without starving anything (an ordinary one waited
        # for a CPU: docs/simulator_wire.md#the-simulator-in-its-own-process-simulatorprocesspy);
        # the physics ticker, which can run long, stays normal.
        try:
            os.sched_setscheduler(sim.server_thread_id, os.SCHED_FIFO, os.sched_param(SERVER_PRIORITY))
        except (AttributeError, OSError, TypeError):
            pass
    # the imports' objects out of the collector's way: a full collection of them delays a
    # reply by several samples at high speedups (docs/simulator_wire.md, same section)
    gc.collect()
    gc.freeze()
    try:
        conn.send(("ready", {"profile": sim.profile, "overrides": sim.profile_overrides,
                             "address": sim.address}))
        while True:
            # A parent killed outright (SIGKILL) may not close the pipe: a forked sibling can
            # hold its end. So the parent's pid is watched too; an orphan stops serving.
            if not conn.poll(PARENT_CHECK_S):
                if os.getppid() != parent_pid:
                    return
                continue
            try:
                request = conn.recv()
            except EOFError:       # parent gone: stop serving
                return
            if request == "stop":
                return
            try:
                if request == "crosshead_status":
                    conn.send(("ok", asdict(sim.machine.crosshead_status())))
                elif request == "snapshot":
                    conn.send(("ok", asdict(sim.machine.snapshot())))
                elif request == "faults_fired":
                    conn.send(("ok", list(sim.machine.faults.fired)))
                elif request == "events":
                    conn.send(("ok", list(sim.machine.events)))
                else:
                    conn.send(("error", f"unknown request {request!r}"))
            except Exception as exc:
                conn.send(("error", f"{type(exc).__name__}: {exc}"))
    finally:
        sim.stop()
        conn.close()


class SimulatorProcess:
    """A simulated machine served by a child process; the same attributes as RunningSimulator."""

    def __init__(self, transport: str, process: mp.Process, conn, info: dict):
        self.transport = transport
        self.process = process
        self._conn = conn
        self.profile: dict = info["profile"]
        self.profile_name: str = self.profile["name"]
        self.profile_overrides: dict = info["overrides"]
        self.address: str = info["address"]
        self._stopped = False

    @property
    def running(self) -> bool:
        return not self._stopped and self.process.is_alive()

    def _ask(self, request: str) -> Any:
        if not self.running:
            raise RuntimeError("the simulator process is not running")
        self._conn.send(request)
        if not self._conn.poll(REPLY_TIMEOUT_S):
            raise TimeoutError(f"the simulator process did not answer {request!r}")
        kind, value = self._conn.recv()
        if kind != "ok":
            raise RuntimeError(f"simulator process: {value}")
        return value

    def crosshead_status(self) -> dict:
        """The simulated crosshead's state (fields of simulator.machine.CrossheadState)."""
        return self._ask("crosshead_status")

    def snapshot(self) -> dict:
        """Noise-free machine state (fields of simulator.machine.MachineSnapshot)."""
        return self._ask("snapshot")

    def faults_fired(self) -> list[tuple[float, str]]:
        return [tuple(f) for f in self._ask("faults_fired")]

    def events(self) -> list[tuple[float, str]]:
        """The machine's recent events (virtual time, what): moves, stops, faults latched."""
        return [tuple(e) for e in self._ask("events")]

    def stop(self) -> None:
        """Stop serving and end the child (idempotent; kills it if it does not end)."""
        if self._stopped:
            return
        self._stopped = True
        try:
            if self.process.is_alive():
                self._conn.send("stop")
        except (OSError, EOFError, BrokenPipeError):
            pass
        self.process.join(REPLY_TIMEOUT_S)
        if self.process.is_alive():
            self.process.kill()
            self.process.join(REPLY_TIMEOUT_S)
        self._conn.close()

    def __enter__(self) -> "SimulatorProcess":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"<SimulatorProcess {self.transport} at {self.address} (pid {self.process.pid})>"


def start_simulator_process(transport: str, *, realtime: bool = False, **kwargs) -> SimulatorProcess:
    """Start simulator.launch.start_simulator(transport, **kwargs) in a child process.

    `realtime`: ask for SCHED_FIFO priority in the child (ignored when not permitted). Off by
    default: a real-time simulator (always busy at high speedups) starves the kernel's
    softirq thread that moves loopback packets, and replies stall (measured:
    docs/simulator_wire.md#the-simulator-in-its-own-process-simulatorprocesspy).
    Raises ValueError with the child's message when it cannot start (bad specimen,
    effect or fault spec, address in use) and TimeoutError when it does not answer.
    """
    # fork is fast (the child inherits the imports) but only safe in a single-threaded parent
    ctx = mp.get_context("fork" if threading.active_count() == 1 and hasattr(os, "fork") else "spawn")
    parent, child = ctx.Pipe()
    process = ctx.Process(target=_child, args=(child, transport, kwargs, realtime), name=f"foamlab-sim-{transport}",
                          daemon=True)
    process.start()
    child.close()
    try:
        if not parent.poll(START_TIMEOUT_S):
            raise TimeoutError(f"the simulated machine did not start within {START_TIMEOUT_S:g} s")
        kind, value = parent.recv()
    except BaseException:
        process.kill()
        process.join(REPLY_TIMEOUT_S)
        parent.close()
        raise
    if kind != "ready":
        process.join(REPLY_TIMEOUT_S)
        parent.close()
        raise ValueError(value)
    return SimulatorProcess(transport, process, parent, value)
