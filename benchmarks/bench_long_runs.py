"""Long runs: fit and diagnosis cost against the number of cycles (issue 19).

Runs of 3, 5, 10, 20 and 50 cycles of the default specimen to 60 % of a 60 mm block at
60 mm/min, sampled at 16 Hz (foamlab's own model, 0.1 N noise), each fitted (the structure the
data determine) and diagnosed in a child process of its own so its peak memory (ru_maxrss) is
its own. Prints per run the fit and diagnosis seconds, the peak memory, the fit's RMSE over the
noise and over that of a fit of the run's first three cycles alone, the structure chosen, and
the growth exponents of time with the number of samples (a log-log fit from 3 to 50 cycles).

    python benchmarks/bench_long_runs.py [--cycles 3,5,10,20,50] [--no-diagnose] [--form auto|causal|paper]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import publish  # noqa: E402

CHILD = r"""
import json, resource, sys, time
import numpy as np
from foamlab.model import ModelParameters, evaluate, triangular_history
from foamlab.rundata import RunData
from foamlab.identification import fit_run
from foamlab.diagnosis import diagnose
cycles, diag, form = int(sys.argv[1]), sys.argv[2] == "1", sys.argv[3]
p = ModelParameters.default()
t, x = triangular_history(36.0, 60.0 / 60.0, cycles, 16.0)
run = RunData(t, x, evaluate(p, t, x).measured_force + np.random.default_rng(cycles).normal(0, 0.1, len(t)))
t0 = time.perf_counter(); fit = fit_run(run, form=form); t_fit = time.perf_counter() - t0
t_diag, verdict = float("nan"), ""
if diag:
    t0 = time.perf_counter(); d = diagnose([run], fit=fit, form=form); t_diag = time.perf_counter() - t0; verdict = d.verdict
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
# a fit of the run's first three cycles alone (the same samples): the whole run must fit as well
n3 = len(triangular_history(36.0, 60.0 / 60.0, 3, 16.0)[0])
first3 = fit_run(RunData(t[:n3], x[:n3], run.force_N[:n3]), form=form) if cycles > 3 else fit
print(json.dumps({"samples": len(t), "fit_s": t_fit, "diag_s": t_diag, "verdict": verdict,
                  "rmse_ratio": fit.rmse / 0.1, "params": fit.n_params, "orders": str(fit.orders),
                  "first3_ratio": fit.rmse / first3.rmse, "peak_mb": peak}))
"""


def measure(cycles: int, diagnose: bool, form: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, str(cycles), "1" if diagnose else "0", form], cwd=ROOT,
                         capture_output=True, text=True, check=True, timeout=3600)
    return json.loads(out.stdout.strip().splitlines()[-1])


def exponent(samples, seconds) -> float:
    ok = np.isfinite(seconds)
    return float(np.polyfit(np.log(np.asarray(samples)[ok]), np.log(np.asarray(seconds)[ok]), 1)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--cycles", default="3,5,10,20,50")
    ap.add_argument("--no-diagnose", action="store_true")
    ap.add_argument("--form", default="auto", help="the residual form fitted (default: auto, both, as foamlab fit)")
    args = ap.parse_args()
    load0 = os.getloadavg()[0]
    rows = []
    for c in [int(v) for v in args.cycles.split(",")]:
        r = measure(c, not args.no_diagnose, args.form)
        rows.append((c, r))
        print(f"{c:3d} cycles {r['samples']:6d} samples: fit {r['fit_s']:6.2f} s, diagnosis {r['diag_s']:6.2f} s "
              f"({r['verdict'] or '-'}), peak {r['peak_mb']:5.0f} MB, RMSE/noise {r['rmse_ratio']:.3f}, "
              f"whole/first 3 cycles {r['first3_ratio']:.3f}, {r['orders']} ({r['params']} parameters), "
              f"load {os.getloadavg()[0]:.1f}", flush=True)
    n = [r["samples"] for _, r in rows]
    e_fit = exponent(n, [r["fit_s"] for _, r in rows])
    e_diag = exponent(n, [r["diag_s"] for _, r in rows]) if not args.no_diagnose else float("nan")
    load = os.getloadavg()[0]
    lines = [f"Default specimen, 60 % of 60 mm at 60 mm/min, 16 Hz, 0.1 N noise; residual form {args.form}; "
             f"each run in its own process (peak = ru_maxrss); 1-minute load average {load0:.1f} at the start, "
             f"{load:.1f} at the end (2 cores shared with other work). whole / first 3: the whole run's "
             "RMSE over that of a fit of its first three cycles alone (target <= 1.5).", "",
             "| cycles | samples | fit s | diagnosis s | verdict | peak MB | RMSE / noise | whole / first 3 | structure | parameters |",
             "|---:|---:|---:|---:|---|---:|---:|---:|---|---:|"]
    lines += [f"| {c} | {r['samples']:,d} | {r['fit_s']:.2f} | {r['diag_s']:.2f} | {r['verdict'] or '-'} | "
              f"{r['peak_mb']:.0f} | {r['rmse_ratio']:.3f} | {r['first3_ratio']:.3f} | {r['orders']} | "
              f"{r['params']} |" for c, r in rows]
    lines += ["", f"**growth exponent of time with samples: fit {e_fit:.2f}, diagnosis {e_diag:.2f}** "
                  "(target <= 1.1; 20 cycles: fit <= 10 s, diagnosis <= 30 s, each < 600 MB)"]
    print("\n".join(lines[-1:]))
    publish("Long runs (benchmarks/bench_long_runs.py)", lines)


if __name__ == "__main__":
    main()
