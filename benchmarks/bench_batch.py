"""Batch throughput: seconds per run of `foamlab.batch.process` on 1 and 2 local worker processes.

    .venv/bin/python benchmarks/bench_batch.py [--runs 10] [--repeats 3] [--hz 2]

The runs are the paper's protocol (3 cycles at 23.6 mm/min, default specimen, load-cell noise)
sampled at --hz and written as plain CSV files; half soften from cycle to cycle. For each number
of workers a LocalCluster is started and warmed up (each worker imports foamlab and analyses one
run) outside the timing; then the whole set is processed --repeats times (no output file: nothing
is skipped) and the median wall time per run is reported. Ratio = s/run with 1 worker / s/run
with 2 workers (the throughput gain of the second worker; 2.0 is perfect scaling). The
1-minute load average before and after is printed: on a shared machine it decides the ratio.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from _table import publish  # noqa: E402

from foamlab.batch import process  # noqa: E402
from foamlab.diagnosis.synthetic import hidden_effect_run  # noqa: E402


def write_runs(folder: Path, n: int, hz: float, first_seed: int) -> list[Path]:
    paths = []
    for i in range(n):
        run = hidden_effect_run({"cycle_softening": 0.03} if i % 2 else None, sampling_hz=hz, seed=first_seed + i)
        path = folder / f"run{first_seed + i:03d}.csv"
        with open(path, "w", encoding="utf-8") as fh:
            fh.write("time_s,displacement_mm,force_N\n")
            for t, x, f in zip(run.time_s.tolist(), run.displacement_mm.tolist(), run.force_N.tolist()):
                fh.write(f"{t!r},{x!r},{f!r}\n")
        paths.append(path)
    return paths


def seconds_per_run(workers: int, runs: list[Path], warmup: list[Path], repeats: int) -> list[float]:
    from distributed import Client, LocalCluster

    env = {"PYTHONPATH": os.pathsep.join(p for p in (str(ROOT), os.environ.get("PYTHONPATH", "")) if p)}
    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                      env=env, silence_logs=40) as cluster, Client(cluster) as client:
        client.wait_for_workers(workers, timeout=120)
        process(warmup[:workers], client)
        times = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            table = process(runs, client)
            times.append((time.perf_counter() - t0) / len(runs))
            assert (table["error"] == "").all(), table["error"].tolist()
    return times


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--hz", type=float, default=2.0)
    args = ap.parse_args()
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as tmp:
        runs = write_runs(Path(tmp), args.runs, args.hz, 0)
        warm = Path(tmp) / "warmup"
        warm.mkdir()
        warmup = write_runs(warm, 2, args.hz, 1000)
        samples = sum(1 for _ in open(runs[0], encoding="utf-8")) - 1
        result = {w: seconds_per_run(w, runs, warmup, args.repeats) for w in (1, 2)}
    load_after = os.getloadavg()[0]
    med = {w: statistics.median(t) for w, t in result.items()}
    ratio = med[1] / med[2]
    lines = [f"{args.runs} runs of the paper's protocol at {args.hz:g} Hz ({samples} samples each), "
             f"plain CSV, LocalCluster of processes (1 thread each), median of {args.repeats} passes; "
             f"{os.cpu_count()} cores; 1-minute load average {load_before:.2f} before, {load_after:.2f} after.",
             "", "| workers | s / run (median) | runs / min | all passes (s / run) |", "|---:|---:|---:|---|"]
    for w in (1, 2):
        lines.append(f"| {w} | {med[w]:.2f} | {60 / med[w]:.1f} | "
                     f"{', '.join(f'{t:.2f}' for t in result[w])} |")
    lines += ["", f"ratio 1 worker / 2 workers (s per run): **{ratio:.2f}** (2.0 = perfect scaling)"]
    publish("Batch throughput (benchmarks/bench_batch.py)", lines)
    print(f"median s/run: 1 worker {med[1]:.3f}, 2 workers {med[2]:.3f}, ratio {ratio:.2f}")


if __name__ == "__main__":
    main()
