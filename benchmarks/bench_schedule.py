"""The run engine's 16 Hz schedule against the simulated machine, through the real drivers.

1. Real time (speedup 1), each transport: deviation of each sample's request from its
   deadline (p50 / p99 / max, ms), request round trip, samples and missed deadlines
   (target: p99 <= 2 ms, zero missed). Medians over repeats.
2. Throughput: the same short method at rising speedups (16 Hz of machine time = 16 x S
   samples per wall second): the fraction of deadlines missed shows what each transport
   sustains, hence the speedups the HIL tests use.
3. Live prediction on / off (--prediction): three cycles (the paper's strokes at 50 mm/min)
   over Modbus TCP, runs with the live prediction off, on (its fits in the worker process, as
   foamlab runs it) and on with the fits in a thread of the acquiring process (what it would
   cost otherwise), alternated in one invocation; missed deadlines and their ratio on / off.

    python benchmarks/bench_schedule.py [--seconds 20] [--repeats 3] [--no-sweep] [--prediction]

The simulated machine runs in its own process (simulator.process), as a real one would.
"""

from __future__ import annotations

import argparse
import concurrent.futures
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from drivers.base import DeviceError  # noqa: E402
from drivers.profile import open_machine  # noqa: E402
from foamlab.acquisition import RunEngine  # noqa: E402
from foamlab.methods import parse_method  # noqa: E402
from foamlab.prediction.live import LivePredictor  # noqa: E402
from foamlab.rundata import Specimen  # noqa: E402
from simulator.process import start_simulator_process  # noqa: E402

try:
    from _table import publish  # noqa: E402
except ImportError:   # run from elsewhere
    from benchmarks._table import publish  # noqa: E402

SECTION = "Run engine: 16 Hz schedule (benchmarks/bench_schedule.py)"
PREDICTION_SECTION = "Run engine with the live prediction on / off (benchmarks/bench_schedule.py --prediction)"
TRANSPORTS = {"modbus-tcp": "Modbus TCP", "modbus-rtu-pty": "Modbus RTU on a pty", "serial": "ASCII serial on a pty"}
SPECIMEN = Specimen("bench", 72.5, 100.0, 100.0)
APPROACH_MM = 4.7          # just above the simulated specimen's top (5 mm)
ABORTED: list[str] = []    # reasons of the runs that did not finish


def method(seconds: float, speed: float = 35.0, cycles: int = 1) -> object:
    """`cycles` cycles lasting `seconds` in all (each half down, half up) at `speed` mm/min, 16 Hz."""
    strain = speed * seconds / cycles / 2 / 60 / SPECIMEN.height_mm
    return parse_method({
        "name": "bench", "sampling_hz": 16.0,
        "contact": {"preload_N": 0.5, "search_speed_mm_min": 20.0, "max_search_mm": 30.0},
        "park": {"speed_mm_min": 400.0},
        "sequence": [{"repeat": cycles, "steps": [{"action": "compress", "strain": strain, "speed_mm_min": speed},
                                {"action": "return", "speed_mm_min": speed}]}],
    })


def approach(sim) -> None:
    machine = open_machine(sim.profile, **sim.profile_overrides)
    try:
        machine.crosshead.move_to(APPROACH_MM, 400.0)
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            try:
                if not machine.crosshead.status().moving:
                    return
            except DeviceError:   # a lost reply while polling: ask again
                pass
            time.sleep(0.01)
    finally:
        machine.close()


def one_run(transport: str, speedup: float, seconds: float, out: Path, realtime: bool = True,
            cycles: int = 1, predict: str = "off"):
    """`predict`: off | process (foamlab's live prediction) | thread (its fits in this process)."""
    with start_simulator_process(transport, speedup=speedup) as sim:
        approach(sim)
        machine = open_machine(sim.profile, connect=False, **sim.profile_overrides)
        m = method(seconds, PREDICTION_SPEED if cycles > 1 else 35.0, cycles)
        engine = RunEngine(machine, m, SPECIMEN, out, speedup=speedup, realtime=realtime)
        predictor = None
        if predict != "off":
            executor = concurrent.futures.ThreadPoolExecutor(1) if predict == "thread" else None
            predictor = LivePredictor(engine.plan, m.sampling_hz, m.n_cycles, executor=executor)
            engine.add_listener(predictor)
            predictor.start()
        try:
            result = engine.run()
        finally:
            if predictor is not None:
                predictor.finish(60.0)
                if not predictor.forecasts:
                    ABORTED.append(f"live prediction ({predict}) made no forecast: {predictor.notes}")
    if result.status != "finished":
        ABORTED.append(f"{TRANSPORTS[transport]}, speedup {speedup:g}: {result.reason}")
        print(f"  {ABORTED[-1]}", flush=True)
    return result, engine.scheduling


def realtime_table(seconds: float, repeats: int, out: Path, transports: dict) -> list[str]:
    lines = [f"Speedup 1 (real time), one {seconds:g} s cycle per run, {repeats} runs per row, medians; "
             f"deviation = request start - deadline.", "",
             "| transport | scheduling | samples | missed | deviation p50 / p99 / max (ms) | request p50 / p99 / max (ms) |",
             "|---|---|---:|---:|---:|---:|"]
    for transport, label in transports.items():
        for realtime in (True, False):
            stats, scheduling, aborted = [], "", []
            while len(stats) < repeats and len(aborted) < repeats:
                result, scheduling = one_run(transport, 1.0, seconds, out, realtime=realtime)
                if result.status == "finished":
                    stats.append(result.timing)
                else:   # a load spike on this shared machine; counted, and the run repeated
                    aborted.append(result.reason)
            if not stats:
                lines.append(f"| {label} | {scheduling} | every run aborted: {aborted[0]} |  |  |  |")
                continue
            med = lambda attr: statistics.median(getattr(s, attr) for s in stats)  # noqa: E731
            note = f" ({len(aborted)} aborted run(s) repeated)" if aborted else ""
            lines.append(
                f"| {label}{note} | {scheduling} | {med('samples'):.0f} | {med('missed'):.0f} "
                f"(max {max(s.missed for s in stats)}) | {med('lateness_p50_ms'):.2f} / {med('lateness_p99_ms'):.2f} / "
                f"{med('lateness_max_ms'):.2f} | {med('rtt_p50_ms'):.2f} / {med('rtt_p99_ms'):.2f} / "
                f"{med('rtt_max_ms'):.2f} |")
            print(lines[-1], flush=True)
    return lines


def sweep_table(out: Path, transports: dict) -> list[str]:
    speedups = (2, 5, 10, 20, 40)
    lines = ["", "Throughput: one cycle of 20 s machine time (320 deadlines) at speedup S = 16 x S samples "
             "per wall second; missed deadlines in % (one run each).", "",
             "| transport | " + " | ".join(f"S = {s}" for s in speedups) + " |",
             "|---|" + "---:|" * len(speedups)]
    for transport, label in transports.items():
        cells = []
        for s in speedups:
            result, _ = one_run(transport, float(s), 20.0, out)
            deadlines = result.n_samples + result.missed
            if result.status != "finished":
                cells.append(f"aborted ({result.end})")
            else:
                cells.append(f"{100 * result.missed / max(deadlines, 1):.1f}")
        lines.append(f"| {label} | " + " | ".join(cells) + " |")
        print(lines[-1], flush=True)
    return lines


#: The prediction runs: the paper's strokes (58 mm) at 50 mm/min, three cycles.
PREDICTION_SPEED = 50.0
PREDICTION_CYCLE_S = 2 * 58.0 / PREDICTION_SPEED * 60.0


def prediction_table(out: Path, speedups=(10.0, 20.0), repeats: int = 2) -> list[str]:
    modes = ("off", "process", "thread")
    lines = ["", f"Live prediction on / off: three cycles to 80 % at {PREDICTION_SPEED:g} mm/min over Modbus TCP "
             f"({3 * PREDICTION_CYCLE_S:.0f} s of machine time, ~{3 * PREDICTION_CYCLE_S * 16:.0f} deadlines), "
             f"{repeats} runs per mode, the modes alternated; the forecast (four fits) is made once, after "
             "cycle 2. Missed: total over the runs; work p99: the engine's own work per sample.", "",
             "| speedup | prediction | deadlines | missed | missed ratio on / off | lateness p99 (ms) | work p99 (ms) |",
             "|---:|---|---:|---:|---:|---:|---:|"]
    for speedup in speedups:
        runs = {m: [] for m in modes}
        for _ in range(repeats):
            for mode in modes:
                result, _ = one_run("modbus-tcp", speedup, 3 * PREDICTION_CYCLE_S, out, cycles=3, predict=mode)
                runs[mode].append(result)
        missed = {m: sum(r.missed for r in rs) for m, rs in runs.items()}
        for mode in modes:
            rs = runs[mode]
            deadlines = sum(r.n_samples + r.missed for r in rs)
            ratio = "" if mode == "off" else (f"{missed[mode] / missed['off']:.2f}" if missed["off"] else
                                              ("1 (0 / 0)" if not missed[mode] else f"{missed[mode]} / 0"))
            label = {"off": "off", "process": "on (worker process: foamlab)", "thread": "on, fits in a thread"}[mode]
            lines.append(f"| {speedup:g} | {label} | {deadlines} | {missed[mode]} | {ratio} | "
                         f"{statistics.median(r.timing.lateness_p99_ms for r in rs):.2f} | "
                         f"{statistics.median(r.timing.work_p99_ms for r in rs):.2f} |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=20.0, help="sampling time per real-time run")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-sweep", action="store_true", help="skip the throughput sweep")
    parser.add_argument("--transports", nargs="+", choices=list(TRANSPORTS), default=list(TRANSPORTS))
    parser.add_argument("--prediction", action="store_true",
                        help="only the live prediction on / off table (its own section)")
    args = parser.parse_args()
    if args.prediction:
        with tempfile.TemporaryDirectory() as tmp:
            lines = prediction_table(Path(tmp), repeats=args.repeats)
        load = os.getloadavg()[0]
        lines += ["", f"Load average at the end: {load:.1f} on {os.cpu_count()} cores (other jobs share them)."]
        if ABORTED:
            lines += ["", "Aborted runs / notes:"] + [f"- {a}" for a in ABORTED]
        publish(PREDICTION_SECTION, lines)
        return
    transports = {t: TRANSPORTS[t] for t in args.transports}
    load = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp)
        lines = realtime_table(args.seconds, args.repeats, out, transports)
        if not args.no_sweep:
            lines += sweep_table(out, transports)
    lines += ["", f"Load average at the start: {load:.1f} on {os.cpu_count()} cores (other jobs share them). "
              "The engine asks SCHED_FIFO for its worker thread and holds a zero CPU wake-up latency request "
              "during the run (both granted here as root; on a lab PC SCHED_FIFO needs CAP_SYS_NICE or an "
              "rtprio limit); the rows 'normal' are the same runs without either. The simulator runs in its "
              "own process, its answering thread SCHED_FIFO 5, the rest at nice -15 (simulator/process.py). "
              "Missed: median over the runs (max). Aborted runs are listed below the tables."]
    if ABORTED:
        lines += ["", "Aborted runs (repeated):"] + [f"- {a}" for a in ABORTED]
    publish(SECTION, lines)


if __name__ == "__main__":
    main()
