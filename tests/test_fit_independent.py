"""Acceptance: `foamlab fit` reaches the load cell's noise on runs it did not generate itself.

The runs come from tests/independent_model.py (the combined model written again, in closed
form, in continuous time; validated in test_independent_model.py): three triangular
cycles at 16 Hz, two parameter regimes unlike the default specimen, contact loss at the
end of every unloading, a load-cell zero offset, 0.15 N Gaussian noise, a 1 um encoder.
In regimes A and B the crosshead turns between samples, as a real machine does (the
motion starts at a phase drawn from the seed); A-grid and B-grid have their turning
points on samples. A perfect fit leaves the noise: rmse / sigma ~ 1.00 (the realised
noise's rms is within 0.6 % of sigma for every case here).

Requirement: the fit's whole-run RMSE (`rmse` of `foamlab fit --json`) <= 1.05 sigma.
Measured on 2026-11-25 (benchmarks/bench_fit_independent.py): A-grid/B-grid 0.996-1.014,
A 3.85-7.90, B 1.02-5.89 (8 of 10 turning-between-samples cases fail): the fit switches
the model at the sample of largest displacement; when that sample lies after the true
turn the model is still loading there (damping on, residual off) while the truth has
turned: that sample is 30-50 N off, and the fit bends its parameters to it
(2.2-2.8 sigma on the samples more than 3 steps from any turning point).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import independent_model as im
import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
TOLERANCE = 1.05
SEEDS = (1, 2, 3, 4, 5)
CASES = ([(r, s) for r in im.REGIMES.values() for s in SEEDS]
         + [(r, s) for r in im.GRID_REGIMES.values() for s in (1, 2)])


@pytest.mark.parametrize("regime,seed", CASES, ids=[f"{r.name}-seed{s}" for r, s in CASES])
def test_fit_reaches_the_noise(regime, seed):
    from foamlab.identification import fit_run

    run = im.generate(regime, seed)
    result = fit_run(run.to_rundata())
    ratio = result.rmse / regime.noise_N
    assert ratio <= TOLERANCE, (f"regime {regime.name} seed {seed} (motion from t = {run.start_s:.4f} s): "
                                f"fit RMSE {result.rmse:.4f} N = {ratio:.3f} x the noise {regime.noise_N} N")
    assert result.success, f"regime {regime.name} seed {seed}: {result.convergence}"


def test_fit_cli_json_reaches_the_noise(tmp_path):
    regime, seed = im.REGIME_A, 1
    run = im.generate(regime, seed)
    path = tmp_path / "independent_A_1.csv"
    run.write_csv(path)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    out = subprocess.run([sys.executable, "-m", "foamlab.cli", "fit", str(path), "--json", "--no-store"],
                         cwd=ROOT, env=env, capture_output=True, text=True, check=False, timeout=300)
    assert out.returncode == 0, out.stderr
    fitted = json.loads(out.stdout)
    rmse = fitted["rmse"]
    assert fitted["converged"] is True, fitted["optimizer"]
    assert rmse / regime.noise_N <= TOLERANCE, (f"foamlab fit --json on regime A seed 1: rmse {rmse:.4f} N = "
                                                f"{rmse / regime.noise_N:.3f} x the noise")


#: A clean B causal run of the limits benchmark (seed fixed there before looking) on which the
#: search's best-probed start led to another basin: identification's first optimum missed the four
#: samples after the first peak by -3.7 noise on average (the diagnosis then gave a friction that
#: is not there Delta BIC 47.6). 2018, the other run the trigger fires on among 40, is only part
#: of the way (19 noise variances better, the first peak still missed): docs/analysis.md,
#: "B causal: identification's basin".
OTHER_BASIN = [3058]


@pytest.mark.parametrize("seed", OTHER_BASIN)
def test_a_fit_that_misses_after_the_turns_is_searched_from_every_start(seed):
    import independent_effects as ie
    from scipy.stats import chi2

    from foamlab.identification import fit_run

    fit = fit_run(ie.independent_run("B", seed, None, form="causal"))
    base = (fit.largest or fit).free_core or (fit.largest or fit).core_fit
    fd = fit.prepared
    r, used = base.solution.residuals[0], np.flatnonzero(fd.series.used)
    # each turn's mean residual over the four samples after it, in its noise standard error
    z = [np.sum(r[after]) / (np.sqrt(len(after)) * fd.noise_N)
         for after in (used[fd.t[used] > when][:4] for when in fd.nodes.turns_between)]
    assert chi2.sf(float(np.sum(np.square(z))), len(z)) > 1e-3, np.round(z, 2)
