"""Byte-exact Modbus RTU transcripts for the device tests (tests/test_device_*.py).

A transcript is written from the manual: the request's bytes (documented address and value)
and the reply's, CRC included, as hex. Played (a) to the driver through a RecordedPeer (the
driver must send exactly these bytes and decode these replies) and (b) to the simulator's
server over an RTU socket (it must answer these bytes).
"""

from __future__ import annotations

import copy
import select
import socket
import time
from contextlib import contextmanager

from pymodbus.framer import FramerRTU

from drivers.profile import load_profile, open_machine
from recorded_peer import RecordedPeer, crc16_modbus
from simulator.clock import ManualClock
from simulator.launch import start_simulator
from simulator.machine import SimulatedMachine


def frame(text: str) -> bytes:
    """Hex text -> bytes; the frame's CRC must check (two independent CRC routines agree)."""
    data = bytes.fromhex(text)
    assert crc16_modbus(data[:-2]) == data[-2:], f"bad CRC in the transcript: {text}"
    assert FramerRTU.compute_CRC(data[:-2]).to_bytes(2, "big") == data[-2:]
    return data


def rtu_profile(name: str = "sim-modbus-rtu", **units) -> dict:
    """An RTU sim profile, with other unit ids if asked (load_cell=..., crosshead=...)."""
    profile = copy.deepcopy(load_profile(name))
    for role, unit in units.items():
        profile[role]["unit_id"] = unit
    return profile


@contextmanager
def driver_on(exchanges: list[tuple[str, str]], *, connect: bool = False, profile: str = "sim-modbus-rtu",
              **units):
    """The Modbus machine of an RTU profile against a recorded peer on a pty, playing `exchanges`."""
    with RecordedPeer([(frame(q), frame(a) if a else b"") for q, a in exchanges], transport="pty") as peer:
        machine = open_machine(rtu_profile(profile, **units), connect=False, port_url=peer.url, timeout_s=0.5)
        try:
            machine.connect() if connect else machine.link.connect()
            yield machine
        finally:
            machine.close()
        peer.verify()


class RtuWire:
    """Raw RTU bytes to and from a simulator's `modbus-rtu` (socket) server."""

    def __init__(self, sim):
        self.url = sim.server.client_url          # socket://host:port, for a driver beside the raw bytes
        self.sock = socket.create_connection((sim.server.host, sim.server.port), timeout=2)

    def ask(self, request: bytes, reply_length: int, timeout: float = 2.0) -> bytes:
        self.sock.sendall(request)
        data, deadline = b"", time.monotonic() + timeout
        while len(data) < reply_length and select.select([self.sock], [], [], max(0.0, deadline - time.monotonic()))[0]:
            chunk = self.sock.recv(256)
            if not chunk:
                break
            data += chunk
        return data

    def close(self) -> None:
        self.sock.close()


@contextmanager
def simulated(profile: dict | None = None, faults=(), **settings):
    """A simulated machine on a manual clock (noise-free unless asked) behind an RTU socket server:
    (machine, clock, wire)."""
    profile = profile or rtu_profile()
    clock = ManualClock()
    settings.setdefault("noise_sigma_N", 0.0)
    machine = SimulatedMachine(profile, clock=clock, faults=list(faults), **settings)
    with start_simulator("modbus-rtu", machine=machine, profile=profile) as sim:
        wire = RtuWire(sim)
        try:
            yield machine, clock, wire
        finally:
            wire.close()
