"""Highest sustained request rate of each simulator transport on loopback, and the
simulator's per-sample physics cost.

The requests are the real drivers' for one sample, built from the device files: on Modbus
what ModbusMachine.read_sample sends - the CS2RS motor position (0x602C, 2 registers, unit
2), the DAD 141.1 result block (0x3500: gross, net, qualifier, 5 registers, unit 1), the
position again; on ASCII the ESM303's `n` (no terminator), answered by two lines (force,
travel, each with its unit). A lean raw client keeps exactly one request outstanding
(Modbus is master/slave: a master waits for each reply) and counts replies for --seconds;
the rate is the median over --repeats. The machine behind the server is the real
SimulatedMachine on its real-time clock (physics ticker running).

The RTU figure is compared with what the wire itself allows at the profile's baud rate:
11 bits per character (start + 8 data + parity or 2nd stop + stop), each request 8 bytes
and its reply 5 + 2 x registers, and a 3.5-character silence after each frame. (The Modbus
serial spec fixes that silence at 1.75 ms above 19200 baud; that figure is printed too.)
ASCII is 8N1: 10 bits per character.

    .venv/bin/python benchmarks/bench_transports.py [--seconds 2] [--repeats 5] [--no-write]
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import re
import select
import socket
import statistics
import struct
import sys
import time
import tty
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from pymodbus.framer import FramerRTU  # noqa: E402

from drivers.mark10_device import CommandSet  # noqa: E402
from drivers.modbus import device_map  # noqa: E402
from drivers.profile import load_profile  # noqa: E402
from simulator.clock import ManualClock  # noqa: E402
from simulator.launch import TRANSPORTS, start_simulator  # noqa: E402
from simulator.machine import MIN_AUTO_STEP_S, SimulatedMachine  # noqa: E402

SECTION = "## Wire transports (benchmarks/bench_transports.py)"
LABELS = {
    "modbus-tcp": "Modbus TCP",
    "modbus-rtu": "Modbus RTU over socket://",
    "modbus-rtu-pty": "Modbus RTU over pty",
    "serial": "ASCII over pty",
}
SAMPLE_RATE_HZ = 16.0   # the paper's protocol samples at 16 Hz (62.5 ms per sample)


def modbus_sample(profile: dict) -> list[tuple[int, int, int]]:
    """(unit, address, registers) of each function-03 read of one sample, as the drivers send them:
    position (Cs2rsCrosshead.read_position), force block (Dad141LoadCell.read), position again
    (Machine.read_sample brackets the force with two position reads)."""
    cell, drive = device_map(profile, "load_cell"), device_map(profile, "crosshead")
    block, position = cell.blocks["result"], drive.registers["motor_position"]
    at_drive = (int(profile["crosshead"]["unit_id"]), position.address, position.count)
    return [at_drive, (int(profile["load_cell"]["unit_id"]), block.address, block.count), at_drive]


def ascii_sample(profile: dict) -> tuple[bytes, int]:
    """The ESM303's `n` as the driver sends it, and how many reply lines it waits for."""
    commands = CommandSet.from_toml(profile["wire"])
    command = commands.stand["read_sample"]
    return command.send.encode("ascii") + commands.stand_terminator, len(command.reply)


class RawClient:
    """Prebuilt request bytes, exact reply lengths: the client costs as little as possible."""

    def __init__(self, sim):
        self.transport = sim.transport
        if self.transport in ("modbus-rtu-pty", "serial"):
            self.fd = os.open(sim.server.client_url, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            self.sock = None
        else:
            self.sock = socket.create_connection((sim.server.host, sim.server.port))
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.fd = self.sock.fileno()
        # (request, reply length in bytes or None, reply lines) per request of one sample
        self.requests: list[tuple[bytes, int | None, int]] = []
        if self.transport == "serial":
            request, lines = ascii_sample(sim.profile)
            self.requests.append((request, None, lines))
        for unit, address, count in (modbus_sample(sim.profile) if self.transport != "serial" else ()):
            pdu = struct.pack(">BHH", 3, address, count)
            if self.transport == "modbus-tcp":
                self.requests.append((struct.pack(">HHHB", 1, 0, len(pdu) + 1, unit) + pdu, 9 + 2 * count, 0))
            else:
                body = bytes([unit]) + pdu
                self.requests.append((body + FramerRTU.compute_CRC(body).to_bytes(2, "big"), 5 + 2 * count, 0))
        self._next = 0
        self.last_reply = b""

    def transact(self) -> None:
        request, reply_len, lines = self.requests[self._next]
        self._next = (self._next + 1) % len(self.requests)
        os.write(self.fd, request) if self.sock is None else self.sock.sendall(request)
        data = b""
        while (len(data) < reply_len) if reply_len else data.count(b"\n") < lines:
            if not select.select([self.fd], [], [], 2.0)[0]:
                raise TimeoutError(f"{self.transport}: no reply to {request!r} (got {data!r})")
            chunk = os.read(self.fd, 4096) if self.sock is None else self.sock.recv(4096)
            if not chunk:
                raise ConnectionError(f"{self.transport}: connection closed")
            data += chunk
        self.last_reply = data

    def close(self) -> None:
        if self.sock is not None:
            self.sock.close()
        else:
            os.close(self.fd)


def sustained_rate(transport: str, seconds: float, repeats: int) -> tuple[float, list[float], int]:
    """(median requests/s, all repeats, reply bytes) with the real-time simulator behind."""
    rates = []
    with start_simulator(transport, speedup=1.0) as sim:
        sim.machine.move_to(30.0, 100.0)   # the physics has work to do while we poll
        client = RawClient(sim)
        try:
            end = time.perf_counter() + 0.3   # warm-up
            while time.perf_counter() < end:
                client.transact()
            for _ in range(repeats):
                n, t0 = 0, time.perf_counter()
                end = t0 + seconds
                while time.perf_counter() < end:
                    client.transact()
                    n += 1
                rates.append(n / (time.perf_counter() - t0))
            reply_bytes = len(client.last_reply)
        finally:
            client.close()
    return statistics.median(rates), rates, reply_bytes


def physics_cost_us(samples: int, repeats: int, steps_per_sample: int | None) -> float:
    """Median wall time (us) for one sample: advance the virtual clock by one 16 Hz period
    and read the load cell, with the crosshead compressing the foam, in steps_per_sample
    physics steps per sample."""
    period = 1.0 / SAMPLE_RATE_HZ
    profile = load_profile("sim-modbus-tcp")
    costs = []
    for _ in range(repeats):
        clock = ManualClock()
        extra = {} if steps_per_sample is None else {"max_step_s": period / steps_per_sample}
        machine = SimulatedMachine(profile, clock=clock, **extra)
        machine.move_to(5.0, 500.0)            # to the foam's surface first
        clock.advance(2.0)
        machine.advance()
        machine.move_to(60.0, 60.0)            # then 55 mm into it at 60 mm/min
        t0 = time.perf_counter()
        for _ in range(samples):
            clock.advance(period)
            machine.read_load_cell()
        costs.append((time.perf_counter() - t0) / samples * 1e6)
        machine.close()
    return statistics.median(costs)


def rtu_wire_limit(baudrate: int, counts: list[int]) -> tuple[float, float]:
    """Requests/s a perfect RTU line allows for these function-03 reads (registers each), in turn:
    (with 3.5-char gaps, with the spec's 1.75 ms gaps)."""
    char_s = 11 / baudrate
    chars = sum(8 + 5 + 2 * count for count in counts)
    gap = 3.5 * char_s if baudrate <= 19200 else 1.75e-3
    with_char_gaps = (chars + 2 * 3.5 * len(counts)) * char_s
    with_spec_gaps = chars * char_s + 2 * gap * len(counts)
    return len(counts) / with_char_gaps, len(counts) / with_spec_gaps


def ascii_wire_limit(baudrate: int, request_bytes: int, reply_bytes: int) -> float:
    return baudrate / (10 * (request_bytes + reply_bytes))


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seconds", type=float, default=2.0, help="length of one repeat (s)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--samples", type=int, default=1000, help="samples per physics repeat")
    parser.add_argument("--no-write", action="store_true", help="don't update docs/benchmarks.md")
    args = parser.parse_args()

    rtu_profile = load_profile(TRANSPORTS["modbus-rtu-pty"].profile)
    ascii_profile = load_profile(TRANSPORTS["serial"].profile)
    reads = modbus_sample(rtu_profile)
    ascii_request, _ = ascii_sample(ascii_profile)
    rtu_baud = int(rtu_profile["connection"]["baudrate"])
    ascii_baud = int(ascii_profile["connection"]["baudrate"])
    rtu_limit, rtu_spec_limit = rtu_wire_limit(rtu_baud, [count for _, _, count in reads])

    load_before = Path("/proc/loadavg").read_text().split()[0] if Path("/proc/loadavg").exists() \
        else f"{os.getloadavg()[0]:.2f}"
    rows = []
    for transport in ("modbus-tcp", "modbus-rtu", "modbus-rtu-pty", "serial"):
        median, rates, reply_bytes = sustained_rate(transport, args.seconds, args.repeats)
        per_sample = 1 if transport == "serial" else len(reads)
        if transport.startswith("modbus-rtu"):
            limit = f"{rtu_limit:.0f} ({rtu_spec_limit:.0f} with 1.75 ms gaps) at {rtu_baud} baud"
        elif transport == "serial":
            limit = f"{ascii_wire_limit(ascii_baud, len(ascii_request), reply_bytes):.0f} at {ascii_baud} baud 8N1"
        else:
            limit = "-"
        rows.append((LABELS[transport], median, median / per_sample, 1e6 / median, min(rates), max(rates), limit))
        print(f"{LABELS[transport]:<28} {median:9.0f} req/s", flush=True)

    one_step = physics_cost_us(args.samples, args.repeats, steps_per_sample=1)
    auto_steps = math.ceil(1 / SAMPLE_RATE_HZ / MIN_AUTO_STEP_S)   # the simulator's step up to speedup 20
    default_step = physics_cost_us(args.samples, args.repeats, steps_per_sample=auto_steps)

    table = ["| transport | requests/s (median) | samples/s | us/request | min..max over repeats "
             "| wire limit (requests/s) |", "|---|---:|---:|---:|---:|---|"]
    for label, median, samples, us, low, high, limit in rows:
        table.append(f"| {label} | {median:.0f} | {samples:.0f} | {us:.0f} | {low:.0f}..{high:.0f} | {limit} |")
    table = "\n".join(table)
    rtu_pty = next(r[1] for r in rows if r[0] == LABELS["modbus-rtu-pty"])
    ratio = rtu_pty / rtu_limit
    verdict = (f"RTU over the pty sustains {rtu_pty:.0f} requests/s, {ratio:.1f}x what a real "
               f"{rtu_baud}-baud line carries ({rtu_limit:.0f}/s with 3.5-character gaps, "
               f"{rtu_spec_limit:.0f}/s with the spec's 1.75 ms gaps): "
               + ("on a real line the wire, not the simulator, is the bottleneck."
                  if ratio > 1 else "the simulator is slower than the wire it imitates."))
    physics = (f"Physics per sample (16 Hz, crosshead compressing the foam at 60 mm/min, one "
               f"`read_load_cell()` after each clock advance): {one_step:.0f} us with one physics step "
               f"per sample, {default_step:.0f} us with the simulator's {MIN_AUTO_STEP_S * 1e3:.0f} ms step "
               f"at speedups <= 20 ({auto_steps} steps per sample).")
    print()
    print(table)
    print()
    print(verdict)
    print(physics)

    if not args.no_write:
        note = (f"{SECTION}\n\n"
                f"Loopback, {platform.python_implementation()} {platform.python_version()}, "
                f"{os.cpu_count()} cores, pymodbus server classes; the drivers' requests for one sample "
                f"(Modbus: CS2RS position 0x602C, DAD 141.1 block 0x3500 (gross, net, qualifier), position "
                f"again - {len(reads)} requests; ASCII: the ESM303's `n`, two reply lines), one request "
                f"outstanding, {args.seconds:g} s x {args.repeats} repeats, real-time SimulatedMachine behind "
                f"the server. Numbers depend on the machine's load: 1-minute load average (/proc/loadavg) "
                f"{load_before} before, {os.getloadavg()[0]:.2f} after the run.\n\n"
                f"{table}\n\n{verdict}\n\n{physics}\n")
        path = ROOT / "docs" / "benchmarks.md"
        path.parent.mkdir(exist_ok=True)
        text = path.read_text(encoding="utf-8") if path.exists() else "# Benchmarks\n"
        # Replace this benchmark's own section (up to the next '## ' heading) or append it.
        pattern = re.compile(re.escape(SECTION) + r".*?(?=^## |\Z)", re.S | re.M)
        if pattern.search(text):
            text = pattern.sub(lambda _m: note + "\n", text)
        else:
            text = text.rstrip("\n") + "\n\n" + note
        path.write_text(text, encoding="utf-8")
        print(f"written to {path.relative_to(ROOT)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
