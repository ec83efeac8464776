"""The residual form the data choose: pick rates, fit quality and the cost of `--form auto`.

    python benchmarks/bench_forms.py [--seeds N] [--time-runs K]

1. For each form (causal, paper) and regime (A, B) of the independent generator
   (tests/independent_model.py) and seeds 1..N: `fit_run` with the default form 'auto';
   prints the share of runs whose form was picked right and the RMSE / noise (median, max,
   share within 1.05).
2. Cost: on a three-cycle 16 Hz run of the default specimen (the README's main job's shape,
   14 157 samples) the fit with one form and with 'auto' (median of K, in process), their
   ratio, and the wall time of a whole `python -m foamlab.cli fit RUN --json --no-store`
   process (median of K).
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
sys.path.insert(0, str(ROOT))

import independent_model as im  # noqa: E402

from foamlab.diagnosis.synthetic import hidden_effect_run  # noqa: E402
from foamlab.identification import fit_run  # noqa: E402
from foamlab.storage.runfile import write_run_file  # noqa: E402


def pick_rates(seeds: int) -> None:
    print(f"{'form':<8}{'regime':<8}{'picked':>8}{'rmse/noise median':>20}{'max':>8}{'<= 1.05':>9}")
    for form in ("causal", "paper"):
        for name, regime in im.REGIMES.items():
            reg = regime.with_(form=form)
            ratios, right = [], 0
            for seed in range(1, seeds + 1):
                result = fit_run(im.generate(reg, seed).to_rundata())
                right += result.params.residual_form == form
                ratios.append(result.rmse / reg.noise_N)
            within = sum(r <= 1.05 for r in ratios)
            print(f"{form:<8}{name:<8}{right:>5}/{seeds:<2}{statistics.median(ratios):>20.3f}"
                  f"{max(ratios):>8.3f}{within:>6}/{seeds}", flush=True)


def cost(repeats: int) -> None:
    run = hidden_effect_run(None, seed=1)          # default specimen, 3 cycles, 16 Hz
    times = {}
    for form in ("causal", "auto"):
        samples = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            fit_run(run, form=form)
            samples.append(time.perf_counter() - t0)
        times[form] = statistics.median(samples)
    with tempfile.TemporaryDirectory() as tmp:
        path = write_run_file(Path(tmp) / "main.csv", run)
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        walls = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(path), "--json", "--no-store"],
                           cwd=ROOT, env=env, capture_output=True, check=True)
            walls.append(time.perf_counter() - t0)
    print(f"\n3-cycle 16 Hz run, {len(run.time_s)} samples (median of {repeats}; load {os.getloadavg()[0]:.2f}):")
    print(f"  fit, one form (causal)    {times['causal']:.2f} s")
    print(f"  fit, --form auto          {times['auto']:.2f} s   ratio {times['auto'] / times['causal']:.2f}")
    print(f"  whole `foamlab fit` process {statistics.median(walls):.2f} s")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--seeds", type=int, default=20)
    ap.add_argument("--time-runs", type=int, default=5)
    args = ap.parse_args()
    print(f"load average at start: {os.getloadavg()[0]:.2f}")
    if args.seeds:
        pick_rates(args.seeds)
    cost(args.time_runs)


if __name__ == "__main__":
    main()
