"""Start the simulated machine behind one wire protocol, in a background thread.

    with start_simulator("modbus-tcp", speedup=50) as sim:
        machine = drivers.open_machine(load_profile(sim.profile_name), **sim.profile_overrides)

The server runs on its own asyncio loop in a daemon thread; ``stop()`` (also on
leaving the ``with`` block) closes the listener, every connection and the pty,
stops the loop and joins the thread. Servers bind 127.0.0.1 on a free port
unless told otherwise.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass
from typing import Any

from drivers.profile import load_profile
from simulator.modbus_server import ModbusSimServer
from simulator.serial_server import AsciiSimServer

#: Seconds allowed for the server to start listening / to shut down.
START_TIMEOUT_S = 10.0
STOP_TIMEOUT_S = 10.0


@dataclass(frozen=True)
class TransportChoice:
    profile: str          # the machine profile a client uses with this transport
    server: str           # ModbusSimServer transport, or "ascii"


TRANSPORTS: dict[str, TransportChoice] = {
    "modbus-tcp": TransportChoice("sim-modbus-tcp", "tcp"),
    "modbus-rtu": TransportChoice("sim-modbus-rtu", "rtu-socket"),
    "modbus-rtu-pty": TransportChoice("sim-modbus-rtu", "rtu-pty"),
    "serial": TransportChoice("sim-serial", "ascii"),
}
#: Simulated machines by their devices (configs/devices/<name>.toml) -> the transport serving them:
#: the ESM303 stand with its gauge; the DAD 141.1 indicator and CS2RS drive on one RS-485 line
#: (Modbus RTU), or behind a Modbus TCP gateway.
DEVICES: dict[str, str] = {"mark10-esm303": "serial", "dad141-cs2rs": "modbus-rtu",
                           "dad141-cs2rs-tcp": "modbus-tcp"}


class RunningSimulator:
    """A simulator serving in the background. Context manager; ``stop()`` is idempotent."""

    def __init__(self, transport: str, profile: dict, machine: Any, server: Any,
                 loop: asyncio.AbstractEventLoop, thread: threading.Thread, owns_machine: bool):
        self.transport = transport
        self.profile = profile
        self.profile_name: str = profile["name"]
        self.machine = machine
        self.server = server
        self._loop = loop
        self._thread = thread
        self._owns_machine = owns_machine
        self._stopped = False
        self._lock = threading.Lock()

    @property
    def profile_overrides(self) -> dict:
        """Connection settings for drivers.open_machine(profile, **overrides)."""
        if self.transport == "modbus-tcp":
            return {"host": self.server.host, "port": self.server.port}
        return {"port_url": self.server.client_url}

    @property
    def address(self) -> str:
        """Where to connect, for people: host:port, socket:// URL or a device path."""
        if self.transport in ("modbus-rtu-pty", "serial"):
            return f"{self.server.client_url} (pty {self.server.pty.device_path})"
        return self.server.client_url

    @property
    def running(self) -> bool:
        return not self._stopped and self._thread.is_alive()

    @property
    def server_thread_id(self) -> int | None:
        """The OS id of the thread that answers requests (for its scheduling priority)."""
        return self._thread.native_id

    def stop(self) -> None:
        with self._lock:
            if self._stopped:
                return
            self._stopped = True
        try:
            if self._thread.is_alive():
                asyncio.run_coroutine_threadsafe(self.server.stop(), self._loop).result(STOP_TIMEOUT_S)
        finally:
            _stop_loop(self._loop, self._thread)
            if self._owns_machine and hasattr(self.machine, "close"):
                self.machine.close()

    def __enter__(self) -> "RunningSimulator":
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def __repr__(self) -> str:
        state = "running" if self.running else "stopped"
        return f"<RunningSimulator {self.transport} at {self.address} ({state})>"


def _serve(loop: asyncio.AbstractEventLoop) -> None:
    asyncio.set_event_loop(loop)
    try:
        loop.run_forever()
    finally:
        pending = [t for t in asyncio.all_tasks(loop) if not t.done()]
        for task in pending:
            task.cancel()
        if pending:
            loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()


def _stop_loop(loop: asyncio.AbstractEventLoop, thread: threading.Thread) -> None:
    if thread.is_alive():
        loop.call_soon_threadsafe(loop.stop)
        thread.join(STOP_TIMEOUT_S)


def make_machine(profile: dict, *, speedup: float = 1.0, specimen=None, effects=None,
                 faults=None, seed: int = 0):
    """A SimulatedMachine configured from a machine profile (capacity, speeds, limits)."""
    from simulator.machine import SimulatedMachine  # physics: imported only when needed

    return SimulatedMachine(profile=profile, speedup=speedup, specimen=specimen,
                            effects=effects, faults=faults, seed=seed)


def start_simulator(transport: str, machine: Any = None, *, host: str = "127.0.0.1", port: int = 0,
                    speedup: float = 1.0, specimen=None, effects=None, faults=None, seed: int = 0,
                    profile: str | dict | None = None) -> RunningSimulator:
    """Serve a simulated machine on `transport` (modbus-tcp, modbus-rtu, modbus-rtu-pty, serial).

    `machine`: an existing SimulatedMachine to serve (then speedup/specimen/effects/faults/seed
    are ignored), else one is built from those arguments. `profile`: the machine profile to serve
    (name, path or loaded dict); default the transport's sim profile. `port` 0 picks a free port
    (TCP transports only). Raises OSError when the address cannot be bound.
    """
    if transport not in TRANSPORTS:
        raise ValueError(f"transport must be one of {', '.join(TRANSPORTS)}, got {transport!r}")
    choice = TRANSPORTS[transport]
    if profile is None or isinstance(profile, str):
        profile = load_profile(profile or choice.profile)
    if (profile["protocol"] == "ascii") != (choice.server == "ascii"):
        raise ValueError(f"profile {profile['name']!r} ({profile['protocol']}) cannot be served as {transport}")
    owns_machine = machine is None
    if owns_machine:
        machine = make_machine(profile, speedup=speedup, specimen=specimen, effects=effects,
                               faults=faults, seed=seed)
    if choice.server == "ascii":
        server = AsciiSimServer(machine, profile, seed=seed)
    else:
        server = ModbusSimServer(machine, profile, choice.server, host=host, port=port, seed=seed)

    loop = asyncio.new_event_loop()
    thread = threading.Thread(target=_serve, args=(loop,), name=f"foamlab-sim-{transport}", daemon=True)
    thread.start()
    try:
        asyncio.run_coroutine_threadsafe(server.start(), loop).result(START_TIMEOUT_S)
    except BaseException:
        try:
            asyncio.run_coroutine_threadsafe(server.stop(), loop).result(STOP_TIMEOUT_S)
        finally:
            _stop_loop(loop, thread)
            if owns_machine and hasattr(machine, "close"):
                machine.close()
        raise
    return RunningSimulator(transport, profile, machine, server, loop, thread, owns_machine)
