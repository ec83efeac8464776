"""The live prediction's rule on runs of the model itself: false alarms on clean runs, where a
softening from cycle 3 on is flagged, what a forecast costs.

Three cycles to 80 % of the default 72.5 mm block (the paper's strokes), at 50 and 23.6 mm/min,
16 Hz, the simulated load cell's noise (0.05 N); cycles 1-2 identify (foamlab.prediction.
make_forecast, as the live predictor does), cycle 3 goes through the departure rule sample by
sample (DepartureWatch), and is scored (score_cycle).

    python benchmarks/bench_prediction.py [--clean 25] [--softened 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from foamlab.methods import parse_method  # noqa: E402
from foamlab.model import ModelParameters, label_history, triangular_history  # noqa: E402
from foamlab.model.effects import CycleSoftening, EffectChain  # noqa: E402
from foamlab.prediction import DepartureWatch, make_forecast, score_cycle  # noqa: E402
from foamlab.rundata import RunData  # noqa: E402

try:
    from _table import publish  # noqa: E402
except ImportError:   # run from elsewhere
    from benchmarks._table import publish  # noqa: E402

SECTION = "Live prediction on runs of the model (benchmarks/bench_prediction.py)"
NOISE_N, HZ, AMPLITUDE, HEIGHT = 0.05, 16.0, 58.0, 72.5


def plan(speed: float):
    return parse_method({
        "name": "bench", "sampling_hz": HZ,
        "contact": {"preload_N": 0.5, "search_speed_mm_min": 20.0, "max_search_mm": 30.0},
        "park": {"speed_mm_min": 400.0},
        "sequence": [{"repeat": 3, "steps": [
            {"action": "compress", "strain": AMPLITUDE / HEIGHT, "speed_mm_min": speed},
            {"action": "return", "speed_mm_min": speed}]}]}).plan(HEIGHT)


def one(speed: float, softening: float, seed: int):
    """(seconds for the forecast, first departure or None, cycle 3's score)."""
    t, x = triangular_history(AMPLITUDE, speed / 60.0, 3, HZ)
    chain = EffectChain([CycleSoftening(softening, from_cycle=3)] if softening else [])
    f = chain.measured_force(ModelParameters.default(), t, x, labels=label_history(x))
    f = f + np.random.default_rng(seed).normal(0.0, NOISE_N, len(t))
    step = np.clip(np.ceil(t / (AMPLITUDE / (speed / 60.0))).astype(int) - 1, 0, 5)
    run = RunData(t, x, f)
    n = int(np.searchsorted(step, 3, side="right"))
    started = time.perf_counter()
    forecast = make_forecast(run.slice(0, n), plan(speed), 2, HZ, 3)
    seconds = time.perf_counter() - started
    watch = DepartureWatch(forecast.noise_N, HZ)
    found = []
    for s in (4, 5):
        rows = np.flatnonzero(step == s)
        found += watch.compare(forecast.step(s), 2, x[rows], t[rows] - t[rows[0]], f[rows], t[rows])[1]
    return seconds, (found[0] if found else None), score_cycle(forecast, run, np.flatnonzero(step >= 4), 3)


def table(clean: int, softened: int) -> list[str]:
    lines = ["| speed (mm/min) | specimen | runs | flagged | where (first flag) | cycle 3 score: RMSE / noise, median (max) | "
             "forecast s, median (max) |", "|---:|---|---:|---:|---|---:|---:|"]
    for speed in (50.0, 23.6):
        for softening, runs in ((0.0, clean), (0.1, softened), (0.2, softened)):
            results = [one(speed, softening, seed) for seed in range(1, runs + 1)]
            flags = [d for _, d, _ in results if d is not None]
            where = ", ".join(f"{d.phase} {d.at_mm:.0f} mm" for d in flags[:5]) + (" ..." if len(flags) > 5 else "")
            ratios = [s.ratio for _, _, s in results]
            secs = [sec for sec, _, _ in results]
            what = "clean" if not softening else f"softens {softening:.0%} from cycle 3"
            lines.append(f"| {speed:g} | {what} | {runs} | {len(flags)} | {where or '-'} | "
                         f"{statistics.median(ratios):.3g} ({max(ratios):.3g}) | "
                         f"{statistics.median(secs):.2f} ({max(secs):.2f}) |")
            print(lines[-1], flush=True)
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--clean", type=int, default=25, help="clean runs per speed")
    parser.add_argument("--softened", type=int, default=5, help="softened runs per speed and size")
    args = parser.parse_args()
    lines = [f"Three cycles to 80 % of the 72.5 mm block, 16 Hz, load-cell noise {NOISE_N} N; cycles 1-2 "
             "identify, cycle 3 goes through the departure rule; one seed per run. Flagged: runs with a "
             "departure (a false alarm on a clean run). The forecast: both residual forms at the largest "
             "orders, three neighbours in the form chosen (one prepared run) and the Jacobian, one core.", ""]
    lines += table(args.clean, args.softened)
    lines += ["", f"Load average at the end: {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores (other jobs share them)."]
    publish(SECTION, lines)


if __name__ == "__main__":
    main()
