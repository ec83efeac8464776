"""Highest sustained request rate of each simulator transport on loopback, and the
simulator's per-sample physics cost.

One request = one sample: the load-cell block read (0x3500, 5 registers, unit 1) on
Modbus, `n` (travel + force) on ASCII. A lean raw client keeps exactly one request
outstanding (Modbus is master/slave: a master waits for each reply) and counts
replies for --seconds; the rate is the median over --repeats. The machine behind the
server is the real SimulatedMachine on its real-time clock (physics ticker running).

The RTU figure is compared with what the wire itself allows at the profile's baud
rate: 11 bits per character (start + 8 data + parity or 2nd stop + stop), request 8
bytes + reply 5 + 2*5 bytes, and a 3.5-character silence after each frame. (The
Modbus serial spec fixes that silence at 1.75 ms above 19200 baud; that figure is
printed too.) ASCII is 8N1: 10 bits per character.

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


class RawClient:
    """Prebuilt request bytes, exact reply lengths: the client costs as little as possible."""

    def __init__(self, sim):
        self.transport = sim.transport
        block = sim.profile["wire"]["load_cell"]["blocks"]["result"] if sim.profile["protocol"] == "modbus" else None
        if self.transport in ("modbus-rtu-pty", "serial"):
            self.fd = os.open(sim.server.client_url, os.O_RDWR | os.O_NOCTTY)
            tty.setraw(self.fd)
            self.sock = None
        else:
            self.sock = socket.create_connection((sim.server.host, sim.server.port))
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            self.fd = self.sock.fileno()
        if self.transport == "serial":
            self.request, self.reply_len = b"n\r", None
        else:
            unit = sim.profile["load_cell"]["unit_id"]
            pdu = struct.pack(">BHH", 3, block["address"], block["count"])
            if self.transport == "modbus-tcp":
                self.request = struct.pack(">HHHB", 1, 0, len(pdu) + 1, unit) + pdu
                self.reply_len = 7 + 2 + 2 * block["count"]
            else:
                body = bytes([unit]) + pdu
                self.request = body + FramerRTU.compute_CRC(body).to_bytes(2, "big")
                self.reply_len = 3 + 2 * block["count"] + 2
        self.last_reply = b""

    def transact(self) -> None:
        os.write(self.fd, self.request) if self.sock is None else self.sock.sendall(self.request)
        data = b""
        while (len(data) < self.reply_len) if self.reply_len else not data.endswith(b"\r\n"):
            if not select.select([self.fd], [], [], 2.0)[0]:
                raise TimeoutError(f"{self.transport}: no reply (got {data!r})")
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


def rtu_wire_limit(baudrate: int, block_count: int) -> tuple[float, float]:
    """Requests/s a perfect RTU line allows: (with 3.5-char gaps, with the spec's 1.75 ms gaps)."""
    bits_per_char = 11
    chars = 8 + (5 + 2 * block_count)
    char_s = bits_per_char / baudrate
    with_char_gaps = (chars + 2 * 3.5) * char_s
    gap = 3.5 * char_s if baudrate <= 19200 else 1.75e-3
    with_spec_gaps = chars * char_s + 2 * gap
    return 1.0 / with_char_gaps, 1.0 / with_spec_gaps


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
    block_count = rtu_profile["wire"]["load_cell"]["blocks"]["result"]["count"]
    rtu_baud = int(rtu_profile["connection"]["baudrate"])
    ascii_baud = int(ascii_profile["connection"]["baudrate"])
    rtu_limit, rtu_spec_limit = rtu_wire_limit(rtu_baud, block_count)

    load_before = os.getloadavg()[0]
    rows = []
    for transport in ("modbus-tcp", "modbus-rtu", "modbus-rtu-pty", "serial"):
        median, rates, reply_bytes = sustained_rate(transport, args.seconds, args.repeats)
        if transport.startswith("modbus-rtu"):
            limit = f"{rtu_limit:.0f} ({rtu_spec_limit:.0f} with 1.75 ms gaps) at {rtu_baud} baud"
        elif transport == "serial":
            limit = f"{ascii_wire_limit(ascii_baud, 2, reply_bytes):.0f} at {ascii_baud} baud 8N1"
        else:
            limit = "-"
        rows.append((LABELS[transport], median, 1e6 / median, min(rates), max(rates), limit))
        print(f"{LABELS[transport]:<28} {median:9.0f} req/s", flush=True)

    one_step = physics_cost_us(args.samples, args.repeats, steps_per_sample=1)
    auto_steps = math.ceil(1 / SAMPLE_RATE_HZ / MIN_AUTO_STEP_S)   # the simulator's step up to speedup 20
    default_step = physics_cost_us(args.samples, args.repeats, steps_per_sample=auto_steps)

    table = ["| transport | requests/s (median) | us/request | min..max over repeats | wire limit (requests/s) |",
             "|---|---:|---:|---:|---|"]
    for label, median, us, low, high, limit in rows:
        table.append(f"| {label} | {median:.0f} | {us:.0f} | {low:.0f}..{high:.0f} | {limit} |")
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
                f"{os.cpu_count()} cores, pymodbus server classes; one request = one sample (Modbus: the "
                f"0x3500 load-cell block, 5 registers; ASCII: `n`), one request outstanding, "
                f"{args.seconds:g} s x {args.repeats} repeats, real-time SimulatedMachine behind the server. "
                f"Numbers depend on the machine's load: 1-minute load average {load_before:.1f} before, "
                f"{os.getloadavg()[0]:.1f} after the run.\n\n"
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
