"""`foamlab fit` and `foamlab diagnose` on runs of the independent generator (tests/independent_model.py).

    python benchmarks/bench_fit_independent.py [--seeds N] [--grid] [--no-diagnose] [--cycles C] [--hz F]
                                               [--form causal|paper]

For each regime (A, B; with --grid also A-grid, B-grid, turning points on samples) and
seed 1..N (C cycles, default the regime's three; sampled at F Hz, default 16; generated in
the residual form given, default the regime's causal one): the run is written as a plain CSV into a temporary directory, then
`python -m foamlab.cli fit PATH --json --no-store` and `python -m foamlab.cli diagnose
PATH --no-store` run on it (subprocesses of this checkout). One line per run:

- fit rmse / sigma (the JSON's `rmse`, sigma = the generator's 0.15 N; the realised
  noise's rms / sigma is printed as `floor`), the CLI's wall time;
- where the fit misses: its rmse / sigma on the samples more than 3 sample steps from a
  true turning point (`away`) and the largest residual (in-process fit_run, same code);
- diagnose: the base model's RMSE / sigma (its text summary: diagnosis leaves samples
  next to a turning point out of its evidence) and the verdict, the CLI's wall time.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

import independent_model as im
import numpy as np

TURN_STEPS = 3


def cli(*args: str) -> tuple[str, float]:
    env = dict(os.environ, PYTHONPATH=str(ROOT), OPENBLAS_NUM_THREADS="1")
    started = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "foamlab.cli", *args], cwd=ROOT, env=env,
                         capture_output=True, text=True, check=False, timeout=900)
    elapsed = time.perf_counter() - started
    if out.returncode != 0:
        raise RuntimeError(f"foamlab {' '.join(args)}: exit {out.returncode}: {out.stderr.strip()}")
    return out.stdout, elapsed


def near_turns(run: im.SyntheticRun, steps: int = TURN_STEPS) -> np.ndarray:
    h = run.model.hist
    turns = [h.start_time(0) + j * h.half_s for j in range(2 * h.n_cycles + 1)]
    dt = 1.0 / run.regime.sampling_hz
    return np.any([np.abs(run.time_s - c) <= steps * dt for c in turns], axis=0)


def measure(regime: im.Regime, seed: int, folder: Path, diagnose: bool, cycles: int | None = None) -> dict:
    from foamlab.identification import fit_run

    run = im.generate(regime, seed, cycles=cycles)
    path = folder / f"{regime.name}_{seed}.csv"
    run.write_csv(path)
    sigma = regime.noise_N
    out, fit_s = cli("fit", str(path), "--json", "--no-store")
    row = {"regime": regime.name, "seed": seed, "start_s": run.start_s,
           "floor": float(np.sqrt(np.mean((run.force_N - run.true_force_N) ** 2))) / sigma,
           "fit": json.loads(out)["rmse"] / sigma, "fit_s": fit_s}
    res = fit_run(run.to_rundata())
    e = run.force_N - res.predicted_force_N
    away = ~near_turns(run)
    row.update(away=float(np.sqrt(np.mean(e[away] ** 2))) / sigma, worst_N=float(e[np.argmax(np.abs(e))]),
               worst_t=float(run.time_s[np.argmax(np.abs(e))]), inproc=res.rmse / sigma)
    if diagnose:
        out, diag_s = cli("diagnose", str(path), "--no-store")
        verdict = re.search(r"^verdict: (\S+)", out, re.MULTILINE).group(1)
        base = float(re.search(r"base model RMSE ([0-9.eE+-]+) N", out).group(1))
        row.update(verdict=verdict, base=base / sigma, diag_s=diag_s)
    return row


def line(r: dict) -> str:
    s = (f"{r['regime']:<7}seed {r['seed']:<3}start {r['start_s']:.4f} s  fit {r['fit']:6.3f} x sigma "
         f"(floor {r['floor']:.3f}, away from turns {r['away']:.3f}, worst {r['worst_N']:+7.2f} N at "
         f"{r['worst_t']:7.3f} s)  {r['fit_s']:5.1f} s")
    if "verdict" in r:
        s += f"  | diagnose base {r['base']:.3f} x sigma, verdict {r['verdict']}, {r['diag_s']:5.1f} s"
    return s


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=5, help="seeds per regime (default 5: 10 runs)")
    ap.add_argument("--grid", action="store_true", help="also the regimes with turning points on samples")
    ap.add_argument("--no-diagnose", action="store_true", help="fit only")
    ap.add_argument("--cycles", type=int, default=None, help="cycles per run (default: the regime's, 3)")
    ap.add_argument("--hz", type=float, default=None, help="sampling rate (default: the regime's, 16 Hz)")
    ap.add_argument("--form", choices=("causal", "paper"), default=None,
                    help="residual form the runs are generated in (default: the regime's, causal)")
    args = ap.parse_args(argv)
    regimes = list(im.REGIMES.values()) + (list(im.GRID_REGIMES.values()) if args.grid else [])
    if args.hz:
        regimes = [r.with_(sampling_hz=args.hz) for r in regimes]
    if args.form:
        regimes = [r.with_(form=args.form) for r in regimes]
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_fit_independent_") as tmp:
        for regime in regimes:
            for seed in range(1, args.seeds + 1):
                rows.append(measure(regime, seed, Path(tmp), not args.no_diagnose, args.cycles))
                print(line(rows[-1]), flush=True)
    for name in dict.fromkeys(r["regime"] for r in rows):
        sel = [r for r in rows if r["regime"] == name]
        s = (f"{name}: fit rmse/sigma median {statistics.median(r['fit'] for r in sel):.3f} "
             f"(range {min(r['fit'] for r in sel):.3f}-{max(r['fit'] for r in sel):.3f}), away from turns "
             f"median {statistics.median(r['away'] for r in sel):.3f}")
        if "base" in sel[0]:
            s += (f"; diagnose base median {statistics.median(r['base'] for r in sel):.3f}, verdicts "
                  + ", ".join(f"{v} {sum(r['verdict'] == v for r in sel)}" for v in
                              dict.fromkeys(r["verdict"] for r in sel)))
        print(s)
    print(f"median fit time (CLI, wall) {statistics.median(r['fit_s'] for r in rows):.2f} s"
          + (f"; median diagnose time {statistics.median(r['diag_s'] for r in rows):.2f} s"
             if "diag_s" in rows[0] else ""))
    return 0


if __name__ == "__main__":
    sys.exit(main())
