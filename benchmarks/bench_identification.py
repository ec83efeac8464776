"""Identification: speed, recovery, coverage and efficiency against the Cramér-Rao bound.

1. Speed: full identification (segmentation, the paper's three steps, joint refinement,
   statistics) of a three-cycle 16 Hz run of the default specimen (14 157 samples),
   median of repeats; and a plain baseline on the same run: the same model
   (foamlab.model.evaluate, contact-censored) fitted by scipy.optimize.curve_fit ('trf',
   numerical 2-point derivatives) from a generic start, with a wall-clock cap.
2. Recovery: RMSE of the fitted curve / noise level.
3. Coverage of the 95 % intervals over >= 50 seeded runs, and efficiency: the Cramér-Rao
   variance (sigma^2 (J^T J)^-1, J the model's Jacobian at the truth, full resolution)
   divided by the variance of the estimates over the runs (1 = efficient). For the
   identifiable reduction of the default specimen (orders 1,1,7) and for the full
   default (2,3,7), whose residual terms the data do not determine.
4. The real Bluehill file: statistics and time.

Run:  .venv/bin/python benchmarks/bench_identification.py [--quick]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import numpy as np
from scipy.optimize import curve_fit

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _table import publish  # noqa: E402

from foamlab.identification import Orders, fit_run  # noqa: E402
from foamlab.analysis.basis import ModelBasis  # noqa: E402
from foamlab.model.layout import Layout  # noqa: E402
from foamlab.analysis.prepared import prepare  # noqa: E402
from foamlab.importers import load_run  # noqa: E402
from foamlab.model import ModelParameters, evaluate, triangular_history  # noqa: E402
from foamlab.rundata import RunData  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
A, RATE, HZ, SIGMA = 58.0, 23.6 / 60.0, 16.0, 0.1
BASELINE_CAP_S = 120.0


def reduced(p: ModelParameters) -> ModelParameters:
    """The default specimen's slow damping mode and strongest residual term per cycle."""
    return ModelParameters(p.x_scale_mm, p.elastic_k, p.damping_a[:1], p.damping_alpha[:1],
                           p.residual_r[:, -1:], p.residual_beta[:, -1:])


def make_run(params: ModelParameters, seed: int) -> tuple[RunData, np.ndarray]:
    t, x = triangular_history(A, RATE, 3, HZ)
    clean = evaluate(params, t, x).measured_force
    return RunData(t, x, clean + np.random.default_rng(seed).normal(0, SIGMA, len(t))), clean


def load_average() -> str:
    try:
        return "load average %.1f / %.1f / %.1f on %d cores" % (*os.getloadavg(), os.cpu_count() or 0)
    except OSError:
        return "load average unknown"


def speed(repeats: int) -> tuple[list[str], float, RunData]:
    params = ModelParameters.default()
    run, _ = make_run(params, seed=1)
    fit_run(run)                                          # warm-up (imports, FFT plans)
    walls, cpus, ratios = [], [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        result = fit_run(run)
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
        ratios.append(result.rmse / SIGMA)
    med = statistics.median(walls)
    lines = [f"Run: default specimen, 3 cycles at {HZ:g} Hz ({len(run)} samples), noise {SIGMA} N, "
             f"orders {Orders()} (the paper's, `foamlab fit` default), {repeats} repeats; "
             f"shared machine, {load_average()} at the start.", "",
             "| | median | min | max |", "|---|---:|---:|---:|",
             f"| fit_run wall time (s) | **{med:.3f}** | {min(walls):.3f} | {max(walls):.3f} |",
             f"| fit_run CPU time (s) | {statistics.median(cpus):.3f} | {min(cpus):.3f} | {max(cpus):.3f} |",
             f"| RMSE / noise | {statistics.median(ratios):.4f} | {min(ratios):.4f} | {max(ratios):.4f} |", ""]
    return lines, med, run


def baseline(run: RunData, ours_s: float) -> list[str]:
    """The same model by curve_fit from a generic start, numerical derivatives."""
    fd = prepare(run)
    orders = Orders()
    lay = Layout(orders.P, orders.N, orders.M, fd.n_residual_cycles)
    template = ModelParameters(fd.x_scale_mm, np.zeros(lay.P + 1), np.zeros(lay.N), np.zeros(lay.N, complex),
                               np.zeros((lay.C, lay.M)), np.zeros((lay.C, lay.M)))
    t, x, y = fd.t, fd.x, fd.f
    obs = fd.observed
    k0 = np.polynomial.polynomial.polyfit(x[obs] / fd.x_scale_mm, y[obs], lay.P)
    generic = template.with_vector(np.zeros(lay.n_params)).to_vector()
    names = template.names()
    for i, n in enumerate(names):                         # generic, not data-tuned
        if n.startswith("k"):
            generic[i] = k0[int(n[1:])]
        elif n.startswith("a"):
            generic[i] = {"_re": 0.05, "_im": 0.05}.get(n[-3:], 0.01)
        elif n.startswith("r"):
            generic[i] = 0.1
        elif n.startswith("beta"):
            generic[i] = 0.5
    lo = np.full(len(names), -np.inf)
    hi = np.full(len(names), np.inf)
    for i, n in enumerate(names):
        if n.endswith("_re"):
            lo[i], hi[i] = 1e-4, 10.0
        elif n.endswith("_im"):
            lo[i], hi[i] = 0.0, 10.0
        elif n.startswith("beta"):
            lo[i], hi[i] = -3.0, 0.99
    started = time.perf_counter()
    best = {"sse": np.inf, "calls": 0}

    class OutOfTime(Exception):
        pass

    def model(_, *v):
        if time.perf_counter() - started > BASELINE_CAP_S:
            raise OutOfTime
        pred = np.maximum(evaluate(template.with_vector(np.asarray(v)), t, x, fd.labels).force,
                          fd.contact_zero_N)[obs]
        best["calls"] += 1
        best["sse"] = min(best["sse"], float(np.sum((pred - y[obs]) ** 2)))
        return pred

    finished = True
    try:
        curve_fit(model, None, y[obs], p0=generic, bounds=(lo, hi), method="trf")
    except OutOfTime:
        finished = False
    except RuntimeError:                                   # max_nfev reached
        pass
    elapsed = time.perf_counter() - started
    rmse = float(np.sqrt(best["sse"] / len(obs)))
    status = (f"converged in {elapsed:.1f} s" if finished
              else f"stopped at the {BASELINE_CAP_S:.0f} s cap, not converged")
    ratio = f"{elapsed / ours_s:.0f}x" if finished else f"> {elapsed / ours_s:.0f}x"
    return ["Baseline: the same model (evaluate, censored at contact loss) by scipy.optimize.curve_fit "
            "('trf', 2-point numerical derivatives) from a generic start (k from a polynomial fit, "
            "a = 0.01, alpha = 0.05+0.05j, r = 0.1, beta = 0.5), one run:", "",
            "| | time (s) | model evaluations | RMSE (N) | speed ratio baseline / fit_run |",
            "|---|---:|---:|---:|---:|",
            f"| curve_fit baseline ({status}) | {elapsed:.1f} | {best['calls']} | {rmse:.4g} | **{ratio}** |", ""]


def crb(params: ModelParameters) -> np.ndarray:
    """Cramér-Rao standard deviations (flat name order) at the truth, full resolution."""
    t, x = triangular_history(A, RATE, 3, HZ)
    ref = evaluate(params, t, x)
    lay = Layout(params.order_P, params.order_N, params.order_M, params.n_residual_cycles)
    lin, nl = lay.from_flat(params.to_vector())
    basis = ModelBasis(t, x, ref.labels, np.arange(len(t)), lay, params.x_scale_mm, t[1] - t[0])
    cols = np.array([lay.column_of_nonlinear(j) for j in range(lay.n_nonlinear)], int)
    J = np.hstack([basis.design(nl), basis.design_derivatives(nl) * lin[cols]])
    J[ref.force <= 0] = 0.0                                # censored samples carry no information
    norms = np.linalg.norm(J, axis=0)
    norms[norms == 0] = 1.0
    _, s, vt = np.linalg.svd(J / norms, full_matrices=False)
    keep = s > s[0] * 1e-12
    cov = SIGMA ** 2 * (vt[keep].T / s[keep] ** 2) @ vt[keep] / np.outer(norms, norms)
    out = np.empty(lay.n_params)
    out[np.concatenate([lay.flat_index_of_linear(), lay.flat_index_of_nonlinear()])] = np.sqrt(np.diag(cov))
    return out


def coverage(params: ModelParameters, orders: Orders, seeds: int, label: str) -> list[str]:
    truth = params.to_vector()
    names = params.names()
    sd_crb = crb(params)
    est, se, ratio, better, gaps = [], [], [], 0, []
    t0 = time.perf_counter()
    for seed in range(seeds):
        run, clean = make_run(params, 1000 + seed)
        result = fit_run(run, orders, x_scale_mm=A)
        est.append(result.values)
        se.append(result.stderr)
        ratio.append(result.rmse / SIGMA)
        truth_sse = float(np.sum((run.force_N - clean)[result.observed] ** 2))
        gap = (result.statistics["joint"].sse - truth_sse) / SIGMA ** 2
        better += gap <= 0
        gaps.append(gap)
    per_fit = (time.perf_counter() - t0) / seeds
    est, se = np.array(est), np.array(se)
    lines = [f"**{label}** (orders {orders}, {seeds} seeded runs, noise {SIGMA} N, {per_fit:.2f} s per fit): "
             f"RMSE/noise {np.mean(ratio):.4f} (max {np.max(ratio):.4f}); fit SSE <= SSE at the truth in "
             f"{better}/{seeds} runs" + (
                 f" (the others stopped in a local optimum, SSE above the truth's by a median "
                 f"{np.median([g for g in gaps if g > 0]):.1f} sigma^2, max {max(gaps):.1f} sigma^2)."
                 if better < seeds else "."), "",
             "| parameter | truth | CRB sd | sd of estimates | efficiency CRB/var | mean stderr | coverage of 95 % CI |",
             "|---|---:|---:|---:|---:|---:|---:|"]
    for i, n in enumerate(names):
        ok = np.isfinite(se[:, i])
        cov = np.mean(np.abs(est[ok, i] - truth[i]) <= 1.96 * se[ok, i]) if ok.any() else float("nan")
        sd = est[:, i].std(ddof=1)
        eff = (sd_crb[i] / sd) ** 2 if sd > 0 else float("nan")
        undetermined = "" if ok.all() else f" ({seeds - ok.sum()} not determined)"
        lines.append(f"| {n} | {truth[i]:.5g} | {sd_crb[i]:.3g} | {sd:.3g} | {eff:.2f} | "
                     f"{np.nanmean(se[:, i]) if ok.any() else float('nan'):.3g} | {cov:.2f}{undetermined} |")
    return lines + [""]


def real_file() -> list[str]:
    path = ROOT / "tests" / "data" / "real" / "Specimen_RawData_6.csv"
    run = load_run(path)
    w0 = time.perf_counter()
    result = fit_run(run)
    wall = time.perf_counter() - w0
    lines = [f"Real Bluehill file (3D-printed lattice, {len(run)} samples at 50 Hz), orders {result.orders}, "
             f"{wall:.2f} s: whole-run RMSE {result.rmse:.3f} N, residual autocorrelation time "
             f"{result.autocorrelation_time:.0f} samples.", "",
             "| step | SSE | R² | adj R² | RMSE (N) |", "|---|---:|---:|---:|---:|"]
    for step, st in result.statistics.items():
        lines.append(f"| {step} | {st.sse:.4g} | {st.r2:.5f} | {st.adj_r2:.5f} | {st.rmse:.4g} |")
    checks = ", ".join(f"{k} {'pass' if v else 'FAIL'}" for k, v in result.constraints.items())
    return lines + ["", f"Thermodynamic checks: {checks}.", ""]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats and seeds, no baseline")
    ap.add_argument("--speed-only", action="store_true",
                    help="only the speed section (timing and baseline; rerun it when the machine is quiet)")
    args = ap.parse_args()
    repeats, seeds = (3, 10) if args.quick else (9, 60)
    lines = ["Script: benchmarks/bench_identification.py --speed-only", ""]
    speed_lines, median_s, run = speed(repeats)
    lines += speed_lines
    if not args.quick:
        lines += baseline(run, median_s)
    publish("Identification speed (benchmarks/bench_identification.py)", lines)
    if args.speed_only:
        return
    default = ModelParameters.default()
    lines = ["Script: benchmarks/bench_identification.py", ""]
    lines += coverage(reduced(default), Orders(1, 1, 7), seeds,
                      "Identifiable reduction of the default specimen")
    lines += coverage(default, Orders(2, 3, 7), max(seeds // 2, 10) if not args.quick else 5,
                      "Full default specimen")
    lines += real_file()
    publish("Identification: recovery, coverage, efficiency, real data (benchmarks/bench_identification.py)",
            lines)


if __name__ == "__main__":
    main()
