"""Cost of the causal time-domain model vs the number of samples (target: linear).

Same three-cycle paper protocol sampled ever faster, 10^4 to 10^6 samples; the
growth exponent is the slope of log(time) against log(n) (1.0 = linear, 2.0 =
the naive history sum). Also the online SpecimenState cost per step (simulator).
Run: .venv/bin/python benchmarks/bench_model.py
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import median_seconds, publish  # noqa: E402

from foamlab.model import ModelParameters, SpecimenState, evaluate, triangular_history  # noqa: E402

A, RATE, CYCLES = 58.0, 23.6 / 60.0, 3
DURATION = CYCLES * 2 * A / RATE



def main() -> None:
    params = ModelParameters.default()
    rows = []
    ns, ts = [], []
    for n_target in (10_000, 30_000, 100_000, 300_000, 1_000_000):
        t, x = triangular_history(A, RATE, CYCLES, n_target / DURATION)
        repeats = 7 if n_target <= 100_000 else 3
        sec = median_seconds(lambda: evaluate(params, t, x), repeats)
        ns.append(len(t))
        ts.append(sec)
        rows.append(f"| {len(t):>9,d} | {sec * 1e3:9.1f} | {sec / len(t) * 1e6:7.2f} |")
    slope = float(np.polyfit(np.log(ns), np.log(ts), 1)[0])
    t, x = triangular_history(A, RATE, CYCLES, 16.0)
    state = SpecimenState(params, h_min=1 / 16)
    n_steps = 4000
    t0 = time.perf_counter()
    for i in range(n_steps):
        state.step(t[i], x[i])
    per_step = (time.perf_counter() - t0) / n_steps
    publish("Model evaluation cost (benchmarks/bench_model.py)", [
        "| samples | evaluate() ms (median) | µs / sample |",
        "|---:|---:|---:|",
        *rows,
        "",
        f"Growth exponent of evaluate() from 10^4 to 10^6 samples: **{slope:.2f}** (1 = linear).",
        f"Online SpecimenState.step(): {per_step * 1e6:.0f} µs per step (3 cycles of memory).",
    ])


if __name__ == "__main__":
    main()
