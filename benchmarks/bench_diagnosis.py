"""Diagnosis benchmark: speed on the paper's protocol, the hard pairs, two causes, the drivers.

1. Speed: `diagnose` (identification included) of three-cycle 16 Hz runs (~14 000
   samples), clean and with a hidden effect; median over the runs.

Detection and false alarms are measured on runs foamlab never made:
benchmarks/bench_detection_independent.py (the table made here on foamlab's own effects is gone).

4. Through the real drivers (--hil N): the cases of tests/test_diagnosis_hil.py (a hidden
   effect per transport, a clean serial run) and a clean run through every transport at
   speedup 4, each recorded N times (simulator + run engine + driver, in real time at
   the speedup): the verdicts, the fitted sizes, the missed samples.

    python benchmarks/bench_diagnosis.py                # the speed table
    python benchmarks/bench_diagnosis.py --quick        # 3 speed runs
    python benchmarks/bench_diagnosis.py --hil 5        # only the through-the-drivers table
    python benchmarks/bench_diagnosis.py --hard 10      # the hard pairs on the independent generator (16 Hz)
    python benchmarks/bench_diagnosis.py --two 5        # two causes hidden together
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.append(str(Path(__file__).resolve().parents[1] / "tests"))   # independent_model

import numpy as np  # noqa: E402
from _table import publish  # noqa: E402

from foamlab.diagnosis import diagnose  # noqa: E402
from foamlab.diagnosis.synthetic import hidden_effect_run  # noqa: E402
from foamlab.model.effects import EFFECTS  # noqa: E402


def speed(repeats: int) -> list[str]:
    cases = [None, None, {"cycle_softening": 0.03}, {"channel_lag": 0.3}, {"force_zero_drift": 0.003},
             {"direction_friction": 4.0}, {"machine_compliance": 0.005}][:max(repeats, 1)]
    times, rows = [], []
    for i, eff in enumerate(cases):
        run = hidden_effect_run(eff, sampling_hz=16.0, seed=40 + i)
        t0 = time.perf_counter()
        d = diagnose([run])
        sec = time.perf_counter() - t0
        times.append(sec)
        rows.append(f"| {len(run):,d} | {eff or 'clean'} | {d.verdict} | {sec:.2f} |")
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (["Three-cycle 16 Hz runs, `diagnose([run])` including identification of the base model; "
             f"1-minute load average {load:.1f} at the end (2 cores shared).", "",
             "| samples | hidden effect | verdict | seconds |", "|---:|---|---|---:|"] + rows +
            ["", f"**median {statistics.median(times):.2f} s**, max {max(times):.2f} s over {len(times)} runs "
                 "(target: median <= 5 s)."])


def physical(name: str, magnitude: float) -> str:
    """A hidden effect's size in the units a lab speaks (frame stiffness, friction force, lag time)."""
    if name == "machine_compliance":
        return f"{1 / magnitude:,.0f} N/mm frame" if magnitude > 0 else "rigid frame"
    if name in ("channel_lag", "memory_lag"):
        return f"{1000 * magnitude:.3g} ms"
    if name == "direction_friction":
        return f"{magnitude:.3g} N"
    return f"{magnitude:.4g} {EFFECTS[name].parameters[0].unit}"


# ----------------------------------------------------------------------------- the hard pairs

def independent_run(regime: str, seed: int, hz: float = 16.0, **effect):
    """A run of tests/independent_model.py with an effect hidden by tests/independent_effects.py
    (its own arithmetic): compliance in mm/N, friction in N, lag_s in s."""
    import independent_effects as ie

    units = {"compliance": ("machine_compliance", lambda c: 1.0 / c), "friction": ("direction_friction", float),
             "lag_s": ("channel_lag", lambda s: 1000.0 * s)}
    causes = {units[k][0]: units[k][1](v) for k, v in effect.items() if v}
    return ie.independent_run(regime, seed, causes, hz=hz)


HARD = [(None, {}), ("machine_compliance", {"compliance": 1e-3}), ("machine_compliance", {"compliance": 5e-4}),
        ("direction_friction", {"friction": 0.45}), ("direction_friction", {"friction": 1.0}),
        ("channel_lag", {"lag_s": 0.05})]


def hard_pairs(seeds: int, hz: float = 16.0, regimes: str = "AB") -> list[str]:
    """The cases of issue 16 on the independent generator (three cycles at 16 Hz, noise 0.15 N).

    'left': what the base model does not absorb of the effect, (RSS of identification's fit
    with the effect - without it, same noise) / sigma^2, mean over the seeds: the chi-square
    evidence an extension can gain at most (~18 is needed for Delta BIC > 10 with one
    parameter). A noise-free fit is no measure: with no noise the samples at the turning
    points count as evidence and misfit there (docs/analysis.md)."""
    from collections import Counter

    import independent_model as im

    rows = []
    for regime in regimes:
        clean_rss: dict[int, float] = {}
        for name, effect in HARD:
            key, value = next(iter(effect.items()), (None, 0.0))
            size = physical({"compliance": "machine_compliance", "friction": "direction_friction",
                             "lag_s": "channel_lag"}.get(key, ""), value) if key else "clean"
            verdicts, left = Counter(), []
            for s in range(seeds):
                d = diagnose([independent_run(regime, 300 + s, hz, **effect)])
                verdicts[d.verdict] += 1
                if key is None:
                    clean_rss[s] = d.base.rss
                else:
                    left.append((d.base.rss - clean_rss[s]) / im.NOISE_N ** 2)
            right = verdicts.get(name or "none", 0)
            shown = f"{np.mean(left):.0f}" if left else "-"
            print(f"  {regime} {size}: {dict(verdicts)} (left {shown})", file=sys.stderr, flush=True)
            rows.append(f"| {regime} | {name or '-'} | {size} | {shown} | {right}/{seeds} | "
                        f"{'; '.join(f'{v} {n}' for v, n in verdicts.most_common())} |")
    return ([(f"Runs of tests/independent_model.py (regimes A: ~285 N peak, B: ~445 N; three cycles at {hz:g} Hz, "
              f"noise {im.NOISE_N} N) with an effect hidden by tests/independent_effects.py (`independent_run`), seeds 300..{299 + seeds}. "
              "'left' = what the base model does not absorb of the effect: (RSS of identification's fit with "
              "it - without it, same noise) / sigma^2, mean over the seeds; about 18 is needed to name a "
              "one-parameter cause (Delta BIC > 10)."), "",
             "| regime | hidden | size | left (chi2) | named | verdicts |", "|---|---|---|---:|---:|---|"] + rows)


TWO_CAUSES = [{"cycle_softening": 0.03, "force_zero_drift": 0.003},
              {"channel_lag": 0.3, "direction_friction": 4.0},
              {"machine_compliance": 0.005, "cycle_softening": 0.03},
              {"damping_cycle_change": 1.0, "force_zero_drift": 0.003}]


def two_causes(seeds: int, hz: float) -> list[str]:
    rows = []
    for combo in TWO_CAUSES:
        both, found = 0, []
        for s in range(seeds):
            d = diagnose([hidden_effect_run(combo, sampling_hz=hz, seed=700 + s)])
            names = [c.name for c in d.findings]
            both += set(combo) <= set(names)
            found.append("+".join(names) or d.verdict)
            print(f"  {combo} seed {700 + s}: {found[-1]}", file=sys.stderr, flush=True)
        hidden = " + ".join(f"{k} {physical(k, v)}" for k, v in combo.items())
        rows.append(f"| {hidden} | {both}/{seeds} | {'; '.join(found)} |")
    return ([(f"Two causes hidden together, the paper's three cycles at {hz:g} Hz, seeds 700..{699 + seeds}: "
              "runs whose findings name both (the verdict is the first finding)."), "",
             "| hidden | both named | findings per seed |", "|---|---:|---|"] + rows)


def through_the_drivers(repeats: int) -> list[str]:
    import tempfile
    from collections import Counter

    from foamlab.diagnosis import CAUSES
    from tests.test_diagnosis_hil import CASES, SPEED_MM_MIN, STRAIN, record

    cases = dict(CASES)
    n_test_cases = len(cases)
    for transport in ("modbus-tcp", "modbus-rtu-pty", "serial"):
        clean = (transport, 4.0, None, 0.0, 0.0)
        if clean not in cases.values():
            cases[f"{transport} clean at 4"] = clean
    rows = []
    for case, (transport, speedup, name, magnitude, _) in cases.items():
        verdicts, sizes, missed = Counter(), [], []
        for i in range(repeats):
            with tempfile.TemporaryDirectory() as tmp:
                result = record(Path(tmp), transport, speedup, {name: magnitude} if name else None, seed=100 + i)
            d = diagnose([result.run])
            verdicts[d.verdict] += 1
            missed.append(result.missed)
            if name and d.verdict == name:
                sizes.append(d.findings[0].values["values"][CAUSES[name].effect.parameters[0].name])
            print(f"  {case} run {i + 1}: {d.verdict} ({result.missed} missed)", file=sys.stderr, flush=True)
        hidden = f"{name} = {magnitude:g}" if name else "none (clean)"
        fitted = f"{min(sizes):.3g} - {max(sizes):.3g}" if sizes else "-"
        rows.append(f"| {case} | {transport} | {speedup:g} | {hidden} | "
                    f"{'; '.join(f'{v} {n}' for v, n in verdicts.most_common())} | {fitted} | "
                    f"{sum(m > 0 for m in missed)} |")
    return ([f"Three cycles to {STRAIN:.0%} strain at {SPEED_MM_MIN:g} mm/min, 16 Hz (~870 samples), "
             f"recorded {repeats} times per case through the simulator, the run engine and the real "
             f"driver (seeds 100...); the first {n_test_cases} cases are tests/test_diagnosis_hil.py's.", "",
             "| case | transport | speedup | hidden | verdicts | fitted size (when named) | runs with missed samples |",
             "|---|---|---:|---|---|---|---:|"] + rows)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="3 speed runs")
    ap.add_argument("--hz", type=float, default=2.0, help="sampling rate of the two-cause runs")
    ap.add_argument("--hil", type=int, default=0, metavar="N",
                    help="only the through-the-drivers table, N recordings per case")
    ap.add_argument("--speed", action="store_true", help="only the speed table (printed, not published)")
    ap.add_argument("--hard", type=int, default=0, metavar="N",
                    help="only the hard pairs on the independent generator (issue 16), N seeds per case")
    ap.add_argument("--two", type=int, default=0, metavar="N", help="only the two-cause table, N seeds per case")
    args = ap.parse_args()
    if args.hil:
        publish("Diagnosis through the real drivers (benchmarks/bench_diagnosis.py --hil)",
                through_the_drivers(args.hil))
        return
    if args.hard:
        publish("Diagnosis: the hard pairs (benchmarks/bench_diagnosis.py --hard)", hard_pairs(args.hard))
        return
    if args.two:
        publish("Diagnosis: two causes at once (benchmarks/bench_diagnosis.py --two)", two_causes(args.two, args.hz))
        return
    if args.speed:
        print("\n".join(speed(3 if args.quick else 7)))
        return
    lines = ["### Speed", ""] + speed(3 if args.quick else 7)
    lines += ["", "Detection and false alarms: the section made by benchmarks/bench_detection_independent.py."]
    publish("Diagnosis (benchmarks/bench_diagnosis.py)", lines)


if __name__ == "__main__":
    main()
